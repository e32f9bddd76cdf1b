"""How loaded each cloud worker is, measured: the cores its process and its child processes
at its priority kept busy lately (niced ones, local BA and the place search, yield), and how
many robots it held all through that window. Every worker
publishes its own every ``placement.load_report_s`` (``fleet/cloud/load/<worker>``) and
keeps the others'; placement ranks the workers for a new robot by it, so robots go by
measured cost, not by count (the merging worker, a robot tracking itself at point 6, a robot
gone quiet: each weighs what it costs).

A report counts every robot its worker held when it measured (the meter weighs a robot at
work at ``placement.robot_cost_cores`` until its frames show in the average, then at its
measured share; one gone quiet weighs nothing). A robot granted since the worker's last report
is in no measurement: it counts ``placement.robot_cost_cores`` until the next report, so a
robot weighs the same before and after the report that first counts it. (Reports that left
robots out until held a whole window, 5 s, while the meter already counted them, weighed a
robot twice once its worker reported and once before: the worker that had reported looked
busier, and robots arriving together went to the other.)
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import zenoh

from fleetslam.backend.process_stats import proc_stat, stat_cpu_seconds
from fleetslam.config import PlacementConfig
from fleetslam.transport import keys
from fleetslam.transport.zenoh_session import put

log = logging.getLogger("fleetslam.placement")

# Loads closer than this (cores) count as equal: the robot's hash decides between them.
EQUAL_CORES = 0.05
# A report is at most this large (bytes); anything else on the key is ignored.
MAX_REPORT_BYTES = 256


class RobotsAtWork(Protocol):
    """The robots a worker is working for now (its session table)."""

    def at_work(self) -> int: ...

    def has_room(self) -> bool:
        """Whether a new robot's hello would get a session here."""


class LoadMeter(Protocol):
    """A worker's load now, in cores busy (CpuMeter), and whether it has room for a robot."""

    def busy(self) -> float: ...

    def has_room(self) -> bool: ...


class Holdings(Protocol):
    """The robots a worker serves now (its placement)."""

    def held(self) -> int: ...


def tree_cpu_seconds(pid: int, unniced_only: bool = False) -> float:
    """User + system CPU seconds of ``pid`` and every process below it (Linux /proc; 0.0
    elsewhere); ``unniced_only``: of those at ``pid``'s priority or above, leaving out
    work niced below it (local BA, the merger's place search), which yields the cores to
    tracking."""
    parent: dict[int, int] = {}
    cpu: dict[int, float] = {}
    nice: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        fields = proc_stat(int(entry.name))
        if fields is None:
            continue
        parent[int(entry.name)] = int(fields[1])
        cpu[int(entry.name)] = stat_cpu_seconds(fields)
        nice[int(entry.name)] = int(fields[16])
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        if not unniced_only or nice.get(p, 0) <= nice.get(pid, 0):
            total += cpu.get(p, 0.0)
        todo += [c for c, pp in parent.items() if pp == p]
    return total


class CpuMeter:
    """Cores a process tree keeps busy for its robots now, at its own priority (its niced
    background work yields to a new robot's tracking, so it does not count). It measures
    the cores used and
    the robots at work (``robots``), each smoothed over ``window_s`` (exponential averages
    updated at each call), and weighs the robots at work now at the measured cost per
    robot: a robot gone quiet stops counting at once, not a window later (measured: a fleet
    that stopped together made its worker look busiest for the next robots, 4 + 1 and
    2 + 4 placements). Robots at work beyond the averaged count (those that came within
    the window) each count ``robot_cost`` cores on top of what was measured: a robot that
    just came would weigh nothing until its frames show in the average (two robots started
    a second apart both went to one worker). Counting them so until the average had
    reached half a robot was not enough: ten robots granted at once passed it within a
    fifth of a window, and were then weighed at the CPU their worker had used before they
    sent a frame; the next robots of the fleet all went to that worker (12 + 8 and 9 + 11
    of 20 robots, bench/worker_scaling.py). Nor was an average still holding the robots of
    a fleet that had just ended: the new fleet's first robots took their places in it
    (8 + 12)."""

    def __init__(self, pid: int, window_s: float, robots: RobotsAtWork,
                 robot_cost: float) -> None:
        self.pid, self.window_s, self._robots = pid, window_s, robots
        self.robot_cost = robot_cost
        self._last = (time.monotonic(), tree_cpu_seconds(pid, unniced_only=True))
        self._busy = 0.0
        self._active_avg = 0.0
        self._lock = threading.Lock()

    def busy(self) -> float:
        with self._lock:
            now, cpu, active = (time.monotonic(), tree_cpu_seconds(self.pid, unniced_only=True),
                                self._robots.at_work())
            dt = now - self._last[0]
            if dt > 0.05:
                rate = max(cpu - self._last[1], 0.0) / dt
                weight = 1.0 - math.exp(-dt / self.window_s)
                self._busy += weight * (rate - self._busy)
                self._active_avg += weight * (active - self._active_avg)
                self._last = (now, cpu)
            if active < self._active_avg:
                # Robots gone quiet: their share goes at once, from the averages too (robots
                # that come next are new, not the quiet ones' places in a stale average).
                self._busy *= active / self._active_avg
                self._active_avg = float(active)
            # The robots the averages have taken in weigh what was measured; those they have
            # not yet (arrived within the window) the configured cost each.
            return self._busy + self.robot_cost * (active - self._active_avg)

    def has_room(self) -> bool:
        return self._robots.has_room()


