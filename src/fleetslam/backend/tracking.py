"""Tracking (ORB-SLAM's Tracking): the back-end's stages that give every frame its pose.

    predict (constant velocity) -> Match -> EstimatePose (PnP + motion-only BA,
    relocalisation when lost) -> DecideKeyframe

Each stage reads and updates only the ``BackEndState``. A new keyframe goes to the back-end's
peers, local mapping and loop closing, through the hook ``DecideKeyframe`` is built with
(backend/back_end.py wires them).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, Protocol

import numpy as np

from fleetslam.backend.matching import descriptor_match, guided_match, in_scale_range
from fleetslam.backend.pose_optimizer import optimize_pose, pnp_pose
from fleetslam.backend.relocaliser import relocalise
from fleetslam.backend.state import BackEndState
from fleetslam.pipeline.states import FeatureFrame, MatchedFrame, PosedFrame, TrackedFrame
from fleetslam.transforms import rotation_angles_deg


class Match:
    """Match features to the local map: guided by the constant-velocity prediction, or
    against the whole local map when too few guided matches are found."""

    name = "match"
    side = "cloud"

    def __call__(self, state: FeatureFrame, backend: BackEndState) -> MatchedFrame:
        n = len(state.keypoints)
        ids = np.full(n, -1, np.int64)
        T_pred = backend.predict_pose()
        repeated = backend.is_repeat_of_last(state)
        if not repeated and backend.map.keyframes and n:
            ids = self._match(state, backend, T_pred)
        xyz = np.full((n, 3), np.nan)
        xyz[ids >= 0] = backend.map.xyz[ids[ids >= 0]]
        return MatchedFrame(state, ids, xyz, T_pred, repeated)

    def _match(self, state: FeatureFrame, backend: BackEndState, T_pred: np.ndarray
               ) -> np.ndarray:
        cfg = backend.config.tracking
        cam = backend.camera
        ids = np.full(len(state.keypoints), -1, np.int64)
        if not backend.lost_frames:
            # Every live landmark of the map that falls in the predicted view is a candidate:
            # returning to a place matches the old landmarks, which bounds the drift.
            visible, proj, P = backend.map.in_view(cam, T_pred, cfg.min_depth_m, cfg.max_depth_m,
                                                   ids=backend.tracking_landmarks())
            level = backend.map.predicted_octave(visible, np.linalg.norm(P, axis=1),
                                                 backend.config.orb.scale_factor,
                                                 backend.config.orb.n_levels)
            radii = [r for r in (cfg.guided_narrow_radius_px, cfg.guided_radius_px) if r > 0]
            for radius in sorted(set(radii)):
                ids = guided_match(state, backend.map.descriptors, visible, proj, level,
                                   radius, backend.config.orb.scale_factor,
                                   cfg.max_hamming, cfg.match_ratio)
                if (ids >= 0).sum() >= cfg.min_guided_matches:
                    break
        if (ids >= 0).sum() < cfg.min_guided_matches:
            # Prediction too far off (fast rotation, after a loss): search the landmarks of
            # the newest keyframes by descriptor alone.
            pool = backend.map.local_landmarks(cfg.local_map_keyframes)
            ids = descriptor_match(state.descriptors, backend.map.descriptors[pool], pool,
                                   cfg.max_hamming, cfg.match_ratio)
        return ids


class EstimatePose:
    """RGB-D motion-only bundle adjustment from the motion model's prediction (kept when
    most matches agree: ORB-SLAM's TrackWithMotionModel), else PnP with RANSAC on the
    matches and then the refinement; when that fails, relocalisation against all of the
    robot's keyframes. Both paths end at the same optimum on these sequences (ATE equal to
    1e-9 m), the first without RANSAC's ~4 ms."""

    name = "estimate_pose"
    side = "cloud"

    def __call__(self, state: MatchedFrame, backend: BackEndState) -> PosedFrame:
        cfg = backend.config.tracking
        f = state.features
        n = len(f.keypoints)
        inliers = np.zeros(n, bool)
        if not backend.map.keyframes:
            # First frame: it defines the robot's map frame.
            return PosedFrame(state, np.eye(4), inliers, tracked=bool((f.depth > 0).sum()
                                                                        >= cfg.min_inliers))
        if state.repeated:
            # A repeated image carries no new observation: keep the motion prediction.
            return PosedFrame(state, state.T_world_camera_predicted, inliers,
                              tracked=backend.last_tracked)
        posed = self._track(state, backend)
        if posed.tracked or not backend.config.relocalisation.enabled:
            return posed
        found = relocalise(backend, f)
        if found is None:
            return posed
        backend.relocalisations += 1
        T_wc, ids, good = found
        xyz = np.full((n, 3), np.nan)
        xyz[ids >= 0] = backend.map.xyz[ids[ids >= 0]]
        return PosedFrame(replace(state, landmark_ids=ids, landmark_xyz=xyz), T_wc, good, True)

    def _track(self, state: MatchedFrame, backend: BackEndState) -> PosedFrame:
        cfg = backend.config.tracking
        f = state.features
        inliers = np.zeros(len(f.keypoints), bool)
        matched = np.flatnonzero(state.landmark_ids >= 0)
        lost = PosedFrame(state, state.T_world_camera_predicted, inliers, tracked=False)
        if len(matched) < cfg.min_inliers:
            return lost
        xyz, uv = state.landmark_xyz[matched], f.uv[matched]
        depth = f.depth[matched].astype(np.float64)
        scale = backend.config.orb.scale_factor ** f.keypoints[matched, 5]
        solved = None
        if cfg.prediction_min_inlier_ratio > 0:
            T_wc, good = optimize_pose(backend.camera, state.T_world_camera_predicted, xyz, uv,
                                       depth, scale, cfg.virtual_baseline_m)
            if good.sum() >= max(cfg.min_inliers, cfg.prediction_min_inlier_ratio * len(good)):
                solved = T_wc, good
        if solved is None:
            backend.pnp_fallbacks += 1
            solved = pnp_pose(backend.camera, xyz, uv, depth, scale, cfg.virtual_baseline_m,
                              state.T_world_camera_predicted, cfg.ransac_iterations,
                              cfg.ransac_reproj_px, cfg.ransac_confidence, cfg.min_inliers)
        if solved is None:
            return lost
        T_wc, good = solved
        inliers[matched[good]] = True
        tracked = int(good.sum()) >= cfg.min_inliers
        return PosedFrame(state, T_wc if tracked else state.T_world_camera_predicted, inliers,
                          tracked)


