"""Flow control: the robot's window of frames in flight (sent, no feedback yet), and what
the feedback tells about the cloud (round trips, the longest silence)."""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict

import numpy as np

from fleetslam.config import Config
from fleetslam.edge.report import RobotReport

log = logging.getLogger("fleetslam.robot")


class FlowWindow:
    """At most ``transport.max_frames_in_flight`` frames without feedback: the robot waits
    for room before it sends another (at most ``in_flight_wait_s``; then the oldest is taken
    as lost). Frames are kept in seq order; feedback comes in seq order, so a frame older
    than one with feedback was lost (link, or dropped by the cloud) and leaves the window.
    Written from the robot's main thread, its send thread and the feedback callback."""

    def __init__(self, robot_id: str, config: Config, report: RobotReport) -> None:
        self.robot_id = robot_id
        self.config = config
        self.report = report
        self._sent_at: OrderedDict[int, float] = OrderedDict()  # seq -> when
        self._changed = threading.Condition()
        self.round_trips_ms: list[float] = []
        self.last_feedback = 0.0  # time.monotonic() of the last feedback, 0 before any

    def in_flight(self) -> list[int]:
        with self._changed:
            return list(self._sent_at)

    def sent(self, seq: int) -> None:
        with self._changed:
            self._sent_at[seq] = time.monotonic()

    def lost(self, seq: int) -> None:
        """The link lost frame ``seq``: no feedback will come for it."""
        with self._changed:
            self._sent_at.pop(seq, None)
            self._changed.notify_all()

    def clear(self) -> None:
        """A new, resumed or taken-over session answers none of the frames in flight."""
        with self._changed:
            self._sent_at.clear()
            self._changed.notify_all()

    def heard(self) -> float:
        """Feedback arrived (now, returned): the longest the cloud was silent (a worker taking
        over, a backlog) goes to the report."""
        now = time.monotonic()
        if self.last_feedback:
            self.report.longest_feedback_gap_s = max(self.report.longest_feedback_gap_s,
                                                     now - self.last_feedback)
        self.last_feedback = now
        return now

    def answered(self, seq: int, now: float) -> float | None:
        """Feedback for frame ``seq`` heard at ``now``: it and every older frame leave the
        window. Its round trip in seconds, or None for a frame no longer in the window."""
        with self._changed:
            sent = self._sent_at.pop(seq, None)
            while self._sent_at and next(iter(self._sent_at)) < seq:
                self._sent_at.popitem(last=False)
            self._changed.notify_all()
        if sent is None:
            return None
        self.round_trips_ms.append(1000.0 * (now - sent))
        return now - sent

    def wait_for_room(self) -> bool:
        """Wait while the window is full; False if the wait ran out (the cloud did not answer
        in time: the oldest frames are dropped from the window, and nobody may be serving
        this robot any more)."""
        cfg = self.config.transport
        if cfg.max_frames_in_flight <= 0:
            return True
        start = time.monotonic()
        with self._changed:
            if self._changed.wait_for(lambda: len(self._sent_at) < cfg.max_frames_in_flight,
                                      cfg.in_flight_wait_s):
                self.report.flow_wait_s += time.monotonic() - start
                return True
            self.report.flow_timeouts += 1
            self.report.flow_wait_s += time.monotonic() - start
            log.warning("robot %s: no feedback for %.0f s with %d frames in flight; saying "
                        "hello again and going on", self.robot_id, cfg.in_flight_wait_s,
                        len(self._sent_at))
            while len(self._sent_at) >= cfg.max_frames_in_flight:
                self._sent_at.popitem(last=False)
            return False

    def record(self, report: RobotReport, t0: float) -> None:
        """The run's end: the last feedback (seconds since ``t0``) and the round trips."""
        report.last_feedback_s = max(0.0, self.last_feedback - t0)
        if self.round_trips_ms:
            report.round_trip_ms_median = float(np.median(self.round_trips_ms))
            report.round_trip_ms_p95 = float(np.percentile(self.round_trips_ms, 95))