@dataclass(frozen=True)
class LoadReport:
    busy: float  # cores
    # Robots the worker held when it measured (their cost is in ``busy``; one granted since
    # counts at placement.robot_cost_cores until the next report).
    owned: int
    # No room for another robot: every session it may hold is live and working.
    full: bool = False


def parse_report(data: bytes) -> LoadReport:
    """A worker's report, or ValueError saying what is wrong with it."""
    if len(data) > MAX_REPORT_BYTES:
        raise ValueError(f"{len(data)} bytes (at most {MAX_REPORT_BYTES})")
    try:
        message: Any = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"not JSON ({exc})") from None
    if not isinstance(message, dict):
        raise ValueError("not a JSON object")
    busy, owned = message.get("busy"), message.get("owned")
    if not isinstance(busy, (int, float)) or isinstance(busy, bool) or \
            not math.isfinite(busy) or not 0 <= busy < 1e4:
        raise ValueError(f"busy is {busy!r}: cores, a number from 0")
    if not isinstance(owned, int) or isinstance(owned, bool) or not 0 <= owned < 10**6:
        raise ValueError(f"owned is {owned!r}: a robot count")
    full = message.get("full", False)  # absent from a worker older than the field
    if not isinstance(full, bool):
        raise ValueError(f"full is {full!r}: true or false")
    return LoadReport(float(busy), owned, full)


def spread(robot: str, worker: str) -> str:
    """Equal loads: robots spread over the workers by a hash of robot and worker, not all
    to the first id. A real hash: a CRC is linear, so names differing in one character
    would compare the same way whatever the robot."""
    return hashlib.blake2s(f"{robot}/{worker}".encode(), digest_size=4).hexdigest()


class WorkerLoads:
    """This worker's reports (``meter``: its cores busy now; ``holdings``: its robots) and
    the other workers' as heard, once started on a Zenoh session."""

    def __init__(self, worker_id: str, cfg: PlacementConfig, meter: LoadMeter,
                 holdings: Holdings) -> None:
        self.worker_id, self.cfg = worker_id, cfg
        self._meter, self._holdings = meter, holdings
        self.z: zenoh.Session | None = None
        self._lock = threading.Lock()
        self.reports: dict[str, LoadReport] = {}
        self._rejected: set[str] = set()  # workers whose bad report was logged
        self._closed = threading.Event()
        self._thread = threading.Thread(target=self._run, name="worker-load", daemon=True)
        self._subscriber: Any = None

    def start(self, z: zenoh.Session) -> "WorkerLoads":
        self.z = z
        self._subscriber = z.declare_subscriber(f"{keys.LOADS}/*", self._on_report)
        self.report()
        self._thread.start()
        return self

    def close(self) -> None:
        self._closed.set()
        if self._subscriber is not None:
            self._subscriber.undeclare()

    def report(self) -> LoadReport:
        """Measure this worker now, keep it as its own report and publish it."""
        # The robots held first: one granted between the two reads is in the meter (at its
        # cost) and counted again until the next report, never left out.
        held = int(self._holdings.held())
        mine = LoadReport(round(float(self._meter.busy()), 3), held, not self._meter.has_room())
        with self._lock:
            self.reports[self.worker_id] = mine
        if self.z is not None:  # started
            # Droppable: the next report replaces it; never waited for behind a full queue.
            put(self.z, keys.load(self.worker_id),
                json.dumps({"busy": mine.busy, "owned": mine.owned, "full": mine.full}).encode(),
                droppable=True)
        return mine

    def _run(self) -> None:
        while not self._closed.wait(self.cfg.load_report_s):
            try:
                self.report()
            except Exception:  # a closed session at shutdown; never the worker's end
                if not self._closed.is_set():
                    log.exception("load report of worker %s failed", self.worker_id)

    def _on_report(self, sample: zenoh.Sample) -> None:
        (worker,) = keys.last_chunks(str(sample.key_expr), 1)
        if worker == self.worker_id:
            return
        try:
            report = parse_report(sample.payload.to_bytes())
        except ValueError as exc:
            if worker not in self._rejected:
                self._rejected.add(worker)
                log.warning("load report of worker %s ignored: %s", worker, exc)
            return
        with self._lock:
            self.reports[worker] = report

    def score(self, worker: str, owned_now: int) -> float:
        """Cores ``worker`` would have busy: its last measurement, plus the robots granted
        to it since (``owned_now`` beyond those it held then) at the configured cost each."""
        with self._lock:
            report = self.reports.get(worker, LoadReport(0.0, 0))
        return report.busy + self.cfg.robot_cost_cores * max(owned_now - report.owned, 0)

    def all_full(self, workers: list[str]) -> bool:
        """Whether every one of ``workers`` has no room for a robot: this worker as it is
        now, the others as their last reports say (a worker never heard from has room)."""
        with self._lock:
            others = [self.reports.get(w) for w in workers if w != self.worker_id]
        return not self._meter.has_room() and all(r is not None and r.full for r in others)

    def ranking(self, robot: str, scores: dict[str, float]) -> list[str]:
        """The workers of ``scores`` (cores, as ``score`` gives), the best to serve
        ``robot`` first: the least loaded (within EQUAL_CORES), then by the robot's hash."""
        return sorted(scores, key=lambda w: (round(scores[w] / EQUAL_CORES), spread(robot, w),
                                             w))