# What the back-end does with a new keyframe (local mapping, then loop closing); returns
# the keyframe's pose after them.
NewKeyframe = Callable[[PosedFrame], np.ndarray]


class MapperStatus(Protocol):
    """What the keyframe decision asks the local mapper (local_mapping.py)."""

    def busy(self) -> bool:
        """A local BA is still in a worker."""

    def settling(self) -> bool:
        """The newest keyframe's local BA has not landed yet."""


class InlineMapper:
    """A mapper that is done with each keyframe before the next frame (in-line)."""

    def busy(self) -> bool:
        return False

    def settling(self) -> bool:
        return False


class DecideKeyframe:
    """The keyframe decision; a keyframe then goes to the back-end's local mapper and loop
    closer (``new_keyframe``, on this thread; with the cloud's workers their local BA and
    database query land at later frames: back_end.py). Also the motion bookkeeping (the
    paper's 'Others')."""

    name = "decide_keyframe"
    side = "cloud"

    def __init__(self, new_keyframe: NewKeyframe, mapper: MapperStatus | None = None) -> None:
        self.new_keyframe = new_keyframe
        self.mapper = mapper if mapper is not None else InlineMapper()

    def __call__(self, state: PosedFrame, backend: BackEndState) -> TrackedFrame:
        f = state.matched.features
        reason = keyframe_reason(backend, state, self.mapper.busy())
        is_kf = reason is not None
        if is_kf:
            backend.keyframe_reasons[reason] = backend.keyframe_reasons.get(reason, 0) + 1
        if state.tracked and not state.matched.repeated and backend.map.keyframes:
            count_views(backend, state)
        if is_kf:
            # The frame is the keyframe: report its pose as local mapping and loop closing
            # left it.
            state = replace(state, T_world_camera=self.new_keyframe(state))
        reference, T_reference_camera = backend.reference_pose(state.T_world_camera)
        # The inlier test's reference waits for local mapping's.
        backend.record(state, f, is_kf, not self.mapper.settling())
        # A keyframe carries the map's keyframe poses as they are now: a robot that tracks
        # itself sends them to the cloud's merger with the keyframe's features.
        return TrackedFrame(state, is_kf, reference, T_reference_camera,
                            backend.map.keyframe_poses() if is_kf else None)


