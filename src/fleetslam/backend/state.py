"""The back-end's state for one robot: what tracking, local mapping and loop closing read
and update between frames, and what a cloud checkpoints. Data and bookkeeping only: this
module imports no algorithm (the stages and the mappers that change it import it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Hashable, Protocol, Sequence

import numpy as np

from fleetslam.backend.local_map import LocalMap
from fleetslam.backend.pose_graph import PoseEdge
from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.pipeline.states import FeatureFrame, PosedFrame
from fleetslam.transforms import poses_from_references


class PlaceDatabase(Protocol):
    """Place recognition over keyframes (backend/place_recognition.py: nearest neighbours,
    or backend/vocabulary.py: a bag of words); entry i is keyframe i."""

    keys: list[Hashable]

    def __len__(self) -> int: ...

    def add(self, key: Hashable, descriptors: np.ndarray) -> int: ...

    def query(self, descriptors: np.ndarray, allowed: np.ndarray | None = None,
              top_k: int | None = None) -> list[Any]: ...


@dataclass
class LoopDetection:
    """A verified match of keyframe ``query`` to the place around keyframe ``candidate``."""

    query: int
    candidate: int
    # Where the old place says the query camera is, and the world-frame correction that
    # takes the query's current pose there: T_world_query_loop = correction @ T_world_query.
    T_world_query: np.ndarray
    correction: np.ndarray
    score: float
    ransac_inliers: int
    inliers: int
    # Landmarks of the query seen again in the place: (place landmark, query landmark).
    same_landmarks: tuple[np.ndarray, np.ndarray]


@dataclass
class LoopClosingState:
    detections: list[LoopDetection] = field(default_factory=list)
    # Accepted loop edges, kept for every later pose graph.
    edges: list[PoseEdge] = field(default_factory=list)
    # One record per loop the closer tried to correct (accepted or rejected by the graph).
    events: list[dict] = field(default_factory=list)
    queries: int = 0
    candidates_verified: int = 0
    detections_total: int = 0
    # Database query (in the worker when asynchronous) plus verification of its candidates.
    query_seconds: list[float] = field(default_factory=list)
    correction_seconds: list[float] = field(default_factory=list)


@dataclass
class BackEndState:
    config: Config
    camera: Camera
    # Place recognition over this robot's keyframes (entry i = keyframe i).
    places: PlaceDatabase
    map: LocalMap = field(default_factory=LocalMap)
    loops: LoopClosingState = field(default_factory=LoopClosingState)
    # Last two estimated poses, for the constant-velocity motion model.
    T_last: np.ndarray | None = None
    T_before_last: np.ndarray | None = None
    last_tracked: bool = True
    lost_frames: int = 0
    # Frames that were lost (pose not estimated from measurements).
    lost_total: int = 0
    # Episodes of loss (a run of lost frames counts once), and those ended by
    # relocalisation against the keyframes.
    loss_events: int = 0
    relocalisations: int = 0
    # Frames whose motion prediction left too few inliers (tracking.prediction_min_inlier_ratio):
    # posed by PnP RANSAC instead, the tracker's dearest step.
    pnp_fallbacks: int = 0
    resets: int = 0
    repeated_frames: int = 0
    # Inliers of the first frame tracked after the newest keyframe, once local mapping was
    # done with it (keyframe decision; 0 until then).
    inliers_after_keyframe: int = 0
    # Local mapping statistics: wall time of each local bundle adjustment, observations it
    # erased as outliers, landmarks culled, observations added by fusion at keyframes.
    local_ba_seconds: list[float] = field(default_factory=list)
    local_ba_outliers: int = 0
    culled_landmarks: int = 0
    # Keyframes culled as redundant (their observations dropped; ORB-SLAM's KeyFrameCulling).
    culled_keyframes: int = 0
    # Keyframes made, by the test that made them (tracking.keyframe_reason).
    keyframe_reasons: dict[str, int] = field(default_factory=dict)
    fused_observations: int = 0
    # Established landmarks (enough observations) of the newest keyframe: the reference of
    # ORB-SLAM's keyframe test.
    reference_tracked: int = 0
    _keyframe_was_last: bool = False
    _last_features: FeatureFrame | None = None

    def predict_pose(self) -> np.ndarray:
        if self.T_last is None:
            return np.eye(4)
        if self.T_before_last is None:
            return self.T_last.copy()
        velocity = np.linalg.solve(self.T_before_last, self.T_last)
        return self.T_last @ velocity

    def tracking_landmarks(self) -> np.ndarray | None:
        """Ids of the landmarks tracking may match (the local map), or None for all of them
        (see ``tracking.local_map_scope``)."""
        cfg = self.config.tracking
        lmap = self.map
        if cfg.local_map_scope == "all" or not lmap.keyframes:
            return None
        if cfg.local_map_scope != "covisible":
            raise ValueError(f"tracking.local_map_scope {cfg.local_map_scope!r}: "
                             f"'covisible' or 'all'")
        newest = lmap.keyframes[-1].id
        neighbours, _ = lmap.covisible(newest)
        members = np.zeros(len(lmap.keyframes), bool)
        members[neighbours[:cfg.local_map_covisible]] = True
        members[max(newest - cfg.local_map_keyframes + 1, 0):] = True
        ids = np.unique(lmap.obs_landmark[members[lmap.obs_keyframe]])
        return ids[lmap.alive[ids]]

    def correct_motion(self, correction: np.ndarray) -> None:
        """The map moved under the camera (local BA, loop correction): move the motion
        model's poses with it, so its velocity is kept."""
        if self.T_last is not None:
            self.T_last = correction @ self.T_last
        if self.T_before_last is not None:
            self.T_before_last = correction @ self.T_before_last

    def is_repeat_of_last(self, features: FeatureFrame) -> bool:
        last = self._last_features
        if last is None or len(last.keypoints) != len(features.keypoints) or not len(last.keypoints):
            return False
        same_place = np.all(np.abs(last.keypoints[:, :2] - features.keypoints[:, :2]) < 1e-3, axis=1)
        same_desc = np.all(last.descriptors == features.descriptors, axis=1)
        return bool((same_place & same_desc).mean() >= self.config.tracking.repeated_frame_fraction)

    def reference_pose(self, T_world_camera: np.ndarray) -> tuple[int, np.ndarray]:
        """(newest keyframe id, pose relative to it): a frame's pose is kept relative to its
        reference keyframe, so the final trajectory follows every later map correction
        (ORB-SLAM's relative frame poses). (-1, pose) before the first keyframe."""
        if not self.map.keyframes:
            return -1, T_world_camera.copy()
        kf = self.map.keyframes[-1]
        return kf.id, np.linalg.solve(kf.T_world_camera, T_world_camera)

    def final_poses(self, references: Sequence[int],
                    T_reference_camera: Sequence[np.ndarray | None],
                    online: Sequence[np.ndarray]) -> np.ndarray:
        """Every frame's pose from its reference keyframe's current pose (N x 4 x 4); a frame
        without a reference (-1, relative pose None) keeps its ``online`` pose."""
        return poses_from_references(self.map.keyframe_poses(), references, T_reference_camera,
                                     online)

    def record(self, posed: PosedFrame, features: FeatureFrame, is_keyframe: bool,
               settled: bool = True) -> None:
        """Bookkeeping after a frame: motion model, loss counters, repeat detection, and the
        keyframe test's reference: the first frame tracked after the newest keyframe once
        local mapping is done with it (``settled``)."""
        if posed.matched.repeated:
            self.repeated_frames += 1
        if posed.tracked:
            self.lost_frames = 0
        else:
            if self.lost_frames == 0:
                self.loss_events += 1
            self.lost_frames += 1
            self.lost_total += 1
            if is_keyframe:
                self.lost_frames = 0
        if self._keyframe_was_last and settled and posed.tracked and not posed.matched.repeated:
            self.inliers_after_keyframe = int(posed.inliers.sum())
            self._keyframe_was_last = False
        if is_keyframe:
            self._keyframe_was_last = True
            self.inliers_after_keyframe = 0
        self.last_tracked = posed.tracked
        self.T_before_last = self.T_last
        self.T_last = posed.T_world_camera.copy()
        self._last_features = features
