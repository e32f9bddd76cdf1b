"""The synthetic multi-robot scene: determinism, exact ground truth, texture, overlap, layout."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from fleetslam.camera import Camera
from fleetslam.config import MapConfig, SyntheticConfig
from fleetslam.datasets.synthetic import (
    MIN_SENSOR_DEPTH_M,
    Room,
    ensure_scene,
    generate_scene,
    render,
    robot_trajectories,
    scene_camera,
    sensor_depth,
)
from fleetslam.datasets.tum import RgbdSequence, read_file_list
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.transforms import invert, rotation_angle_deg, transform_points

FRAMES = 6
# A tiny camera for tests that only need the files, not the pixels.
TINY = dict(width=160, height=120, fx=131.25, fy=131.25, cx=79.5, cy=59.5)


@pytest.fixture(scope="module")
def config() -> SyntheticConfig:
    return SyntheticConfig(frames_per_robot=FRAMES)


@pytest.fixture(scope="module")
def scene(tmp_path_factory, config) -> list[Path]:
    return generate_scene(tmp_path_factory.mktemp("synthetic") / "scene", config)


@pytest.fixture(scope="module")
def room(config) -> Room:
    return Room.from_config(config)


def load_depth(folder: Path, frame: int) -> np.ndarray:
    seq = RgbdSequence(folder)
    return seq[frame].depth_m


def reproject(camera: Camera, depth_i: np.ndarray, T_world_i: np.ndarray, T_world_j: np.ndarray,
              depth_j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points of depth image i seen in camera j: (their z in j, j's depth at their pixel),
    for the points that land inside image j."""
    points_i, _ = camera.backproject_image(depth_i, stride=4)
    points_j = transform_points(invert(T_world_j) @ T_world_i, points_i)
    in_front = points_j[:, 2] > 0.1
    points_j = points_j[in_front]
    uv = np.rint(camera.project(points_j)).astype(int)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    return points_j[inside, 2], depth_j[uv[inside, 1], uv[inside, 0]]


def test_tum_layout_camera_and_ground_truth(scene, config):
    assert [f.name for f in scene] == ["robot_0", "robot_1"]
    record = json.loads((scene[0].parent / "scene.json").read_text())
    assert record["format_version"] == 2 and record["seed"] == config.seed
    assert record["robots"] == ["robot_0", "robot_1"]
    assert record["config"]["frames_per_robot"] == FRAMES
    trajectories = robot_trajectories(config)
    for r, folder in enumerate(scene):
        assert (folder / "rgb.txt").read_text().startswith("# color images\n")
        assert "# timestamp filename" in (folder / "rgb.txt").read_text()
        rgb_list = read_file_list(folder / "rgb.txt")
        depth_list = read_file_list(folder / "depth.txt")
        assert len(rgb_list) == len(depth_list) == FRAMES
        t0 = 1000.0 + 100.0 * r
        assert rgb_list[0] == (t0, f"rgb/{t0:.6f}.png")
        assert rgb_list[1][0] == pytest.approx(t0 + 1 / config.fps, abs=1e-6)
        assert depth_list[2][1] == f"depth/{rgb_list[2][0]:.6f}.png"
        rgb = cv2.imread(str(folder / rgb_list[0][1]), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(folder / depth_list[0][1]), cv2.IMREAD_UNCHANGED)
        assert rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8
        assert depth.shape == (480, 640) and depth.dtype == np.uint16

        camera = Camera.from_json(folder / "camera.json")
        assert camera == scene_camera(config)
        assert camera.depth_scale == 5000 and not camera.has_distortion

        times, poses = read_tum_trajectory(folder / "groundtruth.txt")
        np.testing.assert_allclose(times, [t for t, _ in rgb_list], atol=1e-9)
        np.testing.assert_allclose(poses, trajectories[r], atol=1e-6)

        seq = RgbdSequence(folder)  # the project's own reader takes it as it is
        assert len(seq) == FRAMES and seq.has_ground_truth and seq.camera_source == "camera.json"


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    config = SyntheticConfig(frames_per_robot=1)
    a = generate_scene(tmp_path / "a", config)
    b = generate_scene(tmp_path / "b", config)
    c = generate_scene(tmp_path / "c", replace(config, seed=config.seed + 1))
    for r in range(config.n_robots):
        for kind in ("rgb", "depth"):
            name = sorted((a[r] / kind).iterdir())[0].name
            bytes_a = (a[r] / kind / name).read_bytes()
            assert bytes_a == (b[r] / kind / name).read_bytes()
            assert bytes_a != (c[r] / kind / name).read_bytes()
    assert (a[0] / "groundtruth.txt").read_text() == (b[0] / "groundtruth.txt").read_text()


