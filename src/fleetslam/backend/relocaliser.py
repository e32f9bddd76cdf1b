"""Relocalisation (ORB-SLAM's Relocalization): when the frame cannot be tracked from the
motion prediction (a blackout, fast motion, a gap in the frames), find its pose against
the robot's own keyframes and carry on in the same map frame.

    place recognition over all keyframes -> descriptor matches against each candidate's
    place -> PnP RANSAC + motion-only BA -> projection search over the whole map -> refine
"""

from __future__ import annotations

import numpy as np

from fleetslam.backend.matching import descriptor_match, match_free_keypoints
from fleetslam.backend.pose_optimizer import optimize_pose, pnp_pose
from fleetslam.backend.state import BackEndState
from fleetslam.pipeline.states import FeatureFrame


def relocalise(backend: BackEndState, f: FeatureFrame
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(T_world_camera, landmark id per keypoint, inlier mask), or None if no candidate
    keyframe gives enough inliers."""
    cfg = backend.config.relocalisation
    tcfg, orb, lmap = backend.config.tracking, backend.config.orb, backend.map
    if not len(backend.places) or not len(f.keypoints):
        return None
    scale = orb.scale_factor ** f.keypoints[:, 5]
    depth = f.depth.astype(np.float64)
    # Culled keyframes observe nothing: no candidates.
    allowed = lmap.observing()[: len(backend.places)]
    for candidate in backend.places.query(f.descriptors, allowed, top_k=cfg.candidates):
        kf = lmap.keyframes[candidate.key]
        pool = lmap.place_landmarks(kf.id, backend.config.loop_closing.candidate_neighbours)
        ids = descriptor_match(f.descriptors, lmap.descriptors[pool], pool, tcfg.max_hamming,
                               tcfg.match_ratio)
        matched = np.flatnonzero(ids >= 0)
        solved = pnp_pose(backend.camera, lmap.xyz[ids[matched]], f.uv[matched],
                          depth[matched], scale[matched], tcfg.virtual_baseline_m,
                          kf.T_world_camera, tcfg.ransac_iterations, tcfg.ransac_reproj_px,
                          tcfg.ransac_confidence, tcfg.min_inliers, refine_all=False)
        if solved is None:
            continue
        T_wc, good = solved
        if good.sum() < tcfg.min_inliers:
            continue
        # With a pose, every landmark in view can be searched near its projection.
        kept = np.full(len(ids), -1, np.int64)
        kept[matched[good]] = ids[matched[good]]
        ids = match_free_keypoints(backend, f, T_wc, kept, tcfg.local_map_radius_px,
                                   tcfg.max_hamming, tcfg.match_ratio, scale_check=True)
        matched = np.flatnonzero(ids >= 0)
        T_wc, good = optimize_pose(backend.camera, T_wc, lmap.xyz[ids[matched]], f.uv[matched],
                                   depth[matched], scale[matched], tcfg.virtual_baseline_m)
        if good.sum() >= cfg.min_inliers:
            inliers = np.zeros(len(ids), bool)
            inliers[matched[good]] = True
            return T_wc, np.where(inliers, ids, -1), inliers
    return None
