"""Deterministic synthetic multi-robot RGB-D scenes: the data of ``fleetslam demo`` and of
fast tests.

A textured room (floor, walls, ceiling) with furniture made of boxes is ray cast with
numpy for every pixel at once. Robots walk smooth, bounded paths in the middle of the
room; they start looking at a common region (the middle of the +y wall) and then turn
apart, each sweeping its own side, so their maps overlap and can be merged.

The common region is furnished so that the overlap pins down all six degrees of freedom
of a map merge: a tall piece and a shelf flank it (both robots see their inner sides),
a sideboard with a wall unit above it stands between them, a table with things on it and
a stack of boxes stand in front at other depths; runs of storage modules line the side
walls the robots turn to; every piece has depth relief (recessed plinths, shelf boards
and books, overhanging tops). A bare wall and floor let one map slide along the other:
on such a scene the best-overlapping wrong pose, 1.4 m along the wall, scored better than
the truth, and no ICP can fix that.

World frame: z up, floor at z = 0, room centred on x = y = 0 (x along the first room
dimension). Cameras follow OpenCV (x right, y down, z forward); poses are
``T_world_camera``.

Output per robot is a native TUM RGB-D folder (rgb/, depth/, rgb.txt, depth.txt,
groundtruth.txt) plus camera.json; ``scene.json`` beside the robot folders records the
config and is written last, so only a complete scene has one.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import string
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from fleetslam.camera import Camera
from fleetslam.config import SyntheticConfig
from fleetslam.io.trajectory import write_tum_trajectory

FORMAT_NAME = "fleetslam-synthetic"
FORMAT_VERSION = 2  # 2: furnished common view, views that cross at the start
DEPTH_SCALE = 5000.0  # TUM: raw value per metre
# Texture resolution (texels per metre): 5 mm texels stay about one pixel wide at 3 m.
TEXELS_PER_M = 200.0
# Kinect-like sensors return nothing closer than this.
MIN_SENSOR_DEPTH_M = 0.4
RGB_NOISE_SIGMA = 2.0
# Slight blur after ray casting: one sample per pixel aliases at edges otherwise.
RENDER_BLUR_SIGMA = 0.6
# Furniture keeps at least this distance (m) from the area robots walk in.
ROBOT_CLEARANCE_M = 0.7
MIN_ROOM_SIZE_M = (4.0, 3.5, 2.2)

# Robot paths (see robot_trajectories). Lateral spacing of the start positions (m), extra
# sideways drift while turning away (m), forward/back amplitude (m).
_ROBOT_SPACING_M = 0.5
_ROBOT_DRIFT_M = 0.45
_ROBOT_SWAY_M = 0.3
_MAX_ROBOTS_IN_ZONE = 4
# Heading offset between neighbouring robots at the start (negative: each looks a little
# towards the others, so all views cross in the middle of the +y wall), and how far each
# turns away. (Chosen so each of two robots' 120-frame maps shares ~45% of its 10 cm voxels
# with the other's: with less, sliding one map along the wall gains more overlap than the
# furniture costs.)
_START_SPREAD_DEG = -10.0
_TURN_DEG = 45.0
_TURN_RATE = 0.8  # rad/s of the turning cosine: peak yaw rate = _TURN_DEG/2 * 0.8 = 24 deg/s


# ---------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Box:
    """A box rotated by ``yaw`` about the world z axis. ``kind`` picks its texture."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float = 0.0
    kind: str = "paint"

    def __post_init__(self) -> None:
        # Plain floats, so scene.json and equality do not depend on where numbers came from.
        object.__setattr__(self, "center", tuple(float(v) for v in self.center))
        object.__setattr__(self, "half", tuple(float(v) for v in self.half))
        object.__setattr__(self, "yaw", float(self.yaw))

    @property
    def R(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def corners(self) -> np.ndarray:
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        return (signs * np.asarray(self.half)) @ self.R.T + np.asarray(self.center)

    def footprint(self, pad: float = 0.0) -> tuple[float, float, float, float]:
        """Axis-aligned (xmin, xmax, ymin, ymax) of the rotated footprint."""
        c = self.corners()
        return (c[:, 0].min() - pad, c[:, 0].max() + pad, c[:, 1].min() - pad, c[:, 1].max() + pad)

    def distance_to(self, point: np.ndarray) -> float:
        local = self.R.T @ (np.asarray(point, float) - np.asarray(self.center))
        outside = np.maximum(np.abs(local) - np.asarray(self.half), 0.0)
        return float(np.linalg.norm(outside))

    def to_dict(self) -> dict:
        return {"kind": self.kind, "center": list(self.center), "half": list(self.half),
                "yaw": self.yaw}


def _robot_zone(size_m: tuple[float, float, float]) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) that every robot path of up to 4 robots stays in."""
    half_x = _ROBOT_SPACING_M * (_MAX_ROBOTS_IN_ZONE - 1) / 2 + _ROBOT_DRIFT_M
    y0 = _robot_base_y(size_m)
    return (-half_x, half_x, y0 - _ROBOT_SWAY_M, y0 + _ROBOT_SWAY_M)


def _robot_base_y(size_m: tuple[float, float, float]) -> float:
    # Slightly in the -y half so the +y wall, which every robot looks at first, is not too far.
    return -0.1 * size_m[1]


def _rects_overlap(a: tuple, b: tuple) -> bool:
    return a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]


def _rect_gap(a: tuple, b: tuple) -> float:
    dx = max(b[0] - a[1], a[0] - b[1], 0.0)
    dy = max(b[2] - a[3], a[2] - b[3], 0.0)
    return math.hypot(dx, dy)


# Furniture kinds. Every kind has depth relief (boards, plinths, overhangs, objects on top),
# so pieces differ in 3D, not only in texture, and the wall behind them is no bare plane.
_KINDS = ("table", "shelf", "cabinet", "sideboard", "boxes", "wardrobe", "wall_unit", "pillar")
_RUN_MODULES = ("shelf", "cabinet", "sideboard", "wardrobe")  # of a "run" (storage wall)
_WALL_MOUNTED = ("wall_unit", "pillar")  # fixed to a wall, never turned away from it
# The view every robot starts with: the middle of the +y wall, |x| < _SHARED_HALF_WIDTH_M.
# Its pieces, in this order: a tall piece on one side and a shelf on the other, whose inner
# sides (|x| in _FLANK_INNER_X_M) both robots see; a sideboard (with a wall unit above it)
# against the wall between them; a table and a stack of boxes standing in front at other
# depths. Pieces after these go to the walls robots see when they turn away.
_SHARED_HALF_WIDTH_M = 1.7
_FLANK_INNER_X_M = (0.6, 1.2)
_SHARED_PIECES = (("wardrobe|pillar", "flank"), ("shelf", "flank"), ("sideboard", "wall"),
                  ("table", "free"), ("boxes", "free"))
_PANEL_M = 0.02  # board thickness of shelves


def _furniture_size(rng: np.random.Generator, kind: str, room_height: float
                    ) -> tuple[float, float, float]:
    """(width, depth, height) in metres; for ``boxes`` the size of the bottom box."""
    u = rng.uniform
    if kind == "table":
        return u(0.8, 1.4), u(0.6, 0.9), u(0.72, 0.78)
    if kind == "shelf":
        return u(0.7, 1.2), u(0.3, 0.4), min(u(1.5, 2.0), room_height - 0.15)
    if kind in ("cabinet", "sideboard"):
        return u(0.6, 1.2), u(0.4, 0.55), u(0.75, 1.0)
    if kind == "boxes":
        return u(0.4, 0.7), u(0.35, 0.6), u(0.25, 0.45)
    if kind == "wardrobe":
        return u(0.8, 1.2), u(0.55, 0.65), min(u(1.9, 2.2), room_height - 0.1)
    if kind == "wall_unit":
        return u(0.6, 1.2), u(0.25, 0.35), u(0.45, 0.7)
    if kind == "run":  # modules of their own depth and height, backs against the wall
        return u(1.6, 2.6), 0.65, room_height
    return u(0.4, 0.9), u(0.3, 0.6), room_height  # pillar (or chimney breast)


_Place = Callable[..., Box]


def _objects_on(rng: np.random.Generator, at: _Place, w: float, d: float, z: float,
                count: int) -> list[Box]:
    """Small things standing on a surface of ``w`` x ``d`` at height ``z``: boxes, bottles,
    lying books; different shapes give the map small-scale 3D structure."""
    parts = []
    for _ in range(count):
        shape = int(rng.integers(3))
        if shape == 0:
            ow, od, oh = rng.uniform(0.12, 0.3), rng.uniform(0.1, 0.25), rng.uniform(0.08, 0.3)
        elif shape == 1:
            ow = od = rng.uniform(0.06, 0.1)
            oh = rng.uniform(0.2, 0.35)
        else:
            ow, od, oh = rng.uniform(0.2, 0.32), rng.uniform(0.15, 0.24), rng.uniform(0.03, 0.06)
        ow, od = min(ow, w), min(od, d)
        lx = rng.uniform(-(w - ow) / 2, (w - ow) / 2)
        ly = rng.uniform(-(d - od) / 2, (d - od) / 2) * 0.8
        parts.append(at((lx, ly), z + oh / 2, (ow / 2, od / 2, oh / 2), "object",
                        float(rng.uniform(-0.4, 0.4))))
    return parts


def _shelf_parts(rng: np.random.Generator, at: _Place, w: float, d: float, h: float,
                 z0: float = 0.0, plinth: float = 0.08, level_m: tuple[float, float] = (0.32, 0.42)
                 ) -> list[Box]:
    """An open shelf from ``z0`` to ``z0 + h``: carcass (a recessed plinth, or a bottom board if
    ``plinth`` is 0), boards at even heights, blocks of books of random width, height and
    depth standing against the back (so their fronts are recessed by different amounts),
    now and then a box instead of books, and gaps."""
    t = _PANEL_M
    parts = [at((sx * (w - t) / 2, 0), z0 + h / 2, (t / 2, d / 2, h / 2), "wood") for sx in (-1, 1)]
    parts.append(at((0, -(d - t) / 2), z0 + h / 2, ((w - 2 * t) / 2, t / 2, h / 2), "wood"))  # back
    parts.append(at((0, 0), z0 + h - t / 2, ((w - 2 * t) / 2, d / 2, t / 2), "wood"))  # top
    if plinth > 0:
        parts.append(at((0, -0.02), z0 + plinth / 2, ((w - 2 * t) / 2, d / 2 - 0.02, plinth / 2),
                        "wood"))
    else:
        plinth = t
        parts.append(at((0, 0), z0 + t / 2, ((w - 2 * t) / 2, d / 2, t / 2), "wood"))
    levels = max(1, int(round((h - plinth - t) / rng.uniform(*level_m))))
    pitch = (h - plinth - t) / levels
    inner_w, inner_d = w - 2 * t, d - t
    for k in range(levels):
        lo = z0 + plinth + k * pitch + (t / 2 if k else 0.0)
        hi = z0 + plinth + (k + 1) * pitch - (t / 2 if k < levels - 1 else 0.0)
        if k:
            parts.append(at((0, 0), z0 + plinth + k * pitch, (inner_w / 2, d / 2, t / 2), "wood"))
        x = -inner_w / 2 + float(rng.uniform(0.0, 0.1))
        while x < inner_w / 2 - 0.05:
            bw = min(float(rng.uniform(0.08, 0.35)), inner_w / 2 - x)
            if rng.random() < 0.2:  # an empty stretch of board
                x += bw
                continue
            bh = (hi - lo) * rng.uniform(0.6, 0.92)
            bd = inner_d * rng.uniform(0.55, 0.95)
            kind = "books" if rng.random() < 0.8 else "object"
            parts.append(at((x + bw / 2, -d / 2 + t + bd / 2), lo + bh / 2,
                            (bw / 2, bd / 2, bh / 2), kind))
            x += bw + float(rng.uniform(0.0, 0.02))
    return parts


def _wall_unit_parts(rng: np.random.Generator, at: _Place, w: float, d: float, h: float,
                     bottom: float, back_y: float) -> list[Box]:
    """A wall cabinet or an open wall shelf with books, hung from ``bottom`` (m above the
    floor) with its back at local y = ``back_y``."""
    y = back_y + d / 2
    if rng.random() < 0.5:
        return [at((0, y), bottom + h / 2, (w / 2, d / 2, h / 2), "paint")]

    def moved(xy: tuple[float, float], *args, **kwargs) -> Box:
        return at((xy[0], xy[1] + y), *args, **kwargs)

    return _shelf_parts(rng, moved, w, d, h, z0=bottom, plinth=0.0, level_m=(0.3, 0.4))


def _furniture_parts(rng: np.random.Generator, kind: str, center_xy: np.ndarray, yaw: float,
                     size: tuple[float, float, float], room_height: float) -> list[Box]:
    """Boxes of one piece of furniture; local +y is its front."""
    w, d, h = size
    R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])

    def at(local_xy: tuple[float, float], z: float, half: tuple[float, float, float],
           part_kind: str, extra_yaw: float = 0.0) -> Box:
        xy = center_xy + R @ np.asarray(local_xy)
        return Box((float(xy[0]), float(xy[1]), z), half, yaw + extra_yaw, part_kind)

    parts: list[Box] = []
    if kind == "table":
        top = 0.04
        parts.append(at((0, 0), h - top / 2, (w / 2, d / 2, top / 2), "tabletop"))
        leg = 0.025
        for sx in (-1, 1):
            for sy in (-1, 1):
                parts.append(at((sx * (w / 2 - 0.06), sy * (d / 2 - 0.06)), (h - top) / 2,
                                (leg, leg, (h - top) / 2), "paint"))
        parts += _objects_on(rng, at, w, d, h, int(rng.integers(2, 4)))
    elif kind == "shelf":
        parts += _shelf_parts(rng, at, w, d, h)
    elif kind in ("cabinet", "sideboard"):
        # Recessed plinth, body, overhanging top, things on it; a sideboard has a wall
        # cabinet or wall shelf above it.
        plinth, top = 0.08, 0.03
        parts.append(at((0, -0.03), plinth / 2, (w / 2 - 0.02, d / 2 - 0.03, plinth / 2), "paint"))
        body = h - plinth - top
        parts.append(at((0, 0), plinth + body / 2, (w / 2, d / 2, body / 2), "paint"))
        parts.append(at((0, 0.015), h - top / 2, (w / 2 + 0.02, d / 2 + 0.015, top / 2), "wood"))
        parts += _objects_on(rng, at, w, d, h, int(rng.integers(1, 4)))
        unit_h, unit_d = float(rng.uniform(0.4, 0.7)), float(rng.uniform(0.25, 0.35))
        bottom = max(h + 0.4, 1.4)
        if kind == "sideboard" and bottom + unit_h < room_height - 0.1:
            unit_w = w * rng.uniform(0.6, 1.0)
            shift = rng.uniform(-(w - unit_w) / 2, (w - unit_w) / 2)

            def shifted(xy: tuple[float, float], *args, **kwargs) -> Box:
                return at((xy[0] + shift, xy[1]), *args, **kwargs)

            parts += _wall_unit_parts(rng, shifted, unit_w, unit_d, unit_h, bottom, -d / 2)
    elif kind == "boxes":
        # A stack of two or three boxes, each smaller and turned against the one below.
        z, bw, bd, bh, ox, oy, turn = 0.0, w, d, h, 0.0, 0.0, 0.0
        for level in range(int(rng.integers(2, 4))):
            if level:
                bw, bd = bw * rng.uniform(0.6, 0.9), bd * rng.uniform(0.6, 0.9)
                bh = bh * rng.uniform(0.6, 1.0)
                ox += float(rng.uniform(-0.08, 0.08))
                oy += float(rng.uniform(-0.08, 0.08))
                turn += float(rng.uniform(-0.5, 0.5))
            parts.append(at((ox, oy), z + bh / 2, (bw / 2, bd / 2, bh / 2), "object", turn))
            z += bh
    elif kind == "wardrobe":
        # Recessed plinth, body, cornice, two door handles.
        plinth, top = 0.1, 0.05
        parts.append(at((0, -0.04), plinth / 2, (w / 2 - 0.03, d / 2 - 0.04, plinth / 2), "paint"))
        body = h - plinth - top
        parts.append(at((0, 0), plinth + body / 2, (w / 2, d / 2, body / 2), "wood"))
        parts.append(at((0, 0.02), h - top / 2, (w / 2 + 0.03, d / 2 + 0.02, top / 2), "paint"))
        for sx in (-1, 1):
            parts.append(at((sx * 0.06, d / 2 + 0.015), plinth + body * 0.5,
                            (0.012, 0.015, 0.12), "object"))
    elif kind == "wall_unit":
        parts += _wall_unit_parts(rng, at, w, d, h, float(rng.uniform(1.4, 1.6)), -d / 2)
    elif kind == "run":
        # Two or three modules side by side (a storage wall): each a shelf, cabinet,
        # sideboard or wardrobe of its own width, depth and height.
        n = int(rng.integers(2, 4))
        widths = 0.5 + (w - 0.5 * n) * rng.dirichlet(np.full(n, 4.0))  # >= 0.5 m each
        x = -w / 2
        for width in widths:
            module = _RUN_MODULES[int(rng.integers(len(_RUN_MODULES)))]
            _, depth, height = _furniture_size(rng, module, room_height)
            centre = center_xy + R @ np.array([x + width / 2, -d / 2 + depth / 2])
            parts += _furniture_parts(rng, module, centre, yaw, (float(width), depth, height),
                                      room_height)
            x += width
    else:  # pillar: the wall steps out, floor to ceiling
        parts.append(at((0, 0), h / 2, (w / 2, d / 2, h / 2), "wall"))
    return parts


def _walls(size_m: tuple[float, float, float]) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """(point on wall, inward normal, wall length, yaw that turns local +y to the normal):
    the +y, -x and +x walls, the ones robots look at (never the -y wall behind them)."""
    Lx, Ly, _ = size_m
    return [(np.array([0.0, Ly / 2]), np.array([0.0, -1.0]), Lx, math.pi),
            (np.array([-Lx / 2, 0.0]), np.array([1.0, 0.0]), Ly, -math.pi / 2),
            (np.array([Lx / 2, 0.0]), np.array([-1.0, 0.0]), Ly, math.pi / 2)]


def _wall_spans(where: str, size_m: tuple[float, float, float]
                ) -> list[tuple[int, float, float]]:
    """(wall index in _walls, along from, along to) of the stretches of wall that ``where``
    allows; "along" is the coordinate along the wall's tangent (z x normal)."""
    Lx, Ly, _ = size_m
    half = min(_SHARED_HALF_WIDTH_M, Lx / 2)
    if where == "shared wall":
        return [(0, -half, half)]
    if where.startswith("outer"):
        # The stretches a robot turning towards side s sees: the +y wall beyond the shared
        # view and the side wall in front of the robots.
        side = float(where[5:])
        y0 = _robot_base_y(size_m)
        beyond = (0, half, Lx / 2) if side > 0 else (0, -Lx / 2, -half)
        # y from the robots' line to the +y wall (the +x wall's tangent points to -y).
        front = (2, -Ly / 2, -y0) if side > 0 else (1, y0, Ly / 2)
        return [beyond, front]
    # Anywhere robots look: the +y wall and the side walls in front of the robots' line.
    y0 = _robot_base_y(size_m)
    return [(0, -Lx / 2, Lx / 2), (1, y0, Ly / 2), (2, -Ly / 2, -y0)]


