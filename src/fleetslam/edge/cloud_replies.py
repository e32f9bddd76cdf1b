"""What the cloud says to a robot, on its reply key: each reply checked as it comes (a Zenoh
callback), those about frames and uploads handled at once (held, ack, a takeover, a
placement, errors about one message), and the answers the robot's run waits for (welcome,
ending, need, ended, a refusal) handed to it in order."""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

from fleetslam.edge.encoder import FrameEncoder
from fleetslam.edge.fleet_frame import FleetFrame
from fleetslam.edge.flow import FlowWindow
from fleetslam.edge.report import RobotReport
from fleetslam.edge.uploader import KeyframeUploader
from fleetslam.transport import protocol

log = logging.getLogger("fleetslam.robot")


class CloudRefused(RuntimeError):
    """The cloud answered a hello or an end with a refusal (its reason), not silence."""

    def __init__(self, error: protocol.Error) -> None:
        super().__init__(error.reason)
        self.reason, self.code = error.reason, error.code
        self.full = error.full  # no session slot free: may free up
        self.wait = error.wait  # the cloud cannot serve yet: may change
        self.max_sessions = error.max_sessions


class CloudReplies:
    def __init__(self, robot_id: str, encoder: FrameEncoder, window: FlowWindow,
                 uploader: KeyframeUploader, fleet_frame: FleetFrame,
                 report: RobotReport) -> None:
        self.robot_id = robot_id
        self.encoder, self.window, self.uploader = encoder, window, uploader
        self.fleet_frame, self.report = fleet_frame, report
        self._answers: queue.Queue[protocol.Reply] = queue.Queue()
        # The cloud lost this robot (no session, a silent cloud): say hello before the next
        # frame.
        self.need_hello = threading.Event()

    def take(self, data: bytes) -> None:
        """A reply from the cloud; one that does not parse is logged and dropped."""
        try:
            reply = protocol.parse_reply(data)
        except protocol.BadReply as exc:
            if exc.kind == protocol.Placed.TYPE:
                return self.fleet_frame.rejected(str(exc))
            log.warning("robot %s: reply rejected: %s", self.robot_id, exc)
            return
        if isinstance(reply, protocol.Held):
            self.encoder.held(reply.seq)
        elif isinstance(reply, protocol.Welcome) and reply.taken_over:
            # A worker took the session over from its checkpoint (the one serving it died):
            # the frames in flight went to the dead one, and it holds none as a reference.
            self.window.clear()
            self.encoder.references_lost()
            self.report.takeovers += 1
            self._answers.put(reply)
        elif isinstance(reply, protocol.Ack):
            self.uploader.acknowledged(reply.frame_index)
        elif isinstance(reply, protocol.Error):
            self._on_error(reply)
        elif isinstance(reply, protocol.Placed):
            self.fleet_frame.take(reply)
        else:
            self._answers.put(reply)

    def _on_error(self, error: protocol.Error) -> None:
        log.warning("robot %s: cloud says: %s", self.robot_id, error.reason)
        code = error.code
        if code == protocol.Code.NOT_A_KEYFRAME.value:
            return self.uploader.not_needed(error.frame_index)
        if code == protocol.Code.REFERENCE_MISSING.value:
            return self.encoder.references_lost()
        if code == protocol.Code.OVER_BUDGET.value:
            # Dropped unread: the window forgets those frames at the next feedback, and an
            # upload is resent until acknowledged. Not an answer to a hello.
            return
        if code == protocol.Code.NO_SESSION.value:  # the cloud lost us: hello again
            self.need_hello.set()
        self._answers.put(error)

    def await_reply(self, kinds: tuple[type, ...], timeout: float,
                    answer_to: str | None = None) -> Any:
        """The first reply of one of ``kinds`` (an error included), None after
        ``timeout``; CloudRefused if the cloud refused the ``answer_to`` message ("hello",
        "end") instead."""
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                reply = self._answers.get(timeout=left)
            except queue.Empty:
                return None
            if isinstance(reply, kinds):
                return reply
            if isinstance(reply, protocol.Error) and answer_to is not None \
                    and reply.answer_to == answer_to:
                raise CloudRefused(reply)
        return None
