"""A recording played as a live camera: a thread decodes each frame and puts it into a
``NewestFrame`` when the camera's clock says it is due (at its recorded timestamps, or at a
fixed rate), whether or not the robot took the previous one.

Any ``RecordedSource`` works (a TUM / 7-Scenes folder today, a bag through the same
interface). Frames keep their recorded timestamps, so a run's trajectory is scored against
the recording's ground truth after the run as any other.
"""

from __future__ import annotations

import threading
import time

from fleetslam.camera import Camera
from fleetslam.datasets.live import NewestFrame, SlotCounts, take_numbered
from fleetslam.datasets.source import Frame, RecordedSource


class ReplaySource(SlotCounts):
    """``LiveSource`` over a recording. ``fps`` None: at the recording's timestamps."""

    def __init__(self, recording: RecordedSource, name: str, fps: float | None) -> None:
        if fps is not None and not fps > 0:
            raise ValueError(f"replay of {name}: rate {fps} is not frames per second > 0")
        if len(recording) == 0:
            raise ValueError(f"replay of {name}: the recording has no frames")
        self.recording = recording
        self.fps = fps
        self.description = (f"replay of {name} at "
                            + ("its recorded timestamps" if fps is None else f"{fps:g} fps"))
        self.camera: Camera = recording.camera
        self.camera_source = recording.camera_source
        # Frames the replay thread decoded too late to deliver on time (a machine too slow
        # to decode at the camera's rate): dropped, as a camera driver drops them.
        self.late = 0
        self._slot = NewestFrame()
        self._stop = threading.Event()
        self._first_decoded = threading.Event()
        self._thread = threading.Thread(target=self._play, name="replay-camera", daemon=True)

    def start(self, timeout: float) -> None:
        """Start the camera's clock; return once its first frame is decoded (a folder's
        camera learns the image size from it)."""
        self._thread.start()
        if not self._first_decoded.wait(timeout):
            self.close()
            raise TimeoutError(f"{self.description}: no frame decoded in {timeout:.1f} s")
        self.camera = self.recording.camera

    def take(self, timeout: float) -> Frame | None:
        return take_numbered(self._slot, timeout)

    @property
    def undelivered(self) -> int:
        """The recording's frames this camera dropped, decoded too late (``late``)."""
        return self.late

    def close(self) -> None:
        self._stop.set()
        self._slot.close()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(5.0)

    def due(self, i: int) -> float:
        """Seconds after the first frame at which frame ``i`` is delivered."""
        if self.fps is not None:
            return i / self.fps
        stamps = self.recording.timestamps
        return float(stamps[i] - stamps[0])

    def _play(self) -> None:
        try:
            t0 = time.monotonic()
            n = len(self.recording)
            for i in range(n):
                if i + 1 < n and time.monotonic() - t0 > self.due(i + 1):
                    self.late += 1  # its successor is due already: never decoded
                    continue
                frame = self.recording[i]  # decoded here, as a camera driver would
                self._first_decoded.set()
                # A wait with a deadline that close() cuts short.
                if self._stop.wait(max(0.0, t0 + self.due(i) - time.monotonic())):
                    return
                self._slot.put(frame)
        except Exception as exc:  # an unreadable image ends the stream with its error
            self._slot.close(ValueError(f"{self.description}: {exc}"))
            self._first_decoded.set()
            return
        self._slot.close()
