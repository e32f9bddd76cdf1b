"""Absolute trajectory error after a rigid (SE(3)) Umeyama alignment, as ``evo_ape -a``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetslam.transforms import make_T


def umeyama(source: np.ndarray, target: np.ndarray, with_scale: bool = False
            ) -> tuple[np.ndarray, float]:
    """(T, s) minimising sum |target - (s R source + t)|^2 for points (N, 3)."""
    if len(source) < 3:
        raise ValueError(f"alignment needs at least 3 positions, got {len(source)}")
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    xs, xt = source - mu_s, target - mu_t
    cov = xt.T @ xs / len(source)
    U, d, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    scale = float(np.trace(np.diag(d) @ S) / (xs**2).sum(axis=1).mean()) if with_scale else 1.0
    t = mu_t - scale * R @ mu_s
    return make_T(R, t), scale


@dataclass
class AteResult:
    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    n_poses: int
    T_gt_est: np.ndarray  # alignment applied to the estimate


def absolute_trajectory_error(est_poses: np.ndarray, gt_poses: np.ndarray) -> AteResult:
    """ATE of estimated vs ground-truth camera-to-world poses at the same instants; pairs
    with non-finite ground truth are skipped."""
    ok = np.isfinite(gt_poses).all(axis=(1, 2)) & np.isfinite(est_poses).all(axis=(1, 2))
    p_est, p_gt = est_poses[ok, :3, 3], gt_poses[ok, :3, 3]
    T, _ = umeyama(p_est, p_gt)
    err = np.linalg.norm(p_est @ T[:3, :3].T + T[:3, 3] - p_gt, axis=1)
    return AteResult(float(np.sqrt((err**2).mean())), float(err.mean()), float(np.median(err)),
                     float(err.max()), int(ok.sum()), T)
