"""A robot session's checkpoints, written on a thread of their own: the session snapshots its
state where it stands (quick), this writes it durably to the store (slow), and the session's
replies wait until the checkpoint they depend on is on disk. A new keyframe goes to the
merger only after the checkpoint that holds it: a worker taking the session over from the
store never finds the merger ahead of the store.

A checkpoint asked within ``interval_s`` of the last capture waits: the session's thread
calls ``capture_due`` after each message and when ``due_in`` runs out, and that capture
covers every request since (transport.checkpoint_interval_s). Frames without a keyframe
are checkpointed too once the last checkpoint asked for is older than
transport.checkpoint_every_s (the session asks, ``older_than``).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Callable

import numpy as np

from fleetslam.cloud.session.store import CloudStore, NotOwner
from fleetslam.wire.data_tree import Capture
from fleetslam.wire.merger_keyframes import KeyframeSummary

log = logging.getLogger("fleetslam.cloud")

# The longest a reply waits for the checkpoint that must be on disk before it goes out.
CHECKPOINT_WAIT_S = 30.0

# Where a session hands each new keyframe (and its robot's latest keyframe poses): the merger.
KeyframeSink = Callable[[KeyframeSummary, np.ndarray], None]
# What the merger gets of a new keyframe (the arguments of a KeyframeSink).
NewKeyframe = tuple[KeyframeSummary, np.ndarray]


class CheckpointWriter:
    def __init__(self, robot_id: str, store: CloudStore, snapshot: Callable[[], Capture],
                 durable_index: int, keyframe_sink: KeyframeSink | None = None,
                 ended: Callable[[], bool] = lambda: False,
                 written: Callable[[Capture, bool], None] = lambda blob, ended: None,
                 interval_s: float = 0.0) -> None:
        """``snapshot``: the session's state as a checkpoint now; ``durable_index``: the
        newest frame index a checkpoint on disk covers already (a restored session: all);
        ``ended``: whether the robot has finished (taken with each snapshot); ``written``:
        told each checkpoint written and whether the robot had finished (its chunks: later
        snapshots leave them out)."""
        self.robot_id = robot_id
        self.store = store
        self.keyframe_sink = keyframe_sink
        self._snapshot = snapshot
        self._ended = ended
        self._chunks_written = written
        self._queue: queue.Queue = queue.Queue()
        self._durable_index = durable_index
        # Checkpoints queued and written, counted: the end's checkpoint is awaited by number
        # (it may cover no newer frame than the last keyframe's).
        self._queued = 0
        self._written = 0
        # The newest checkpoint number whose write failed, and why (the end must not say
        # "ended" over it).
        self._failed: tuple[int, str] = (0, "")
        self._durable = threading.Condition()
        self._interval_s = interval_s
        self._captured_at = -float("inf")
        self._asked_at = time.monotonic()  # the last checkpoint asked for
        # Checkpoints written and their bytes (new chunks included): what the store costs.
        self.writes = 0
        self.bytes_written = 0
        # Requests not captured yet: the newest frame index and the keyframes for the merger.
        self._waiting: tuple[int, list[NewKeyframe]] | None = None
        self._thread = threading.Thread(target=self._write, name=f"cloud-{robot_id}-checkpoints",
                                        daemon=True)

    def start(self) -> None:
        self._thread.start()

    def close(self, timeout: float) -> None:
        """Stop once every checkpoint queued so far is written."""
        self._queue.put(None)
        if self._thread.is_alive():
            self._thread.join(timeout)

    def checkpoint(self, frame_index: int, keyframe: NewKeyframe | None = None,
                   now: bool = True) -> int:
        """Ask for a checkpoint covering frames up to ``frame_index``; its number. Captured
        at once, or (``now`` False) within interval_s of the last capture, see the
        module's docstring. ``keyframe``: what the merger gets of the new keyframe, handed on
        once a checkpoint that holds it is on disk."""
        with self._durable:
            self._queued += 1
            number = self._queued
        self._asked_at = time.monotonic()
        index, keyframes = self._waiting or (frame_index, [])
        self._waiting = (max(index, frame_index), keyframes + ([keyframe] if keyframe else []))
        if now or self.due_in() == 0.0:
            self.capture()
        return number

    @property
    def asked(self) -> int:
        """Checkpoints asked for so far (several asked together are written as one)."""
        with self._durable:
            return self._queued

    def older_than(self, age_s: float) -> bool:
        """No checkpoint asked for within ``age_s`` (> 0) and none waiting."""
        return age_s > 0 and self._waiting is None \
            and time.monotonic() - self._asked_at >= age_s

    def due_in(self) -> float | None:
        """Seconds until the waiting request is to be captured; None if none waits."""
        if self._waiting is None:
            return None
        return max(0.0, self._captured_at + self._interval_s - time.monotonic())

    def capture_due(self) -> None:
        """Capture the waiting request if its time has come (the session's thread)."""
        if self.due_in() == 0.0:
            self.capture()

    def capture(self) -> None:
        """Capture the state now for every waiting request (the session's thread)."""
        if self._waiting is None:
            return
        (index, keyframes), self._waiting = self._waiting, None
        with self._durable:
            number = self._queued
        self._captured_at = time.monotonic()
        self._queue.put((index, number, self._snapshot(), self._ended(), keyframes))

    def wait_for_frame(self, frame_index: int, timeout: float = CHECKPOINT_WAIT_S) -> bool:
        """Until a checkpoint on disk covers ``frame_index``; whether one does."""
        with self._durable:
            return self._durable.wait_for(lambda: self._durable_index >= frame_index, timeout)

    def wait_for_number(self, number: int, timeout: float = CHECKPOINT_WAIT_S) -> bool:
        """Until checkpoint ``number`` (or a later one) is on disk; whether it is."""
        return self.not_durable(number, timeout) is None

    def not_durable(self, number: int, timeout: float = CHECKPOINT_WAIT_S) -> str | None:
        """Until checkpoint ``number`` (or a later one) is on disk and current, or its write
        failed: None when it is, else why not (the store's refusal, or the time it took)."""
        with self._durable:
            self._durable.wait_for(lambda: self._written >= number
                                   or self._failed[0] >= number, timeout)
            if self._written >= number:
                return None
            if self._failed[0] >= number:
                return self._failed[1]
            return f"not written within {timeout:.0f} s"

    def _fail(self, number: int, why: str) -> None:
        with self._durable:
            self._failed = (max(self._failed[0], number), why)
            self._durable.notify_all()

    def _write(self) -> None:
        while (item := self._queue.get()) is not None:
            index, number, blob, ended, keyframes = item
            while not self._queue.empty():  # only the newest one matters
                newer = self._queue.get()
                if newer is None:
                    self._queue.put(None)
                    break
                index, number, blob, ended, more = newer
                keyframes = keyframes + more
            try:
                written = self.store.write_checkpoint(self.robot_id, blob, ended=ended)
            except NotOwner as exc:
                # Fenced or taken over: the placement drops this session; nothing it holds
                # is acknowledged or merged from here on.
                log.warning("robot %s: checkpoint not written: %s", self.robot_id, exc)
                self._fail(number, f"refused: {exc}")
                continue
            except ConnectionError as exc:  # etcd not reachable (fenced_store.py): said
                log.warning("robot %s: checkpoint not written: %s", self.robot_id, exc)
                self._fail(number, f"not made current: {exc}")
            except OSError as exc:
                log.exception("robot %s: checkpoint not written", self.robot_id)
                self._fail(number, f"not written: {exc}")
            else:
                if isinstance(blob, Capture):
                    self._chunks_written(blob, ended)
                self.writes += 1
                self.bytes_written += written or 0
                with self._durable:
                    self._durable_index = max(self._durable_index, index)
                    self._written = max(self._written, number)
                    self._durable.notify_all()
            # The merger holds no keyframe the store lacks (unless a write failed, logged
            # above): a worker taking the session over from the store goes on from the
            # keyframes the merger has, never from an older map beside them.
            for kf in keyframes:
                if self.keyframe_sink is not None:
                    try:
                        self.keyframe_sink(*kf)
                    except Exception:  # the merger's loss, never the checkpoints'
                        log.exception("robot %s: keyframe not handed to the merger",
                                      self.robot_id)