def _furniture_candidate(rng: np.random.Generator, kind: str, where: str,
                         size_m: tuple[float, float, float]) -> list[Box] | None:
    """One randomly placed piece. ``where``: "wall" (anywhere along the +y wall, or the -x or
    +x wall in front of the robots; longer stretches more often); "outer-1" / "outer+1" (the
    walls a robot turning towards -x / +x sees beyond the shared view); "flank-1" / "flank+1"
    (against the +y wall on the -x / +x side of the shared view, its inner side at |x| in
    _FLANK_INNER_X_M); "shared wall" (against the +y wall within the shared view); "shared
    free" (free-standing in front of it). Pieces that are neither wall-mounted nor hold a
    wall unit are sometimes turned a little away from their wall. None if the piece drawn
    fits on none of the allowed stretches."""
    Lx, Ly, Lz = size_m
    size = _furniture_size(rng, kind, Lz)
    if where == "shared free":
        half = min(_SHARED_HALF_WIDTH_M, Lx / 2)
        y_lo = _robot_zone(size_m)[3] + ROBOT_CLEARANCE_M
        center = np.array([rng.uniform(-half + 0.3, half - 0.3), rng.uniform(y_lo, Ly / 2 - 0.5)])
        return _furniture_parts(rng, kind, center, float(rng.uniform(-0.6, 0.6)), size, Lz)
    walls = _walls(size_m)
    mounted = kind in _WALL_MOUNTED
    turnable = not mounted and kind not in ("sideboard", "run")  # (wall units hang on the wall)
    jitter = float(rng.uniform(-0.25, 0.25)) if turnable and rng.random() < 0.3 else 0.0
    if where.startswith("flank"):
        wall, jitter = 0, 0.0
        along = float(where[5:]) * (rng.uniform(*_FLANK_INNER_X_M) + size[0] / 2)
    else:
        # Stretches the piece fits in (with 5 cm to spare at either end).
        spans = [(wall, lo + size[0] / 2 + 0.05, hi - size[0] / 2 - 0.05)
                 for wall, lo, hi in _wall_spans(where, size_m)]
        spans = [span for span in spans if span[2] > span[1]]
        if not spans:
            return None
        lengths = np.array([hi - lo for _, lo, hi in spans]) + 0.1 + size[0]
        wall, lo, hi = spans[int(rng.choice(len(spans), p=lengths / lengths.sum()))]
        along = rng.uniform(lo, hi)
    point, normal, _, yaw = walls[wall]
    tangent = np.array([-normal[1], normal[0]])
    # Off the wall by half its depth, plus what a turned piece needs to clear the wall.
    off = size[1] / 2 + (0.0 if kind == "pillar" else 0.01 if mounted else 0.03)
    off += abs(math.sin(jitter)) * size[0] / 2
    return _furniture_parts(rng, kind, point + along * tangent + off * normal, yaw + jitter, size,
                            Lz)


