"""The Room: shell, furniture boxes (layout) and the textures of all their faces
(textures), baked once into flat arrays that rendering samples with a single gather; built
once per process per config."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from fleetslam.config import SyntheticConfig
from fleetslam.datasets.synthetic.box import Box
from fleetslam.datasets.synthetic.layout import place_furniture
from fleetslam.datasets.synthetic.textures import TEXELS_PER_M, paint_texture

MIN_ROOM_SIZE_M = (4.0, 3.5, 2.2)


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
        pieces = place_furniture(np.random.default_rng([seed, 1]), size_m, n_furniture)
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
