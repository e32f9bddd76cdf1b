"""Registration: metrics by hand, FS-HICP on synthetic and real clouds, baselines, errors."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fleetslam.config import FsHicpConfig
from fleetslam.io.ply import read_ply
from fleetslam.registration.baselines import point_to_plane_icp, point_to_point_icp
from fleetslam.registration.fshicp import fshicp, preprocess
from fleetslam.registration.metrics import build_tree, fitness_score, rmse, transform_error
from fleetslam.registration.metrics import random_perturbation
from fleetslam.transforms import invert, make_T, transform_points

FRAGMENTS = Path(__file__).parents[1] / ".." / "shared" / "data" / \
    "3dmatch_7scenes-redkitchen_fragments"

# One thread: pytest runs two workers on two cores, and one thread is bit-reproducible.
CONFIG = FsHicpConfig(num_threads=1)


# --- helpers ----------------------------------------------------------------------------------

def plane_grid(spacing: float = 0.01, size: float = 1.0) -> np.ndarray:
    """A dense square of the z = 0 plane."""
    u = np.arange(0.0, size + 1e-9, spacing)
    x, y = np.meshgrid(u, u)
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def synthetic_room(rng: np.random.Generator, n: int = 40_000) -> np.ndarray:
    """Floor, two walls and a box, 4 x 3 x 2.5 m, 2 mm noise: constrains all six DoF."""
    def rect(n_pts: int, origin, e1, e2) -> np.ndarray:
        a, b = rng.random((2, n_pts, 1))
        return np.asarray(origin) + a * np.asarray(e1) + b * np.asarray(e2)
    parts = [
        rect(n // 3, (0, 0, 0), (4, 0, 0), (0, 3, 0)),  # floor
        rect(n // 4, (0, 0, 0), (4, 0, 0), (0, 0, 2.5)),  # wall y = 0
        rect(n // 4, (0, 0, 0), (0, 3, 0), (0, 0, 2.5)),  # wall x = 0
        rect(n // 24, (1.5, 1.0, 0), (0.8, 0, 0), (0, 0, 0.7)),  # box faces
        rect(n // 24, (1.5, 1.0, 0), (0, 0.5, 0), (0, 0, 0.7)),
        rect(n // 24, (1.5, 1.0, 0.7), (0.8, 0, 0), (0, 0.5, 0)),
    ]
    points = np.vstack(parts)
    return points + rng.normal(0.0, 0.002, points.shape)


def small_motion(rng: np.random.Generator, deg: float, metres: float) -> np.ndarray:
    return random_perturbation(rng, deg, metres)


@pytest.fixture(scope="module")
def fragments() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if not FRAGMENTS.exists():
        pytest.skip(f"real data not present: {FRAGMENTS}")
    p0, _ = read_ply(FRAGMENTS / "cloud_bin_0.ply")
    p4, _ = read_ply(FRAGMENTS / "cloud_bin_4.ply")
    T_0_4 = np.loadtxt(FRAGMENTS / "T_0_4_from_7scenes_poses.txt")  # p0 = T_0_4 @ p4
    return p0, p4, T_0_4


# --- (a) metrics by hand --------------------------------------------------------------------

def test_fitness_of_cloud_against_itself_is_zero() -> None:
    cloud = plane_grid()
    assert fitness_score(cloud, cloud) == 0.0
    assert rmse(cloud, build_tree(cloud)) == 0.0


def test_fitness_of_shifted_plane_is_shift_squared() -> None:
    target = plane_grid()
    shift = 0.03  # along the normal: every nearest neighbour is the point straight below
    source = target + [0.0, 0.0, shift]
    assert fitness_score(source, target) == pytest.approx(shift**2, rel=1e-9)
    assert rmse(source, target) == pytest.approx(shift, rel=1e-9)
    # The same through a transform and a prebuilt tree.
    T = make_T(np.eye(3), [0.0, 0.0, shift])
    assert fitness_score(target, build_tree(target), T_target_source=T) == \
        pytest.approx(shift**2, rel=1e-9)
    # Nothing within range: inf, as PCL's DBL_MAX.
    assert fitness_score(source, target, max_range=0.02) == math.inf


def test_fitness_max_range_is_a_distance() -> None:
    target = np.zeros((1, 3))
    source = np.array([[0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [1.0, 0.0, 0.0]])
    assert fitness_score(source, target) == pytest.approx((0.01 + 0.04 + 1.0) / 3)
    assert fitness_score(source, target, max_range=0.5) == pytest.approx((0.01 + 0.04) / 2)
    assert rmse(source, target, max_range=0.5) == pytest.approx(math.sqrt(0.025))


def test_transform_error_eq6_of_known_perturbation() -> None:
    theta = math.radians(2.0)
    T_est = make_T(Rotation.from_euler("z", theta).as_matrix(), [0.03, -0.04, 0.0])
    err = transform_error(T_est, np.eye(4))
    # Rotation about z: (cos - 1) twice and sin twice -> 4 (1 - cos); translation 0.05^2.
    # No "- 1" (paper's typo).
    assert err.eq6 == pytest.approx(4 * (1 - math.cos(theta)) + 0.05**2, rel=1e-12)
    assert err.rotation_deg == pytest.approx(2.0, abs=1e-9)
    assert err.translation_m == pytest.approx(0.05, abs=1e-12)
    T_true = random_perturbation(np.random.default_rng(3), 30.0, 2.0)
    assert transform_error(T_true, T_true).eq6 == 0.0


# --- FS-HICP on synthetic clouds (no data needed) ---------------------------------------------

def test_fshicp_recovers_synthetic_room() -> None:
    rng = np.random.default_rng(11)
    room = synthetic_room(rng)
    G = small_motion(rng, 5.0, 0.15)
    source = transform_points(G, synthetic_room(rng))  # a second, independent sampling
    result = fshicp(source, room, np.eye(4), CONFIG)
    err = transform_error(result.T_target_source, invert(G))
    assert err.rotation_deg < 0.3 and err.translation_m < 0.01
    assert result.final_fitness < result.initial_fitness
    assert result.coarse_steps >= 1 and result.fine_steps >= 1
    assert len(result.history) == result.coarse_steps + result.fine_steps
    assert {s.level for s in result.history} == {"coarse", "fine"}


def test_fshicp_is_deterministic_for_a_seed() -> None:
    rng = np.random.default_rng(12)
    room = synthetic_room(rng)
    source = transform_points(small_motion(rng, 5.0, 0.15), synthetic_room(rng))
    a = fshicp(source, room, np.eye(4), CONFIG)
    b = fshicp(source, room, np.eye(4), CONFIG)
    assert np.array_equal(a.T_target_source, b.T_target_source)
    assert a.history == b.history
    # Two threads: small_gicp's threaded sums may differ in the last bits, decisions do not.
    threaded = dataclasses.replace(CONFIG, num_threads=2)
    c = fshicp(source, room, np.eye(4), threaded)
    d = fshicp(source, room, np.eye(4), threaded)
    assert [(s.level, s.accepted) for s in c.history] == [(s.level, s.accepted) for s in d.history]
    np.testing.assert_allclose(c.T_target_source, d.T_target_source, atol=1e-9)


# --- (b), (c) real data -----------------------------------------------------------------------

@pytest.mark.realdata
def test_fshicp_recovers_known_motion_of_real_fragment(fragments) -> None:
    """cloud_bin_0 against a moved, re-sampled copy of itself (10 deg, 0.3 m): FS-HICP must
    land within 0.5 deg / 1 cm. Note: the 5 cm fine voxel limits the precision to about a
    centimetre (1 of 6 such starts tried ended at 1.06 cm, 0.21 deg)."""
    p0, _, _ = fragments
    rng = np.random.default_rng(100)
    G = random_perturbation(rng, 10.0, 0.3)
    subset = p0[rng.random(len(p0)) < 0.5]  # another sampling ...
    moved = transform_points(G, subset + rng.normal(0.0, 0.003, subset.shape))  # ... and noise
    result = fshicp(moved, p0, np.eye(4), CONFIG)
    err = transform_error(result.T_target_source, invert(G))
    assert err.rotation_deg <= 0.5 and err.translation_m <= 0.01, err


@pytest.mark.realdata
def test_fshicp_on_real_partial_overlap_pair(fragments) -> None:
    """bin_4 -> bin_0 from T_0_4 perturbed by 10 deg / 0.3 m. T_0_4 itself is cm-level and
    ICP slides ~1.7 deg / 5.5 cm on this 43 % overlap, so the bound is 5 deg / 10 cm."""
    p0, p4, T_0_4 = fragments
    T_guess = random_perturbation(np.random.default_rng(0), 10.0, 0.3) @ T_0_4
    result = fshicp(p4, p0, T_guess, CONFIG)
    err = transform_error(result.T_target_source, T_0_4)
    assert err.rotation_deg <= 5.0 and err.translation_m <= 0.10, err
    assert result.final_fitness < result.initial_fitness
    assert result.rmse < 0.05


# --- baselines --------------------------------------------------------------------------------

@pytest.mark.parametrize("icp", [point_to_point_icp, point_to_plane_icp])
def test_baselines_converge_on_synthetic_room(icp) -> None:
    rng = np.random.default_rng(15)
    room = synthetic_room(rng)
    G = small_motion(rng, 3.0, 0.05)
    source = transform_points(G, synthetic_room(rng))
    result = icp(source, room, np.eye(4), voxel_m=0.05, num_threads=1)
    err = transform_error(result.T_target_source, invert(G))
    assert err.rotation_deg < 0.3 and err.translation_m < 0.01
    assert 1 <= result.iterations <= 100 and result.seconds > 0
    assert result.rmse == pytest.approx(math.sqrt(result.fitness))


# --- (e) bad input ----------------------------------------------------------------------------

def test_bad_input_raises_clear_value_error() -> None:
    room = synthetic_room(np.random.default_rng(16), 3000)
    with pytest.raises(ValueError, match="source: empty"):
        fshicp(np.zeros((0, 3)), room, np.eye(4), CONFIG)
    with pytest.raises(ValueError, match="target: 0 valid points"):
        fshicp(room, np.full((100, 3), np.nan), np.eye(4), CONFIG)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        fshicp(room[:, :2], room, np.eye(4), CONFIG)
    bad_T = np.eye(4)
    bad_T[0, 3] = np.nan
    with pytest.raises(ValueError, match="T_init: contains NaN"):
        fshicp(room, room, bad_T, CONFIG)
    with pytest.raises(ValueError, match="not a rotation"):
        fshicp(room, room, np.diag([2.0, 1.0, 1.0, 1.0]), CONFIG)
    with pytest.raises(ValueError, match="target: empty"):
        fitness_score(room, np.zeros((0, 3)))  # small_gicp would crash on an empty tree
    with pytest.raises(ValueError, match="empty"):
        point_to_point_icp(np.zeros((0, 3)), room, np.eye(4))


def test_some_nan_points_are_dropped_not_fatal() -> None:
    rng = np.random.default_rng(17)
    room = synthetic_room(rng, 20_000)
    noisy = room.copy()
    noisy[::50] = np.nan
    result = fshicp(noisy, room, np.eye(4), CONFIG)
    assert transform_error(result.T_target_source, np.eye(4)).translation_m < 0.01


def test_camera_frame_preprocess_drops_invalid_depth() -> None:
    points = np.array([[0, 0, 0.0], [0, 0, 1.0], [0, 0, 7.0], [0, 0, 7.5], [0, 0, -1.0]] * 8)
    assert len(preprocess(points, CONFIG, camera_frame=True)) == 16  # z in (0, 7]
    assert len(preprocess(points, CONFIG, camera_frame=False)) == 40
    with pytest.raises(ValueError, match="depth outside"):
        preprocess(points[:20], CONFIG, camera_frame=True)  # 8 valid < MIN_POINTS
