"""A robot's end (the session's tracking thread, in order with its frames). At most one end
per session waits, queued or for frames still in flight: a robot's resent ends only replace
the waiting one's content, so a flood of ends is one end (no queue, no timer each). Once
the last frame is in and every keyframe uploaded, the robot's outputs are written and a
final checkpoint is on disk before it hears "ended" (with its summary); "need" names the
uploads still missing; anything else is an error that says why."""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.cloud.session.checkpoint_writer import CheckpointWriter
from fleetslam.cloud.session.inbox import ControlItem, WorkQueue
from fleetslam.cloud.session.replies import Replies
from fleetslam.cloud.session.session_outputs import FinishedMap, SessionOutputs
from fleetslam.cloud.session.session_state import SessionState
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.transport import protocol

log = logging.getLogger("fleetslam.cloud")


class EndHandshake:
    def __init__(self, state: SessionState, config: Config, store: CloudStore,
                 slam: RobotSlam, outputs: SessionOutputs,
                 checkpoints: CheckpointWriter, replies: Replies, inbox: WorkQueue) -> None:
        """``inbox``: the session's frames and control in arrival order (an end that came
        while one was answered goes there, in turn)."""
        self.state, self.config, self.store = state, config, store
        self.slam, self.outputs, self.checkpoints = slam, outputs, checkpoints
        self.replies, self.inbox = replies, inbox
        self.robot_id = state.robot_id
        # Under _lock: a Zenoh callback (offer) and the tracking thread (take) change them.
        self._lock = threading.Lock()
        self._waiting = False
        self._latest: dict[str, Any] | None = None
        self._message: dict[str, Any] | None = None  # the end the tracking thread holds
        self._since: float | None = None  # when the tracking thread first got to it
        # The robot's finished map, once its end is durable (before it hears "ended").
        self.finished: FinishedMap | None = None

    def offer(self, message: dict[str, Any]) -> bool:
        """An end arrived (a Zenoh callback): whether it goes to the inbox (False: one waits
        already, and this one replaces its content)."""
        with self._lock:
            if self._waiting:
                self._latest = message
                self.replies.count("ends while one waits")
                return False
            self._waiting = True
            return True

    @property
    def held_for_frames(self) -> bool:
        """An end waits for frames still in flight (the tracking thread looks again)."""
        return self._since is not None

    def take(self, message: dict[str, Any] | None, arrival: float) -> None:
        """The robot's end: once its last frame is in and every keyframe uploaded, the
        robot's outputs are written and a final checkpoint is on disk before it hears
        "ended" (with its summary); "need" names the uploads still missing. An end before
        any frame was tracked is refused with the reason: there is no trajectory or map to
        write, and a finished session without them would enter the merge as a robot
        without a map; unfinished, the session takes the robot's frames if they come."""
        with self._lock:  # the newest end the robot sent is the one answered
            if self._latest is not None:
                message, self._latest = self._latest, None
        message = message or self._message
        if message is None:
            return
        now = time.monotonic()
        # The grace period runs from when this session first got to the end (behind any
        # backlog of frames), not from its arrival: a busy session must not give up on
        # a last frame that arrived while it was still working through earlier ones.
        if self._since is None:
            self._since = now
        self._message = message
        last_seq = protocol.End.last_seq_of(message)
        if (last_seq is not None and last_seq > self.state.last_seq
                and now - self._since < self.config.transport.end_grace_s):
            # Frames travel on another key than control messages and may arrive after
            # the end that follows them: the tracking thread looks again (held_for_frames).
            return
        self._since = self._message = None
        try:
            self._answer(message)
        finally:
            with self._lock:
                latest, self._latest = self._latest, None
                self._waiting = latest is not None
            if latest is not None:  # one more came meanwhile: answered in turn
                self.inbox.put(ControlItem(latest, arrival))

    def _answer(self, message: dict[str, Any]) -> None:
        """The answer to an end: error, need, or ended (``finished`` set first, durable)."""
        try:
            end = protocol.End.parse(message)
        except ValueError as exc:
            return self.replies.reply(protocol.Error.of(protocol.Code.BAD_MESSAGE, str(exc),
                                                        answer_to="end"))
        if not self.state.rows:
            rejected = self.replies.counts()["rejected frame"]
            return self.replies.reply(protocol.Error.of(
                protocol.Code.REFUSED,
                f"nothing to end: the cloud tracked no frame of robot {self.robot_id}"
                + (f" ({rejected} frames rejected)" if rejected else "")
                + "; no trajectory or map is written", answer_to="end"))
        self.state.robot_keyframe_poses.update(end.keyframe_poses)
        t0 = time.perf_counter()
        self.slam.finish()
        t1 = time.perf_counter()
        # A keyframe the robot cannot upload (a live camera's, gone) is mapped without its
        # images rather than asked for again.
        missing = [i for i in self.outputs.keyframe_poses()
                   if not self.store.has_keyframe(self.robot_id, i) and i not in end.unavailable]
        if missing:
            return self.replies.reply(protocol.Need(tuple(missing)))
        finished = self.outputs.finish(end.camera)
        t2 = time.perf_counter()
        # Durable before the robot hears "ended": another worker restores it finished.
        self.state.ended = True
        number = self.checkpoints.checkpoint(self.state.last_index)
        why = self.checkpoints.not_durable(number)
        if why is not None:
            # "ended" means the finished session is durable and current: not so, the robot
            # keeps what it holds and ends again (with this worker, or the next owner).
            self.state.ended = False
            log.error("robot %s: its final checkpoint is not durable (%s): not ended",
                      self.robot_id, why)
            return self.replies.reply(protocol.Error.of(
                protocol.Code.FAILED, f"the session's final checkpoint is not durable ({why}): "
                f"nothing ended; keep what you hold and end again", answer_to="end"))
        log.info("robot %s ended in %.2f s: last loop queries and local BA %.2f s, outputs "
                 "%.2f s, final checkpoint %.2f s", self.robot_id, time.perf_counter() - t0,
                 t1 - t0, t2 - t1, time.perf_counter() - t2)
        self.finished = finished
        self.replies.reply(protocol.Ended(finished.summary))
