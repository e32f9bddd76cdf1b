"""Robust rigid alignment of 3D-3D matches: the geometric check of a place-recognition
candidate (depth-backed keypoints of one keyframe against landmarks of another place).

RANSAC over minimal samples of three matches, all hypotheses at once: the rotations come
from one batched SVD (Kabsch), the inliers of every hypothesis from one broadcast distance
test. The best hypothesis is refitted on its inliers until the inlier set stops changing.
A match is an inlier within max(inlier_m, depth_ratio * depth): depth noise of a
structured-light or time-of-flight camera grows with distance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RigidMatch:
    T_target_source: np.ndarray  # 4 x 4
    inliers: np.ndarray  # bool per match
    rmse_m: float

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least-squares rigid T (4 x 4) with target ~ R source + t; batched over a leading
    axis when the inputs are (B, n, 3)."""
    batched = source.ndim == 3
    src = source if batched else source[None]
    dst = target if batched else target[None]
    mu_s, mu_d = src.mean(axis=1), dst.mean(axis=1)
    H = np.einsum("bni,bnj->bij", src - mu_s[:, None], dst - mu_d[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("bij,bjk->bik", U, Vt)))
    D = np.ones((len(src), 3))
    D[:, 2] = d
    R = np.einsum("bji,bj,bkj->bik", Vt, D, U)  # V diag(D) U^T
    T = np.tile(np.eye(4), (len(src), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = mu_d - np.einsum("bij,bj->bi", R, mu_s)
    return T if batched else T[0]


def ransac_rigid(source: np.ndarray, target: np.ndarray, threshold_m: np.ndarray,
                 iterations: int, min_inliers: int, rng: np.random.Generator,
                 refits: int = 5) -> RigidMatch | None:
    """Rigid T_target_source from matched points (n x 3 each) with per-match inlier
    thresholds; None when fewer than ``min_inliers`` agree."""
    n = len(source)
    if n < max(3, min_inliers):
        return None
    samples = np.array([rng.choice(n, 3, replace=False) for _ in range(iterations)])
    src, dst = source[samples], target[samples]
    # Degenerate samples (nearly collinear points) give arbitrary rotations: skip them.
    area = np.linalg.norm(np.cross(src[:, 1] - src[:, 0], src[:, 2] - src[:, 0]), axis=1)
    good = area > 1e-4
    if not good.any():
        return None
    T = kabsch(src[good], dst[good])
    moved = np.einsum("bij,nj->bni", T[:, :3, :3], source) + T[:, None, :3, 3]
    err = np.linalg.norm(moved - target[None], axis=2)
    counts = (err <= threshold_m[None]).sum(axis=1)
    best = int(np.argmax(counts))
    inliers = err[best] <= threshold_m
    if inliers.sum() < min_inliers:
        return None
    T_best = T[best]
    for _ in range(refits):
        T_best = kabsch(source[inliers], target[inliers])
        err1 = np.linalg.norm(source @ T_best[:3, :3].T + T_best[:3, 3] - target, axis=1)
        new = err1 <= threshold_m
        if new.sum() < 3 or np.array_equal(new, inliers):
            inliers = new if new.sum() >= 3 else inliers
            break
        inliers = new
    if inliers.sum() < min_inliers:
        return None
    err1 = np.linalg.norm(source @ T_best[:3, :3].T + T_best[:3, 3] - target, axis=1)
    return RigidMatch(T_best, inliers, float(np.sqrt(np.mean(err1[inliers] ** 2))))
