"""Furniture made of boxes: the size of a piece of each kind and the boxes it consists of
(local +y is its front).

Every kind has depth relief (recessed plinths, shelf boards and books, overhanging tops,
objects on top), so pieces differ in 3D, not only in texture, and the wall behind them is
no bare plane. Where pieces stand is up to layout.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from fleetslam.datasets.synthetic.box import Box

_RUN_MODULES = ("shelf", "cabinet", "sideboard", "wardrobe")  # of a "run" (storage wall)
_PANEL_M = 0.02  # board thickness of shelves


def furniture_size(rng: np.random.Generator, kind: str, room_height: float
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


def furniture_parts(rng: np.random.Generator, kind: str, center_xy: np.ndarray, yaw: float,
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
            _, depth, height = furniture_size(rng, module, room_height)
            centre = center_xy + R @ np.array([x + width / 2, -d / 2 + depth / 2])
            parts += furniture_parts(rng, module, centre, yaw, (float(width), depth, height),
                                     room_height)
            x += width
    else:  # pillar: the wall steps out, floor to ceiling
        parts.append(at((0, 0), h / 2, (w / 2, d / 2, h / 2), "wall"))
    return parts
