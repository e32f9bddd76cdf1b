"""Live sources run on the camera's clock: frames arrive whether or not the robot keeps up.

A camera thread (the device's, a Zenoh subscriber's, a replay's) puts each frame into a
``NewestFrame`` slot; the robot takes the newest one when it is ready for the next. A frame
overwritten before it was taken is skipped and counted, so a robot slower than its camera
holds one waiting frame, never a growing queue. The slot may hold what a frame is made from
instead (``NewestFrame[T]``), so a camera thread decodes nothing the robot skips.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from typing import Generic, Protocol, TypeVar, runtime_checkable

from fleetslam.camera import Camera
from fleetslam.datasets.source import Frame

T = TypeVar("T")  # a Frame, or what one is made from


class NewestFrame(Generic[T]):
    """A one-frame slot between a camera thread (``put``) and the robot (``take``)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._frame: T | None = None
        self._closed = False
        self._error: BaseException | None = None
        self.delivered = 0  # frames the camera put
        self.taken = 0  # frames the robot took
        self.skipped = 0  # frames overwritten before the robot took them

    @property
    def waiting(self) -> int:
        """Frames in the slot: 0 or 1, however far the robot falls behind."""
        with self._cond:
            return int(self._frame is not None)

    def put(self, frame: T) -> None:
        with self._cond:
            if self._closed:
                return
            if self._frame is not None:
                self.skipped += 1
            self._frame = frame
            self.delivered += 1
            self._cond.notify_all()

    def close(self, error: BaseException | None = None) -> None:
        """The stream ended (``error``: why it broke); a waiting ``take`` returns."""
        with self._cond:
            self._closed = True
            self._error = self._error or error
            self._cond.notify_all()

    def take(self, timeout: float) -> T | None:
        """The newest frame not taken yet, waiting up to ``timeout`` seconds for one; None
        once the stream has ended and its last frame was taken. Raises the camera's error,
        or ``TimeoutError`` when no frame came in time."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._frame is None:
                if self._error is not None:
                    raise self._error
                if self._closed:
                    return None
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no frame from the camera in {timeout:.1f} s")
                self._cond.wait(left)
            frame, self._frame = self._frame, None
            self.taken += 1
            return frame


class SlotCounts:
    """The counts of a live source that feeds a ``NewestFrame`` slot (``self._slot``)."""

    _slot: NewestFrame
    # Messages the source could not make a frame of, skipped (a live ROS 2 topic's); a
    # camera read through its driver (RealSense, a replay) has none to refuse.
    rejected: int = 0

    @property
    def skipped(self) -> int:
        """Frames the camera delivered that the robot never took."""
        return self._slot.skipped

    @property
    def delivered(self) -> int:
        return self._slot.delivered

    @property
    def undelivered(self) -> int:
        """Frames the camera produced that never reached the robot (a replay's decoded too
        late); 0 where the driver does not say (a RealSense, ROS 2 topics: their own
        counts)."""
        return 0

    @property
    def waiting(self) -> int:
        """Frames held for the robot: at most one, whatever its pace."""
        return self._slot.waiting


def take_numbered(slot: NewestFrame[Frame], timeout: float) -> Frame | None:
    """``slot.take`` with the frame's index set to the count of frames taken before it: the
    camera thread cannot know which of its frames will be taken, and the robot's frame
    indices must be dense."""
    frame = slot.take(timeout)
    return None if frame is None else replace(frame, index=slot.taken - 1)


@runtime_checkable
class LiveSource(Protocol):
    """A camera the robot cannot hold back (``datasets.replay``, ``datasets.realsense``,
    ``datasets.ros2_topics``)."""

    description: str  # what it is, for logs and the summary (e.g. "RealSense D435 #123")
    camera: Camera  # known once ``start`` returned
    camera_source: str

    def start(self, timeout: float) -> None:
        """Open the camera and wait (up to ``timeout`` s) until its camera model is known."""
        ...

    def take(self, timeout: float) -> Frame | None:
        """The newest frame (``NewestFrame.take``); frame indices count taken frames from 0."""
        ...

    @property
    def skipped(self) -> int:
        """Frames the camera delivered that the robot never took."""
        ...

    rejected: int  # messages it could not make a frame of, skipped

    @property
    def delivered(self) -> int:
        """Frames the camera delivered (``NewestFrame.delivered``): with the frames taken and
        skipped, what a run's summary shows of its camera."""
        ...

    @property
    def undelivered(self) -> int:
        """Frames the camera produced that it never delivered: produced = delivered +
        undelivered."""
        ...

    def close(self) -> None: ...
