"""When the robot takes its frames: ``--rate`` (as fast as it can, at a fixed rate, at the
recording's timestamps) and a read-ahead thread that decodes the next images, as a camera
driver delivers them."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator

from fleetslam.datasets.source import Frame, RecordedSource


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
