"""Who tracks a session's robot, one of two variants chosen once from its offloading point:
the cloud (points 0-3: its RobotSlam runs the stages after the point, and the keyframes are
those of its tracking map, moved by local BA), or the robot itself (point 6: the cloud
records the poses it sent and keeps each keyframe's features it sends, at the poses it last
sent). Both give the session the same calls: ``refusal`` (why a frame cannot be taken),
``track`` and the keyframes as the merger and the live view take them."""

from __future__ import annotations

import numpy as np

from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.backend.workers import LocalMappingPool
from fleetslam.cloud.session.session_state import SessionState
from fleetslam.config import Config
from fleetslam.merging.inter_robot import keyframe_summary
from fleetslam.pipeline.split import CLOUD_TRACKS, StageTimer
from fleetslam.pipeline.states import TrackedFrame, TrackedPose
from fleetslam.wire.merger_keyframes import KeyframeSummary
from fleetslam.wire.pose_deltas import PoseTable


def _tracked_pose(state: SessionState, frame_index: int) -> np.ndarray:
    """The frame's pose as it was tracked (identity if the trajectory lacks it)."""
    for row in reversed(list(state.rows)):
        if row.index == frame_index:
            return row.T_world_camera
    return np.eye(4)


class CloudTracks:
    """The cloud tracks the robot: the keyframes of its tracking map."""

    def __init__(self, state: SessionState, config: Config,
                 local_mapping: LocalMappingPool | None) -> None:
        self.state = state
        self.slam = RobotSlam(config, state.hello.camera, local_mapping, state.front_end,
                              state.tracking)

    def refusal(self, sent: object) -> str | None:
        return None

    def poses_missing(self, sent: object) -> str | None:
        return None

    def track(self, sent: object, at: int, seq: int) -> tuple[TrackedFrame, bool]:
        """The frame tracked from what the robot sent at point ``at`` (each stage's time
        added to the session's), and whether a keyframe of it goes to the merger (always:
        the cloud has its features)."""
        timer = StageTimer()
        out = self.slam.track(sent, at, timer)
        # The robot offloads before its front end ends (points 0-2, or an adaptive robot
        # that switched there): the session holds the front end's state from now on.
        self.state.front_end = self.slam.front_end
        for name, seconds in timer.seconds.items():
            self.state.stage_seconds[name] = self.state.stage_seconds.get(name, 0.0) \
                + sum(seconds)
        return out, True

    def moved_keyframes(self) -> tuple[list[int], np.ndarray] | None:
        """Every keyframe's frame index and pose after a new keyframe (local BA moved the
        recent ones)."""
        lmap = self.state.tracking.map
        return [kf.frame_index for kf in lmap.keyframes], lmap.keyframe_poses()

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


class RobotTracks:
    """The robot tracks itself: the keyframes it sent, at the poses it last sent. The
    back-end's state is kept all the same (its counts go in the summary)."""

    def __init__(self, state: SessionState, config: Config) -> None:
        self.state = state
        self.max_keyframes = config.transport.max_keyframes
        self.slam = RobotSlam(config, state.hello.camera, None, state.front_end, state.tracking)
        # The robot's keyframe poses as applied (their deltas need it; not checkpointed: a
        # restored session takes a whole table first).
        self.pose_table = PoseTable()

    def refusal(self, sent: object) -> str | None:
        """Why a keyframe the robot sent cannot join its keyframes (its id not after the
        last one's, more than the session keeps), or None."""
        if not isinstance(sent, TrackedPose) or sent.features is None:
            return None
        ids = self.state.robot_keyframe_ids
        if ids and sent.reference_keyframe <= ids[-1]:
            return (f"keyframe {sent.reference_keyframe} is not after the last keyframe's "
                    f"{ids[-1]}")
        if len(ids) >= self.max_keyframes:
            return (f"the session keeps at most {self.max_keyframes} keyframes "
                    f"(transport.max_keyframes)")
        return None

    def poses_missing(self, sent: object) -> str | None:
        """Why the keyframe poses ``sent`` carries as a delta cannot be applied (its base is
        not a table this session applied), or None."""
        if not isinstance(sent, TrackedPose) or sent.pose_delta is None:
            return None
        return self.pose_table.refusal(sent.pose_delta)

    def track(self, sent: TrackedPose, at: int, seq: int) -> tuple[TrackedPose, bool]:
        """The robot's own result, recorded as sent; whether it carried a keyframe's
        features, kept (the checkpoint holds it) for the merger as the next of its
        keyframes, with the robot's keyframe poses then (message ``seq``'s, whole or as a
        delta that poses_missing() passed)."""
        if isinstance(sent, TrackedPose) and sent.features is not None:
            if sent.pose_delta is not None:
                sent.keyframe_poses = self.pose_table.apply(seq, sent.pose_delta)
                sent.pose_delta = None
            elif sent.keyframe_poses is not None:
                self.pose_table.whole(seq, sent.keyframe_poses)
        if not isinstance(sent, TrackedPose) or sent.features is None \
                or sent.keyframe_poses is None:
            return sent, False
        st = self.state
        st.robot_keyframes.append(KeyframeSummary(
            st.robot_id, len(st.robot_keyframes), sent.index, sent.timestamp, sent.features,
            sent.keyframe_poses[-1].copy()))
        st.robot_keyframe_ids.append(sent.reference_keyframe)
        # The poses by id: those of the keyframes the cloud has (a lost one's is not known
        # by its frame index, and the merger numbers without it).
        for kf, robot_id in zip(st.robot_keyframes, st.robot_keyframe_ids):
            st.robot_keyframe_poses[kf.frame_index] = sent.keyframe_poses[robot_id].copy()
        return sent, True

    def moved_keyframes(self) -> tuple[list[int], np.ndarray] | None:
        return None  # the robot's poses reach the view with its frames

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


SessionTracker = CloudTracks | RobotTracks


def session_tracker(state: SessionState, config: Config,
                    local_mapping: LocalMappingPool | None) -> SessionTracker:
    """The variant for the session's offloading point."""
    if state.hello.offload_at in CLOUD_TRACKS:
        return CloudTracks(state, config, local_mapping)
    return RobotTracks(state, config)