def test_depth_agrees_with_ground_truth_within_and_across_robots(scene, config, room):
    camera = scene_camera(config)
    trajectories = robot_trajectories(config)
    depth_0 = load_depth(scene[0], 0)
    for robot_j, frame_j in ((0, FRAMES - 1), (1, 0), (1, FRAMES - 1)):
        T_j = trajectories[robot_j][frame_j]
        _, clean_j = render(room, camera, T_j)
        z, z_rendered = reproject(camera, depth_0, trajectories[0][0], T_j, clean_j)
        assert len(z) > 2000
        error = np.abs(z - z_rendered)
        # Occluded points and depth noise aside, the geometry is the same.
        assert np.median(error) < 0.02
        assert np.mean(error < 0.05) > 0.8


def test_robots_see_a_common_part_of_the_room(scene, config, room):
    camera = scene_camera(config)
    trajectories = robot_trajectories(config)
    for frame in (0, FRAMES - 1):
        depth_0 = load_depth(scene[0], frame)
        T_1 = trajectories[1][frame]
        _, clean_1 = render(room, camera, T_1)
        z, z_rendered = reproject(camera, depth_0, trajectories[0][frame], T_1, clean_1)
        n_points = np.count_nonzero(depth_0[::4, ::4])
        seen_by_both = np.count_nonzero(np.abs(z - z_rendered) < 0.05)
        assert seen_by_both > 0.3 * n_points


def world_map(room: Room, camera: Camera, poses: np.ndarray, cell_m: float = 0.05) -> np.ndarray:
    """Noise-free points of the given views within the dense map's range, one per cell."""
    clouds = []
    for T in poses:
        _, depth = render(room, camera, T)
        local, _ = camera.backproject_image(depth, stride=4, max_depth_m=MapConfig().max_depth_m)
        clouds.append(transform_points(T, local))
    points = np.vstack(clouds)
    _, first = np.unique(np.floor(points / cell_m).astype(np.int64), axis=0, return_index=True)
    return points[first]


def test_default_scene_overlap_pins_down_a_map_merge():
    """The two robots' maps (every 20th frame of the default 120) overlap on 3D structure,
    not just on the wall and floor: sliding one map along the wall, which on a bare room
    gains overlap (the wrong merge scored better than the truth), must lose it; and the
    point-to-plane normal equations of the overlap constrain all six degrees of freedom."""
    config = SyntheticConfig()
    room = Room.from_config(config)
    camera = scene_camera(config)
    map_0, map_1 = (world_map(room, camera, T[::20]) for T in robot_trajectories(config))
    tree = cKDTree(map_0)

    def truncated_score(shift: np.ndarray, r: float = 0.1) -> float:  # FS-HICP's fitness
        d, _ = tree.query(map_1 + shift, distance_upper_bound=r)
        return float(np.mean(np.minimum(d, r) ** 2))

    truth = truncated_score(np.zeros(3))
    slides = [truncated_score(np.array([dx, 0.0, 0.0])) for dx in np.arange(-2.4, 2.45, 0.1)
              if abs(dx) > 0.35]
    assert min(slides) > 1.1 * truth  # a bare wall + floor + one table: 0.7 x truth

    d, index = tree.query(map_1, distance_upper_bound=0.05)
    overlap = np.isfinite(d)
    assert overlap.mean() > 0.3
    points, matched = map_1[overlap], map_0[index[overlap]]
    _, neighbours = tree.query(matched, k=12)
    patches = map_0[neighbours] - map_0[neighbours].mean(axis=1, keepdims=True)
    normals = np.linalg.svd(patches, full_matrices=False)[2][:, 2]
    J = np.hstack([np.cross(points - points.mean(axis=0), normals), normals])  # metres, radians
    eigenvalues = np.linalg.eigvalsh(J.T @ J)
    assert eigenvalues[0] > 0.05 * eigenvalues[-1]  # bare room: 0.001-0.014


def test_orb_finds_many_well_spread_keypoints_on_every_frame(scene):
    orb = cv2.ORB_create(nfeatures=1000, scaleFactor=1.2, nlevels=8)
    for folder in scene:
        for _, name in read_file_list(folder / "rgb.txt"):
            gray = cv2.imread(str(folder / name), cv2.IMREAD_GRAYSCALE)
            keypoints = orb.detect(gray, None)
            assert len(keypoints) >= 500, name
            uv = np.array([k.pt for k in keypoints])
            cells, _, _ = np.histogram2d(uv[:, 1], uv[:, 0], bins=(3, 4), range=((0, 480), (0, 640)))
            assert np.count_nonzero(cells >= 5) >= 10, (name, cells)
            quadrants, _, _ = np.histogram2d(uv[:, 1], uv[:, 0], bins=2, range=((0, 480), (0, 640)))
            assert quadrants.min() >= 0.08 * len(keypoints), (name, quadrants)


