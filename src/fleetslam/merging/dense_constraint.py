"""Dense refinement of a constraint between two keyframes: GICP (small_gicp) of their depth
clouds, started from the feature estimate.

A feature constraint (descriptor matches, RANSAC, reprojection refinement) rests on a few
hundred keypoints and the colour camera's model; on 7-Scenes it is 1-7 degrees off. The
depth clouds carry the scene's geometry in the depth camera's own model, so GICP takes the
estimate much closer, where the clouds constrain it. Where they do not (a wall, a floor:
GICP slides along planes), its Hessian is weak, and the feature estimate is kept there:

    x_dense, H   GICP from x_feature (converged, enough overlap, near the start, or refused)
    fused        argmin |x - x_feature|^2_Lf + |x - x_dense|^2_(s H)   (one Gauss-Newton
                 step in the tangent space at x_dense; information Lf + s H)

``s`` turns GICP's Hessian (its covariances are normalised, so H has no unit of belief) into
an information matrix: H is scaled so its stiffest translation direction gets
``merge.dense_sigma_translation_m`` (every other direction keeps its ratio to that one).

Poses and information are in gtsam's Pose3 convention, which small_gicp shares: tangent
[rotation, translation], perturbation on the right (T_place_query * Exp(d)).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np
import small_gicp

from fleetslam.config import MergeConfig
from fleetslam.registration.metrics import transform_error


@dataclass
class DenseRefinement:
    """The outcome of one refinement: accepted (``T_place_query`` and ``information`` set)
    or refused (``reason``)."""

    accepted: bool
    reason: str  # why refused; "" when accepted
    T_place_query: np.ndarray | None  # the fused measurement
    information: np.ndarray | None  # 6 x 6, tangent [rotation, translation]
    moved_rotation_deg: float  # GICP's result against the feature start
    moved_translation_m: float
    overlap: float  # source points with a correspondence, as a fraction
    iterations: int
    seconds: float
    T_dense: np.ndarray | None = None  # GICP's own result, before the fusion

    def to_json(self) -> dict[str, object]:
        return {"accepted": self.accepted, "reason": self.reason,
                "moved_rotation_deg": self.moved_rotation_deg,
                "moved_translation_m": self.moved_translation_m,
                "overlap": self.overlap, "iterations": self.iterations,
                "ms": 1000.0 * self.seconds}


def information(sigma_rotation_deg: float, sigma_translation_m: float) -> np.ndarray:
    """The 6 x 6 information of an edge with these isotropic sigmas (tangent order)."""
    sigmas = np.array([np.deg2rad(sigma_rotation_deg)] * 3 + [sigma_translation_m] * 3)
    return np.diag(1.0 / sigmas ** 2)


def feature_information(cfg: MergeConfig) -> np.ndarray:
    """The information of a feature constraint (the inter-robot edge's sigmas)."""
    return information(cfg.inter_sigma_rotation_deg, cfg.inter_sigma_translation_m)


def _scaled_hessian(H: np.ndarray, sigma_translation_m: float) -> np.ndarray:
    """H scaled so its stiffest translation direction has ``sigma_translation_m``."""
    H = 0.5 * (H + H.T)
    stiffest = float(np.linalg.eigvalsh(H[3:, 3:])[-1])
    return H / (stiffest * sigma_translation_m ** 2)


def fuse(T_feature: np.ndarray, info_feature: np.ndarray, T_dense: np.ndarray,
         info_dense: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pose that best agrees with both estimates under their informations (one step in
    the tangent space at ``T_dense``; the two are a few degrees apart at most)."""
    delta_f = gtsam.Pose3.Logmap(gtsam.Pose3(T_dense).between(gtsam.Pose3(T_feature)))
    info = info_feature + info_dense
    step = np.linalg.solve(info, info_feature @ delta_f)
    fused = gtsam.Pose3(T_dense).compose(gtsam.Pose3.Expmap(step))
    return fused.matrix(), info


@dataclass
class DenseCloud:
    """A keyframe's depth cloud made ready for GICP once (downsampled, covariances, tree),
    however many constraints it takes part in."""

    points: int  # before downsampling
    cloud: small_gicp.PointCloud
    tree: small_gicp.KdTree


def prepare(points: np.ndarray, cfg: MergeConfig) -> DenseCloud:
    """``points``: N x 3 in the keyframe's camera frame."""
    cloud, tree = small_gicp.preprocess_points(np.asarray(points, np.float64),
                                               downsampling_resolution=cfg.dense_voxel_m,
                                               num_neighbors=cfg.dense_neighbours)
    return DenseCloud(len(points), cloud, tree)


def refine(place: np.ndarray | DenseCloud, query: np.ndarray | DenseCloud,
           T_place_query: np.ndarray, cfg: MergeConfig) -> DenseRefinement:
    """Refine a constraint between two keyframes from their clouds, each in its own camera
    frame (N x 3, or prepared). The feature estimate ``T_place_query`` (an inter-robot
    feature constraint, of that information) starts GICP, and is fused with its result."""
    found = register(place, query, T_place_query, cfg)
    if not found.accepted:
        return found
    found.T_place_query, found.information = fuse(
        T_place_query, feature_information(cfg), found.T_dense, found.information)
    return found


def register(place: np.ndarray | DenseCloud, query: np.ndarray | DenseCloud,
             T_start: np.ndarray, cfg: MergeConfig) -> DenseRefinement:
    """GICP of two keyframes' clouds from ``T_start`` (place <- query), refused unless it
    converges on enough overlapping points near the start; accepted, its measurement is
    GICP's own, with its Hessian scaled (nothing fused: the start may be no measurement)."""
    start = time.perf_counter()

    def refused(reason: str, moved: tuple[float, float] = (0.0, 0.0), overlap: float = 0.0,
                iterations: int = 0) -> DenseRefinement:
        return DenseRefinement(False, reason, None, None, moved[0], moved[1], overlap,
                               iterations, time.perf_counter() - start)

    n_place = place.points if isinstance(place, DenseCloud) else len(place)
    n_query = query.points if isinstance(query, DenseCloud) else len(query)
    if min(n_place, n_query) < cfg.dense_min_points:
        return refused(f"too few depth points ({n_place} / {n_query}, "
                       f"need {cfg.dense_min_points})")
    target = place if isinstance(place, DenseCloud) else prepare(place, cfg)
    source = query if isinstance(query, DenseCloud) else prepare(query, cfg)
    result = small_gicp.align(target.cloud, source.cloud, target.tree, T_start,
                              registration_type="GICP",
                              max_correspondence_distance=cfg.dense_max_correspondence_m,
                              max_iterations=cfg.dense_max_iterations)
    moved = transform_error(result.T_target_source, T_start)
    how_far = (moved.rotation_deg, moved.translation_m)
    overlap = result.num_inliers / max(source.cloud.size(), 1)
    if not result.converged:
        return refused(f"GICP did not converge in {result.iterations} iterations", how_far,
                       overlap, result.iterations)
    if overlap < cfg.dense_min_overlap:
        return refused(f"overlap {overlap:.2f} below {cfg.dense_min_overlap}", how_far, overlap,
                       result.iterations)
    if moved.rotation_deg > cfg.dense_max_rotation_deg \
            or moved.translation_m > cfg.dense_max_translation_m:
        return refused(f"moved {moved.rotation_deg:.1f} deg / {moved.translation_m:.3f} m from "
                       f"the start (at most {cfg.dense_max_rotation_deg} deg / "
                       f"{cfg.dense_max_translation_m} m)", how_far, overlap, result.iterations)
    H = np.asarray(result.H, np.float64)
    if not np.isfinite(H).all() or np.linalg.eigvalsh(0.5 * (H + H.T))[-1] <= 0:
        return refused("GICP's Hessian is degenerate", how_far, overlap, result.iterations)
    T = np.asarray(result.T_target_source, np.float64)
    return DenseRefinement(True, "", T, _scaled_hessian(H, cfg.dense_sigma_translation_m),
                           how_far[0], how_far[1], overlap, result.iterations,
                           time.perf_counter() - start, T)
