"""Rendering: a noise-free view of a Room from a camera pose.

The room (floor, walls, ceiling) and its furniture boxes are ray cast with numpy for every
pixel at once; colour is a bilinear lookup in the room's baked face textures, lit by light
that depends on the surface point only. Cameras follow OpenCV (x right, y down, z
forward); poses are ``T_world_camera``.
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np

from fleetslam.camera import Camera
from fleetslam.datasets.synthetic.box import Box
from fleetslam.datasets.synthetic.room import Room

# Slight blur after ray casting: one sample per pixel aliases at edges otherwise.
RENDER_BLUR_SIGMA = 0.6


@lru_cache(maxsize=8)
def _ray_components(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame ray direction (x, y, 1) per pixel as a row (1, W) of x and a column
    (H, 1) of y: a pinhole ray's x depends on u only and y on v only."""
    x = ((np.arange(camera.width) - camera.cx) / camera.fx).astype(np.float32)[None, :]
    y = ((np.arange(camera.height) - camera.cy) / camera.fy).astype(np.float32)[:, None]
    return x, y


def _screen_rect(box: Box, R_wc: np.ndarray, t_wc: np.ndarray, camera: Camera
                 ) -> tuple[int, int, int, int] | None:
    """Pixel rectangle (v0, v1, u0, u1) that can see the box; None if it is off screen."""
    pc = (box.corners() - t_wc) @ R_wc
    if (pc[:, 2] <= 0.0).all():
        return None
    if (pc[:, 2] < 0.01).any():  # straddles the camera plane: projection bounds are useless
        return 0, camera.height, 0, camera.width
    u = camera.fx * pc[:, 0] / pc[:, 2] + camera.cx
    v = camera.fy * pc[:, 1] / pc[:, 2] + camera.cy
    u0, u1 = max(0, int(math.floor(u.min())) - 1), min(camera.width, int(math.ceil(u.max())) + 2)
    v0, v1 = max(0, int(math.floor(v.min())) - 1), min(camera.height, int(math.ceil(v.max())) + 2)
    if u0 >= u1 or v0 >= v1:
        return None
    return v0, v1, u0, u1


def _cast_box(index: int, box: Box, R_wc: np.ndarray, t_wc: np.ndarray, camera: Camera,
              depth: np.ndarray, face: np.ndarray, inside: bool) -> None:
    """Slab test of all rays in the box's screen rectangle; keep hits nearer than ``depth``.

    Rays are (x, y, 1) in the camera frame, so the ray parameter is the z-depth."""
    rect = (0, camera.height, 0, camera.width) if inside else _screen_rect(box, R_wc, t_wc, camera)
    if rect is None:
        return
    v0, v1, u0, u1 = rect
    xr, yc = _ray_components(camera)
    xr, yc = xr[:, u0:u1], yc[v0:v1]
    M = box.R.T @ R_wc  # camera direction -> box-local direction
    origin = box.R.T @ (t_wc - np.asarray(box.center))
    half = np.asarray(box.half)
    near, far, dirs = [], [], []
    with np.errstate(divide="ignore", invalid="ignore"):
        for a in range(3):
            d = float(M[a, 0]) * xr + float(M[a, 1]) * yc + float(M[a, 2])
            inv = np.float32(1.0) / d
            t_lo = float(-half[a] - origin[a]) * inv
            t_hi = float(half[a] - origin[a]) * inv
            near.append(np.minimum(t_lo, t_hi))
            far.append(np.maximum(t_lo, t_hi))
            dirs.append(d)
        if inside:
            # From inside, the visible surface is where the ray leaves the shell.
            t = np.minimum(np.minimum(far[0], far[1]), far[2])
            hit = t > 0
        else:
            t = np.maximum(np.maximum(near[0], near[1]), near[2])
            t_out = np.minimum(np.minimum(far[0], far[1]), far[2])
            hit = (t <= t_out) & (t > 0)
    depth_rect = depth[v0:v1, u0:u1]
    face_rect = face[v0:v1, u0:u1]
    nearer = hit & (t < depth_rect)
    if not nearer.any():
        return
    # Which face was hit, only where it is kept (usually a small part of the rectangle).
    s0, s1, s2 = (far if inside else near)
    s0, s1, s2 = s0[nearer], s1[nearer], s2[nearer]
    if inside:
        axis = np.where(s0 <= s1, np.where(s0 <= s2, 0, 2), np.where(s1 <= s2, 1, 2))
    else:
        axis = np.where(s0 >= s1, np.where(s0 >= s2, 0, 2), np.where(s1 >= s2, 1, 2))
    d0, d1, d2 = dirs[0][nearer], dirs[1][nearer], dirs[2][nearer]
    d_axis = np.where(axis == 0, d0, np.where(axis == 1, d1, d2))
    # Entering through the +half face means travelling towards -axis; leaving the shell
    # through it means travelling towards +axis.
    side = (d_axis > 0) if inside else (d_axis < 0)
    depth_rect[nearer] = t[nearer]
    face_rect[nearer] = (6 * index + 2 * axis + side).astype(np.int32)


