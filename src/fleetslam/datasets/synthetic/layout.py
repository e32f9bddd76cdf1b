"""Room layout: where the furniture stands, along the walls robots look at, never near the
zone the robots walk in (trajectories.robot_zone).

The common region (the middle of the +y wall, which every robot looks at first) is
furnished so that the overlap pins down all six degrees of freedom of a map merge: a tall
piece and a shelf flank it (both robots see their inner sides), a sideboard with a wall
unit above it stands between them, a table with things on it and a stack of boxes stand in
front at other depths; runs of storage modules line the side walls the robots turn to;
every piece has depth relief (recessed plinths, shelf boards and books, overhanging tops).
A bare wall and floor let one map slide along the other: on such a scene the
best-overlapping wrong pose, 1.4 m along the wall, scored better than the truth, and no ICP
can fix that.
"""

from __future__ import annotations

import math

import numpy as np

from fleetslam.datasets.synthetic.box import Box
from fleetslam.datasets.synthetic.furniture import furniture_parts, furniture_size
from fleetslam.datasets.synthetic.trajectories import robot_base_y, robot_zone

# Furniture keeps at least this distance (m) from the area robots walk in.
ROBOT_CLEARANCE_M = 0.7
# Furniture kinds (each built of boxes with depth relief in furniture).
_KINDS = ("table", "shelf", "cabinet", "sideboard", "boxes", "wardrobe", "wall_unit", "pillar")
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


def _rects_overlap(a: tuple, b: tuple) -> bool:
    return a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]


def _rect_gap(a: tuple, b: tuple) -> float:
    dx = max(b[0] - a[1], a[0] - b[1], 0.0)
    dy = max(b[2] - a[3], a[2] - b[3], 0.0)
    return math.hypot(dx, dy)


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
        y0 = robot_base_y(size_m)
        beyond = (0, half, Lx / 2) if side > 0 else (0, -Lx / 2, -half)
        # y from the robots' line to the +y wall (the +x wall's tangent points to -y).
        front = (2, -Ly / 2, -y0) if side > 0 else (1, y0, Ly / 2)
        return [beyond, front]
    # Anywhere robots look: the +y wall and the side walls in front of the robots' line.
    y0 = robot_base_y(size_m)
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
    size = furniture_size(rng, kind, Lz)
    if where == "shared free":
        half = min(_SHARED_HALF_WIDTH_M, Lx / 2)
        y_lo = robot_zone(size_m)[3] + ROBOT_CLEARANCE_M
        center = np.array([rng.uniform(-half + 0.3, half - 0.3), rng.uniform(y_lo, Ly / 2 - 0.5)])
        return furniture_parts(rng, kind, center, float(rng.uniform(-0.6, 0.6)), size, Lz)
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
    return furniture_parts(rng, kind, point + along * tangent + off * normal, yaw + jitter, size,
                           Lz)


def _footprint(parts: list[Box]) -> tuple[float, float, float, float]:
    rects = np.array([p.footprint() for p in parts])
    return (rects[:, 0].min(), rects[:, 1].max(), rects[:, 2].min(), rects[:, 3].max())


def place_furniture(rng: np.random.Generator, size_m: tuple[float, float, float],
                    n_furniture: int) -> list[list[Box]]:
    """Up to ``n_furniture`` pieces, not overlapping, none near the robots' zone.

    The first ones (_SHARED_PIECES) furnish the view every robot starts with, the middle of
    the +y wall: pieces of different shapes and heights at different depths, so that maps
    overlapping there fit together in one way only (a bare wall, floor and one table let a
    map slide along the wall). The rest stand against the walls robots turn to, alternately
    a run of storage modules on the -x side, one on the +x side and any kind anywhere."""
    Lx, Ly, _ = size_m
    zone = robot_zone(size_m)
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
