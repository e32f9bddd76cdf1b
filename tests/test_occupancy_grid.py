"""The nav2 map every run writes (mapping/occupancy_grid.py): map_server's format, occupied
cells on the dense map's points, and the synthetic scene's known floor plan (walls and
furniture occupied, the room free) recovered; ground truth only places the known plan."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml

from fleetslam.config import GridConfig
from fleetslam.io.ply import read_ply
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.mapping.occupancy_grid import (
    _unique_cells,
    FREE,
    OCCUPIED,
    UNKNOWN,
    occupancy_grid,
    write_nav2_map,
)
from fleetslam.transforms import invert, make_T, rotation_exp, transform_points


def _load(yaml_path):
    meta = yaml.safe_load(yaml_path.read_text())
    image = cv2.imread(str(yaml_path.parent / meta["image"]), cv2.IMREAD_UNCHANGED)
    return meta, image


def _cells(meta, image, points_grid):
    res = meta["resolution"]
    col = np.floor((points_grid[:, 0] - meta["origin"][0]) / res).astype(int)
    row = image.shape[0] - 1 - np.floor((points_grid[:, 1] - meta["origin"][1]) / res
                                        ).astype(int)
    inside = (row >= 0) & (row < image.shape[0]) & (col >= 0) & (col < image.shape[1])
    return row, col, inside


def _near(mask: np.ndarray) -> np.ndarray:
    """Cells within one cell (8-neighbourhood) of ``mask``."""
    return cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def test_the_run_writes_maps_nav2_loads(synthetic_run):
    out, summary = synthetic_run
    for yaml_path, entry in ((out / "global_map.yaml", summary["merge"]["grid"]),
                             (out / "r0" / "map.yaml", None)):
        meta, image = _load(yaml_path)
        assert set(meta) == {"image", "mode", "resolution", "origin", "negate",
                             "occupied_thresh", "free_thresh"}
        assert meta["mode"] == "trinary" and meta["negate"] == 0 and len(meta["origin"]) == 3
        assert image.dtype == np.uint8 and image.ndim == 2
        assert set(np.unique(image)) <= {OCCUPIED, FREE, UNKNOWN}
        # map_server's reading: occupied above occupied_thresh, free below free_thresh.
        occ = (255 - image.astype(float)) / 255
        assert ((occ > meta["occupied_thresh"]) == (image == OCCUPIED)).all()
        assert ((occ < meta["free_thresh"]) == (image == FREE)).all()
        if entry is not None:
            assert entry["size"] == [image.shape[1], image.shape[0]]
            assert entry["up_source"] == "floor plane"
            assert entry["occupied_cells"] == int((image == OCCUPIED).sum()) > 100


def test_occupied_cells_lie_on_the_dense_maps_points(synthetic_run):
    """The PLY's points in the height band, projected into the grid, hit the occupied
    cells: nearly every occupied cell has such a point in it or next to it, and cells
    with several such points are occupied."""
    out, summary = synthetic_run
    meta, image = _load(out / "global_map.yaml")
    grid = summary["merge"]["grid"]
    points, _ = read_ply(out / "global_map.ply")
    local = transform_points(invert(np.array(grid["T_map_grid"])), points)
    cfg = GridConfig()
    band = local[(local[:, 2] >= cfg.min_height_m) & (local[:, 2] <= cfg.max_height_m)]
    row, col, inside = _cells(meta, image, band)
    assert inside.all()
    hits = np.zeros(image.shape, np.int64)
    np.add.at(hits, (row, col), 1)
    occupied = image == OCCUPIED
    assert (occupied & _near(hits > 0)).sum() >= 0.95 * occupied.sum()
    assert (occupied[hits >= 3]).mean() >= 0.9


def _known_plan(summary, folders, meta, image, out):
    """(obstacle, inside the room) per cell of the grid: the synthetic room's shell and
    furniture in the height band, placed with the anchor's ground truth."""
    from fleetslam.datasets.synthetic.room import Room

    from fleetslam.config import Config

    anchor = summary["merge"]["anchor"]
    folder = folders[int(anchor[1:])]
    _, gt = read_tum_trajectory(folder / "groundtruth.txt")
    # The map frame is level (map_frame.py); the summary says where it lies in the
    # anchor's own map, whose origin is the anchor's first camera.
    T_world_grid = gt[0] @ np.array(summary["merge"]["map_frame"]["T_anchor_map"]) \
        @ np.array(summary["merge"]["grid"]["T_map_grid"])
    h, w = image.shape
    res = meta["resolution"]
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    centres = np.column_stack([meta["origin"][0] + (cols.ravel() + 0.5) * res,
                               meta["origin"][1] + (h - 1 - rows.ravel() + 0.5) * res,
                               np.zeros(h * w)])
    cfg = GridConfig()
    room = Room.from_config(Config().synthetic)
    Lx, Ly, _ = room.size_m
    # The grid is level to ~1 degree: each cell's centre on the floor, in the world.
    world = transform_points(T_world_grid, centres)
    distance = np.maximum(np.minimum(Lx / 2 - np.abs(world[:, 0]),
                                     Ly / 2 - np.abs(world[:, 1])), 0.0)
    for box in room.furniture:
        bottom, top = box.center[2] - box.half[2], box.center[2] + box.half[2]
        if top < cfg.min_height_m or bottom > cfg.max_height_m:
            continue  # not in the robot's height band
        local = (world[:, :2] - box.center[:2]) @ box.R[:2, :2]
        outside = np.maximum(np.abs(local) - np.asarray(box.half[:2]), 0.0)
        distance = np.minimum(distance, np.linalg.norm(outside, axis=1))
    inside = (np.abs(world[:, 0]) < Lx / 2) & (np.abs(world[:, 1]) < Ly / 2)
    return (distance <= 1e-9).reshape(h, w), inside.reshape(h, w), T_world_grid


