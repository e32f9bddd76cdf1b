"""Inter-robot place recognition: does a new keyframe of one robot show a place that
another robot has mapped, and where is its camera in that place's camera frame?

    query (the other robot's keyframe database, the same component loop closing uses)
    -> descriptor matches between depth-backed keypoints of the two keyframes
    -> 3D-3D RANSAC (each side back-projected from its own depth)
    -> refinement of the query pose against the place's points (reprojection with depth)

Everything works on keyframe summaries (features and pose), never on another robot's live
session, so the merger can run on its own thread (or process) while robots keep tracking.
Whether a verified match becomes a constraint is the merger's decision (consistency).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.backend.geometric_verification import ransac_rigid
from fleetslam.backend.local_map import Keyframe
from fleetslam.backend.matching import descriptor_match
from fleetslam.backend.pose_optimizer import optimize_pose
from fleetslam.pipeline.states import FeatureFrame
from fleetslam.wire.merger_keyframes import KeyframeSummary


def keyframe_summary(robot: str, keyframe: Keyframe) -> KeyframeSummary:
    """What the merger takes of one keyframe of a robot's map, as the map has it now."""
    return KeyframeSummary(robot, keyframe.id, keyframe.frame_index, keyframe.timestamp,
                           keyframe.features, keyframe.T_world_camera.copy())


@dataclass
class PlaceMatch:
    """A verified view of the same place by two robots' keyframes."""

    query: KeyframeSummary
    place: KeyframeSummary
    T_place_query: np.ndarray  # pose of the query camera in the place camera's frame
    score: float  # place-recognition score
    ransac_inliers: int
    inliers: int  # after refinement


def _depth_backed(features: FeatureFrame) -> np.ndarray:
    return np.flatnonzero(features.depth > 0)


def verify_places(query: KeyframeSummary, query_camera: Camera, place: KeyframeSummary,
                  place_camera: Camera, score: float, config: Config) -> PlaceMatch | None:
    """Geometric check of ``query`` against ``place``; None when too few matches agree."""
    return verify_counting(query, query_camera, place, place_camera, score, config)[0]


def verify_counting(query: KeyframeSummary, query_camera: Camera, place: KeyframeSummary,
                    place_camera: Camera, score: float, config: Config
                    ) -> tuple[PlaceMatch | None, int]:
    """``verify_places``, and how many descriptor matches it started from."""
    cfg, lcfg, tcfg = config.merge, config.loop_closing, config.tracking
    qf, pf = query.features, place.features
    q_idx, p_idx = _depth_backed(qf), _depth_backed(pf)
    if min(len(q_idx), len(p_idx)) < lcfg.min_ransac_inliers:
        return None, 0
    ids = descriptor_match(qf.descriptors[q_idx], pf.descriptors[p_idx], p_idx,
                           tcfg.max_hamming, tcfg.match_ratio)
    kp, pp = q_idx[ids >= 0], ids[ids >= 0]
    if len(kp) < lcfg.min_ransac_inliers:
        return None, len(kp)
    q_depth = qf.depth[kp].astype(np.float64)
    src = query_camera.backproject(qf.uv[kp], q_depth)
    dst = place_camera.backproject(pf.uv[pp], pf.depth[pp].astype(np.float64))
    threshold = np.maximum(lcfg.ransac_inlier_m, lcfg.ransac_inlier_depth_ratio * q_depth)
    rng = np.random.default_rng(cfg.seed + query.keyframe)
    rigid = ransac_rigid(src, dst, threshold, lcfg.ransac_iterations, lcfg.min_ransac_inliers,
                         rng)
    if rigid is None:
        return None, len(kp)
    # Reprojection refinement over every descriptor match (the RANSAC outliers get another
    # chance at the refined pose; the chi-square test decides).
    T, good = optimize_pose(query_camera, rigid.T_target_source, dst, qf.uv[kp], q_depth,
                            config.orb.scale_factor ** qf.keypoints[kp, 5],
                            tcfg.virtual_baseline_m)
    if good.sum() < cfg.min_refined_inliers:
        return None, len(kp)
    return PlaceMatch(query, place, T, score, rigid.n_inliers, int(good.sum())), len(kp)
