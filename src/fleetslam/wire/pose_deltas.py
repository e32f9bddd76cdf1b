"""Point 6's keyframe poses as deltas: a robot that tracks itself sends, with each keyframe,
the poses that changed since a table the cloud applied, not all K of its keyframes' poses
(K x 96 bytes a keyframe message, so a run's bytes grew with K squared).

The robot (``PoseDeltaEncoder``) codes against its *base*: the newest keyframe message
whose feedback came back (the cloud tracked it, so its table holds that message's poses).
A message carries every keyframe whose pose differs, bit for bit, from the base's table,
every keyframe new since it, and every keyframe that a message sent after the base carried:
the cloud may or may not have applied those, and either way it ends with the poses sent
now. Without a base (the session's start, a takeover, a refusal) the whole table goes.

The cloud (``PoseTable``) applies a delta only on a base it applied itself in this process,
since its first whole table there; any other is refused with ``reference_missing``, and the
robot sends a whole table next. The table is not checkpointed: a restored session waits for
a whole one (its robot is told to say hello, and starts over).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

# Keyframe messages sent and not yet answered that the robot remembers. More than this
# unanswered (a cloud that stopped answering) and it sends whole tables until one is.
MAX_PENDING = 64


@dataclass(frozen=True)
class PoseDelta:
    """The keyframe poses of one message, coded against message ``base_seq``'s table."""

    base_seq: int
    count: int  # keyframes in the table after it (the message's keyframe is the last)
    ids: np.ndarray  # int64, strictly increasing, < count: the rows sent
    poses: np.ndarray  # len(ids) x 4 x 4


@dataclass
class PoseCounts:
    """What the robot's report says about its keyframe poses (RobotReport.inter_coding)."""

    whole_tables: int = 0
    delta_tables: int = 0
    poses_sent: int = 0
    poses_in_tables: int = 0  # what whole tables would have carried

    def summary(self) -> dict[str, int]:
        return {"pose_tables_whole": self.whole_tables, "pose_tables_delta": self.delta_tables,
                "keyframe_poses_sent": self.poses_sent,
                "keyframe_poses_in_tables": self.poses_in_tables}


class PoseDeltaEncoder:
    """The robot's side. Feedback arrives on Zenoh threads while the main thread encodes."""

    def __init__(self) -> None:
        self.enabled = False  # the cloud's welcome says whether it takes deltas
        self.counts = PoseCounts()
        self._lock = threading.Lock()
        self._base: tuple[int, np.ndarray] | None = None
        # seq -> (the table it sent, the rows it carried), oldest first.
        self._pending: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()

    def restart(self, enabled: bool) -> None:
        """A new or resumed session (``enabled``: its cloud takes deltas): no base."""
        with self._lock:
            self.enabled = enabled
            self._base = None
            self._pending.clear()

    def lost(self) -> None:
        """The cloud may hold no table the robot knows of: whole tables until one is tracked."""
        with self._lock:
            self._base = None
            self._pending.clear()

    def choose(self, table: np.ndarray) -> PoseDelta | None:
        """The rows of ``table`` (K x 4 x 4) to send against the base; None: the whole."""
        with self._lock:
            if not self.enabled or self._base is None:
                return None
            base_seq, base = self._base
            n, m = len(table), len(base)
            if n < m:
                return None
            changed = np.ones(n, bool)
            changed[:m] = (table[:m] != base).any(axis=(1, 2))
            for _, rows in self._pending.values():
                changed[rows[rows < n]] = True
            ids = np.flatnonzero(changed)
            return PoseDelta(base_seq, n, ids, table[ids].copy())

    def sent(self, seq: int, table: np.ndarray, delta: PoseDelta | None) -> None:
        """Keyframe message ``seq`` went out with ``table`` (as ``delta``, or whole)."""
        rows = np.arange(len(table)) if delta is None else delta.ids
        with self._lock:
            if delta is None:
                self.counts.whole_tables += 1
            else:
                self.counts.delta_tables += 1
            self.counts.poses_sent += len(rows)
            self.counts.poses_in_tables += len(table)
            self._pending[seq] = (np.array(table, np.float64), rows)
            if len(self._pending) > MAX_PENDING:
                self._base = None  # what the cloud applied is no longer known
                self._pending.clear()

    def tracked(self, seq: int) -> None:
        """The cloud tracked message ``seq`` (its feedback): a keyframe message's table is
        the base from now on."""
        with self._lock:
            entry = self._pending.get(seq)
            if entry is None:
                return
            self._base = (seq, entry[0])
            for old in [s for s in self._pending if s <= seq]:
                del self._pending[old]


class PoseTable:
    """The cloud's side: the robot's keyframe poses as the session applied them (its
    tracking thread only)."""

    def __init__(self) -> None:
        self.table: np.ndarray | None = None
        self._first_whole: int | None = None  # in this process
        self._last: int | None = None

    def refusal(self, delta: PoseDelta) -> str | None:
        """Why ``delta`` cannot be applied, or None."""
        if self.table is None or self._first_whole is None or self._last is None:
            return (f"keyframe poses coded against message {delta.base_seq}, but this session "
                    "holds no table of them (it started or was restored since): send them "
                    "whole")
        if not self._first_whole <= delta.base_seq <= self._last:
            return (f"keyframe poses coded against message {delta.base_seq}, which this "
                    f"session did not apply (it holds messages {self._first_whole}-"
                    f"{self._last}): send them whole")
        k = len(self.table)
        if delta.count < k:
            return f"{delta.count} keyframe poses, but the session holds {k}"
        new = delta.ids[delta.ids >= k]
        if not np.array_equal(new, np.arange(k, delta.count)):
            return (f"keyframe poses {k}-{delta.count - 1} are new, but the message carries "
                    f"{new.tolist()[:8]}")
        return None

    def whole(self, seq: int, poses: np.ndarray) -> np.ndarray:
        self.table = np.array(poses, np.float64)
        if self._first_whole is None:
            self._first_whole = seq
        self._last = seq
        return self.table.copy()

    def apply(self, seq: int, delta: PoseDelta) -> np.ndarray:
        """The whole table after ``delta`` (refusal() said None)."""
        assert self.table is not None
        table = np.empty((delta.count, 4, 4))
        table[:len(self.table)] = self.table
        table[delta.ids] = delta.poses
        self.table = table
        self._last = seq
        return table.copy()