def test_the_synthetic_scene_s_floor_plan_is_recovered(synthetic_run, synthetic_scene):
    """Against the room's known plan: >= 95 % of the walls' cells the robots saw (dense map
    points on them) are occupied within one cell; occupied cells are on an obstacle within
    one cell; free cells are in the room and not inside an obstacle by more than a cell."""
    out, summary = synthetic_run
    _, folders = synthetic_scene
    meta, image = _load(out / "global_map.yaml")
    obstacle, inside, T_world_grid = _known_plan(summary, folders, meta, image, out)
    occupied, free = image == OCCUPIED, image == FREE
    near_obstacle = _near(obstacle)
    assert (occupied & near_obstacle).sum() >= 0.95 * occupied.sum()
    deep_inside = ~_near(~obstacle)  # an obstacle (or beyond the walls) by over a cell
    assert (free & deep_inside).sum() <= 0.05 * free.sum()
    assert (free & inside).sum() >= 0.95 * free.sum()
    # The walls seen: wall cells with dense-map points in the band on them.
    cfg = GridConfig()
    points, _ = read_ply(out / "global_map.ply")
    local = transform_points(invert(np.array(summary["merge"]["grid"]["T_map_grid"])), points)
    band = local[(local[:, 2] >= cfg.min_height_m) & (local[:, 2] <= cfg.max_height_m)]
    row, col, _ = _cells(meta, image, band)
    seen = np.zeros(image.shape, bool)
    seen[row, col] = True
    walls_seen = obstacle & seen
    assert walls_seen.sum() > 100
    assert (walls_seen & _near(occupied)).sum() >= 0.95 * walls_seen.sum()


def _plane(n: int, rng, up: np.ndarray, height: float) -> np.ndarray:
    a = np.cross(up, [1.0, 0, 0] if abs(up[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    uv = rng.uniform(-2, 2, (n, 2))
    return uv[:, :1] * a + uv[:, 1:] * b + height * up


def test_up_from_the_floor_else_from_the_config(tmp_path):
    """A tilted camera over a floor: the floor plane gives up (not the camera); a wall and
    no floor: ``[grid] up``. Either way the grid says which it used."""
    rng = np.random.default_rng(1)
    up = np.array([0.1, -1.0, 0.2]) / np.linalg.norm([0.1, -1.0, 0.2])
    camera = make_T(rotation_exp([0.3, 0.1, 0.0]), 1.2 * up)  # 1.2 m above the floor
    floor = _plane(4000, rng, up, 0.0)
    wall = _plane(4000, rng, np.array([0.0, 0.0, 1.0]), 3.0)
    wall = wall[(wall @ up > 0.0) & (wall @ up < 1.5)]  # from the floor up
    cfg = GridConfig()
    grid = occupancy_grid([(np.vstack([floor, wall]), camera[:3, 3])], camera[None], cfg)
    assert grid.up_source == "floor plane"
    # The wall's foot on the floor pulls it a little (0.1 degrees here).
    assert np.degrees(np.arccos(grid.T_map_grid[:3, 2] @ up)) < 0.5
    assert abs(grid.T_map_grid[:3, 3] @ up) < 0.01  # the grid's origin is on the floor
    assert grid.occupied > 0 and grid.free > 0
    alone = occupancy_grid([(wall, camera[:3, 3])], camera[None], cfg)
    assert alone.up_source == "config"
    np.testing.assert_allclose(alone.T_map_grid[:3, 2], [0, -1, 0], atol=1e-12)
    meta_path = write_nav2_map(tmp_path / "m", grid, "test")
    meta, image = _load(meta_path)
    assert image.shape == grid.image.shape and meta["resolution"] == cfg.resolution_m
    with pytest.raises(ValueError, match=r"\[grid\] up = \[0.0, 0.0, 0.0\] is not a direction"):
        occupancy_grid([(wall, camera[:3, 3])], camera[None], GridConfig(up=(0.0, 0.0, 0.0)))


def test_cells_are_made_unique_without_losing_any_sign_or_size():
    rng = np.random.default_rng(3)
    cells = np.concatenate([rng.integers(-70000, 70000, (5000, 2)),
                            [[-(1 << 30), (1 << 30) - 1], [0, -1], [-1, 0], [0, 0]]])
    cells = np.concatenate([cells, cells[::7]])  # some twice
    expected = np.unique(cells, axis=0)
    got = _unique_cells(cells)
    np.testing.assert_array_equal(got[np.lexsort((got[:, 1], got[:, 0]))], expected)