def _sample_texture(room: Room, face: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear texture lookup; u, v in texel units of each pixel's face. Returns float32 RGB."""
    width = room.face_width[face]
    height = room.face_height[face]
    u = np.clip(u - 0.5, 0.0, (width - 1.001).astype(np.float32))
    v = np.clip(v - 0.5, 0.0, (height - 1.001).astype(np.float32))
    iu, iv = u.astype(np.int64), v.astype(np.int64)
    fu, fv = (u - iu)[..., None], (v - iv)[..., None]
    i00 = room.face_offset[face] + iv * width + iu
    tex = room.texels
    top = tex[i00] * (1 - fu) + tex[i00 + 1] * fu
    bottom = tex[i00 + width] * (1 - fu) + tex[i00 + width + 1] * fu
    return (top * (1 - fv) + bottom * fv).astype(np.float32)


def _shading(room: Room, face: np.ndarray, px: np.ndarray, py: np.ndarray, pz: np.ndarray
             ) -> np.ndarray:
    """Lambertian light that depends on the surface point only (never on the viewer), so
    a point keeps its brightness from frame to frame."""
    n = room.face_normal[face]
    sun = np.array([0.3, -0.45, 0.84], np.float32)
    sun /= np.linalg.norm(sun)
    direct = np.maximum(n @ sun, 0.0)
    lamp = np.array([0.4, 0.3, room.size_m[2] - 0.1], np.float32)
    lx, ly, lz = lamp[0] - px, lamp[1] - py, lamp[2] - pz
    r2 = lx * lx + ly * ly + lz * lz + np.float32(1e-6)
    cos_l = np.maximum(n[..., 0] * lx + n[..., 1] * ly + n[..., 2] * lz, 0.0) / np.sqrt(r2)
    return np.float32(0.62) + np.float32(0.18) * direct + np.float32(0.35) * cos_l / (1 + r2 / 9)


def render(room: Room, camera: Camera, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free view: (rgb (H, W, 3) uint8 RGB order, depth (H, W) float32 metres, z-depth)."""
    R_wc = np.asarray(T_world_camera, float)[:3, :3]
    t_wc = np.asarray(T_world_camera, float)[:3, 3]
    depth = np.full((camera.height, camera.width), np.inf, np.float32)
    face = np.zeros((camera.height, camera.width), np.int32)
    for index, box in enumerate(room.boxes):
        _cast_box(index, box, R_wc, t_wc, camera, depth, face, inside=(index == 0))
    missed = ~np.isfinite(depth)  # only possible if the camera is outside the room
    depth[missed] = 0.0
    xr, yc = _ray_components(camera)
    # Hit points in the world: origin + depth * (R_wc @ (x, y, 1)).
    p = [float(t_wc[k]) + depth * (float(R_wc[k, 0]) * xr + float(R_wc[k, 1]) * yc
                                   + float(R_wc[k, 2])) for k in range(3)]
    A = room.face_uv[face]  # (H, W, 2, 4)
    u = A[..., 0, 0] * p[0] + A[..., 0, 1] * p[1] + A[..., 0, 2] * p[2] + A[..., 0, 3]
    v = A[..., 1, 0] * p[0] + A[..., 1, 1] * p[1] + A[..., 1, 2] * p[2] + A[..., 1, 3]
    colour = _sample_texture(room, face, u, v) * _shading(room, face, *p)[..., None]
    colour[missed] = 0.0
    rgb = np.clip(colour + 0.5, 0, 255).astype(np.uint8)
    rgb = cv2.GaussianBlur(rgb, (3, 3), RENDER_BLUR_SIGMA)
    return rgb, depth
