"""The tracking stages, in the paper's order (Table "Time using of each part"):

    Extract -> Describe -> AssociateDepth -> Match -> EstimatePose -> DecideKeyframe

Stage k maps state k to state k+1 (see states.py). Stages before the offloading point run
on the robot and touch only the robot's side of the session; stages after it run in the
cloud and own the tracking map.
"""

from __future__ import annotations

import hashlib
import operator
from dataclasses import replace
from typing import Any, Protocol

import cv2
import numpy as np

from fleetslam.pipeline.local_ba import local_bundle_adjustment, reprojection_chi2
from fleetslam.pipeline.matching import descriptor_match, guided_match
from fleetslam.pipeline.pose_optimizer import CHI2_MONO, CHI2_STEREO, optimize_pose
from fleetslam.pipeline.session import TrackingSession
from fleetslam.pipeline.states import (
    CapturedFrame,
    DescribedFrame,
    DetectedFrame,
    FeatureFrame,
    MatchedFrame,
    PosedFrame,
    TrackedFrame,
)
from fleetslam.transforms import invert, rotation_angle_deg


class Stage(Protocol):
    name: str

    def __call__(self, state: Any, session: TrackingSession) -> Any: ...


# OpenCV's Python API hands keypoints over as objects; these two conversions do it column by
# column in C (KeyPoint_convert, map with attrgetter / the constructor) instead of a Python
# loop body per keypoint: 4x faster, same values.
_KEYPOINT_ATTRIBUTES = ("size", "angle", "response", "octave", "class_id")


def _keypoints_to_array(kps: tuple[cv2.KeyPoint, ...]) -> np.ndarray:
    n = len(kps)
    table = np.zeros((n, 7), dtype=np.float32)
    if n:
        table[:, :2] = cv2.KeyPoint_convert(kps).reshape(n, 2)
        for column, name in enumerate(_KEYPOINT_ATTRIBUTES, start=2):
            table[:, column] = np.fromiter(map(operator.attrgetter(name), kps), np.float64, n)
    return table


def _array_to_keypoints(table: np.ndarray) -> list[cv2.KeyPoint]:
    x, y, size, angle, response = (table[:, i].tolist() for i in range(5))
    octave, class_id = (table[:, i].astype(int).tolist() for i in (5, 6))
    return list(map(cv2.KeyPoint, x, y, size, angle, response, octave, class_id))


def spread_over_grid(table: np.ndarray, n: int, shape: tuple[int, int], cols: int, rows: int
                     ) -> np.ndarray:
    """Keep ``n`` keypoints spread over a grid: the strongest of each cell first, in rounds,
    so that texture-rich areas cannot take the whole budget."""
    if len(table) <= n:
        return table
    h, w = shape
    cell = (np.minimum((table[:, 1] * rows / h).astype(int), rows - 1) * cols
            + np.minimum((table[:, 0] * cols / w).astype(int), cols - 1))
    order = np.lexsort((-table[:, 4], cell))
    sorted_cell = cell[order]
    starts = np.searchsorted(sorted_cell, sorted_cell, side="left")
    rank_in_cell = np.arange(len(order)) - starts
    # Round by rank in cell, then by response within a round.
    pick = order[np.lexsort((-table[order, 4], rank_in_cell))][:n]
    return table[np.sort(pick)]


class Extract:
    """ORB keypoint detection (FAST on an image pyramid, oriented)."""

    name = "extract"

    def __call__(self, state: CapturedFrame, session: TrackingSession) -> DetectedFrame:
        gray = cv2.cvtColor(state.rgb, cv2.COLOR_RGB2GRAY)
        kps = session.orb.detect(gray, None)
        table = _keypoints_to_array(kps)
        cfg = session.config.orb
        table = spread_over_grid(table, cfg.n_features, gray.shape, cfg.grid_cols, cfg.grid_rows)
        # One canonical order (pyramid level, then row, then column): neighbours follow each
        # other, so the wire's delta-coded positions are small (OpenCV's order is partly
        # shuffled by its per-level selection), and Describe keeps it (it wants level order).
        table = table[np.lexsort((table[:, 0], table[:, 1], table[:, 5]))]
        return DetectedFrame(state.index, state.timestamp, gray, state.depth_m, table)


