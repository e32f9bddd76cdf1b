"""A session's keyframes as the merger and the live view take them, in the session's one of
two variants, chosen once from its offloading point: the cloud tracks the robot (its tracking
map holds the keyframes, and local BA moves them), or the robot tracks itself (point 6: it
sends each keyframe's features, and the poses of all of them, with its frames)."""

from __future__ import annotations

import numpy as np

from fleetslam.cloud.session.session_state import SessionState
from fleetslam.merging.inter_robot import keyframe_summary
from fleetslam.pipeline.split import CLOUD_TRACKS
from fleetslam.wire.merger_keyframes import KeyframeSummary


def _tracked_pose(state: SessionState, frame_index: int) -> np.ndarray:
    """The frame's pose as it was tracked (identity if the trajectory lacks it)."""
    for row in reversed(list(state.rows)):
        if row.index == frame_index:
            return row.T_world_camera
    return np.eye(4)


class TrackedKeyframes:
    """The cloud tracks the robot: the keyframes of its tracking map."""

    def __init__(self, state: SessionState) -> None:
        self.state = state

    def newest(self) -> tuple[KeyframeSummary, np.ndarray]:
        """The newest keyframe as the merger takes it, and every keyframe's current pose."""
        lmap = self.state.tracking.map
        return keyframe_summary(self.state.robot_id, lmap.keyframes[-1]), lmap.keyframe_poses()

    def all(self) -> list[KeyframeSummary]:
        """Every keyframe as the merger takes it (a restored session re-joins the merger)."""
        return [keyframe_summary(self.state.robot_id, kf)
                for kf in self.state.tracking.map.keyframes]

    def poses(self) -> np.ndarray:
        """The current pose of every keyframe of ``all`` (K x 4 x 4, in order)."""
        return self.state.tracking.map.keyframe_poses()

    def pose(self, frame_index: int) -> np.ndarray:
        """A keyframe's current pose in the tracking map (as tracked, if no longer in it)."""
        for kf in reversed(list(self.state.tracking.map.keyframes)):
            if kf.frame_index == frame_index:
                return kf.T_world_camera.copy()
        return _tracked_pose(self.state, frame_index)


class RobotKeyframes:
    """The robot tracks itself: the keyframes it sent, at the poses it last sent."""

    def __init__(self, state: SessionState) -> None:
        self.state = state

    def newest(self) -> tuple[KeyframeSummary, np.ndarray]:
        return self.state.robot_keyframes[-1], self.poses()

    def all(self) -> list[KeyframeSummary]:
        return list(self.state.robot_keyframes)

    def poses(self) -> np.ndarray:
        poses = self.state.robot_keyframe_poses
        return np.array([poses[kf.frame_index] for kf in self.state.robot_keyframes]
                        ).reshape(-1, 4, 4)

    def pose(self, frame_index: int) -> np.ndarray:
        return _tracked_pose(self.state, frame_index)


SessionKeyframes = TrackedKeyframes | RobotKeyframes


def session_keyframes(state: SessionState) -> SessionKeyframes:
    """The variant for the session's offloading point."""
    if state.hello.offload_at in CLOUD_TRACKS:
        return TrackedKeyframes(state)
    return RobotKeyframes(state)
