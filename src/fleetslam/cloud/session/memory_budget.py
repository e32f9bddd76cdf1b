"""A robot session's memory in bytes (``transport.session_budget_mb``): its frames waiting
(undecoded and decoded), its keyframe uploads waiting and the reference frames it keeps for
inter-frame coding. A message that does not fit is dropped unread (before decoding), so a
robot ignoring flow control costs the cloud at most its budget, never another session's.

Frames are charged when they arrive, at the size they will have decoded (a point-0 frame
is ~0.6 MB on the wire and ~2.2 MB decoded): the largest this session's frames decoded to
so far, or a captured RGB-D frame of its camera before the first. After decoding, the
charge is trued up to the arrays' real size. So what is charged never falls below what is
held, and nothing waits for room (a full session drops, it never blocks a Zenoh thread).
The cloud-wide budget is a reservation: SessionTable opens at most
``cloud_budget_mb // session_budget_mb`` sessions (``sessions_allowed``).
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import TransportConfig

MB = 1 << 20

def held_bytes(state: object) -> int:
    """Bytes of the arrays a decoded frame state holds (its dataclass fields, and theirs:
    a point-6 keyframe holds its features; the rest is small)."""
    if not dataclasses.is_dataclass(state):
        return 0
    values = [getattr(state, f.name) for f in dataclasses.fields(state)]
    return sum(v.nbytes if isinstance(v, np.ndarray) else held_bytes(v) for v in values)


def captured_frame_bytes(camera: Camera) -> int:
    """A captured RGB-D frame decoded: uint8 colour and float32 metres."""
    return camera.width * camera.height * (3 + 4)


def sessions_allowed(transport: TransportConfig) -> int:
    """Sessions the cloud opens at once: each reserves its whole budget."""
    by_memory = int(transport.cloud_budget_mb // transport.session_budget_mb)
    return max(0, min(transport.max_sessions, by_memory))


class SessionBudget:
    """One session's bytes held, against its limit. Zenoh's threads admit; the session's
    threads true up and release."""

    def __init__(self, limit_bytes: int, first_frame_bytes: int) -> None:
        self.limit = int(limit_bytes)
        self.used = 0
        self.peak = 0
        self._first_frame_bytes = first_frame_bytes
        self._largest_decoded = 0
        self._references = 0
        self._lock = threading.Lock()

    def frame_charge(self, raw_bytes: int) -> int:
        """What a frame of ``raw_bytes`` on the wire is charged until it is decoded."""
        return max(raw_bytes, self._largest_decoded or self._first_frame_bytes)

    def admit(self, charge: int) -> bool:
        """Take ``charge`` bytes if they fit."""
        with self._lock:
            if self.used + charge > self.limit:
                return False
            self._add(charge)
            return True

    def decoded(self, charged: int, actual: int) -> None:
        """A frame charged ``charged`` decoded to ``actual`` bytes (already held: taken even
        beyond the limit, and later frames are charged at least this much)."""
        with self._lock:
            self._largest_decoded = max(self._largest_decoded, actual)
            self._add(actual - charged)

    def release(self, charge: int) -> None:
        with self._lock:
            self.used -= charge

    def references(self, total: int) -> None:
        """The reference frames kept now hold ``total`` bytes."""
        with self._lock:
            self._add(total - self._references)
            self._references = total

    def _add(self, n: int) -> None:
        self.used += n
        self.peak = max(self.peak, self.used)
