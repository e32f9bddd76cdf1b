"""Who owned which robot when, read back from the cloud workers' logs, and whether two workers
ever owned one robot at the same time.

The logs are ``fleetslam`` CLI logs ("%(asctime)s %(name)s %(levelname)s %(message)s", local
time to the millisecond; every worker on one host, so one clock). Two placements write
different lines:

- etcd placement (cloud/coordination/ownership.py, logger fleetslam.ownership):
  ``grant robot R to worker W epoch E (lease L)`` starts W's ownership of R,
  ``release robot R by worker W epoch E`` / ``fence robot R on worker W epoch E`` ends it.
  The merger is granted as robot ``@merger`` the same way.
- liveliness placement (cloud/coordination/placement.py): ``worker W serves robot R (bids:
  ...)`` starts it, ``robot R is also served by worker X: giving it up`` (in W's log) ends it.

An ownership with no end line ends when its worker's process ended (``ends``: the time the
harness saw it exit or killed it): a worker believes it owns its robots until then.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

_LINE = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) (\S+) (\S+) (.*)$")
_GRANT = re.compile(r"^grant robot (\S+) to worker (\S+) epoch (\d+)")
_END = re.compile(r"^(release|fence) robot (\S+) (?:by|on) worker (\S+) epoch (\d+)")
_SERVES = re.compile(r"^worker (\S+) serves robot (\S+) \(bids")
_GIVES_UP = re.compile(r"^robot (\S+) is also served by worker (\S+): giving it up")
_FENCED = re.compile(r"^worker (\S+) fenced")


@dataclass
class Interval:
    robot: str
    worker: str
    start: float  # time.time() seconds
    end: float | None = None  # None while open
    epoch: int | None = None
    ended_by: str = "process end"


@dataclass(frozen=True)
class Overlap:
    robot: str
    first: Interval
    second: Interval

    @property
    def seconds(self) -> float:
        ends = [iv.end if iv.end is not None else float("inf")
                for iv in (self.first, self.second)]
        return min(ends) - max(self.first.start, self.second.start)


def stamp(asctime: str) -> float:
    """A log line's asctime (local time, ms) as time.time() seconds."""
    return datetime.strptime(asctime, "%Y-%m-%d %H:%M:%S,%f").timestamp()


def lines(path: Path) -> list[tuple[float, str, str]]:
    """(time, logger, message) of every line in the log format; others (tracebacks) skipped."""
    out = []
    for line in path.read_text(errors="replace").splitlines():
        m = _LINE.match(line)
        if m:
            out.append((stamp(m.group(1)), m.group(2), m.group(4)))
    return out


def intervals(log: Path, worker: str, ends: float | None) -> list[Interval]:
    """The ownerships ``worker`` logged in ``log``; those still open close at ``ends``."""
    found: list[Interval] = []
    open_: dict[tuple[str, int | None], Interval] = {}
    for t, _, message in lines(log):
        if m := _GRANT.match(message):
            robot, who, epoch = m.group(1), m.group(2), int(m.group(3))
            if who == worker:
                open_[(robot, epoch)] = Interval(robot, worker, t, epoch=epoch)
        elif m := _END.match(message):
            kind, robot, who, epoch = m.group(1), m.group(2), m.group(3), int(m.group(4))
            if who == worker and (robot, epoch) in open_:
                iv = open_.pop((robot, epoch))
                iv.end, iv.ended_by = t, kind
                found.append(iv)
        elif m := _SERVES.match(message):
            who, robot = m.group(1), m.group(2)
            if who == worker and (robot, None) not in open_:
                open_[(robot, None)] = Interval(robot, worker, t)
        elif m := _GIVES_UP.match(message):
            robot = m.group(1)
            if (robot, None) in open_:
                iv = open_.pop((robot, None))
                iv.end, iv.ended_by = t, "gave up"
                found.append(iv)
    for iv in open_.values():
        iv.end = ends
        found.append(iv)
    return sorted(found, key=lambda iv: iv.start)


def fenced_at(log: Path, worker: str) -> list[float]:
    """When ``worker`` said it was fenced (its lease not renewed in time)."""
    return [t for t, _, message in lines(log)
            if (m := _FENCED.match(message)) and m.group(1) == worker]


def overlaps(all_intervals: list[Interval]) -> list[Overlap]:
    """Pairs of ownerships of one robot by two workers that overlap in time (an ownership
    still open, end None, counts as never ending)."""
    found = []
    by_robot: dict[str, list[Interval]] = {}
    for iv in all_intervals:
        by_robot.setdefault(iv.robot, []).append(iv)
    for robot, ivs in by_robot.items():
        for i, a in enumerate(ivs):
            for b in ivs[i + 1:]:
                if a.worker == b.worker:
                    continue
                a_end = a.end if a.end is not None else float("inf")
                b_end = b.end if b.end is not None else float("inf")
                if max(a.start, b.start) < min(a_end, b_end):
                    found.append(Overlap(robot, a, b))
    return found


def owner_at(all_intervals: list[Interval], robot: str, t: float) -> list[str]:
    """The workers owning ``robot`` at time ``t``."""
    return sorted({iv.worker for iv in all_intervals if iv.robot == robot and iv.start <= t
                   and (iv.end is None or t < iv.end)})
