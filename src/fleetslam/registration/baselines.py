"""The paper's baselines, run to convergence: point-to-point ICP (its PCL "classical ICP") and
point-to-plane ICP (KinectFusion's). Both take the same start as FS-HICP and run either on
the unfiltered clouds (``voxel_m=None``, the paper's classical ICP) or at a voxel size (pass
FS-HICP's ``fine_voxel_m`` for the like-for-like comparison DESIGN.md asks for).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import small_gicp

from fleetslam.registration.fshicp import drop_invalid, voxel_filter
from fleetslam.registration.metrics import as_rigid_transform, squared_nn_distances

IcpMethod = Literal["point_to_point", "point_to_plane"]
_SMALL_GICP_TYPE = {"point_to_point": "ICP", "point_to_plane": "PLANE_ICP"}

# Convergence: an update smaller than this stops ICP. Far below the cm / sub-degree errors
# measured, so "converged" means the step no longer matters, not small_gicp's looser default
# (0.1 deg, 1 mm), which stops point-to-point ICP early while it still slides.
ROTATION_EPS_RAD = 1e-5
TRANSLATION_EPS_M = 1e-5
# Neighbours for the target normals of point-to-plane ICP (small_gicp's default).
NORMAL_NEIGHBOURS = 20


@dataclass
class IcpResult:
    method: IcpMethod
    voxel_m: float | None  # None: unfiltered clouds
    T_target_source: np.ndarray
    fitness: float  # PCL fitness score (m^2) on the clouds ICP ran on, within max_corr_m
    rmse: float  # sqrt(fitness), m
    inlier_fraction: float  # fraction of source points within max_corr_m of the target
    seconds: float  # filtering, KD-tree, normals and ICP; not the fitness evaluation
    iterations: int  # ICP iterations run (correspondence searches)
    converged: bool  # False: stopped by max_iterations or a failed step


def run_icp(method: IcpMethod, source: np.ndarray, target: np.ndarray, T_init: np.ndarray, *,
            voxel_m: float | None = None, max_corr_m: float = 0.2, max_iterations: int = 100,
            num_threads: int = 2) -> IcpResult:
    """One ICP variant from ``T_init`` (T_target_source) until the update is negligible or
    ``max_iterations``. ``max_corr_m`` defaults to FS-HICP's coarse distance, so both start
    with the same capture range."""
    if method not in _SMALL_GICP_TYPE:
        raise ValueError(f"unknown ICP method '{method}' (known: {', '.join(_SMALL_GICP_TYPE)})")
    T0 = as_rigid_transform(T_init, "T_init")
    source = drop_invalid(source, "source")
    target = drop_invalid(target, "target")

    start = time.perf_counter()
    if voxel_m is None:
        src, tgt = small_gicp.PointCloud(source), small_gicp.PointCloud(target)
    else:
        src, tgt = voxel_filter(source, voxel_m), voxel_filter(target, voxel_m)
    tree = small_gicp.KdTree(tgt, num_threads)
    if method == "point_to_plane":
        small_gicp.estimate_normals(tgt, tree, NORMAL_NEIGHBOURS, num_threads)
    result = small_gicp.align(
        tgt, src, tree, init_T_target_source=T0, registration_type=_SMALL_GICP_TYPE[method],
        max_correspondence_distance=max_corr_m, num_threads=num_threads,
        max_iterations=max_iterations, rotation_epsilon=ROTATION_EPS_RAD,
        translation_epsilon=TRANSLATION_EPS_M)
    seconds = time.perf_counter() - start

    T = np.asarray(result.T_target_source)
    sq = squared_nn_distances(src.points()[:, :3], tree, T, num_threads)
    inliers = sq[sq <= max_corr_m * max_corr_m]
    fitness = float(inliers.mean()) if len(inliers) else math.inf
    return IcpResult(
        method=method, voxel_m=voxel_m, T_target_source=T, fitness=fitness,
        rmse=math.sqrt(fitness), inlier_fraction=len(inliers) / len(sq), seconds=seconds,
        # small_gicp reports the 0-based index of the last iteration.
        iterations=int(result.iterations) + 1, converged=bool(result.converged))


def point_to_point_icp(source: np.ndarray, target: np.ndarray, T_init: np.ndarray, *,
                       voxel_m: float | None = None, max_corr_m: float = 0.2,
                       max_iterations: int = 100, num_threads: int = 2) -> IcpResult:
    """Classical point-to-point ICP (Besl & McKay; the paper's PCL baseline)."""
    return run_icp("point_to_point", source, target, T_init, voxel_m=voxel_m,
                   max_corr_m=max_corr_m, max_iterations=max_iterations, num_threads=num_threads)


def point_to_plane_icp(source: np.ndarray, target: np.ndarray, T_init: np.ndarray, *,
                       voxel_m: float | None = None, max_corr_m: float = 0.2,
                       max_iterations: int = 100, num_threads: int = 2) -> IcpResult:
    """Point-to-plane ICP (KinectFusion's), with target normals from 20 neighbours."""
    return run_icp("point_to_plane", source, target, T_init, voxel_m=voxel_m,
                   max_corr_m=max_corr_m, max_iterations=max_iterations, num_threads=num_threads)
