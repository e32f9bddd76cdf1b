"""What a robot's session says to its robot, and its counts of what it took and refused: one
object the session's threads share. A rejection is told at most once per interval
(inbox.Admission); a session dropped because another worker serves the robot now says
nothing more."""

from __future__ import annotations

import threading
from collections import Counter
from typing import Any, Callable

from fleetslam.cloud.session.inbox import Admission
from fleetslam.transport import keys, protocol

# Puts bytes on a Zenoh key (the worker's session).
Publish = Callable[[str, bytes], None]


class Replies:
    def __init__(self, robot_id: str, publish: Publish, admission: Admission, counts: Counter,
                 counts_lock: threading.Lock) -> None:
        """``counts``: the session's (SessionState.counts), changed only under
        ``counts_lock``, which a checkpoint's snapshot holds while it copies them."""
        self.robot_id = robot_id
        self._send = publish
        self.admission = admission
        self._counts = counts
        self.counts_lock = counts_lock
        self.dropped = threading.Event()

    def publish(self, key: str, data: bytes) -> None:
        if not self.dropped.is_set():
            self._send(key, data)

    def reply(self, message: protocol.Reply) -> None:
        self.publish(keys.reply(self.robot_id), protocol.encode(message))

    def reject(self, what: str, reason: str, code: protocol.Code = protocol.Code.REJECTED,
               **extra: Any) -> None:
        """Count and log a rejected message; the robot hears why unless it heard a reason
        less than a second ago."""
        told = self.admission.rejected(what, reason)
        if told is not None:
            self.reply(protocol.Error.of(code, told, rejected=what, **extra))

    def count(self, name: str, n: int = 1) -> None:
        with self.counts_lock:
            self._counts[name] += n

    def counts(self) -> Counter:
        with self.counts_lock:
            return Counter(self._counts)
