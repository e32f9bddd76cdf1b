"""Keyframe uploads: the cloud builds its dense map from each keyframe's RGB-D, which the
robot sends (decimated to the map's pixel stride) on an uploader thread and resends until
the cloud acknowledges it (what it has written to disk), or says it is not needed."""

from __future__ import annotations

import logging
import queue
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from fleetslam.config import Config
from fleetslam.datasets.source import Frame, RecordedSource
from fleetslam.edge.report import RobotReport
from fleetslam.transport import keys
from fleetslam.wire.messages import KeyframeUpload, encode_keyframe

log = logging.getLogger("fleetslam.robot")


class KeyframeUploader:
    """Keeps the uploads of the last ``transport.keyframe_buffer_frames`` frames and the
    point each went at, and a keyframe's until the cloud acknowledges it; an older keyframe
    is read again from the recording, or, without one (``sequence`` None: a live camera),
    is unavailable: the robot tells the cloud so at its end. Uploads each keyframe once,
    resending it every ``ack_timeout_s`` up to ``max_attempts`` times."""

    def __init__(self, robot_id: str, sequence: RecordedSource | None, offload_at: int,
                 config: Config, report: RobotReport) -> None:
        self.robot_id = robot_id
        self.sequence = sequence
        self.offload_at = offload_at
        self.config = config
        self.report = report
        self.error: str | None = None  # an upload that failed: the run fails at its end
        self._acks: dict[int, threading.Event] = {}
        self._acks_lock = threading.Lock()
        self._uploads: queue.Queue = queue.Queue()
        self._buffer: OrderedDict[int, KeyframeUpload] = OrderedDict()
        # Keyframes' uploads until acknowledged (small: decimated to the map's stride).
        self._pinned: dict[int, KeyframeUpload] = {}
        self._buffer_lock = threading.Lock()
        self.unavailable: set[int] = set()  # keyframes this robot can no longer upload
        # The point each recent frame went at (an adaptive robot switches).
        self._point_of: OrderedDict[int, int] = OrderedDict()
        self._thread: threading.Thread | None = None

    # -- the main thread ------------------------------------------------------------------

    def keep(self, frame: Frame, k: int) -> None:
        """Frame ``frame`` was sent at point ``k``: keep its upload, should it be a keyframe."""
        limit = self.config.transport.keyframe_buffer_frames
        self._point_of[frame.index] = k
        while len(self._point_of) > limit:
            self._point_of.popitem(last=False)
        if k > 0:
            with self._buffer_lock:
                self._buffer[frame.index] = KeyframeUpload.from_frame(
                    frame.index, frame.timestamp, frame.rgb, frame.depth_raw,
                    self.config.map.pixel_stride)
                while len(self._buffer) > limit:
                    self._buffer.popitem(last=False)

    # -- what the cloud says --------------------------------------------------------------

    def keyframe(self, index: int) -> None:
        """The cloud made frame ``index`` a keyframe: upload it, unless it went at point 0
        (which gave the cloud its images already)."""
        if self._point_of.get(index, self.offload_at) > 0:
            with self._buffer_lock:
                upload = self._buffer.get(index)
                if upload is not None:
                    self._pinned[index] = upload
            self.queue(index)

    def queue(self, index: int) -> None:
        """Upload a keyframe once: the cloud's 'need' at the end may name one whose feedback
        came after the end was sent, and is already on its way."""
        with self._acks_lock:
            if index in self._acks:
                return
            self._acks[index] = threading.Event()
        self._uploads.put(index)

    def acknowledged(self, index: int) -> None:
        self._unpin(index)
        with self._acks_lock:
            event = self._acks.get(index)
            if event is not None and not event.is_set():
                self.report.acknowledged.append(index)
        if event is not None:
            event.set()

    def settled(self, index: int) -> bool:
        """Whether a queued keyframe's upload is over (acknowledged, or not needed)."""
        with self._acks_lock:
            event = self._acks.get(index)
        return event is not None and event.is_set()

    def not_needed(self, index: Any) -> None:
        """The cloud's session does not hold this frame as a keyframe (a cloud restarted from
        an older checkpoint lost it): resending cannot help, so its upload ends here."""
        with self._acks_lock:
            event = self._acks.get(index) if isinstance(index, int) else None
        if event is not None and not event.is_set():
            self.report.uploads_not_needed += 1
            self._unpin(index)
            event.set()

    def _unpin(self, index: int) -> None:
        with self._buffer_lock:
            self._pinned.pop(index, None)

    # -- the uploader thread --------------------------------------------------------------

    def start(self, send: Callable[[str, bytes], bool]) -> None:
        """Start uploading over ``send`` (the robot's link)."""
        self._thread = threading.Thread(target=self._run, args=(send,),
                                        name=f"robot-{self.robot_id}-upload", daemon=True)
        self._thread.start()

    def wait(self) -> None:
        """Until every upload queued so far is acknowledged, not needed, or failed."""
        self._uploads.join()

    def stop(self) -> None:
        self._uploads.put(None)
        if self._thread is not None:
            self._thread.join(5.0)

    def _run(self, send: Callable[[str, bytes], bool]) -> None:
        while (index := self._uploads.get()) is not None:
            try:
                self._upload(index, send)
            except Exception as exc:
                self.error = f"robot {self.robot_id}: {exc}"
                log.error("%s", self.error)
            finally:
                self._uploads.task_done()
        self._uploads.task_done()

    def _upload(self, index: int, send: Callable[[str, bytes], bool]) -> None:
        cfg = self.config.transport
        with self._acks_lock:
            event = self._acks[index]
        upload = self._keyframe_upload(index)
        if upload is None:  # never resent: nothing to send; the end message says so
            log.warning("robot %s: keyframe %d is no longer held (a live camera keeps no "
                        "recording); the cloud maps without it", self.robot_id, index)
            self.unavailable.add(index)
            self.report.keyframes_unavailable += 1
            event.set()
            return
        data = encode_keyframe(self.robot_id, index, upload, self.config.wire)
        for attempt in range(cfg.max_attempts):
            if attempt:
                self.report.upload_retries += 1
            send(keys.keyframe(self.robot_id), data)
            self.report.keyframe_uploads += 1
            self.report.keyframe_bytes += len(data)
            if event.wait(cfg.ack_timeout_s):
                return
        raise RuntimeError(f"keyframe {index} not acknowledged after {cfg.max_attempts} tries")

    def _keyframe_upload(self, index: int) -> KeyframeUpload | None:
        """The keyframe's upload; None if it is gone (a live camera's, older than the buffer
        and never pinned: its feedback came late, or before a restart)."""
        with self._buffer_lock:
            upload = self._pinned.get(index) or self._buffer.get(index)
        if upload is None:  # older than the buffer: read it again from the recording
            if self.sequence is None:
                return None
            frame = self.sequence[index]
            upload = KeyframeUpload.from_frame(index, frame.timestamp, frame.rgb, frame.depth_raw,
                                               self.config.map.pixel_stride)
        return upload
