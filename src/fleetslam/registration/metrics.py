"""Registration quality measures: PCL's fitness score, its RMSE, and the paper's eq. 6 error.

Fitness score (the paper's section IV.B; our reading of it: shared/paper-notes.md §2,
outside this repository): the paper's text says "sum of squared distances", its eq. 8 a
mean of distances; the paper used PCL's ``getFitnessScore``, which is the *mean of squared*
nearest-neighbour distances from each (transformed) source point to the target, over the
points whose neighbour lies within ``max_range``. That is the meaning used here. One
difference from PCL: PCL compares the *squared* distance with ``max_range``; here
``max_range`` is a distance in metres, as its name says.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import small_gicp
from scipy.spatial.transform import Rotation

from fleetslam.transforms import make_T, orthonormalize, rotation_angle_deg, transform_points


def as_points(points: np.ndarray, name: str = "points") -> np.ndarray:
    """``points`` as a float64 (N, 3) array; a clear ValueError for anything else."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name}: expected an (N, 3) array of points, got shape {array.shape}")
    return array


def as_rigid_transform(T: np.ndarray, name: str = "transform") -> np.ndarray:
    """``T`` as a float64 4x4 rigid transform, its rotation re-orthonormalised (poses read
    from text files are off by ~1e-5); a clear ValueError if it is not near-rigid."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{name}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError(f"{name}: contains NaN or infinite values")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-3) or np.linalg.det(R) <= 0:
        raise ValueError(f"{name}: upper-left 3x3 block is not a rotation")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1]")
    return make_T(orthonormalize(R), T[:3, 3])


def build_tree(points: np.ndarray, num_threads: int = 1) -> small_gicp.KdTree:
    """KD-tree over ``points``. small_gicp crashes on an empty tree, so refuse it here."""
    points = as_points(points, "target")
    if len(points) == 0:
        raise ValueError("target: empty point cloud")
    if not np.isfinite(points).all():
        raise ValueError("target: contains NaN or infinite coordinates")
    return small_gicp.KdTree(points, num_threads)


def squared_nn_distances(source_pts: np.ndarray, target: small_gicp.KdTree | np.ndarray,
                         T_target_source: np.ndarray | None = None,
                         num_threads: int = 1) -> np.ndarray:
    """Squared distance from each source point (moved by ``T_target_source`` if given) to its
    nearest target point. ``target`` is a prebuilt KdTree (reused across calls) or points."""
    source_pts = as_points(source_pts, "source")
    if len(source_pts) == 0:
        raise ValueError("source: empty point cloud")
    if T_target_source is not None:
        source_pts = transform_points(as_rigid_transform(T_target_source, "T_target_source"),
                                      source_pts)
    tree = target if isinstance(target, small_gicp.KdTree) else build_tree(target, num_threads)
    _, sq_dists = tree.batch_knn_search(source_pts, 1, num_threads)
    return sq_dists[:, 0]


def _inlier_mean(sq_dists: np.ndarray, max_range: float) -> float:
    inliers = sq_dists[sq_dists <= max_range * max_range] if math.isfinite(max_range) else sq_dists
    # PCL returns DBL_MAX when nothing is in range; inf says the same without a magic number.
    return float(inliers.mean()) if len(inliers) else math.inf


def fitness_score(source_pts: np.ndarray, target_tree_or_pts: small_gicp.KdTree | np.ndarray,
                  max_range: float = math.inf, *, T_target_source: np.ndarray | None = None,
                  num_threads: int = 1) -> float:
    """PCL ``getFitnessScore``: mean squared nearest-neighbour distance (m^2) from the source
    points to the target, over the points whose neighbour is within ``max_range`` metres.
    inf when no point is in range."""
    sq = squared_nn_distances(source_pts, target_tree_or_pts, T_target_source, num_threads)
    return _inlier_mean(sq, max_range)


def rmse(source_pts: np.ndarray, target_tree_or_pts: small_gicp.KdTree | np.ndarray,
         max_range: float = math.inf, *, T_target_source: np.ndarray | None = None,
         num_threads: int = 1) -> float:
    """Root of :func:`fitness_score` (metres): the RMS nearest-neighbour distance."""
    return math.sqrt(fitness_score(source_pts, target_tree_or_pts, max_range,
                                   T_target_source=T_target_source, num_threads=num_threads))


@dataclass(frozen=True)
class TransformError:
    """How far an estimated transform is from the true one."""

    eq6: float  # paper eq. 6 without the printed "- 1": sum of squared entry differences of R and t
    rotation_deg: float  # angle of R_est^T R_true
    translation_m: float  # |t_est - t_true|


def transform_error(T_est: np.ndarray, T_true: np.ndarray) -> TransformError:
    T_est = np.asarray(T_est, dtype=np.float64)
    T_true = np.asarray(T_true, dtype=np.float64)
    if T_est.shape != (4, 4) or T_true.shape != (4, 4):
        raise ValueError(f"transform_error: expected 4x4 matrices, "
                         f"got {T_est.shape} and {T_true.shape}")
    diff = T_est[:3, :4] - T_true[:3, :4]  # the 9 rotation and 3 translation entries
    return TransformError(
        eq6=float(np.sum(diff * diff)),
        rotation_deg=rotation_angle_deg(T_est[:3, :3].T @ T_true[:3, :3]),
        translation_m=float(np.linalg.norm(diff[:, 3])),
    )


def random_perturbation(rng: np.random.Generator, max_rot_deg: float, max_trans_m: float
                        ) -> np.ndarray:
    """A transform with rotation of exactly ``max_rot_deg`` about a random axis and a
    translation of exactly ``max_trans_m`` in a random direction (worst case of the bound)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    R = Rotation.from_rotvec(axis * np.radians(max_rot_deg)).as_matrix()
    return make_T(R, direction * max_trans_m)
