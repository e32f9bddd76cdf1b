"""Local mapping (ORB-SLAM's LocalMapping): what happens to the map when the tracker makes
a keyframe.

    insert keyframe -> fuse (known landmarks seen again) -> new landmarks -> cull -> local BA

It runs in-line, at the keyframe, on the thread that tracks: the next frame is matched
against the map as local BA left it, so poses are the same in every process and at every
split point (the exactness tests rely on it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetslam.pipeline.local_ba import local_bundle_adjustment, reprojection_chi2
from fleetslam.pipeline.local_map import Keyframe
from fleetslam.pipeline.matching import match_free_keypoints
from fleetslam.pipeline.pose_optimizer import CHI2_MONO, CHI2_STEREO
from fleetslam.pipeline.session import CloudSession
from fleetslam.pipeline.states import FeatureFrame, PosedFrame


@dataclass
class InsertedKeyframe:
    keyframe: Keyframe
    # World-frame correction local BA applied to the keyframe: T_new = correction @ T_old.
    correction: np.ndarray


def insert_keyframe(session: CloudSession, state: PosedFrame) -> InsertedKeyframe:
    """Add the frame as a keyframe: its inlier matches become observations (plus those
    fusion finds), its other keypoints with depth become landmarks; then cull recent
    landmarks and bundle-adjust the keyframe's neighbourhood."""
    cfg = session.config.tracking
    lmap = session.map
    f = state.matched.features
    matched_ids = np.where(state.inliers, state.matched.landmark_ids, -1)
    if cfg.fuse_at_keyframe and lmap.keyframes and state.tracked:
        matched_ids = fuse_search(session, f, state.T_world_camera, matched_ids)
    kf = lmap.add_keyframe(session.camera, f, state.T_world_camera, matched_ids)
    if cfg.cull_landmarks:
        session.culled_landmarks += lmap.cull_recent(
            kf.id, cfg.cull_min_found_ratio, cfg.cull_min_observation_weight,
            cfg.cull_probation_keyframes)
    correction = np.eye(4)
    if cfg.local_ba and kf.id > 0:
        result = local_bundle_adjustment(
            lmap, session.camera, kf.id, baseline_m=cfg.virtual_baseline_m,
            scale_factor=session.config.orb.scale_factor,
            window_size=cfg.local_ba_window, min_shared=cfg.covisibility_min_shared,
            iterations=tuple(cfg.local_ba_iterations))
        session.local_ba_seconds.append(result.seconds)
        session.local_ba_outliers += result.n_outliers
        correction = result.correction
    # ORB-SLAM's reference: the keyframe's landmarks with enough observations
    # (3, or 2 while the map has at most two keyframes; with depth counts 2).
    min_weight = 3 if len(lmap.keyframes) > 2 else 2
    session.reference_tracked = lmap.tracked_by_keyframe(kf.id, min_weight)
    return InsertedKeyframe(kf, correction)


def fuse_search(session: CloudSession, f: FeatureFrame, T_world_camera: np.ndarray,
                matched_ids: np.ndarray) -> np.ndarray:
    """At a keyframe, search the keypoints tracking left unmatched against the live landmarks
    projected from the keyframe's pose, within a few pixels (ORB-SLAM's Fuse): a match that
    is also consistent with the keypoint's depth becomes an observation of the old landmark
    instead of a duplicate landmark. Returns the updated ``matched_ids``."""
    cfg, orb, lmap = session.config.tracking, session.config.orb, session.map
    if not (matched_ids < 0).any():
        return matched_ids
    ids = match_free_keypoints(session, f, T_world_camera, matched_ids, cfg.fuse_radius_px,
                               cfg.fuse_max_hamming, 1.0, scale_check=False)
    kp = np.flatnonzero((ids >= 0) & (matched_ids < 0))
    if not len(kp):
        return matched_ids
    lm = ids[kp]
    depth = f.depth[kp].astype(np.float64)
    chi2, z = reprojection_chi2(session.camera, session.camera.fx * cfg.virtual_baseline_m,
                                np.broadcast_to(T_world_camera, (len(kp), 4, 4)), lmap.xyz[lm],
                                f.uv[kp], depth, orb.scale_factor ** f.keypoints[kp, 5])
    ok = (chi2 <= np.where(depth > 0, CHI2_STEREO, CHI2_MONO)) & (z > 0)
    out = matched_ids.copy()
    out[kp[ok]] = lm[ok]
    session.fused_observations += int(ok.sum())
    return out
