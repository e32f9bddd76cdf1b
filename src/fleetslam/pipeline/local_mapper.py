"""Local mapping (ORB-SLAM's LocalMapping): what happens to the map when the tracker makes
a keyframe.

    insert keyframe -> fuse (known landmarks seen again) -> new landmarks -> cull -> local BA

Insertion, fusion and culling run in-line, at the keyframe, on the thread that tracks.
Local BA runs in-line too when ``tracking.local_mapping`` is "inline": the next frame is
matched against the map as local BA left it, so poses are the same in every process and at
every split point (the exactness tests rely on it). In the cloud it is "async": the solve
goes to a worker process and its result lands a few frames later
(``local_mapping_worker``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetslam.pipeline.local_ba import (
    LocalBAProblem,
    LocalBASolution,
    apply_local_ba,
    local_ba_problem,
    reprojection_chi2,
    solve_local_ba,
)
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
        if session.local_mapping is not None:
            session.local_mapping.request(session, kf.id)
        else:
            problem = build_problem(session, kf.id)
            if problem is not None:
                correction = apply_solution(session, problem, solve_local_ba(problem))
    update_reference(session)
    return InsertedKeyframe(kf, correction)


def build_problem(session: CloudSession, kf_id: int) -> LocalBAProblem | None:
    """The local BA problem around keyframe ``kf_id``, as the config asks."""
    cfg = session.config.tracking
    return local_ba_problem(
        session.map, session.camera, kf_id, baseline_m=cfg.virtual_baseline_m,
        scale_factor=session.config.orb.scale_factor, window_size=cfg.local_ba_window,
        min_shared=cfg.covisibility_min_shared, iterations=tuple(cfg.local_ba_iterations))


def apply_solution(session: CloudSession, problem: LocalBAProblem,
                   solution: LocalBASolution | None) -> np.ndarray:
    """Write a local BA solution into the session's map (None: the solve failed, nothing
    changes). Returns the world-frame correction of the problem's keyframe."""
    if solution is None:
        return np.eye(4)
    result = apply_local_ba(session.map, problem, solution)
    session.local_ba_seconds.append(result.seconds)
    session.local_ba_outliers += result.n_outliers
    return result.correction


def update_reference(session: CloudSession) -> None:
    """ORB-SLAM's reference for the keyframe test: the newest keyframe's landmarks with
    enough observations (3, or 2 while the map has at most two keyframes; with depth
    counts 2)."""
    lmap = session.map
    min_weight = 3 if len(lmap.keyframes) > 2 else 2
    session.reference_tracked = lmap.tracked_by_keyframe(lmap.keyframes[-1].id, min_weight)


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
