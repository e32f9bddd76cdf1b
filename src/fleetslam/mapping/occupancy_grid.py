"""A 2D occupancy grid of a dense map, in nav2 ``map_server``'s format (a PGM image and its
YAML: image, mode, resolution, origin, negate, occupied_thresh, free_thresh), so a robot
can navigate in what fleetslam mapped.

- Up: the floor plane found in the map (RANSAC among the lowest points, its normal within
  ``floor_max_tilt_deg`` of the cameras' up, the cameras above it); where no floor shows,
  the camera mounting's up where one is given (map_frame.py), else ``[grid] up`` (a
  direction in the map frame) with the floor at the lowest points. The grid says which it
  used. (A robot's own TF knows up too: not read here, the cloud has no TF.)
- The grid's frame is level (REP 103: z up, x the first camera's view along the floor,
  origin under the first camera on the floor); ``T_map_grid`` places it in the map frame.
- Occupied: at least ``occupied_min_points`` map points in a cell between ``min_height_m``
  and ``max_height_m`` above the floor (the robot's height band). Free: cells a depth ray
  crossed from its keyframe's camera within the band (rays leave the band above a table,
  so the floor under it stays unknown). Unknown otherwise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fleetslam.config import GridConfig
from fleetslam.transforms import invert, transform_points

# map_server's trinary image: the values its map_saver writes.
OCCUPIED, FREE, UNKNOWN = 0, 254, 205
# The YAML's thresholds: map_server reads a pixel p as occupied when (255 - p) / 255 exceeds
# occupied_thresh, free below free_thresh, unknown between. 0.196 (ROS 1 map_saver's) keeps
# 205 (0.19608) unknown; 0.25 would read it as free.
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196
# RANSAC for the floor: tries, and the points it samples from.
_RANSAC_TRIES = 300
_RANSAC_POINTS = 20_000


@dataclass
class OccupancyGrid:
    image: np.ndarray  # H x W uint8 (OCCUPIED, FREE, UNKNOWN), row 0 at the largest y
    resolution: float
    origin_xy: tuple[float, float]  # the lower-left cell's corner in the grid frame
    T_map_grid: np.ndarray  # 4 x 4: the level grid frame in the map frame
    up_source: str  # "floor plane" or "config"

    @property
    def occupied(self) -> int:
        return int((self.image == OCCUPIED).sum())

    @property
    def free(self) -> int:
        return int((self.image == FREE).sum())

    def ros_cells(self) -> np.ndarray:
        """nav_msgs/OccupancyGrid's data: -1 unknown, 0 free, 100 occupied, row 0 at the
        origin (the image's bottom row)."""
        cells = np.full(self.image.shape, -1, np.int8)
        cells[self.image == FREE] = 0
        cells[self.image == OCCUPIED] = 100
        return cells[::-1].copy()

    @property
    def T_map_origin(self) -> np.ndarray:
        """The lower-left cell's corner (OccupancyGrid's origin) in the map frame."""
        T = self.T_map_grid.copy()
        T[:3, 3] = transform_points(self.T_map_grid,
                                    np.array([[*self.origin_xy, 0.0]]))[0]
        return T

    def summary(self, image: str) -> dict:
        return {"image": image, "resolution_m": self.resolution,
                "size": [int(self.image.shape[1]), int(self.image.shape[0])],
                "origin": [self.origin_xy[0], self.origin_xy[1], 0.0],
                "up_source": self.up_source, "T_map_grid": self.T_map_grid.tolist(),
                "occupied_cells": self.occupied, "free_cells": self.free}


def unit(v: np.ndarray) -> np.ndarray | None:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-9 else None


def find_floor(points: np.ndarray, camera_poses: np.ndarray, cfg: GridConfig,
               known_up: np.ndarray | None = None) -> tuple[np.ndarray, float, str]:
    """(up, floor height along up, source): the floor plane's, else ``known_up`` (the
    camera's mounting), else the configured up."""
    configured = unit(np.asarray(cfg.up, np.float64))
    if configured is None:
        raise ValueError(f"[grid] up = {list(cfg.up)} is not a direction (all zero)")
    fallback = "config"
    # A camera's image y points down: the cameras' mean -y is roughly up.
    guess = unit(-camera_poses[:, :3, 1].mean(axis=0)) if len(camera_poses) else None
    guess = configured if guess is None else guess
    if known_up is not None:
        configured = guess = unit(np.asarray(known_up, np.float64))
        fallback = "camera mounting"
    centres = camera_poses[:, :3, 3]
    if len(points) >= cfg.floor_min_points:
        rng = np.random.default_rng(0)
        heights = points @ guess
        low = points[heights <= np.percentile(heights, 30)]
        if len(low) > _RANSAC_POINTS:
            low = low[rng.choice(len(low), _RANSAC_POINTS, replace=False)]
        best, best_count = None, 0
        cos_tilt = np.cos(np.radians(cfg.floor_max_tilt_deg))
        for _ in range(_RANSAC_TRIES):
            a, b, c = low[rng.choice(len(low), 3, replace=False)]
            n = unit(np.cross(b - a, c - a))
            if n is None or abs(float(n @ guess)) < cos_tilt:
                continue
            n = n if n @ guess > 0 else -n
            count = int((np.abs((low - a) @ n) < cfg.floor_inlier_m).sum())
            if count > best_count:
                best, best_count = (n, float(a @ n)), count
        if best is not None and best_count >= cfg.floor_min_points:
            n, d = best
            # Refined on every point near it (not only the lowest by the guess), closer
            # each time: a wall's foot within the first band pulls less.
            for band in (cfg.floor_inlier_m, cfg.floor_inlier_m / 2):
                inliers = points[np.abs(points @ n - d) < band]
                centre = inliers.mean(axis=0)
                refined = unit(np.linalg.svd(inliers - centre, full_matrices=False)[2][2])
                if refined is None:
                    break
                n = refined if refined @ guess > 0 else -refined
                d = float(centre @ n)
            # Every horizontal surface gives up; the floor is the lowest of them (the plane
            # found may be a kitchen counter): the lowest height where points pile up.
            d = _lowest_surface(points @ n, d, cfg)
            if not len(centres) or (centres @ n - d).min() > cfg.min_height_m:
                return n, d, "floor plane"
    heights = points @ configured if len(points) else np.zeros(1)
    return configured, float(np.percentile(heights, 1)), fallback


def _lowest_surface(heights: np.ndarray, found: float, cfg: GridConfig) -> float:
    """The height of the lowest horizontal surface: the lowest slab floor_inlier_m thick
    holding floor_min_points points, and twice the points of each slab of the 30 cm above
    it (a wall's foot holds as many as the wall above it); ``found`` if none is lower."""
    slab = cfg.floor_inlier_m
    lo = float(heights.min())
    counts = np.bincount(((heights - lo) / slab).astype(np.int64))
    above = int(round(0.3 / slab))
    for i in range(len(counts)):
        if lo + i * slab >= found:
            break
        over = counts[i + 2:i + 2 + above]
        if counts[i] >= cfg.floor_min_points and \
                counts[i] >= 2 * (over.mean() if len(over) else 0.0):
            near = heights[np.abs(heights - (lo + (i + 0.5) * slab)) < slab]
            return float(np.median(near))
    return found


def level_frame(up: np.ndarray, floor: float, camera_poses: np.ndarray) -> np.ndarray:
    """T_map_grid: z up, x the first camera's view along the floor, the origin on the floor
    under the first camera."""
    first = camera_poses[0] if len(camera_poses) else np.eye(4)
    x = None
    for axis in (first[:3, 2], first[:3, 0], np.array([1.0, 0, 0]), np.array([0, 1.0, 0])):
        x = unit(axis - (axis @ up) * up)
        if x is not None:
            break
    assert x is not None
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = x, np.cross(up, x), up
    centre = first[:3, 3]
    T[:3, 3] = centre - (centre @ up - floor) * up
    return T


def _unique_cells(cells: np.ndarray) -> np.ndarray:
    """The distinct rows of ``cells`` (N x 2 int64), packed into one int64 each for a 1-D
    unique (np.unique over rows is several times slower)."""
    packed = np.unique((cells[:, 0] << 32) + (cells[:, 1] + (1 << 31)))
    return np.column_stack([packed >> 32,
                            (packed & 0xFFFFFFFF) - (1 << 31)])


def _ray_cells(origin: np.ndarray, ends: np.ndarray, cfg: GridConfig) -> np.ndarray:
    """The grid-frame xy of samples along each ray from ``origin`` to ``ends`` where the ray
    is within the height band's top and at most max_range_m long, every half cell, stopping
    half a cell before an end that is an obstacle (or beyond the range)."""
    step = cfg.resolution_m / 2
    d = ends - origin
    length = np.linalg.norm(d, axis=1)
    keep = length > step
    d, length, ends = d[keep], length[keep], ends[keep]
    # The part of each ray below the band's top: t in [0, t_top] (the camera is in it).
    with np.errstate(divide="ignore", invalid="ignore"):
        t_top = np.where(d[:, 2] > 0, (cfg.max_height_m - origin[2]) / d[:, 2], np.inf)
    obstacle = ends[:, 2] >= cfg.min_height_m
    t_end = np.where(obstacle, 1.0 - cfg.resolution_m / length, 1.0)
    t_max = np.clip(np.minimum(np.minimum(t_top, t_end), cfg.max_range_m / length), 0.0, 1.0)
    reach = t_max * length
    counts = np.floor(reach / step).astype(np.int64)
    ok = counts > 0
    if origin[2] > cfg.max_height_m or not ok.any():
        return np.zeros((0, 2))
    d, length, counts = d[ok], length[ok], counts[ok]
    ray = np.repeat(np.arange(len(counts)), counts)
    k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    t = (k + 0.5) * step / length[ray]
    return origin[:2] + t[:, None] * d[ray, :2]


def occupancy_grid(scans: Sequence[tuple[np.ndarray, np.ndarray]], camera_poses: np.ndarray,
                   cfg: GridConfig, known_up: np.ndarray | None = None) -> OccupancyGrid:
    """The grid of keyframe scans, each (points in the map frame, its camera centre);
    ``camera_poses`` (K x 4 x 4, the keyframes', first one first) give the guess of up and
    the grid frame's heading; ``known_up`` (from a mounting) replaces the guess."""
    points = np.vstack([p for p, _ in scans]) if scans else np.zeros((0, 3))
    up, floor, source = find_floor(points, camera_poses, cfg, known_up)
    T_map_grid = level_frame(up, floor, camera_poses)
    T_grid_map = invert(T_map_grid)
    res = cfg.resolution_m
    # Cells as integer (x, y) keys, the free ones made unique per scan: a scan's rays share
    # most of their cells near the camera, and stacking every sample first took most of
    # the grid's time (0.87 s for 38 keyframes of 7-Scenes).
    occupied_cells, free_cells = [np.zeros((0, 2), np.int64)], [np.zeros((0, 2), np.int64)]
    for scan_points, centre in scans:
        if not len(scan_points):
            continue
        local = transform_points(T_grid_map, np.asarray(scan_points, np.float64))
        origin = transform_points(T_grid_map, np.asarray(centre, np.float64)[None])[0]
        band = (local[:, 2] >= cfg.min_height_m) & (local[:, 2] <= cfg.max_height_m)
        keys = np.floor(local[:, :2] / res).astype(np.int64)
        occupied_cells.append(keys[band])
        # One ray per end cell and kind (an obstacle or not): from one camera, rays to one
        # cell cross the same cells; of the others, the lowest end's ray stays longest
        # within the band (one to the floor all the way, one to the ceiling leaves it).
        order = np.lexsort((local[:, 2], band, keys[:, 1], keys[:, 0]))
        first = np.ones(len(order), bool)
        sorted_keys = np.column_stack([keys[order], band[order]])
        first[1:] = (sorted_keys[1:] != sorted_keys[:-1]).any(axis=1)
        samples = np.floor(_ray_cells(origin, local[order[first]], cfg) / res).astype(np.int64)
        free_cells.append(_unique_cells(samples))
    occupied = np.vstack(occupied_cells)
    free = np.vstack(free_cells)
    both = np.vstack([occupied, free, np.zeros((1, 2), np.int64)])  # the origin: a 1-cell grid
    lo = both.min(axis=0) - cfg.margin_cells
    hi = both.max(axis=0) + cfg.margin_cells
    width, height = (hi - lo + 1).astype(int)
    image = np.full((height, width), UNKNOWN, np.uint8)

    def cells(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = keys - lo
        return height - 1 - c[:, 1], c[:, 0]

    image[cells(free)] = FREE
    if len(occupied):
        rows, cols = cells(occupied)
        counts = np.bincount(rows * width + cols, minlength=height * width)
        image[(counts >= cfg.occupied_min_points).reshape(height, width)] = OCCUPIED
    return OccupancyGrid(image, res, (float(lo[0] * res), float(lo[1] * res)), T_map_grid,
                         source)


def read_nav2_map(yaml_path: Path, T_map_grid: np.ndarray, up_source: str = ""
                  ) -> OccupancyGrid:
    """A grid ``write_nav2_map`` wrote (its image, resolution, origin); ValueError naming
    the file and what is wrong."""
    fields = {}
    for line in Path(yaml_path).read_text().splitlines():
        key, _, value = line.partition(":")
        if value and not line.startswith("#"):
            fields[key.strip()] = value.strip()
    try:
        resolution = float(fields["resolution"])
        origin = [float(v) for v in fields["origin"].strip("[]").split(",")]
        raw = (Path(yaml_path).parent / fields["image"]).read_bytes()
        magic, width, height, depth, *_ = raw.split(maxsplit=4)
        width, height = int(width), int(height)
        if magic != b"P5" or int(depth) != 255 or len(raw) < width * height:
            raise ValueError("not an 8-bit binary PGM")
        image = np.frombuffer(raw[-width * height:], np.uint8).reshape(height, width)
    except (KeyError, ValueError, OSError) as exc:
        raise ValueError(f"{yaml_path}: not a nav2 map fleetslam wrote: {exc}") from None
    return OccupancyGrid(image.copy(), resolution, (origin[0], origin[1]),
                         np.asarray(T_map_grid, np.float64), up_source)


def write_nav2_map(base: Path, grid: OccupancyGrid, frame: str) -> Path:
    """``base``.pgm and ``base``.yaml as nav2's map_saver writes them; the YAML's comments
    say which frame the grid is in and how it lies in it. Returns the YAML's path."""
    base.parent.mkdir(parents=True, exist_ok=True)
    pgm, yaml = base.with_suffix(".pgm"), base.with_suffix(".yaml")
    height, width = grid.image.shape
    pgm.write_bytes(f"P5\n{width} {height}\n255\n".encode() + grid.image.tobytes())
    T = grid.T_map_grid
    rows = "\n".join(f"#   [{', '.join(f'{v:.9f}' for v in row)}]" for row in T)
    yaml.write_text(
        f"# fleetslam occupancy grid: {grid.occupied} occupied, {grid.free} free cells; up "
        f"from the {grid.up_source}.\n"
        f"# The grid's frame is level (z up) on the floor; in {frame} it lies at "
        f"T_map_grid =\n{rows}\n"
        f"image: {pgm.name}\n"
        f"mode: trinary\n"
        f"resolution: {grid.resolution}\n"
        f"origin: [{grid.origin_xy[0]:.6f}, {grid.origin_xy[1]:.6f}, 0.0]\n"
        f"negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n")
    return yaml
