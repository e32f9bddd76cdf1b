"""ATE and trajectory I/O, checked against hand-made cases and against evo."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import SHARED_DATA, require
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.evaluation.ate import absolute_trajectory_error, umeyama
from fleetslam.evaluation.fleet import trajectory_ate
from fleetslam.io.trajectory import read_tum_trajectory, write_tum_trajectory
from fleetslam.registration.metrics import random_perturbation
from fleetslam.transforms import interpolate_poses, make_T


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