def _footprint(parts: list[Box]) -> tuple[float, float, float, float]:
    rects = np.array([p.footprint() for p in parts])
    return (rects[:, 0].min(), rects[:, 1].max(), rects[:, 2].min(), rects[:, 3].max())


def _place_furniture(rng: np.random.Generator, size_m: tuple[float, float, float],
                     n_furniture: int) -> list[list[Box]]:
    """Up to ``n_furniture`` pieces, not overlapping, none near the robots' zone.

    The first ones (_SHARED_PIECES) furnish the view every robot starts with, the middle of
    the +y wall: pieces of different shapes and heights at different depths, so that maps
    overlapping there fit together in one way only (a bare wall, floor and one table let a
    map slide along the wall). The rest stand against the walls robots turn to, alternately
    a run of storage modules on the -x side, one on the +x side and any kind anywhere."""
    Lx, Ly, _ = size_m
    zone = _robot_zone(size_m)
    placed: list[list[Box]] = []
    footprints: list[tuple[float, float, float, float]] = []
    flank_side = 1 if rng.random() < 0.5 else -1
    for item in range(n_furniture):
        if item < len(_SHARED_PIECES):
            kinds, where = _SHARED_PIECES[item]
            choices = kinds.split("|")
            kind = choices[int(rng.integers(len(choices)))]
            if where == "flank":
                where = f"flank{flank_side:+d}"
                flank_side = -flank_side
            else:
                where = "shared " + where
        else:
            where = ("outer-1", "outer+1", "wall")[(item - len(_SHARED_PIECES)) % 3]
            kind = "run" if where != "wall" else _KINDS[int(rng.integers(len(_KINDS)))]
        for _attempt in range(200):
            parts = _furniture_candidate(rng, kind, where, size_m)
            if parts is None:
                continue
            fp = _footprint(parts)
            eps = 1e-6  # a pillar stands flush with its wall
            inside = (fp[0] > -Lx / 2 - eps and fp[1] < Lx / 2 + eps and fp[2] > -Ly / 2 - eps
                      and fp[3] < Ly / 2 + eps)
            padded = (fp[0] - 0.05, fp[1] + 0.05, fp[2] - 0.05, fp[3] + 0.05)
            if (inside and _rect_gap(fp, zone) >= ROBOT_CLEARANCE_M
                    and not any(_rects_overlap(padded, other) for other in footprints)):
                placed.append(parts)
                footprints.append(fp)
                break
    return placed


