"""Trajectory errors as evo computes them: the absolute trajectory error after a rigid (SE(3))
Umeyama alignment, of the translation (``evo_ape -a``) and of the rotation (``evo_ape -a -r
angle_deg``), and the relative pose error between consecutive poses (``evo_rpe``, delta 1
frame; ``-r angle_deg`` for its rotation). Evaluation only: after a run, never fed back."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetslam.transforms import make_T, rotation_angles_deg


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
    rotation_rmse_deg: float = 0.0  # angle of est^-1 gt per pose, after the alignment
    rotation_mean_deg: float = 0.0
    rotation_max_deg: float = 0.0


def _paired(est_poses: np.ndarray, gt_poses: np.ndarray) -> np.ndarray:
    """Mask of the instants where both poses are finite (the pairs evo associates)."""
    return np.isfinite(gt_poses).all(axis=(1, 2)) & np.isfinite(est_poses).all(axis=(1, 2))


def ate_errors(est_poses: np.ndarray, gt_poses: np.ndarray, T_gt_est: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: (translation error m, rotation error deg) of the estimate moved by
    ``T_gt_est`` against ground truth; NaN where either pose is not finite."""
    est = np.einsum("ij,njk->nik", T_gt_est, est_poses)
    trans = np.linalg.norm(est[:, :3, 3] - gt_poses[:, :3, 3], axis=1)
    rot = rotation_angles_deg(np.einsum("nji,njk->nik", est[:, :3, :3], gt_poses[:, :3, :3]))
    ok = _paired(est_poses, gt_poses)
    return np.where(ok, trans, np.nan), np.where(ok, rot, np.nan)


def absolute_trajectory_error(est_poses: np.ndarray, gt_poses: np.ndarray) -> AteResult:
    """ATE of estimated vs ground-truth camera-to-world poses at the same instants; pairs
    with non-finite ground truth are skipped."""
    ok = _paired(est_poses, gt_poses)
    T, _ = umeyama(est_poses[ok, :3, 3], gt_poses[ok, :3, 3])
    err, rot = (e[ok] for e in ate_errors(est_poses, gt_poses, T))
    return AteResult(float(np.sqrt((err**2).mean())), float(err.mean()), float(np.median(err)),
                     float(err.max()), int(ok.sum()), T, float(np.sqrt((rot**2).mean())),
                     float(rot.mean()), float(rot.max()))


@dataclass
class RpeResult:
    """Relative pose error over consecutive pairs (delta 1 frame), as ``evo_rpe`` computes
    it: E_i = (gt_i^-1 gt_i+1)^-1 (est_i^-1 est_i+1); its translation's norm and its
    rotation's angle. A rigid alignment of the estimate cancels in it."""

    translation_rmse_m: float
    translation_mean_m: float
    translation_max_m: float
    rotation_rmse_deg: float
    rotation_mean_deg: float
    rotation_max_deg: float
    n_pairs: int


def rpe_errors(est_poses: np.ndarray, gt_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                     np.ndarray]:
    """(index of the later pose of each pair, translation error m, rotation error deg) over
    consecutive paired poses: frames without ground truth are skipped, as evo's association
    drops them, so a pair spans such a gap."""
    idx = np.flatnonzero(_paired(est_poses, gt_poses))
    est, gt = est_poses[idx], gt_poses[idx]
    rel_est = np.linalg.inv(est[:-1]) @ est[1:]
    rel_gt = np.linalg.inv(gt[:-1]) @ gt[1:]
    E = np.linalg.inv(rel_gt) @ rel_est
    return idx[1:], np.linalg.norm(E[:, :3, 3], axis=1), rotation_angles_deg(E[:, :3, :3])


def relative_pose_error(est_poses: np.ndarray, gt_poses: np.ndarray) -> RpeResult:
    """RPE (delta 1 frame) of estimated vs ground-truth poses at the same instants;
    ValueError with fewer than 2 paired poses."""
    _, trans, rot = rpe_errors(est_poses, gt_poses)
    if not len(trans):
        raise ValueError("the relative pose error needs at least 2 poses with ground truth")
    return RpeResult(float(np.sqrt((trans**2).mean())), float(trans.mean()),
                     float(trans.max()), float(np.sqrt((rot**2).mean())), float(rot.mean()),
                     float(rot.max()), len(trans))
