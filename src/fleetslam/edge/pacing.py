"""When the robot takes its frames: ``--rate`` (as fast as it can, at a fixed rate, at the
recording's timestamps) and a read-ahead thread that decodes the next images, as a camera
driver delivers them; a live camera's newest frame each time the robot is ready."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import replace

from fleetslam.datasets.live import LiveSource
from fleetslam.datasets.source import Frame, RecordedSource
from fleetslam.edge.report import RobotReport

log = logging.getLogger("fleetslam.robot")

# How often a robot waiting for a live camera's frame looks whether it was stopped.
STOP_POLL_S = 0.25


def parse_rate(text: str) -> float | None:
    """'max' (None: as fast as stages and link allow), 'recorded' (0: at the recording's
    timestamps) or frames per second."""
    if text == "max":
        return None
    if text == "recorded":
        return 0.0
    try:
        fps = float(text)
    except ValueError:
        fps = -1.0
    if not fps > 0:
        raise ValueError(f"rate {text!r}: 'max', 'recorded' or frames per second > 0")
    return fps


class Pacer:
    """Holds each frame back until it is due: frame ``i`` at ``(i - first) / fps`` seconds
    after ``t0``, or at its timestamp's distance from the first paced frame's (``fps`` 0);
    ``fps`` None never waits."""

    def __init__(self, fps: float | None, t0: float, first: int) -> None:
        self.fps = fps
        self.t0 = t0
        self.first = first
        self._first_stamp: float | None = None

    def wait(self, i: int, timestamp: float) -> None:
        if self.fps is None:
            return
        if self._first_stamp is None:
            self._first_stamp = timestamp
        due = (timestamp - self._first_stamp) if self.fps == 0 else (i - self.first) / self.fps
        wait = self.t0 + due - time.monotonic()
        if wait > 0:
            time.sleep(wait)


def read_ahead(sequence: RecordedSource, start: int, name: str,
               depth: int = 3) -> Iterator[Frame]:
    """Frames from ``start`` on, decoded by a background thread (named ``name``) so reading
    images does not stall the stages; an unreadable image ends the stream with its error."""
    frames: queue.Queue = queue.Queue(maxsize=depth)

    def read() -> None:
        try:
            for i in range(start, len(sequence)):
                frames.put(sequence[i])
        except Exception as exc:  # an unreadable image ends the stream with its error
            frames.put(exc)
        frames.put(None)

    threading.Thread(target=read, name=name, daemon=True).start()
    while (frame := frames.get()) is not None:
        if isinstance(frame, Exception):
            raise frame
        yield frame


def live_frames(live: LiveSource, start_index: int, timeout_s: float,
                stopping: threading.Event, report: RobotReport, resume_after: float | None,
                robot_id: str) -> Iterator[Frame]:
    """The live camera's newest frame each time the robot asks, numbered on from
    ``start_index``, until it is stopped, the stream ends, or the camera is silent for
    ``timeout_s`` (said, and in the report: the run so far is kept as at a stop). Frames
    not after ``resume_after`` (a resumed session has that moment already) are dropped."""
    index = start_index
    deadline = time.monotonic() + timeout_s
    while not stopping.is_set():
        try:  # short waits, so a stop is seen while the camera is silent
            frame = live.take(min(STOP_POLL_S, max(deadline - time.monotonic(), 0.0)))
        except TimeoutError:
            if time.monotonic() < deadline:
                continue
            # A camera node restarting, a cable out: the run so far is kept as at a stop
            # (the end, the uploads, the map), with the reason in the report.
            why = (f"{live.description} delivered no frame in {timeout_s:.1f} s "
                   f"(source.live_frame_timeout_s): is the camera still streaming?")
            log.warning("robot %s: %s; the robot ends its session with what it has",
                        robot_id, why)
            report.camera_ended = why
            return
        deadline = time.monotonic() + timeout_s
        if frame is None:  # the camera's stream ended (a replay or a recording did)
            return
        if resume_after is not None and frame.timestamp <= resume_after:
            report.camera_before_resume += 1  # the session has this moment already
            continue
        report.camera_taken += 1
        yield replace(frame, index=index)
        index += 1
