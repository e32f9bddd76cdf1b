"""A robot session's way in: its inbox (frames best effort, control messages never dropped)
and its admission (what a robot hears of its rejected messages, when a robot rejected too
often is paused, and how many control messages a second it may send). Used by
robot_session.py and routing.py; nothing here decodes or tracks.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Callable

from fleetslam.cloud.session.memory_budget import SessionBudget
from fleetslam.config import TransportConfig

log = logging.getLogger("fleetslam.cloud")

# A robot is told why a message was rejected at most this often.
REJECTION_REPLY_INTERVAL_S = 1.0


# What a session's inbox holds, in arrival order.
@dataclass(frozen=True)
class FrameItem:
    """A frame message, as it arrived (``data``) or once decoded (``decoded``: its header and
    state); ``charge``: the bytes it holds in the session's budget until tracked or dropped."""

    data: bytes | None
    arrival: float
    charge: int
    decoded: tuple[Any, Any] | None = None


@dataclass(frozen=True)
class ControlItem:
    """A control message (hello, end), parsed from JSON."""

    message: dict[str, Any]
    arrival: float


@dataclass(frozen=True)
class CallItem:
    """Something to run on the thread that takes it, in order with the frames."""

    call: Callable[[], object]


InboxItem = FrameItem | ControlItem | CallItem


class Idle:
    """What WorkQueue.get returns when its timeout passed with nothing to take."""


IDLE = Idle()


class Throttle:
    """Says whether something keyed (a reply key, a log topic) is due again: at most once
    per interval per key. The table forgets old keys, so a flood of made-up ids cannot grow
    it without bound."""

    MAX_KEYS = 4096

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._lock = threading.Lock()

    def due(self, key: str) -> bool:
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -float("inf")) < self.interval_s:
                return False
            if len(self._last) >= self.MAX_KEYS:
                self._last = {k: t for k, t in self._last.items()
                              if now - t < self.interval_s}
            self._last[key] = now
            return True


class WorkQueue:
    """A session's inbox: frames and control messages in arrival order, at most ``max_frames``
    frames. Frames are best effort, so when a robot sends faster than its session tracks, the
    oldest waiting frame is dropped (and counted); control messages are never dropped.
    A frame dropped gives its bytes back to the session's ``budget``."""

    def __init__(self, max_frames: int, budget: SessionBudget | None = None) -> None:
        self.max_frames = max_frames
        self._budget = budget
        self.dropped = 0
        self._items: deque[InboxItem | None] = deque()
        self._frames = 0
        self._ready = threading.Condition()

    def put(self, item: InboxItem | None) -> None:
        """An item to take in order; None: the end (the taker stops)."""
        with self._ready:
            if isinstance(item, FrameItem):
                if self._frames >= self.max_frames:
                    oldest = next(i for i, x in enumerate(self._items)
                                  if isinstance(x, FrameItem))
                    if self._budget is not None:
                        self._budget.release(self._items[oldest].charge)
                    del self._items[oldest]
                    self._frames -= 1
                    self.dropped += 1
                self._frames += 1
            self._items.append(item)
            self._ready.notify()

    def waiting_frames(self) -> list[FrameItem]:
        """The frames waiting now, oldest first."""
        with self._ready:
            return [item for item in self._items if isinstance(item, FrameItem)]

    def get(self, timeout: float | None = None) -> InboxItem | Idle | None:
        """The next item; IDLE if ``timeout`` passed with none."""
        with self._ready:
            if not self._ready.wait_for(lambda: bool(self._items), timeout):
                return IDLE
            item = self._items.popleft()
            if isinstance(item, FrameItem):
                self._frames -= 1
            return item


class Admission:
    """Whether a robot is heard, and what it hears of its rejected messages. A robot rejected
    more than ``transport.max_rejections_per_s`` times a second (a broken or hostile client)
    has its messages dropped unread for ``transport.misbehaving_pause_s``: decoding
    them would take the CPU the other robots' sessions need. It is told why a message was
    rejected at most once per REJECTION_REPLY_INTERVAL_S (a flood of bad messages must not
    become a flood of replies); the log gives every reason, except while it is paused.
    Control messages pass the same door: paused, they are dropped too, and beyond
    ``transport.max_control_per_s`` they are rejected (each end or hello costs the session
    work and a reply, so a flood of them must cost the flooder, not the cloud).

    ``counts`` is the session's (SessionState.counts), changed only under ``counts_lock``:
    several of the session's threads reject, and status and checkpoints read the counts."""

    def __init__(self, robot_id: str, transport: TransportConfig, counts: Counter,
                 counts_lock: threading.Lock) -> None:
        self.robot_id = robot_id
        self.transport = transport
        self._counts = counts
        self._counts_lock = counts_lock
        self._last_rejection_reply = -float("inf")
        self._rejected_since_reply = 0
        self._paused_until = -float("inf")
        # Control messages heard in the current one-second window (the rate limit).
        self._control_window = -float("inf")
        self._control_in_window = 0

    def control_refused(self) -> str | None:
        """Why a control message is not taken now (paused, or over the rate limit; counted
        as a rejection), or None when it is."""
        if self.paused():
            return "paused"
        now = time.monotonic()
        with self._counts_lock:
            if now - self._control_window >= 1.0:
                self._control_window, self._control_in_window = now, 0
            self._control_in_window += 1
            over = self._control_in_window > self.transport.max_control_per_s
        if over:
            return (f"over {self.transport.max_control_per_s:.0f} control messages a second "
                    f"(transport.max_control_per_s)")
        return None

    def paused(self) -> bool:
        """Whether the robot's messages are dropped unread now (counted so)."""
        if time.monotonic() >= self._paused_until:
            return False
        with self._counts_lock:
            self._counts["dropped unread (too many rejected)"] += 1
        return True

    def rejected(self, what: str, reason: str) -> str | None:
        """Count and log a rejected message (``what``: "frame", "keyframe"); what the robot
        is to hear of it, or None when it heard a reason less than an interval ago."""
        cfg = self.transport
        now = time.monotonic()
        with self._counts_lock:
            self._counts[f"rejected {what}"] += 1
            due = now - self._last_rejection_reply >= REJECTION_REPLY_INTERVAL_S
            # Frames and uploads: every reason (each costs a decode anyway); control
            # messages are cheap to flood, so their reasons go with the replies only.
            if now >= self._paused_until and (due or what != "control"):
                log.warning("robot %s: %s rejected: %s", self.robot_id, what, reason)
            if due:
                burst, self._rejected_since_reply = self._rejected_since_reply, 0
                self._last_rejection_reply = now
            else:
                # Counted since the last reason, so within one interval.
                self._rejected_since_reply += 1
                if self._rejected_since_reply >= \
                        cfg.max_rejections_per_s * REJECTION_REPLY_INTERVAL_S:
                    self._rejected_since_reply = 0
                    paused = now < self._paused_until  # (its backlog is still rejected)
                    self._paused_until = now + cfg.misbehaving_pause_s
                    if not paused:
                        self._counts["pauses (too many rejected)"] += 1
                        log.warning("robot %s: over %.0f rejected messages per second: "
                                    "its messages are dropped unread for %.1f s",
                                    self.robot_id, cfg.max_rejections_per_s,
                                    cfg.misbehaving_pause_s)
        if not due:
            return None
        more = f" ({burst} more rejected since the last reason)" if burst else ""
        return f"{what} rejected: {reason}{more}"
