"""ATE (translation and rotation), RPE and trajectory I/O, checked against hand-made cases
and against evo."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED_DATA, require
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.evaluation.ate import (absolute_trajectory_error, relative_pose_error,
                                      rpe_errors, umeyama)
from fleetslam.evaluation.fleet import trajectory_ate
from fleetslam.io.trajectory import read_tum_trajectory, write_tum_trajectory
from fleetslam.registration.metrics import random_perturbation
from fleetslam.transforms import interpolate_poses, make_T, matrix_from_quaternion


def test_umeyama_recovers_a_rigid_transform():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    T = random_perturbation(rng, 40.0, 2.0)
    moved = pts @ T[:3, :3].T + T[:3, 3]
    T_est, scale = umeyama(pts, moved)
    np.testing.assert_allclose(T_est, T, atol=1e-9)
    assert scale == 1.0


def test_ate_is_zero_for_a_moved_copy_and_sees_noise():
    rng = np.random.default_rng(1)
    gt = np.stack([make_T(np.eye(3), [0.1 * i, np.sin(i / 5), 0.0]) for i in range(40)])
    T = random_perturbation(rng, 30.0, 1.0)
    est = np.einsum("ij,njk->nik", T, gt)
    assert absolute_trajectory_error(est, gt).rmse_m < 1e-9
    est[:, :3, 3] += rng.normal(scale=0.01, size=(40, 3))
    assert 0.005 < absolute_trajectory_error(est, gt).rmse_m < 0.03


def test_trajectory_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    poses = np.stack([random_perturbation(rng, 20.0, 1.0) for _ in range(5)])
    times = np.arange(5) * 0.1 + 1000.0
    write_tum_trajectory(tmp_path / "t.tum", times, poses, comment="test")
    t2, p2 = read_tum_trajectory(tmp_path / "t.tum")
    np.testing.assert_allclose(t2, times)
    np.testing.assert_allclose(p2, poses, atol=1e-8)


def test_interpolation_midpoint():
    a, b = np.eye(4), random_perturbation(np.random.default_rng(3), 20.0, 1.0)
    mid = interpolate_poses(np.array([0.0, 1.0]), np.stack([a, b]), np.array([0.5]))[0]
    np.testing.assert_allclose(mid[:3, 3], b[:3, 3] / 2)


def estimate_as_sequence(root: Path, estimate: Path, ground_truth: Path) -> RgbdSequence:
    """A TUM folder whose frames are the estimate's stamps (empty image files: nothing here
    reads images) and whose groundtruth.txt is ``ground_truth``: what a run's trajectory is
    scored against."""
    times, _ = read_tum_trajectory(estimate)
    for name in ("rgb", "depth"):
        (root / name).mkdir(parents=True)
        lines = []
        for i, t in enumerate(times):
            (root / name / f"{i:04d}.png").touch()
            lines.append(f"{t:.6f} {name}/{i:04d}.png\n")
        (root / f"{name}.txt").write_text("".join(lines))
    shutil.copyfile(ground_truth, root / "groundtruth.txt")
    return RgbdSequence(root)


def test_ate_agrees_with_evo(tmp_path):
    """Our whole scoring path (evaluation.fleet.trajectory_ate: read the trajectory, pair
    its poses with the sequence's frames, ground truth per frame, SE(3) alignment) against
    evo's (associate within 10 ms, align, APE) on the same two files. We interpolate the
    ground truth at each frame where evo takes the nearest sample, so the numbers agree to
    a fraction of a percent, not exactly."""
    evo_sync = pytest.importorskip("evo.core.sync")
    from evo.core import metrics
    from evo.tools import file_interface

    folder = require(SHARED_DATA / "tum_trajectories_evo")
    gt_path = folder / "freiburg1_xyz-groundtruth.txt"
    est_path = folder / "freiburg1_xyz-rgbdslam.txt"
    traj_ref = file_interface.read_tum_trajectory_file(str(gt_path))
    traj_est = file_interface.read_tum_trajectory_file(str(est_path))
    n_estimated = traj_est.num_poses
    traj_ref, traj_est = evo_sync.associate_trajectories(traj_ref, traj_est, max_diff=0.01)
    traj_est.align(traj_ref)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    expected = ape.get_all_statistics()

    ours = trajectory_ate(est_path, estimate_as_sequence(tmp_path / "seq", est_path, gt_path))
    assert ours is not None
    # evo leaves out the 3 frames with no mocap sample within 10 ms; we interpolate there.
    assert traj_est.num_poses <= ours["n_poses"] <= n_estimated
    assert ours["n_poses"] - traj_est.num_poses <= 3
    assert ours["rmse_m"] == pytest.approx(expected["rmse"], rel=0.01)
    assert ours["mean_m"] == pytest.approx(expected["mean"], rel=0.01)
    assert ours["median_m"] == pytest.approx(expected["median"], rel=0.01)


def test_rotation_error_and_rpe_by_hand():
    """Four poses along x; the estimate's second step is 1 cm too long and turned 2 degrees
    about z, the third step right again. By hand: RPE pairs (0,1) (1,2) (2,3) have errors 0,
    (1 cm, 2 deg), 0 (the RPE sees each step, not the heading carried on); frame 2 without
    ground truth joins 1 and 3 into one pair, whose step is wrong by the turn."""
    turn = make_T(matrix_from_quaternion(np.array([0, 0, np.sin(np.radians(1)),
                                                  np.cos(np.radians(1))])), np.zeros(3))
    step = make_T(np.eye(3), [0.1, 0.0, 0.0])
    gt = np.stack([np.linalg.matrix_power(step, i) for i in range(4)])
    est = gt.copy()
    est[2:] = est[1] @ make_T(np.eye(3), [0.11, 0, 0]) @ turn @ np.stack([np.eye(4), step])
    _, trans, rot = rpe_errors(est, gt)
    np.testing.assert_allclose(trans, [0.0, 0.01, 0.0], atol=1e-12)
    np.testing.assert_allclose(rot, [0.0, 2.0, 0.0], atol=1e-9)
    # Without ground truth at frame 2, frames 1 and 3 are a pair: 2 steps, 1 cm, 2 degrees.
    gt_gap = gt.copy()
    gt_gap[2] = np.nan
    later, trans, rot = rpe_errors(est, gt_gap)
    assert list(later) == [1, 3]
    # est 1 -> 3: 0.11 m along x, then 0.1 m at 2 degrees; true: 0.2 m along x.
    c, s = np.cos(np.radians(2)), np.sin(np.radians(2))
    np.testing.assert_allclose(trans[1], np.hypot(0.11 + 0.1 * c - 0.2, 0.1 * s), atol=1e-12)
    np.testing.assert_allclose(rot[1], 2.0, atol=1e-9)
    # The ATE's rotation: the alignment cannot undo a turn of only the last two poses.
    ate = absolute_trajectory_error(est, gt)
    assert 0.5 < ate.rotation_max_deg <= 2.0 and ate.rotation_rmse_deg > 0.3


def test_rotation_error_and_rpe_agree_with_evo():
    """On the pose pairs evo associates (freiburg1_xyz, an RGBD-SLAM estimate), our ATE
    rotation (evo_ape -a -r angle_deg) and RPE (evo_rpe, delta 1 frame, translation and
    -r angle_deg) equal evo's."""
    evo_sync = pytest.importorskip("evo.core.sync")
    from evo.core import metrics
    from evo.tools import file_interface

    folder = require(SHARED_DATA / "tum_trajectories_evo")
    ref = file_interface.read_tum_trajectory_file(str(folder / "freiburg1_xyz-groundtruth.txt"))
    est = file_interface.read_tum_trajectory_file(str(folder / "freiburg1_xyz-rgbdslam.txt"))
    ref, est = evo_sync.associate_trajectories(ref, est, max_diff=0.01)
    P, Q = np.array(est.poses_se3), np.array(ref.poses_se3)
    rpe = relative_pose_error(P, Q)
    est.align(ref)
    evo = {}
    for name, metric in (
            ("ape_rot", metrics.APE(metrics.PoseRelation.rotation_angle_deg)),
            ("rpe_trans", metrics.RPE(metrics.PoseRelation.translation_part)),
            ("rpe_rot", metrics.RPE(metrics.PoseRelation.rotation_angle_deg))):
        metric.process_data((ref, est))
        evo[name] = metric.get_all_statistics()
    ate = absolute_trajectory_error(P, Q)
    assert ate.rotation_rmse_deg == pytest.approx(evo["ape_rot"]["rmse"], rel=1e-6)
    assert ate.rotation_mean_deg == pytest.approx(evo["ape_rot"]["mean"], rel=1e-6)
    assert ate.rotation_max_deg == pytest.approx(evo["ape_rot"]["max"], rel=1e-6)
    assert rpe.n_pairs == len(P) - 1
    assert rpe.translation_rmse_m == pytest.approx(evo["rpe_trans"]["rmse"], rel=1e-6)
    assert rpe.translation_max_m == pytest.approx(evo["rpe_trans"]["max"], rel=1e-6)
    assert rpe.rotation_rmse_deg == pytest.approx(evo["rpe_rot"]["rmse"], rel=1e-6)
    assert rpe.rotation_mean_deg == pytest.approx(evo["rpe_rot"]["mean"], rel=1e-6)


def test_ground_truth_files_are_matched_to_robots_and_checked_first(tmp_path):
    """--groundtruth (issue 45 item 3): FILE in the robots' order or NAME=FILE; a file that
    is no TUM trajectory, or a flag that fits no robot, is one line naming the flag."""
    from fleetslam.evaluation.fleet import match_ground_truth

    good = tmp_path / "gt.txt"
    good.write_text("# t tx ty tz qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n")
    names = ["r0", "r1"]
    assert match_ground_truth([str(good)], names) == {"r0": good.resolve()}
    assert match_ground_truth([f"r1={good}"], names) == {"r1": good.resolve()}
    assert match_ground_truth([], names) == {}
    bad = tmp_path / "rgb.txt"
    bad.write_text("1.0 rgb/1.png\n")
    for values, words in (([str(bad)], f"--groundtruth: {bad}:1: expected 8 values"),
                          ([f"r5={good}"], "--groundtruth r5="),
                          ([str(good)] * 3, "3 --groundtruth for 2 robots"),
                          ([f"r0={good}", str(good)], "give every one as NAME=FILE"),
                          ([f"r0={good}", f"r0={good}"], "robot r0 has one already")):
        with pytest.raises(ValueError, match=re.escape(words)) as exc:
            match_ground_truth(values, names)
        assert "\n" not in str(exc.value)


def test_map_to_map_is_how_far_two_robots_maps_are_from_where_ground_truth_has_them():
    """Two robots, each placed exactly but for the second's whole map turned 5 degrees about
    the vertical at the origin: each aligned apart has no error, the bound is zero, the
    map-to-map error is the 5 degrees, and one alignment for both sees the bend."""
    from fleetslam.evaluation.fleet import map_to_map

    rng = np.random.default_rng(3)
    gt = [np.stack([make_T(np.eye(3), rng.normal(size=3)) for _ in range(40)])
          for _ in range(2)]
    turn = make_T(matrix_from_quaternion(np.array([0, 0, np.sin(np.radians(2.5)),
                                                   np.cos(np.radians(2.5))]))[0], np.zeros(3))
    est = [gt[0].copy(), np.einsum("ij,njk->nik", turn, gt[1])]
    out = map_to_map(["r0", "r1"], est, gt)
    assert out["separately_aligned_bound_m"] < 1e-9
    (row,) = out["map_to_map"]
    assert (row["robot"], row["to"]) == ("r1", "r0")
    assert row["rotation_deg"] == pytest.approx(5.0, abs=1e-6)
    assert row["translation_m"] < 1e-9
    joint = absolute_trajectory_error(np.concatenate(est), np.concatenate(gt))
    assert joint.rmse_m > 0.01
