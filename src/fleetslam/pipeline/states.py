"""The typed state between each pair of tracking stages: what crosses a split point.

State k is the input of stage k (state 0 is the captured frame). Every state is plain
numpy arrays and numbers, so it can be serialised at any split point. Images are dropped
as soon as no later stage needs them: that is what makes late split points cheap to send.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

# Keypoint table columns, as OpenCV KeyPoint and the paper's YAML message: x, y, size,
# angle, response, octave, class_id.
KEYPOINT_COLUMNS = ("x", "y", "size", "angle", "response", "octave", "class_id")


@dataclass
class CapturedFrame:
    """State 0: the RGB-D frame as captured (what total offloading sends)."""

    index: int
    timestamp: float
    rgb: np.ndarray  # H x W x 3 uint8 RGB
    depth_m: np.ndarray  # H x W float32 metres, 0 = no measurement


@dataclass
class DetectedFrame:
    """State 1: keypoints found; the grey image is still needed for descriptors."""

    index: int
    timestamp: float
    gray: np.ndarray  # H x W uint8
    depth_m: np.ndarray
    keypoints: np.ndarray  # N x 7 float32, KEYPOINT_COLUMNS


@dataclass
class DescribedFrame:
    """State 2: ORB descriptors computed; only the depth image is still needed."""

    index: int
    timestamp: float
    depth_m: np.ndarray
    keypoints: np.ndarray  # N x 7 float32
    descriptors: np.ndarray  # N x 32 uint8


@dataclass
class FeatureFrame:
    """State 3: features with a depth per keypoint (the paper's chosen offloading point)."""

    index: int
    timestamp: float
    keypoints: np.ndarray  # N x 7 float32 (distorted pixel coordinates, as detected)
    descriptors: np.ndarray  # N x 32 uint8
    depth: np.ndarray  # N float32 metres, 0 = no reliable depth
    # Undistorted (ideal pinhole) keypoint coordinates; derived from keypoints and the
    # camera, carried so the cloud does not redo it.
    uv: np.ndarray  # N x 2 float64


@dataclass
class MatchedFrame:
    """State 4: features matched to the tracking map."""

    features: FeatureFrame
    landmark_ids: np.ndarray  # N int64, -1 = unmatched
    landmark_xyz: np.ndarray  # N x 3 float64 world points of the matches (NaN if unmatched)
    T_world_camera_predicted: np.ndarray  # 4 x 4, constant-velocity prediction
    # The frame is a byte-for-byte repeat of the previous one (dropped-frame filler).
    repeated: bool


@dataclass
class PosedFrame:
    """State 5: camera pose estimated."""

    matched: MatchedFrame
    T_world_camera: np.ndarray  # 4 x 4
    inliers: np.ndarray  # N bool over keypoints
    tracked: bool


@dataclass
class TrackedFrame:
    """State 6: the pipeline's output for one frame."""

    posed: PosedFrame
    is_keyframe: bool
    # The frame's reference keyframe (-1: none) and its pose relative to it, so the final
    # trajectory follows later corrections of the keyframes (local BA, loop closing).
    reference_keyframe: int = -1
    T_reference_camera: np.ndarray | None = None
    # A keyframe's: every keyframe's pose (K x 4 x 4, by keyframe id; this one is the last)
    # once local mapping and loop closing took it. A robot that tracks itself sends them
    # with the keyframe's features, so the cloud's map merger takes its keyframes.
    keyframe_poses: np.ndarray | None = None

    @property
    def index(self) -> int:
        return self.posed.matched.features.index

    @property
    def timestamp(self) -> float:
        return self.posed.matched.features.timestamp

    @property
    def T_world_camera(self) -> np.ndarray:
        return self.posed.T_world_camera

    @property
    def tracked(self) -> bool:
        return self.posed.tracked

    @property
    def n_inliers(self) -> int:
        return int(self.posed.inliers.sum())

    @property
    def sends_keyframe(self) -> bool:
        """Whether a robot that tracks itself sends this frame's features (a keyframe)."""
        return self.is_keyframe and self.keyframe_poses is not None

    def pose_only(self) -> "TrackedPose":
        """What a robot that tracks itself sends (point 6): the result; of a keyframe also
        its features and every keyframe's pose (what the cloud's merger needs)."""
        kf = self.sends_keyframe
        return TrackedPose(self.index, self.timestamp, self.T_world_camera.copy(), self.tracked,
                           self.is_keyframe, self.n_inliers, self.reference_keyframe,
                           None if self.T_reference_camera is None
                           else self.T_reference_camera.copy(),
                           self.posed.matched.features if kf else None,
                           np.array(self.keyframe_poses, np.float64) if kf else None)


@dataclass
class TrackedPose:
    """A tracked frame's result, as the cloud receives it from a robot that tracks itself:
    the fields of TrackedFrame the cloud records; a keyframe's features and the robot's
    keyframe poses too, for the map merger (non-keyframes carry no features)."""

    index: int
    timestamp: float
    T_world_camera: np.ndarray
    tracked: bool
    is_keyframe: bool
    n_inliers: int
    reference_keyframe: int = -1
    T_reference_camera: np.ndarray | None = None
    # A keyframe's only: its features (as point 3 sends them) and every keyframe's pose
    # (K x 4 x 4 by keyframe id; this keyframe, ``reference_keyframe``, is the last).
    features: FeatureFrame | None = None
    keyframe_poses: np.ndarray | None = None
    # Instead of keyframe_poses, those changed since a table the cloud applied
    # (wire/pose_deltas.PoseDelta; the cloud's session makes the whole table of it).
    pose_delta: Any = None
