"""A robot's keyframe uploads (the session's keyframe thread): each checked against the
session (its decimation and size, a keyframe the session took), stored once a checkpoint
that knows it as a keyframe is on disk, and only then acknowledged; at point 0 the cloud
stores the keyframe's RGB-D itself. Each stored one is shown in the live view."""

from __future__ import annotations

from fleetslam.cloud.session.checkpoint_writer import CheckpointWriter
from fleetslam.cloud.session.memory_budget import SessionBudget
from fleetslam.cloud.session.replies import Replies
from fleetslam.cloud.session.session_tracker import SessionTracker
from fleetslam.cloud.session.session_state import SessionState
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.mapping.dense_map import KeyframeClouds
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.transport import protocol
from fleetslam.visualisation.live_view import NullView
from fleetslam.wire.envelope import WireError
from fleetslam.wire.messages import KeyframeUpload, decode_keyframe, encode_keyframe


class KeyframeUploads:
    def __init__(self, state: SessionState, config: Config, store: CloudStore,
                 checkpoints: CheckpointWriter, budget: SessionBudget, replies: Replies,
                 keyframes: SessionTracker, view: NullView, clouds: KeyframeClouds) -> None:
        """``clouds``: where each stored keyframe's cloud is made for the robot's map."""
        self.state, self.config, self.store = state, config, store
        self.checkpoints, self.budget, self.replies = checkpoints, budget, replies
        self.keyframes, self.view, self.clouds = keyframes, view, clouds
        self.robot_id = state.robot_id

    def take(self, data: bytes) -> None:
        """An upload off the keyframe queue; its bytes leave the budget once handled."""
        try:
            self._check_and_store(data)
        finally:
            self.budget.release(len(data))

    def _check_and_store(self, data: bytes) -> None:
        """A keyframe's upload: checked, stored, acknowledged once a checkpoint covers it."""
        try:
            header, upload = decode_keyframe(data, self.state.hello.camera)
        except WireError as exc:
            return self.replies.reject("keyframe", str(exc))
        if header.robot_id != self.robot_id:
            return self.replies.reject("keyframe", f"header names robot {header.robot_id!r}")
        wrong_size = self._wrong_size(upload)
        if wrong_size is not None:
            return self.replies.reject("keyframe", wrong_size)
        if upload.frame_index not in self._keyframe_frames():
            return self.replies.reject(
                "keyframe", f"frame {upload.frame_index} is not a keyframe of this session",
                protocol.Code.NOT_A_KEYFRAME, frame_index=upload.frame_index)
        # Stored only once a checkpoint that knows it as a keyframe is on disk (it may wait
        # for transport.checkpoint_interval_s), so a keyframe file in the store is one of the
        # map's after any restart; a crash between the two leaves a keyframe without its
        # file, which the end asks the robot for again. Acknowledged once both are on disk
        # (a resent one is acknowledged again).
        if not self.checkpoints.wait_for_frame(upload.frame_index):
            return self.replies.reject("keyframe", f"frame {upload.frame_index}: no checkpoint "
                                                   f"covers it yet (not acknowledged; resend)")
        if self.store.has_keyframe(self.robot_id, upload.frame_index):
            self.replies.count("duplicate keyframe uploads")
        elif self.replies.counts()["keyframes stored"] >= self.config.transport.max_keyframes:
            return self.replies.reject(
                "keyframe", f"the session stores at most {self.config.transport.max_keyframes} "
                            f"keyframes (transport.max_keyframes)")
        else:
            self.store.put_keyframe(self.robot_id, upload.frame_index, data)
            self.replies.count("keyframes stored")
            self._show(upload)
        self.replies.reply(protocol.Ack(upload.frame_index))
        self._prepare(upload)

    def _prepare(self, upload: KeyframeUpload) -> None:
        """The keyframe's cloud for the robot's map, after its acknowledgement (a resent
        upload's is made once)."""
        if self.clouds.get(upload.frame_index) is None:
            self.clouds.add(upload.frame_index, upload.rgb, upload.depth_raw, upload.stride)

    def _wrong_size(self, upload: KeyframeUpload) -> str | None:
        """Why an upload's images are not the map's (decimation, size), or None."""
        if upload.stride not in (1, self.config.map.pixel_stride):
            return (f"decimated by {upload.stride}, the map samples "
                    f"every {self.config.map.pixel_stride} pixels")
        camera = self.state.hello.camera
        expected = (-(-camera.height // upload.stride), -(-camera.width // upload.stride))
        if upload.rgb.shape[:2] != expected or upload.depth_raw.shape != expected:
            return (f"frame {upload.frame_index}: images of "
                    f"{upload.rgb.shape[:2]} / {upload.depth_raw.shape}, "
                    f"the camera decimated by {upload.stride} gives {expected}")
        return None

    def _keyframe_frames(self) -> set[int]:
        """Frame indices this session took as keyframes (a robot at point 6 says which)."""
        rows = list(self.state.rows)
        return {r.index for r in rows if r.is_keyframe}

    def store_captured(self, frame: CapturedFrame, seq: int) -> None:
        """A keyframe of a robot offloading everything (point 0): its RGB-D is the frame's."""
        depth_raw = self.state.hello.camera.metres_to_depth(frame.depth_m)
        if depth_raw is None:  # decoded from sensor units, so this cannot happen
            raise ValueError(f"frame {frame.index}: depth is not in the camera's sensor units")
        upload = KeyframeUpload.from_frame(frame.index, frame.timestamp, frame.rgb, depth_raw,
                                           self.config.map.pixel_stride)
        self.store.put_keyframe(self.robot_id, frame.index,
                                encode_keyframe(self.robot_id, seq, upload, self.config.wire))
        self._show(upload)
        self._prepare(upload)

    def _show(self, upload: KeyframeUpload) -> None:
        """A stored keyframe's points in the live view (nothing when it is off)."""
        if self.view.enabled:
            self.view.keyframe_points(self.robot_id, upload.frame_index,
                                      self.keyframes.pose(upload.frame_index), upload.rgb,
                                      upload.depth_raw, upload.stride)