class Describe:
    """ORB (rotated BRIEF) descriptors of the detected keypoints."""

    name = "describe"

    def __call__(self, state: DetectedFrame, session: TrackingSession) -> DescribedFrame:
        kps, desc = session.orb.compute(state.gray, _array_to_keypoints(state.keypoints))
        table = _keypoints_to_array(kps)
        if desc is None:
            desc = np.zeros((0, 32), np.uint8)
        return DescribedFrame(state.index, state.timestamp, state.depth_m, table, desc)


class AssociateDepth:
    """Depth per keypoint (ORB-SLAM's 'compute stereo' for RGB-D) and undistortion.

    A keypoint on a depth edge gets no depth: its pixel mixes foreground and background,
    which would create a landmark floating in between."""

    name = "associate_depth"

    def __call__(self, state: DescribedFrame, session: TrackingSession) -> FeatureFrame:
        cfg = session.config.tracking
        depth_img = state.depth_m
        h, w = depth_img.shape
        u = np.clip(np.round(state.keypoints[:, 0]).astype(int), 1, w - 2)
        v = np.clip(np.round(state.keypoints[:, 1]).astype(int), 1, h - 2)
        du, dv = np.meshgrid([-1, 0, 1], [-1, 0, 1])
        patch = depth_img[v[:, None] + dv.ravel(), u[:, None] + du.ravel()]  # N x 9
        z = depth_img[v, u]
        valid = patch > 0
        spread = (np.where(valid, patch, -np.inf).max(axis=1)
                  - np.where(valid, patch, np.inf).min(axis=1))
        ok = (z >= cfg.min_depth_m) & (z <= cfg.max_depth_m) & (spread < 0.05 * z)
        # A depth image that is a byte-for-byte copy of the previous one (7-Scenes fills
        # dropped frames so) belongs to another instant than this colour image: its values
        # at the keypoints would be wrong, so the frame goes on without depth. (Every second
        # pixel of every second row is hashed: sensor noise changes far more pixels than
        # that between two real frames, and it is 4x cheaper.)
        digest = hashlib.blake2b(np.ascontiguousarray(depth_img[::2, ::2]).tobytes(),
                                 digest_size=16).digest()
        if digest == session.last_depth_digest:
            ok[:] = False
            session.stale_depth_frames += 1
        session.last_depth_digest = digest
        depth = np.where(ok, z, 0.0).astype(np.float32)
        uv = session.camera.undistort_points(state.keypoints[:, :2].astype(np.float64))
        return FeatureFrame(state.index, state.timestamp, state.keypoints, state.descriptors,
                            depth, uv)


class Match:
    """Match features to the local map: guided by the constant-velocity prediction, or
    against the whole local map when too few guided matches are found."""

    name = "match"

    def __call__(self, state: FeatureFrame, session: TrackingSession) -> MatchedFrame:
        n = len(state.keypoints)
        ids = np.full(n, -1, np.int64)
        T_pred = session.predict_pose()
        repeated = session.is_repeat_of_last(state)
        if not repeated and session.map.keyframes and n:
            ids = self._match(state, session, T_pred)
        xyz = np.full((n, 3), np.nan)
        xyz[ids >= 0] = session.map.xyz[ids[ids >= 0]]
        return MatchedFrame(state, ids, xyz, T_pred, repeated)

    def _match(self, state: FeatureFrame, session: TrackingSession, T_pred: np.ndarray
               ) -> np.ndarray:
        cfg = session.config.tracking
        cam = session.camera
        ids = np.full(len(state.keypoints), -1, np.int64)
        if not session.lost_frames:
            # Every live landmark of the map that falls in the predicted view is a candidate:
            # returning to a place matches the old landmarks, which bounds the drift.
            visible, proj, P = session.map.in_view(cam, T_pred, cfg.min_depth_m, cfg.max_depth_m)
            level = session.map.predicted_octave(visible, np.linalg.norm(P, axis=1),
                                                 session.config.orb.scale_factor,
                                                 session.config.orb.n_levels)
            ids = guided_match(state, session.map.descriptors, visible, proj, level,
                               cfg.guided_radius_px, session.config.orb.scale_factor,
                               cfg.max_hamming, cfg.match_ratio)
        if (ids >= 0).sum() < cfg.min_guided_matches:
            # Prediction too far off (fast rotation, after a loss): search the landmarks of
            # the newest keyframes by descriptor alone.
            pool = session.map.local_landmarks(cfg.local_map_keyframes)
            ids = descriptor_match(state.descriptors, session.map.descriptors[pool], pool,
                                   cfg.max_hamming, cfg.match_ratio)
        return ids