# ---------------------------------------------------------------------------------------
# Textures: drawn per face from the seed, in metric units (TEXELS_PER_M)
# ---------------------------------------------------------------------------------------

_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN)
_CHARS = string.ascii_letters + string.digits + "#%&@?+"

# style: (base colour range low, high, shapes, text blobs, posters, specks; all per m^2)
_STYLES: dict[str, tuple[tuple[int, int, int], tuple[int, int, int], float, float, float, float]] = {
    "wall": ((150, 140, 120), (215, 210, 200), 28.0, 8.0, 0.45, 150.0),
    "floor": ((70, 60, 50), (150, 130, 110), 30.0, 3.0, 0.25, 150.0),
    "ceiling": ((170, 170, 165), (220, 220, 215), 20.0, 3.0, 0.3, 80.0),
    # Furniture is seen from a metre or less too: denser marks than on the walls, so a face
    # filling a quadrant of the image still holds its share of ORB's strongest corners.
    "wood": ((90, 60, 35), (170, 120, 80), 60.0, 10.0, 0.0, 600.0),
    "tabletop": ((90, 60, 35), (170, 120, 80), 60.0, 15.0, 0.0, 600.0),
    "paint": ((50, 50, 50), (200, 200, 200), 60.0, 10.0, 0.0, 600.0),
    "books": ((60, 45, 35), (120, 90, 70), 0.0, 0.0, 0.0, 0.0),
    "object": ((40, 40, 40), (220, 220, 220), 60.0, 20.0, 0.0, 150.0),
}