def keyframe_reason(backend: BackEndState, state: PosedFrame, mapper_busy: bool = False
                    ) -> str | None:
    """Why this frame becomes a keyframe, or None: "first", "inliers" (fewer than a fraction
    of the first frame after the newest keyframe, once its local BA landed: none before),
    "motion" (far from every keyframe still observing landmarks), "reference" /
    "close" (ORB-SLAM's tests), "reset" (lost too long; counted as a map reset)."""
    cfg = backend.config.tracking
    if not backend.map.keyframes:
        return "first" if state.tracked else None
    if state.tracked and not state.matched.repeated:
        n_in = int(state.inliers.sum())
        # Inliers fall against the first frame tracked after the keyframe: the view has
        # moved on. (The keyframe's own landmark count is no reference: many of its
        # keypoints are never matched again.)
        reference = backend.inliers_after_keyframe or n_in
        if n_in < cfg.keyframe_inlier_ratio * reference:
            return "inliers"
        if far_from_live_keyframes(backend, state):
            return "motion"
        return orb_slam_keyframe_reason(backend, state, mapper_busy) \
            if cfg.orb_slam_keyframe_policy else None
    if not state.tracked and backend.lost_frames + 1 >= cfg.lost_frames_before_reset:
        # Lost for too long: continue from the prediction with fresh landmarks.
        backend.resets += 1
        return "reset"
    return None


def far_from_live_keyframes(backend: BackEndState, state: PosedFrame) -> bool:
    """Whether the camera moved more than ``keyframe_translation_m`` or turned more than
    ``keyframe_rotation_deg`` from every keyframe that still observes landmarks."""
    cfg, lmap = backend.config.tracking, backend.map
    live = np.flatnonzero(lmap.observing())
    if not len(live):
        return True
    poses = lmap.keyframe_poses(live)
    T = state.T_world_camera
    near = np.linalg.norm(poses[:, :3, 3] - T[:3, 3], axis=1) <= cfg.keyframe_translation_m
    if not near.any():
        return True
    turned = rotation_angles_deg(np.transpose(poses[near, :3, :3], (0, 2, 1)) @ T[:3, :3])
    return not bool((turned <= cfg.keyframe_rotation_deg).any())


def orb_slam_keyframe_reason(backend: BackEndState, state: PosedFrame,
                             mapper_busy: bool = False) -> str | None:
    """ORB-SLAM's keyframe test for RGB-D: "reference" when the frame tracks fewer than a
    fraction of the landmarks the reference keyframe tracks (those with enough observations
    to be established), "close" when it tracks few close points while many close points
    could be created. While the local mapper is busy (``mapper_busy``: a local BA still in
    a worker), "reference" needs weak tracking (``tracking.keyframe_weak_ratio``), as
    ORB-SLAM's tracking asks a busy mapper for a keyframe only then."""
    cfg = backend.config.tracking
    inliers = state.inliers
    n_in = int(inliers.sum())
    depth = state.matched.features.depth
    close = (depth > 0) & (depth < cfg.close_depth_baselines * cfg.virtual_baseline_m)
    ratio = cfg.keyframe_reference_ratio
    if mapper_busy and cfg.keyframe_wait_for_mapper:
        ratio = min(ratio, cfg.keyframe_weak_ratio)
    if n_in < ratio * backend.reference_tracked:
        return "reference"
    if (int((close & inliers).sum()) < cfg.keyframe_close_tracked
            and int((close & ~inliers).sum()) > cfg.keyframe_close_untracked):
        return "close"
    return None


def count_views(backend: BackEndState, state: PosedFrame) -> None:
    """ORB-SLAM's visible/found counters for one tracked frame: landmarks predicted in view
    at the estimated pose (inside the image, within their scale-invariance distance range)
    and the landmarks matched as pose inliers. Visibility is tested on the local map's
    newest landmarks only, those still on probation at the next keyframe: the counters are
    read by their culling alone (``LocalMap.cull_recent``), so culling is as with every
    landmark tested, and a frame's cost does not grow with the map."""
    cfg, lmap = backend.config.tracking, backend.map
    probation = lmap.created_since(lmap.keyframes[-1].id + 1 - cfg.cull_probation_keyframes)
    ids, _, P = lmap.in_view(backend.camera, state.T_world_camera, cfg.min_depth_m,
                             cfg.max_depth_m, ids=probation)
    ids = ids[in_scale_range(backend, ids, P)]
    found = state.matched.landmark_ids[state.inliers]
    lmap.count_views(ids, found[found >= 0])