@pytest.mark.parametrize("n_robots", [1, 2, 3, 4])
def test_trajectories_smooth_realistic_inside_the_room(n_robots, room):
    config = SyntheticConfig(n_robots=n_robots, frames_per_robot=900)  # 30 s
    trajectories = robot_trajectories(config)
    assert len(trajectories) == n_robots
    starts = [T[0] for T in trajectories]
    for T in trajectories:
        assert T.shape == (900, 4, 4)
        np.testing.assert_allclose(T[:, :3, :3] @ T[:, :3, :3].transpose(0, 2, 1),
                                   np.tile(np.eye(3), (900, 1, 1)), atol=1e-9)
        speed = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) * config.fps
        assert speed.max() <= 0.5
        turn = [rotation_angle_deg((invert(a) @ b)[:3, :3]) * config.fps for a, b in zip(T[:-1], T[1:])]
        assert max(turn) <= 30.0
        assert np.abs(np.diff(speed)).max() * config.fps < 0.5  # no jumps in velocity (m/s^2)
        assert 1.0 <= T[:, 2, 3].min() and T[:, 2, 3].max() <= 1.6
        assert min(room.clearance(p) for p in T[::5, :3, 3]) >= 0.6
        # Camera y axis (image down) points mostly down: small pitch and roll.
        assert (T[:, 2, 1] < -0.95).all()
    for i in range(n_robots):
        for j in range(i):
            assert np.linalg.norm(starts[i][:3, 3] - starts[j][:3, 3]) > 0.2
            assert rotation_angle_deg(starts[i][:3, :3].T @ starts[j][:3, :3]) > 5.0


def test_sensor_depth_noise_holes_and_range(room, config):
    camera = scene_camera(config)
    T = robot_trajectories(config)[1][0]
    _, clean = render(room, camera, T)
    raw = sensor_depth(clean, config, np.random.default_rng(0))
    assert raw.dtype == np.uint16
    depth = raw / 5000.0
    valid = raw > 0
    assert 0.9 < valid.mean() < 0.99  # dropout blobs and edges, most pixels measured
    assert depth[valid].min() >= MIN_SENSOR_DEPTH_M and depth[valid].max() <= config.max_depth_m
    z = clean[valid].astype(float)
    sigma = config.depth_noise_a + config.depth_noise_b * (z - 0.4) ** 2
    normalised = (depth[valid] - z) / sigma
    assert abs(normalised.mean()) < 0.1 and 0.85 < normalised.std() < 1.15
    # A surface too near for the sensor has no measurement.
    near = sensor_depth(np.full((40, 40), 0.3, np.float32), config, np.random.default_rng(0))
    assert not near.any()


def test_ensure_scene_reuses_a_complete_scene_and_replaces_a_stale_one(tmp_path):
    config = SyntheticConfig(frames_per_robot=2, n_furniture=3, **TINY)
    out = tmp_path / "scene"
    calls = []
    folders = ensure_scene(out, config, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (4, 4) and [f.name for f in folders] == ["robot_0", "robot_1"]
    stamp = (out / "scene.json").stat().st_mtime_ns
    assert ensure_scene(out, config) == folders
    assert (out / "scene.json").stat().st_mtime_ns == stamp  # reused, not rewritten

    other = replace(config, frames_per_robot=3)
    ensure_scene(out, other)
    assert len(read_file_list(out / "robot_1" / "rgb.txt")) == 3
    assert json.loads((out / "scene.json").read_text())["config"]["frames_per_robot"] == 3


def test_interrupted_run_leaves_nothing_that_looks_complete(tmp_path):
    config = SyntheticConfig(frames_per_robot=3, n_furniture=3, **TINY)

    def interrupt(done: int, total: int) -> None:
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate_scene(tmp_path / "scene", config, progress=interrupt)
    assert list(tmp_path.iterdir()) == []


def test_refuses_to_replace_a_folder_that_is_not_a_scene(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError):
        generate_scene(tmp_path, SyntheticConfig(frames_per_robot=1, **TINY))
    assert (tmp_path / "notes.txt").read_text() == "mine"