def _smooth_noise(rng: np.random.Generator, w: int, h: int, cell_px: float, sigma: float) -> np.ndarray:
    """Smooth random field (h, w, 3) float32 with features about ``cell_px`` texels wide:
    mostly brightness, a little colour (real surfaces are not rainbow-mottled)."""
    gw, gh = max(2, int(w / cell_px) + 2), max(2, int(h / cell_px) + 2)
    grid = (rng.normal(0.0, sigma, (gh, gw, 1)) + rng.normal(0.0, sigma / 4, (gh, gw, 3)))
    return cv2.resize(grid.astype(np.float32), (w, h), interpolation=cv2.INTER_CUBIC)


def _random_colour(rng: np.random.Generator, avoid: np.ndarray) -> tuple[int, int, int]:
    """A colour clearly different in brightness from ``avoid`` so FAST sees its edges."""
    for _ in range(8):
        c = rng.integers(0, 256, 3)
        if abs(float(c.mean()) - float(avoid.mean())) > 45:
            break
    return int(c[0]), int(c[1]), int(c[2])


def _random_text(rng: np.random.Generator) -> str:
    return "".join(rng.choice(list(_CHARS), int(rng.integers(3, 11))))


def _draw_text(rng: np.random.Generator, img: np.ndarray, x: int, y: int, height_px: float,
               colour: tuple[int, int, int]) -> None:
    font = _FONTS[int(rng.integers(len(_FONTS)))]
    scale = max(0.3, height_px / 22.0)
    thickness = max(1, int(round(scale * 1.8)))
    cv2.putText(img, _random_text(rng), (x, y), font, scale, colour, thickness, cv2.LINE_AA)


def _draw_shape(rng: np.random.Generator, img: np.ndarray, base: np.ndarray,
                size_m: tuple[float, float]) -> None:
    """One random rectangle, circle, ellipse, line, polygon or cluster of dots."""
    h, w = img.shape[:2]
    s = float(np.exp(rng.uniform(np.log(size_m[0]), np.log(size_m[1])))) * TEXELS_PER_M
    x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
    colour = _random_colour(rng, base)
    kind = int(rng.integers(7))
    filled = -1 if rng.random() < 0.6 else max(1, int(s / 12))
    if kind == 0:
        a = s * rng.uniform(0.3, 1.0)
        cv2.rectangle(img, (int(x - s / 2), int(y - a / 2)), (int(x + s / 2), int(y + a / 2)),
                      colour, filled, cv2.LINE_AA)
    elif kind == 1:
        cv2.circle(img, (x, y), max(2, int(s / 2)), colour, filled, cv2.LINE_AA)
    elif kind == 2:
        axes = (max(2, int(s / 2)), max(2, int(s / 2 * rng.uniform(0.3, 0.9))))
        cv2.ellipse(img, (x, y), axes, float(rng.uniform(0, 180)), 0, 360, colour, filled, cv2.LINE_AA)
    elif kind == 3:
        angle = rng.uniform(0, np.pi)
        dx, dy = s * np.cos(angle), s * np.sin(angle)
        cv2.line(img, (int(x - dx), int(y - dy)), (int(x + dx), int(y + dy)), colour,
                 max(2, int(s / 10)), cv2.LINE_AA)
    elif kind == 4:
        n = int(rng.integers(3, 6))
        pts = np.array([x, y]) + rng.uniform(-s / 2, s / 2, (n, 2))
        cv2.fillPoly(img, [pts.astype(np.int32)], colour, cv2.LINE_AA)
    elif kind == 5:
        for _ in range(int(rng.integers(3, 8))):
            px, py = x + rng.normal(0, s / 2), y + rng.normal(0, s / 2)
            cv2.circle(img, (int(px), int(py)), max(2, int(s / 8)), colour, -1, cv2.LINE_AA)
    else:
        _draw_text(rng, img, x, y, max(8.0, s / 3), colour)


def _draw_specks(rng: np.random.Generator, img: np.ndarray, base: np.ndarray, per_m2: float) -> None:
    """Many small dots and dashes (0.6-2 cm): corners for close views, where the larger
    shapes are too sparse. Parameters are drawn at once; only the drawing loops."""
    h, w = img.shape[:2]
    n = int(rng.poisson(per_m2 * w * h / TEXELS_PER_M**2))
    xy = np.stack([rng.integers(0, w, n), rng.integers(0, h, n)], axis=1)
    size = rng.uniform(0.006, 0.02, n) * TEXELS_PER_M
    step = (size[:, None] * rng.uniform(-1.0, 1.0, (n, 2))).astype(np.int32)
    dark = rng.random(n) < (0.75 if base.mean() > 110 else 0.25)
    shade = np.where(dark[:, None], rng.integers(0, 90, (n, 3)), rng.integers(170, 256, (n, 3)))
    square = rng.random(n) < 0.5
    for (x, y), s, (dx, dy), c, sq in zip(xy.tolist(), size.tolist(), step.tolist(),
                                          shade.tolist(), square.tolist()):
        if sq:
            cv2.rectangle(img, (x, y), (x + dx, y + dy), c, -1)
        else:
            cv2.circle(img, (x, y), max(1, int(s / 2)), c, -1, cv2.LINE_AA)


