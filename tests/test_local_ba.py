"""Local bundle adjustment on a synthetic scene with known geometry: keyframes inserted with
perturbed poses and noisy depth, then one local BA must bring poses and landmarks closer to
the truth, keep the first keyframe fixed, and erase corrupted observations."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fleetslam.camera import Camera
from fleetslam.backend.local_ba import (
    local_bundle_adjustment,
    reprojection_chi2,
    select_window,
)
from fleetslam.backend.local_map import LocalMap
from fleetslam.backend.pose_optimizer import CHI2_STEREO
from fleetslam.pipeline.states import FeatureFrame
from fleetslam.transforms import invert, make_T, rotation_angle_deg

CAMERA = Camera(525.0, 525.0, 319.5, 239.5)
BASELINE_M = 0.08
SCALE_FACTOR = 1.2
N_KEYFRAMES = 6


def _pose(rotvec_deg, t) -> np.ndarray:
    return make_T(Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix(), np.asarray(t, float))


def build_scene(seed: int, outlier_fraction: float = 0.0, perturb_from: int = 1):
    """Insert keyframes into a LocalMap the way DecideKeyframe does, keyframes from
    ``perturb_from`` on with tracking error. Returns (map, true poses, true landmark position
    per map landmark id)."""
    rng = np.random.default_rng(seed)
    n_points = 400
    truth = np.column_stack([rng.uniform(-2.0, 2.0, n_points), rng.uniform(-1.5, 1.5, n_points),
                             rng.uniform(1.5, 3.5, n_points)])
    poses = [_pose([0, 2.0 * i, 0.5 * i], [0.1 * i, 0.01 * i, 0.02 * i])
             for i in range(N_KEYFRAMES)]
    lmap = LocalMap()
    map_id = np.full(n_points, -1)
    for i, T_true in enumerate(poses):
        # The tracked pose carries error; the first keyframe defines the map frame.
        error = _pose(rng.normal(0, 0.6, 3), rng.normal(0, 0.02, 3))
        T_est = T_true if i < perturb_from else T_true @ error
        P = transform_to_camera(T_true, truth)
        uv = CAMERA.project(P)
        visible = np.flatnonzero((P[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < 640)
                                 & (uv[:, 1] >= 0) & (uv[:, 1] < 480))
        octave = rng.integers(0, 3, len(visible))
        sigma = SCALE_FACTOR**octave
        uv_meas = uv[visible] + rng.normal(0, 1, (len(visible), 2)) * sigma[:, None] * 0.5
        z = P[visible, 2]
        # Depth noise as the BA models it (ORB-SLAM's virtual stereo): disparity bf/z with
        # the keypoint's pixel noise, i.e. sigma_z = z^2 sigma_px / bf.
        bf = CAMERA.fx * BASELINE_M
        depth = (bf / (bf / z + rng.normal(0, 1, len(z)) * sigma * 0.5)).astype(np.float32)
        if outlier_fraction and i > 0:
            bad = rng.random(len(visible)) < outlier_fraction
            n_bad = int(bad.sum())
            uv_meas[bad] += rng.choice([-1, 1], (n_bad, 2)) * rng.uniform(15, 30, (n_bad, 2))
        matched = map_id[visible]
        desc = rng.integers(0, 256, (len(visible), 32), dtype=np.uint8)
        start = lmap.n_landmarks
        keypoints = np.zeros((len(visible), 7), np.float32)
        keypoints[:, :2], keypoints[:, 5] = uv_meas, octave
        features = FeatureFrame(i, float(i), keypoints, desc, depth, uv_meas)
        lmap.add_keyframe(CAMERA, features, T_est, matched)
        created = visible[matched < 0]
        map_id[created] = np.arange(start, start + len(created))
    truth_of = np.full((lmap.n_landmarks, 3), np.nan)
    truth_of[map_id[map_id >= 0]] = truth[map_id >= 0]
    return lmap, np.array(poses), truth_of


def transform_to_camera(T_world_camera: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return (xyz - T_world_camera[:3, 3]) @ T_world_camera[:3, :3]


def pose_errors(lmap: LocalMap, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    est = lmap.keyframe_poses()
    trans = np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1)
    rot = np.array([rotation_angle_deg((invert(t) @ e)[:3, :3]) for e, t in zip(est, truth)])
    return trans, rot


def landmark_rmse(lmap: LocalMap, truth_of: np.ndarray) -> float:
    seen = np.bincount(lmap.obs_landmark, minlength=lmap.n_landmarks) >= 2
    return float(np.sqrt(((lmap.xyz[seen] - truth_of[seen]) ** 2).sum(axis=1).mean()))


def run_ba(lmap: LocalMap):
    return local_bundle_adjustment(lmap, CAMERA, N_KEYFRAMES - 1, baseline_m=BASELINE_M,
                                   scale_factor=SCALE_FACTOR, window_size=10, min_shared=15)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_local_ba_reduces_pose_and_landmark_error(seed):
    lmap, truth, truth_of = build_scene(seed)
    T0 = lmap.keyframes[0].T_world_camera.copy()
    T_newest = lmap.keyframes[-1].T_world_camera.copy()
    trans0, rot0 = pose_errors(lmap, truth)
    lm0 = landmark_rmse(lmap, truth_of)

    result = run_ba(lmap)

    np.testing.assert_array_equal(select_window(lmap, N_KEYFRAMES - 1, 10, 15),
                                  np.arange(N_KEYFRAMES))
    assert 0 in result.fixed and 0 not in result.window
    # The first keyframe defines the map frame: it does not move at all.
    np.testing.assert_array_equal(lmap.keyframes[0].T_world_camera, T0)
    trans1, rot1 = pose_errors(lmap, truth)
    lm1 = landmark_rmse(lmap, truth_of)
    assert trans1[1:].mean() < 0.3 * trans0[1:].mean(), (trans0, trans1)
    assert rot1[1:].mean() < 0.3 * rot0[1:].mean(), (rot0, rot1)
    assert trans1.max() < 0.01 and rot1.max() < 0.2
    assert lm1 < 0.9 * lm0, (lm0, lm1)
    # The correction reported for the newest keyframe is what moved it.
    np.testing.assert_allclose(result.correction @ T_newest, lmap.keyframes[-1].T_world_camera,
                               atol=1e-12)


def test_local_ba_erases_outlier_observations():
    lmap, truth, truth_of = build_scene(3, outlier_fraction=0.05)
    n_obs = lmap.n_observations
    trans0, _ = pose_errors(lmap, truth)
    result = run_ba(lmap)
    assert result.n_outliers > 0
    assert lmap.n_observations == n_obs - result.n_outliers
    trans1, rot1 = pose_errors(lmap, truth)
    assert trans1[1:].mean() < 0.3 * trans0[1:].mean()
    assert rot1.max() < 0.3
    # Every observation left in the problem agrees with the optimised map (chi-square 3 dof,
    # 95%); all the synthetic observations have depth.
    T = lmap.keyframe_poses()[lmap.obs_keyframe]
    chi2, z = reprojection_chi2(CAMERA, CAMERA.fx * BASELINE_M, T, lmap.xyz[lmap.obs_landmark],
                                lmap.obs_uv, lmap.obs_depth, SCALE_FACTOR**lmap.obs_octave)
    n_obs_of = np.bincount(lmap.obs_landmark, minlength=lmap.n_landmarks)
    in_problem = n_obs_of[lmap.obs_landmark] >= 2
    assert (chi2[in_problem] <= CHI2_STEREO).all() and (z > 0).all()


def test_map_stays_plain_numpy_and_picklable():
    lmap, _, _ = build_scene(4)
    run_ba(lmap)
    again = pickle.loads(pickle.dumps(lmap))
    np.testing.assert_array_equal(again.xyz, lmap.xyz)
    np.testing.assert_array_equal(again.keyframe_poses(), lmap.keyframe_poses())


def test_window_without_anchor_holds_its_oldest_keyframe():
    """A map restarted after a loss has no first keyframe in reach: the oldest keyframe of the
    window is held instead, so the problem has no free gauge."""
    lmap, _, _ = build_scene(5)
    # Pretend keyframe 0 is gone from the window's view: drop its observations.
    lmap.remove_observations(lmap.obs_keyframe == 0)
    T1 = lmap.keyframes[1].T_world_camera.copy()
    result = run_ba(lmap)
    assert list(result.fixed) == [1]
    np.testing.assert_array_equal(lmap.keyframes[1].T_world_camera, T1)


def test_keyframes_outside_the_window_are_held_fixed():
    # Keyframes 0-2 were tracked exactly; the window (3 keyframes) is 3-5.
    lmap, truth, _ = build_scene(6, perturb_from=3)
    before = lmap.keyframe_poses().copy()
    result = local_bundle_adjustment(lmap, CAMERA, N_KEYFRAMES - 1, baseline_m=BASELINE_M,
                                     scale_factor=SCALE_FACTOR, window_size=3, min_shared=15)
    after = lmap.keyframe_poses()
    assert len(result.window) == 3 and N_KEYFRAMES - 1 in result.window
    outside = np.setdiff1d(np.arange(N_KEYFRAMES), result.window)
    np.testing.assert_array_equal(np.sort(result.fixed), outside)
    np.testing.assert_array_equal(after[outside], before[outside])
    trans0 = np.linalg.norm(before[result.window, :3, 3] - truth[result.window, :3, 3], axis=1)
    trans1 = np.linalg.norm(after[result.window, :3, 3] - truth[result.window, :3, 3], axis=1)
    assert trans1.mean() < 0.5 * trans0.mean()
