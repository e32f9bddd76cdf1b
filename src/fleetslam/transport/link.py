"""An emulated network link on a robot's send path, so a robot never sends faster than its link.

The link puts one message on the wire at a time (FIFO across all sending threads): ``send``
blocks until the message's last bit is out, and the message reaches ``deliver`` one latency
later, from a background thread, in send order. A lost message still costs its wire time.
"""

from __future__ import annotations

import logging
import math
import random
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

from fleetslam.config import LinkConfig

logger = logging.getLogger("fleetslam.link")


@dataclass
class LinkStats:
    """What went over the link; lost messages are counted in ``messages`` and ``bytes`` too."""

    messages: int = 0
    bytes: int = 0
    lost_messages: int = 0
    lost_bytes: int = 0
    # Time the link spent serialising bits (sum of size / bandwidth), lost messages included.
    busy_s: float = 0.0
    # Messages handed to ``deliver`` (a callback that raised still counts: it was handed over).
    delivered: int = 0


def validate_link_config(config: LinkConfig) -> None:
    if not math.isfinite(config.bandwidth_mbps) or config.bandwidth_mbps < 0:
        raise ValueError(f"link.bandwidth_mbps must be >= 0 (0 = unlimited), "
                         f"got {config.bandwidth_mbps}")
    if not math.isfinite(config.latency_ms) or config.latency_ms < 0:
        raise ValueError(f"link.latency_ms must be >= 0, got {config.latency_ms}")
    if not 0.0 <= config.loss < 1.0:
        raise ValueError(f"link.loss must be in [0, 1), got {config.loss}")


def parse_link_trace(text: str) -> list[tuple[int, float]]:
    """``"0:10,300:1,700:10"``: from frame 0 on 10 Mbit/s, from frame 300 on 1, ... as
    (first frame, Mbit/s) pairs in frame order."""
    trace = []
    for part in text.split(","):
        try:
            frame, mbps = part.split(":")
            trace.append((int(frame), float(mbps)))
        except ValueError as exc:
            raise ValueError(f"link trace {text!r}: each part is FRAME:MBPS, got {part!r}") \
                from exc
    if any(f < 0 or not (math.isfinite(b) and b > 0) for f, b in trace):
        raise ValueError(f"link trace {text!r}: frames >= 0 and bandwidths > 0")
    if [f for f, _ in trace] != sorted({f for f, _ in trace}):
        raise ValueError(f"link trace {text!r}: frames must rise")
    return trace


class EmulatedLink:
    def __init__(self, config: LinkConfig, deliver: Callable[[str, bytes], None],
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        validate_link_config(config)
        self._deliver = deliver
        self._clock = clock
        self._sleep = sleep
        self._bits_per_s = config.bandwidth_mbps * 1e6
        self._latency_s = config.latency_ms / 1000.0
        self._loss = config.loss
        # One draw per message in send order: the same seed loses the same messages.
        self._rng = random.Random(config.seed)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._free_at = -math.inf
        self._queue: deque[tuple[float, str, bytes]] = deque()
        self._pending = 0
        self._stats = LinkStats()
        self._closed = False
        self._stopping = False
        # A perfect link needs no thread: deliver straight from send.
        self._direct = self._bits_per_s == 0 and self._latency_s == 0
        self._thread: threading.Thread | None = None
        if not self._direct:
            # Daemon so a link never closed cannot hold the interpreter open.
            self._thread = threading.Thread(target=self._run, name="fleetslam-link", daemon=True)
            self._thread.start()

    @property
    def stats(self) -> LinkStats:
        with self._lock:
            return replace(self._stats)

    def send(self, key: str, data: bytes) -> bool:
        """Put ``data`` on the link; return when its last bit is sent. False if it was lost."""
        size = len(data)
        with self._lock:
            if self._closed:
                raise RuntimeError("send on a closed EmulatedLink")
            # Reserve the link under the lock (FIFO); the wait itself happens outside it.
            start = max(self._clock(), self._free_at)
            duration = size * 8 / self._bits_per_s if self._bits_per_s > 0 else 0.0
            finish = start + duration
            self._free_at = finish
            lost = self._loss > 0 and self._rng.random() < self._loss
            stats = self._stats
            stats.messages += 1
            stats.bytes += size
            stats.busy_s += duration
            if lost:
                stats.lost_messages += 1
                stats.lost_bytes += size
            elif self._direct:
                # Under the lock so concurrent senders' messages arrive in send order.
                self._deliver_one(key, data)
                stats.delivered += 1
            else:
                self._queue.append((finish + self._latency_s, key, data))
                self._pending += 1
                self._changed.notify_all()
        self._sleep_until(finish)
        return not lost

    def set_bandwidth(self, mbps: float) -> None:
        """Change the bandwidth from the next message on (a link trace; 0 = unlimited)."""
        if not math.isfinite(mbps) or mbps < 0:
            raise ValueError(f"bandwidth must be >= 0 Mbit/s, got {mbps}")
        with self._lock:
            self._bits_per_s = mbps * 1e6

    def flush(self, timeout: float | None = None) -> None:
        """Wait until every message sent so far is delivered (or lost).

        ``timeout`` is in real seconds; TimeoutError if messages are still in flight by then.
        """
        with self._changed:
            if not self._changed.wait_for(lambda: self._pending == 0, timeout):
                raise TimeoutError(f"link flush: {self._pending} messages still in flight "
                                   f"after {timeout} s")

    def close(self) -> None:
        """Refuse further sends, deliver what is in flight, stop the delivery thread."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self.flush()
        with self._changed:
            self._stopping = True
            self._changed.notify_all()
        if self._thread is not None:
            self._thread.join()

    def __enter__(self) -> EmulatedLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _sleep_until(self, deadline: float) -> None:
        # Sleep the whole remaining time (no busy wait); loop in case sleep wakes early.
        while (remaining := deadline - self._clock()) > 0:
            self._sleep(remaining)

    def _deliver_one(self, key: str, data: bytes) -> None:
        # A failing receiver must not stop the link: later messages still get through.
        try:
            self._deliver(key, data)
        except Exception:
            logger.exception("link: deliver failed for message on %r", key)

    def _run(self) -> None:
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._queue or self._stopping)
                if not self._queue:
                    return
                # Due times rise along the queue (FIFO link, one latency), so the head is next.
                due, key, data = self._queue[0]
            self._sleep_until(due)
            with self._lock:
                self._queue.popleft()
            self._deliver_one(key, data)
            with self._changed:
                self._pending -= 1
                self._stats.delivered += 1
                self._changed.notify_all()