class EstimatePose:
    """PnP with RANSAC on the matches, then RGB-D motion-only bundle adjustment."""

    name = "estimate_pose"

    def __call__(self, state: MatchedFrame, session: TrackingSession) -> PosedFrame:
        cfg = session.config.tracking
        f = state.features
        n = len(f.keypoints)
        matched = np.flatnonzero(state.landmark_ids >= 0)
        inliers = np.zeros(n, bool)
        if not session.map.keyframes:
            # First frame: it defines the robot's map frame.
            return PosedFrame(state, np.eye(4), inliers, tracked=bool((f.depth > 0).sum()
                                                                        >= cfg.min_inliers))
        if state.repeated:
            # A repeated image carries no new observation: keep the motion prediction.
            return PosedFrame(state, state.T_world_camera_predicted, inliers,
                              tracked=session.last_tracked)
        if len(matched) < cfg.min_inliers:
            return PosedFrame(state, state.T_world_camera_predicted, inliers, tracked=False)
        obj = state.landmark_xyz[matched]
        img = f.uv[matched]
        T_cw = invert(state.T_world_camera_predicted)
        rvec, _ = cv2.Rodrigues(T_cw[:3, :3])
        ok, rvec, tvec, ransac_inliers = cv2.solvePnPRansac(
            obj, img, session.camera.K, None, rvec=rvec, tvec=T_cw[:3, 3].copy(),
            useExtrinsicGuess=False, iterationsCount=cfg.ransac_iterations,
            reprojectionError=cfg.ransac_reproj_px, confidence=cfg.ransac_confidence,
            flags=cv2.SOLVEPNP_SQPNP)
        if not ok or ransac_inliers is None or len(ransac_inliers) < cfg.min_inliers:
            return PosedFrame(state, state.T_world_camera_predicted, inliers, tracked=False)
        R, _ = cv2.Rodrigues(rvec)
        T_cw = np.eye(4)
        T_cw[:3, :3], T_cw[:3, 3] = R, tvec.ravel()
        scale = session.config.orb.scale_factor ** f.keypoints[matched, 5]
        T_wc, good = optimize_pose(session.camera, invert(T_cw), obj, img,
                                   f.depth[matched].astype(np.float64), scale,
                                   cfg.virtual_baseline_m)
        inliers[matched[good]] = True
        tracked = int(good.sum()) >= cfg.min_inliers
        if tracked and cfg.track_local_map:
            state, T_wc, inliers = track_local_map(session, state, T_wc, inliers)
            tracked = int(inliers.sum()) >= cfg.min_inliers
        return PosedFrame(state, T_wc if tracked else state.T_world_camera_predicted, inliers,
                          tracked)