def _draw_poster(rng: np.random.Generator, img: np.ndarray) -> None:
    """A framed light rectangle with a title, shapes and rows of small text."""
    h, w = img.shape[:2]
    pw = int(rng.uniform(0.3, 0.9) * TEXELS_PER_M)
    ph = int(pw * rng.uniform(0.6, 1.5))
    if pw >= w - 4 or ph >= h - 4:
        return
    x0, y0 = int(rng.integers(0, w - pw)), int(rng.integers(0, h - ph))
    paper = rng.integers(200, 250, 3)
    sub = img[y0:y0 + ph, x0:x0 + pw]
    sub[:] = paper.astype(np.uint8)
    cv2.rectangle(sub, (0, 0), (pw - 1, ph - 1), _random_colour(rng, paper), max(2, pw // 60))
    for _ in range(int(rng.integers(3, 9))):
        _draw_shape(rng, sub, paper, (0.03, 0.2))
    ink = (int(rng.integers(0, 80)), int(rng.integers(0, 80)), int(rng.integers(0, 80)))
    line_h = int(rng.uniform(0.015, 0.03) * TEXELS_PER_M)
    for row in range(int(rng.integers(2, 6))):
        y = int(ph * 0.6) + row * int(line_h * 1.6)
        if y < ph - 4:
            _draw_text(rng, sub, int(pw * 0.08), y, line_h, ink)


def _draw_books(rng: np.random.Generator, img: np.ndarray) -> None:
    """The spines of a row of books filling the face: random width, colour and height (the
    shelf boards are geometry), labels, and the odd gap."""
    h, w = img.shape[:2]
    x = 0
    while x < w:
        bw = int(rng.uniform(0.015, 0.07) * TEXELS_PER_M)
        if rng.random() < 0.08:  # gaps and leaning books break any rhythm
            x += bw
            continue
        top = int(h * rng.uniform(0.0, 0.25))
        colour = tuple(int(c) for c in rng.integers(20, 240, 3))
        cv2.rectangle(img, (x, top), (x + bw - 1, h - 1), colour, -1)
        if bw > 6 and rng.random() < 0.7:
            label = tuple(int(255 - c) for c in colour)
            ly = int(top + (h - top) * rng.uniform(0.15, 0.6))
            cv2.rectangle(img, (x + 1, ly), (x + bw - 2, ly + max(2, bw // 2)), label, -1)
        x += bw + int(rng.integers(0, 3))


def paint_texture(rng: np.random.Generator, width_m: float, height_m: float, style: str) -> np.ndarray:
    """Texture image (H, W, 3) uint8 RGB of a ``width_m`` x ``height_m`` face."""
    w = max(2, int(math.ceil(width_m * TEXELS_PER_M)))
    h = max(2, int(math.ceil(height_m * TEXELS_PER_M)))
    lo, hi, shapes, texts, posters, specks = _STYLES[style]
    base = rng.uniform(np.asarray(lo, float), np.asarray(hi, float))
    # Blotches (~40 cm) and mottling (~4 cm): bare areas still carry some structure.
    field = (base.astype(np.float32) + _smooth_noise(rng, w, h, 0.4 * TEXELS_PER_M, 14.0)
             + _smooth_noise(rng, w, h, 0.04 * TEXELS_PER_M, 7.0))
    img = np.clip(field, 0, 255).astype(np.uint8)
    area = width_m * height_m
    if style == "books":
        _draw_books(rng, img)
    else:
        _draw_specks(rng, img, base, specks)
    for _ in range(int(rng.poisson(shapes * area))):
        _draw_shape(rng, img, base, (0.02, 0.3))
    for _ in range(int(rng.poisson(texts * area))):
        colour = _random_colour(rng, base)
        _draw_text(rng, img, int(rng.integers(0, w)), int(rng.integers(0, h)),
                   rng.uniform(0.02, 0.07) * TEXELS_PER_M, colour)
    for _ in range(int(rng.poisson(posters * area))):
        _draw_poster(rng, img)
    # Soften drawn edges to about one texel so distant views do not shimmer.
    return cv2.GaussianBlur(img, (3, 3), 0.7)


# ---------------------------------------------------------------------------------------
# Room
# ---------------------------------------------------------------------------------------


def _face_frame(box: Box, axis: int, side: int, inward: bool
                ) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Affine rows (2, 4) mapping world points to texel (u, v) on one face, its world normal,
    and its size (m). Vertical faces get v pointing down so posters and text stand upright."""
    R, c, half = box.R, np.asarray(box.center), np.asarray(box.half)
    normal = R[:, axis] * (1.0 if side == 1 else -1.0) * (-1.0 if inward else 1.0)
    if axis == 2:
        u_row = np.append(R[:, 0], -R[:, 0] @ c + half[0])
        v_row = np.append(R[:, 1], -R[:, 1] @ c + half[1])
        size = (2 * half[0], 2 * half[1])
    else:
        ua = 1 - axis  # the other horizontal axis
        # u runs to the viewer's right (z x normal), so text is not mirrored.
        u_dir = np.cross([0.0, 0.0, 1.0], normal)
        u_row = np.append(u_dir, -u_dir @ c + half[ua])
        v_row = np.array([0.0, 0.0, -1.0, c[2] + half[2]])
        size = (2 * half[ua], 2 * half[2])
    return np.stack([u_row, v_row]) * TEXELS_PER_M, normal, size


def _face_style(box_index: int, box: Box, axis: int, side: int) -> str:
    if box_index == 0:
        return ("ceiling" if side == 1 else "floor") if axis == 2 else "wall"
    if box.kind == "books" and (axis, side) != (1, 1):
        return "wood"  # only the front (local +y) of a block of books shows their spines
    return box.kind


@dataclass
class Room:
    """Room shell, furniture boxes and the textures of all their faces.

    Face ``6 * b + 2 * axis + side`` belongs to box ``b`` (0 is the shell), ``side`` 1 is
    the face at +half along the box's local ``axis``. All face textures live in one flat
    texel array so rendering samples every pixel with a single gather.
    """

    size_m: tuple[float, float, float]
    seed: int
    boxes: list[Box]  # boxes[0] is the room shell (seen from inside)
    face_uv: np.ndarray  # (F, 2, 4) float32 world point -> texel coordinates
    face_normal: np.ndarray  # (F, 3) float32, pointing into free space
    face_offset: np.ndarray  # (F,) int64 first texel of the face in ``texels``
    face_width: np.ndarray  # (F,) int64 texels
    face_height: np.ndarray  # (F,) int64 texels
    texels: np.ndarray  # (T, 3) uint8 RGB

    @classmethod
    def build(cls, seed: int, size_m: tuple[float, float, float], n_furniture: int) -> "Room":
        size_m = tuple(float(s) for s in size_m)  # type: ignore[assignment]
        if any(s < m for s, m in zip(size_m, MIN_ROOM_SIZE_M)):
            raise ValueError(f"room_size_m {size_m} is smaller than the minimum {MIN_ROOM_SIZE_M}")
        Lx, Ly, Lz = size_m
        shell = Box((0.0, 0.0, Lz / 2), (Lx / 2, Ly / 2, Lz / 2), 0.0, "shell")
        pieces = _place_furniture(np.random.default_rng([seed, 1]), size_m, n_furniture)
        boxes = [shell] + [part for piece in pieces for part in piece]
        room = cls(size_m, seed, boxes, *_bake_faces(seed, boxes))
        for array in (room.face_uv, room.face_normal, room.face_offset, room.face_width,
                      room.face_height, room.texels):
            array.flags.writeable = False  # rooms are shared through _cached_room
        return room

    @classmethod
    def from_config(cls, config: SyntheticConfig) -> "Room":
        """The room of a config; built once per process (building takes about a second)."""
        return _cached_room(config.seed, tuple(float(s) for s in config.room_size_m),
                            config.n_furniture)

    @property
    def furniture(self) -> list[Box]:
        return self.boxes[1:]

    def clearance(self, point: np.ndarray) -> float:
        """Distance (m) from a point inside the room to the nearest surface."""
        p = np.asarray(point, float)
        shell = self.boxes[0]
        walls = np.asarray(shell.half) - np.abs(p - np.asarray(shell.center))
        return float(min([walls.min()] + [b.distance_to(p) for b in self.furniture]))


def _bake_faces(seed: int, boxes: list[Box]) -> tuple[np.ndarray, ...]:
    """Per-face texel mapping, normal and texture (in one flat texel array) of all boxes:
    (face_uv, face_normal, face_offset, face_width, face_height, texels) as in Room."""
    uv, normals, offsets, widths, heights, chunks = [], [], [], [], [], []
    offset = 0
    for b, box in enumerate(boxes):
        for axis in range(3):
            for side in range(2):
                rows, normal, size = _face_frame(box, axis, side, inward=(b == 0))
                # One generator per face: textures do not change when furniture is added.
                rng = np.random.default_rng([seed, 2, b, axis, side])
                tex = paint_texture(rng, size[0], size[1], _face_style(b, box, axis, side))
                uv.append(rows)
                normals.append(normal)
                offsets.append(offset)
                heights.append(tex.shape[0])
                widths.append(tex.shape[1])
                chunks.append(tex.reshape(-1, 3))
                offset += tex.shape[0] * tex.shape[1]
    return (np.array(uv, np.float32), np.array(normals, np.float32), np.array(offsets, np.int64),
            np.array(widths, np.int64), np.array(heights, np.int64), np.concatenate(chunks))


@lru_cache(maxsize=2)
def _cached_room(seed: int, size_m: tuple[float, float, float], n_furniture: int) -> Room:
    return Room.build(seed, size_m, n_furniture)


# ---------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------
# Sensor models
# ---------------------------------------------------------------------------------------


def _depth_edges(depth_m: np.ndarray) -> np.ndarray:
    """Pixels next to a depth discontinuity (where real sensors return nothing)."""
    kernel = np.ones((3, 3), np.uint8)
    spread = cv2.dilate(depth_m, kernel) - cv2.erode(depth_m, kernel)
    return spread > 0.02 + 0.03 * depth_m


def _dropout_mask(rng: np.random.Generator, shape: tuple[int, int], fraction: float) -> np.ndarray:
    """Random holes as small blobs covering about ``fraction`` of the image."""
    mask = np.zeros(shape, np.uint8)
    if fraction <= 0:
        return mask.astype(bool)
    radii_choices = np.arange(1, 5)
    mean_area = float(np.mean(np.pi * radii_choices**2))
    n = int(rng.poisson(fraction * shape[0] * shape[1] / mean_area))
    us = rng.integers(0, shape[1], n)
    vs = rng.integers(0, shape[0], n)
    radii = rng.choice(radii_choices, n)
    for u, v, r in zip(us, vs, radii):
        cv2.circle(mask, (int(u), int(v)), int(r), 1, -1)
    return mask.astype(bool)


def sensor_depth(depth_m: np.ndarray, config: SyntheticConfig, rng: np.random.Generator) -> np.ndarray:
    """Kinect-like raw depth (uint16, TUM scale 5000, 0 = none) from a noise-free depth."""
    z = depth_m.astype(np.float64)
    holes = _dropout_mask(rng, z.shape, config.depth_dropout) | _depth_edges(depth_m)
    sigma = config.depth_noise_a + config.depth_noise_b * (z - MIN_SENSOR_DEPTH_M) ** 2
    noisy = z + rng.standard_normal(z.shape) * sigma
    valid = ((z >= MIN_SENSOR_DEPTH_M) & (z <= config.max_depth_m) & ~holes
             & (noisy >= MIN_SENSOR_DEPTH_M) & (noisy <= config.max_depth_m))
    raw = np.clip(np.rint(noisy * DEPTH_SCALE), 1, 65535).astype(np.uint16)
    raw[~valid] = 0
    return raw


def sensor_rgb(rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Colour image with small Gaussian pixel noise."""
    noise = rng.standard_normal(rgb.shape, dtype=np.float32) * np.float32(RGB_NOISE_SIGMA)
    return np.clip(rgb.astype(np.float32) + noise + 0.5, 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------
# Robot trajectories
# ---------------------------------------------------------------------------------------


def robot_timestamps(config: SyntheticConfig, robot: int) -> np.ndarray:
    """Frame times (s) of one robot, rounded to the 6 decimals of the file names."""
    return np.round(1000.0 + 100.0 * robot + np.arange(config.frames_per_robot) / config.fps, 6)


def _robot_pose(t: np.ndarray, robot: int, n_robots: int, size_m: tuple[float, float, float]
                ) -> np.ndarray:
    """Poses (N, 4, 4) at times ``t`` (s from the robot's start).

    Robot k (offset ``k`` from the middle of the group) starts looking at the middle of the
    +y wall (turned a little towards the group's middle, so the views cross there), then
    turns towards its own side by up to _TURN_DEG and
    back (periodic, so any length stays bounded), drifting sideways the same way. Every
    motion is a sinusoid, so velocity is smooth and starts at zero."""
    k = robot - (n_robots - 1) / 2
    away = float(np.sign(k))  # -1: the -x side, turning left (yaw up); +1: the +x side
    x0, y0 = k * _ROBOT_SPACING_M, _robot_base_y(size_m)
    if away != 0:
        x = x0 + away * _ROBOT_DRIFT_M * (1 - np.cos(0.7 * t)) / 2
        yaw = (90.0 - _START_SPREAD_DEG * k) - away * _TURN_DEG * (1 - np.cos(_TURN_RATE * t)) / 2
    else:  # the middle robot of an odd group looks both ways
        x = x0 + 0.25 * np.sin(0.5 * t)
        yaw = 90.0 + _TURN_DEG / 2 * np.sin(_TURN_RATE * t)
    y = y0 + _ROBOT_SWAY_M * np.sin(0.7 * t + 1.3 * robot)
    z = 1.15 + 0.12 * robot + 0.05 * np.sin(0.9 * t + robot)
    tilt_down = 8.0 + 3.0 * np.sin(0.7 * t + 0.9 * robot)
    roll = 2.0 * np.sin(0.9 * t + 2.1 * robot)
    # Body frame: x forward, y left, z up; intrinsic z-y-x = yaw, then pitch (+ = nose down),
    # then roll. The OpenCV camera looks along body x with image x = -body y, image y = -body z.
    R_world_body = Rotation.from_euler("ZYX", np.stack([yaw, tilt_down, roll], axis=1),
                                       degrees=True).as_matrix()
    R_body_camera = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = R_world_body @ R_body_camera
    poses[:, :3, 3] = np.stack([x, y, z], axis=1)
    return poses


def robot_trajectories(config: SyntheticConfig) -> list[np.ndarray]:
    """Ground-truth T_world_camera (frames_per_robot, 4, 4) of every robot."""
    if not 1 <= config.n_robots <= _MAX_ROBOTS_IN_ZONE:
        raise ValueError(f"n_robots must be 1..{_MAX_ROBOTS_IN_ZONE}, got {config.n_robots}")
    t = np.arange(config.frames_per_robot) / config.fps
    return [_robot_pose(t, r, config.n_robots, tuple(config.room_size_m))
            for r in range(config.n_robots)]


# ---------------------------------------------------------------------------------------
# Scene folders
# ---------------------------------------------------------------------------------------


def scene_camera(config: SyntheticConfig) -> Camera:
    return Camera(config.fx, config.fy, config.cx, config.cy, width=config.width,
                  height=config.height, distortion=(), depth_scale=DEPTH_SCALE)


def robot_folder_name(robot: int) -> str:
    return f"robot_{robot}"


def _config_json(config: SyntheticConfig) -> dict:
    # Through JSON so tuples compare equal to the lists read back from scene.json.
    return json.loads(json.dumps(dataclasses.asdict(config)))


def _write_list(path: Path, header: str, times: np.ndarray, folder: str) -> None:
    lines = [f"# {header}", f"# file: '{path.parent.name}' (fleetslam synthetic)",
             "# timestamp filename"]
    lines += [f"{t:.6f} {folder}/{t:.6f}.png" for t in times]
    path.write_text("\n".join(lines) + "\n")


def _frame_rng(config: SyntheticConfig, robot: int, frame: int) -> np.random.Generator:
    return np.random.default_rng([config.seed, 3, robot, frame])


def _write_robot(folder: Path, room: Room, camera: Camera, config: SyntheticConfig, robot: int,
                 poses: np.ndarray, tick: Callable[[], None]) -> None:
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    times = robot_timestamps(config, robot)
    for i, (t, T) in enumerate(zip(times, poses)):
        rgb, depth = render(room, camera, T)
        rng = _frame_rng(config, robot, i)
        raw = sensor_depth(depth, config, rng)
        noisy = sensor_rgb(rgb, rng)
        name = f"{t:.6f}.png"
        if not cv2.imwrite(str(folder / "rgb" / name), cv2.cvtColor(noisy, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{folder / 'rgb' / name}: cannot write image")
        if not cv2.imwrite(str(folder / "depth" / name), raw):
            raise OSError(f"{folder / 'depth' / name}: cannot write image")
        tick()
    _write_list(folder / "rgb.txt", "color images", times, "rgb")
    _write_list(folder / "depth.txt", "depth maps", times, "depth")
    write_tum_trajectory(folder / "groundtruth.txt", times, poses,
                         comment=f"ground truth trajectory\nfile: '{folder.name}' (fleetslam synthetic, "
                                 f"T_world_camera, OpenCV camera axes)")
    (folder / "camera.json").write_text(camera.to_json() + "\n")


def _scene_record(config: SyntheticConfig, room: Room) -> dict:
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "seed": config.seed,
        "config": _config_json(config),
        "robots": [robot_folder_name(r) for r in range(config.n_robots)],
        "frames_per_robot": config.frames_per_robot,
        "world_frame": "z up, floor at z=0, room centred on x=y=0; poses are T_world_camera",
        "room": {"size_m": list(room.size_m), "boxes": [b.to_dict() for b in room.boxes]},
    }


def _looks_like_scene(path: Path) -> bool:
    """Only folders we wrote (or empty ones) may be replaced."""
    if not path.exists():
        return True
    if not path.is_dir():
        return False
    entries = list(path.iterdir())
    return not entries or (path / "scene.json").exists()


def _remove_stale_partials(out_dir: Path) -> None:
    """Temporary folders left by killed runs (their process is gone)."""
    leftovers = [*out_dir.parent.glob(f".{out_dir.name}.partial-*"),
                 *out_dir.parent.glob(f".{out_dir.name}.old-*")]
    for tmp in leftovers:
        try:
            pid = int(tmp.name.rsplit("-", 1)[1])
            os.kill(pid, 0)
        except ProcessLookupError:
            shutil.rmtree(tmp, ignore_errors=True)
        except (ValueError, PermissionError):
            pass


def generate_scene(out_dir: Path, config: SyntheticConfig,
                   progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """Write the scene to ``out_dir`` (replacing a previous scene there); returns the robot
    folders. Everything is written to a temporary sibling folder that is renamed into place
    at the end, so an interrupted run never leaves a folder that looks complete."""
    out_dir = Path(out_dir)
    if not _looks_like_scene(out_dir):
        raise FileExistsError(f"{out_dir}: exists and is not a synthetic scene; not replacing it")
    poses = robot_trajectories(config)
    room = Room.from_config(config)
    camera = scene_camera(config)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_partials(out_dir)
    tmp = out_dir.parent / f".{out_dir.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    total = config.n_robots * config.frames_per_robot
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    try:
        tmp.mkdir()
        for r in range(config.n_robots):
            _write_robot(tmp / robot_folder_name(r), room, camera, config, r, poses[r], tick)
        (tmp / "scene.json").write_text(json.dumps(_scene_record(config, room), indent=2) + "\n")
        if out_dir.exists():
            old = out_dir.parent / f".{out_dir.name}.old-{os.getpid()}"
            out_dir.rename(old)
            tmp.rename(out_dir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return [out_dir / robot_folder_name(r) for r in range(config.n_robots)]


def _count_entries(path: Path) -> int:
    return sum(1 for line in path.read_text().splitlines() if line.strip() and not line.startswith("#"))


def scene_matches(out_dir: Path, config: SyntheticConfig) -> bool:
    """True if ``out_dir`` holds a complete scene generated with exactly this config."""
    out_dir = Path(out_dir)
    try:
        record = json.loads((out_dir / "scene.json").read_text())
        if (record.get("format") != FORMAT_NAME or record.get("format_version") != FORMAT_VERSION
                or record.get("config") != _config_json(config)):
            return False
        for name in record["robots"]:
            folder = out_dir / name
            for f in ("groundtruth.txt", "camera.json"):
                if not (folder / f).is_file():
                    return False
            for f in ("rgb.txt", "depth.txt"):
                if _count_entries(folder / f) != config.frames_per_robot:
                    return False
        return len(record["robots"]) == config.n_robots
    except (OSError, ValueError, KeyError, TypeError):
        return False


def ensure_scene(out_dir: Path, config: SyntheticConfig,
                 progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """The robot folders of the scene in ``out_dir``, generating it unless a complete scene
    with the same config is already there."""
    out_dir = Path(out_dir)
    if scene_matches(out_dir, config):
        total = config.n_robots * config.frames_per_robot
        if progress is not None:
            progress(total, total)
        return [out_dir / robot_folder_name(r) for r in range(config.n_robots)]
    return generate_scene(out_dir, config, progress)
