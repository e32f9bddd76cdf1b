"""The tracker's PnP fallback (pose_optimizer.pnp_pose): from 2D-3D matches with a third of
them wrong and a guess far from the truth, RANSAC over minimal samples and the motion-only
refinement find the true pose and tell the wrong matches apart."""

from __future__ import annotations

import numpy as np

from fleetslam.backend.pose_optimizer import pnp_pose
from fleetslam.camera import Camera
from fleetslam.transforms import (invert, make_T, rotation_angle_deg, rotation_exp,
                                  transform_points)

CAMERA = Camera(fx=525.0, fy=525.0, cx=319.5, cy=239.5)


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    return rotation_exp(np.radians(degrees) * axis / np.linalg.norm(axis))[0]


def _scene(seed: int, n: int = 300, wrong: float = 0.35):
    rng = np.random.default_rng(seed)
    T_wc = make_T(_rotation(rng.standard_normal(3), 20.0), rng.uniform(-0.5, 0.5, 3))
    # Points in front of the camera, 1-4 m away, inside the image.
    uv = rng.uniform([20, 20], [620, 460], (n, 2))
    depth = rng.uniform(1.0, 4.0, n)
    xyz = transform_points(T_wc, CAMERA.backproject(uv, depth))
    uv = uv + rng.normal(0, 0.5, uv.shape)
    bad = rng.random(n) < wrong  # wrong matches: another pixel, no depth
    uv[bad] = rng.uniform([20, 20], [620, 460], (int(bad.sum()), 2))
    depth = np.where(bad, 0.0, depth)
    return T_wc, xyz, uv, depth, np.ones(n), bad


def _apart(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    d = invert(T_a) @ T_b
    return rotation_angle_deg(d[:3, :3]), float(np.linalg.norm(d[:3, 3]))


def test_pnp_finds_the_pose_from_a_bad_guess_among_wrong_matches() -> None:
    for seed in range(3):
        T_true, xyz, uv, depth, scale, bad = _scene(seed)
        guess = T_true.copy()
        guess[:3, :3] = _rotation(np.array([0.0, 1.0, 0.2]), 40.0) @ guess[:3, :3]
        guess[:3, 3] += [0.4, -0.3, 0.2]
        solved = pnp_pose(CAMERA, xyz, uv, depth, scale, 0.08, guess, 200, 3.0, 0.999, 30)
        assert solved is not None
        T, inliers = solved
        angle, shift = _apart(T, T_true)
        assert angle < 0.2 and shift < 0.01, (seed, angle, shift)
        # The wrong matches are the outliers, the right ones inliers (a wrong one may
        # land near its true pixel by chance: a few).
        assert (inliers & bad).sum() <= 3
        assert inliers[~bad].mean() > 0.95


def test_pnp_refuses_matches_that_agree_on_no_pose() -> None:
    rng = np.random.default_rng(7)
    xyz = rng.uniform([-1, -1, 1], [1, 1, 4], (60, 3))
    uv = rng.uniform([20, 20], [620, 460], (60, 2))
    assert pnp_pose(CAMERA, xyz, uv, np.zeros(60), np.ones(60), 0.08, np.eye(4), 200, 3.0,
                    0.999, 30) is None