def in_scale_range(session: TrackingSession, ids: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Landmarks ``ids`` at camera-frame points ``P`` whose distance lies within their
    scale-invariance range, ORB-SLAM's [0.8 d_min, 1.2 d_max] with d_max = d * s^octave,
    d_min = d_max / s^(levels - 1) (d, octave: of the landmark's reference view)."""
    orb, lmap = session.config.orb, session.map
    dist = np.linalg.norm(P, axis=1)
    d_max = lmap.distance[ids] * orb.scale_factor ** lmap.octave[ids]
    d_min = d_max / orb.scale_factor ** (orb.n_levels - 1)
    return (dist >= 0.8 * d_min) & (dist <= 1.2 * d_max)


def match_free_keypoints(session: TrackingSession, f: FeatureFrame, T_world_camera: np.ndarray,
                         matched_ids: np.ndarray, radius_px: float, max_hamming: int,
                         ratio: float, scale_check: bool) -> np.ndarray:
    """``matched_ids`` plus matches of its free keypoints (-1) to the live landmarks not yet
    matched, projected from ``T_world_camera`` and searched within ``radius_px``;
    ``scale_check`` also requires each landmark's scale-invariance distance range."""
    cfg, orb, lmap = session.config.tracking, session.config.orb, session.map
    free_kp = np.flatnonzero(matched_ids < 0)
    cand, proj, P = lmap.in_view(session.camera, T_world_camera, cfg.min_depth_m,
                                 cfg.max_depth_m)
    unmatched = np.ones(lmap.n_landmarks, bool)
    unmatched[matched_ids[matched_ids >= 0]] = False
    keep = unmatched[cand]
    if scale_check:
        keep[keep] = in_scale_range(session, cand[keep], P[keep])
    cand, proj, P = cand[keep], proj[keep], P[keep]
    ids = matched_ids.copy()
    if len(free_kp) and len(cand):
        level = lmap.predicted_octave(cand, np.linalg.norm(P, axis=1), orb.scale_factor,
                                      orb.n_levels)
        sub = replace(f, keypoints=f.keypoints[free_kp], descriptors=f.descriptors[free_kp],
                      depth=f.depth[free_kp], uv=f.uv[free_kp])
        ids[free_kp] = guided_match(sub, lmap.descriptors, cand, proj, level, radius_px,
                                    orb.scale_factor, max_hamming, ratio)
    return ids


def track_local_map(session: TrackingSession, state: MatchedFrame, T_world_camera: np.ndarray,
                    inliers: np.ndarray) -> tuple[MatchedFrame, np.ndarray, np.ndarray]:
    """ORB-SLAM's TrackLocalMap: with the pose now known, project the live landmarks not yet
    matched into the frame and search the keypoints left free within a few pixels, then
    refine the pose on all matches. Returns (matched frame with the new associations, pose,
    inlier mask)."""
    cfg, orb, lmap = session.config.tracking, session.config.orb, session.map
    f = state.features
    ids = match_free_keypoints(session, f, T_world_camera,
                               np.where(inliers, state.landmark_ids, -1),
                               cfg.local_map_radius_px, cfg.max_hamming, cfg.match_ratio,
                               scale_check=True)
    matched = np.flatnonzero(ids >= 0)
    xyz = np.full((len(ids), 3), np.nan)
    xyz[matched] = lmap.xyz[ids[matched]]
    scale = orb.scale_factor ** f.keypoints[matched, 5]
    T_wc, good = optimize_pose(session.camera, T_world_camera, xyz[matched], f.uv[matched],
                               f.depth[matched].astype(np.float64), scale,
                               cfg.virtual_baseline_m)
    out = np.zeros(len(ids), bool)
    out[matched[good]] = True
    return replace(state, landmark_ids=ids, landmark_xyz=xyz), T_wc, out


class DecideKeyframe:
    """Keyframe decision, map update and motion bookkeeping (the paper's 'Others')."""

    name = "decide_keyframe"

    def __call__(self, state: PosedFrame, session: TrackingSession) -> TrackedFrame:
        cfg = session.config.tracking
        f = state.matched.features
        is_kf = False
        if not session.map.keyframes:
            is_kf = state.tracked
        elif state.tracked and not state.matched.repeated:
            ref = session.map.keyframes[-1]
            T_rel = invert(ref.T_world_camera) @ state.T_world_camera
            n_in = int(state.inliers.sum())
            # Inliers fall against the first frame tracked after the keyframe: the view has
            # moved on. (The keyframe's own landmark count is no reference: many of its
            # keypoints are never matched again.)
            reference = session.inliers_after_keyframe or n_in
            is_kf = (n_in < cfg.keyframe_inlier_ratio * reference
                     or np.linalg.norm(T_rel[:3, 3]) > cfg.keyframe_translation_m
                     or rotation_angle_deg(T_rel[:3, :3]) > cfg.keyframe_rotation_deg
                     or (cfg.orb_slam_keyframe_policy and orb_slam_needs_keyframe(session, state)))
        elif not state.tracked and session.lost_frames + 1 >= cfg.lost_frames_before_reset:
            # Lost for too long: continue from the prediction with fresh landmarks.
            is_kf = True
            session.resets += 1
        lmap = session.map
        if state.tracked and not state.matched.repeated and lmap.keyframes:
            count_views(session, state)
        if is_kf:
            matched_ids = np.where(state.inliers, state.matched.landmark_ids, -1)
            if cfg.fuse_at_keyframe and lmap.keyframes and state.tracked:
                matched_ids = fuse_search(session, f, state.T_world_camera, matched_ids)
            kf = lmap.add_keyframe(session.camera, f.index, f.timestamp, state.T_world_camera,
                                   f.uv, f.depth, f.descriptors,
                                   f.keypoints[:, 5].astype(np.int64), matched_ids)
            if cfg.cull_landmarks:
                session.culled_landmarks += lmap.cull_recent(
                    kf.id, cfg.cull_min_found_ratio, cfg.cull_min_observation_weight,
                    cfg.cull_probation_keyframes)
            if cfg.local_ba and kf.id > 0:
                result = local_bundle_adjustment(
                    lmap, session.camera, kf.id, baseline_m=cfg.virtual_baseline_m,
                    scale_factor=session.config.orb.scale_factor,
                    window_size=cfg.local_ba_window, min_shared=cfg.covisibility_min_shared,
                    iterations=tuple(cfg.local_ba_iterations))
                session.local_ba_seconds.append(result.seconds)
                session.local_ba_outliers += result.n_outliers
                # The frame is the keyframe: report its refined pose, and move the previous
                # pose with it so the constant-velocity model keeps its velocity.
                state = replace(state, T_world_camera=kf.T_world_camera.copy())
                if session.T_last is not None:
                    session.T_last = result.correction @ session.T_last
            # ORB-SLAM's reference: the keyframe's landmarks with enough observations
            # (3, or 2 while the map has at most two keyframes; with depth counts 2).
            min_weight = 3 if len(lmap.keyframes) > 2 else 2
            session.reference_tracked = lmap.tracked_by_keyframe(kf.id, min_weight)
        session.record(state, f, is_kf)
        return TrackedFrame(state, is_kf)


def orb_slam_needs_keyframe(session: TrackingSession, state: PosedFrame) -> bool:
    """ORB-SLAM's keyframe test for RGB-D (with local mapping always idle, as it runs
    in-line): the frame tracks fewer than a fraction of the landmarks the reference keyframe
    tracks (those with enough observations to be established), or it tracks few close points
    while many close points could be created."""
    cfg = session.config.tracking
    inliers = state.inliers
    n_in = int(inliers.sum())
    depth = state.matched.features.depth
    close = (depth > 0) & (depth < cfg.close_depth_baselines * cfg.virtual_baseline_m)
    need_close = (int((close & inliers).sum()) < cfg.keyframe_close_tracked
                  and int((close & ~inliers).sum()) > cfg.keyframe_close_untracked)
    return n_in < cfg.keyframe_reference_ratio * session.reference_tracked or need_close


def count_views(session: TrackingSession, state: PosedFrame) -> None:
    """ORB-SLAM's visible/found counters for one tracked frame: landmarks predicted in view
    at the estimated pose (inside the image, within their scale-invariance distance range)
    and the landmarks matched as pose inliers."""
    cfg, lmap = session.config.tracking, session.map
    ids, _, P = lmap.in_view(session.camera, state.T_world_camera, cfg.min_depth_m,
                             cfg.max_depth_m)
    ids = ids[in_scale_range(session, ids, P)]
    found = state.matched.landmark_ids[state.inliers]
    lmap.count_views(ids, found[found >= 0])


def fuse_search(session: TrackingSession, f: FeatureFrame, T_world_camera: np.ndarray,
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


def default_stages() -> list[Stage]:
    return [Extract(), Describe(), AssociateDepth(), Match(), EstimatePose(), DecideKeyframe()]
