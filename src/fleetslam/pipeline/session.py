"""The per-robot tracking session: everything the stages remember between frames."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.pipeline.local_map import LocalMap
from fleetslam.pipeline.states import FeatureFrame

if TYPE_CHECKING:
    from fleetslam.pipeline.states import PosedFrame


@dataclass
class TrackingSession:
    config: Config
    camera: Camera
    map: LocalMap = field(default_factory=LocalMap)
    # Last two estimated poses, for the constant-velocity motion model.
    T_last: np.ndarray | None = None
    T_before_last: np.ndarray | None = None
    last_tracked: bool = True
    lost_frames: int = 0
    # Frames that were lost (pose not estimated from measurements).
    lost_total: int = 0
    # Episodes of loss (a run of lost frames counts once).
    loss_events: int = 0
    resets: int = 0
    repeated_frames: int = 0
    # Inliers of the first frame tracked after the newest keyframe (keyframe decision).
    inliers_after_keyframe: int = 0
    # Local mapping statistics: wall time of each local bundle adjustment, observations it
    # erased as outliers, landmarks culled, observations added by fusion at keyframes.
    local_ba_seconds: list[float] = field(default_factory=list)
    local_ba_outliers: int = 0
    culled_landmarks: int = 0
    fused_observations: int = 0
    # Robot side: digest of the previous depth image, to spot a repeated (stale) one, and
    # how many frames went on without depth because of it.
    last_depth_digest: bytes | None = None
    stale_depth_frames: int = 0
    # Established landmarks (enough observations) of the newest keyframe: the reference of
    # ORB-SLAM's keyframe test.
    reference_tracked: int = 0
    _keyframe_was_last: bool = False
    _last_features: FeatureFrame | None = None
    _orb: cv2.ORB | None = None

    @property
    def orb(self) -> cv2.ORB:
        # Created lazily: cv2 objects cannot be pickled with the session.
        if self._orb is None:
            cfg = self.config.orb
            self._orb = cv2.ORB_create(
                nfeatures=2 * cfg.n_features, scaleFactor=cfg.scale_factor,
                nlevels=cfg.n_levels, fastThreshold=cfg.fast_threshold)
        return self._orb

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_orb"] = None
        return state

    def predict_pose(self) -> np.ndarray:
        if self.T_last is None:
            return np.eye(4)
        if self.T_before_last is None:
            return self.T_last.copy()
        velocity = np.linalg.solve(self.T_before_last, self.T_last)
        return self.T_last @ velocity

    def is_repeat_of_last(self, features: FeatureFrame) -> bool:
        last = self._last_features
        if last is None or len(last.keypoints) != len(features.keypoints) or not len(last.keypoints):
            return False
        same_place = np.all(np.abs(last.keypoints[:, :2] - features.keypoints[:, :2]) < 1e-3, axis=1)
        same_desc = np.all(last.descriptors == features.descriptors, axis=1)
        return bool((same_place & same_desc).mean() >= self.config.tracking.repeated_frame_fraction)

    def record(self, posed: "PosedFrame", features: FeatureFrame, is_keyframe: bool) -> None:
        """Bookkeeping after a frame: motion model, loss counters, repeat detection."""
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
        if self._keyframe_was_last and posed.tracked and not posed.matched.repeated:
            self.inliers_after_keyframe = int(posed.inliers.sum())
            self._keyframe_was_last = False
        if is_keyframe:
            self._keyframe_was_last = True
            self.inliers_after_keyframe = 0
        self.last_tracked = posed.tracked
        self.T_before_last = self.T_last
        self.T_last = posed.T_world_camera.copy()
        self._last_features = features
