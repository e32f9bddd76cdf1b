"""Where a machine's CPU went over a bench phase: the cloud workers' tracking (their own
priority) and their niced background (local BA, the merger's place search), the router,
etcd, the bench process itself, and everything else on the machine (``other``: another
tenant's job, or this VM's host taking the cores, which shows as ``steal`` only where the
hypervisor reports it). Linux /proc only; elsewhere every share reads 0.

``speed_probe_ms`` times a fixed piece of single-threaded work (numpy and pure Python)
while the fleet is idle between phases: the same code on the same input, so a slower
probe says the machine itself was slower at that moment, whatever ran on it.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from fleetslam.backend.process_stats import process_cpu_seconds
from fleetslam.cloud.coordination.worker_load import tree_cpu_seconds

TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def _machine() -> tuple[float, float, float]:
    """(busy, steal, total) CPU seconds of the whole machine since boot, from /proc/stat."""
    try:
        with open("/proc/stat") as f:
            fields = [int(v) for v in f.readline().split()[1:]]
    except OSError:
        return 0.0, 0.0, 0.0
    idle = fields[3] + fields[4]  # idle, iowait
    # guest time is already counted in user; leave it out of the total.
    total = sum(fields[:8])
    return (total - idle) * TICK_S, fields[7] * TICK_S, total * TICK_S


@dataclass(frozen=True)
class Snapshot:
    wall: float
    machine: tuple[float, float, float]
    tracking: float  # the workers' processes at their own priority
    workers: dict[str, float]  # each worker's whole process tree
    router: float
    etcd: float
    bench: float


class CpuAccount:
    """Snapshots of the CPU used by each part of a bench's cloud (``workers``: each
    worker's pid by name); ``shares`` and ``worker_cores`` turn two of them into cores used
    over the wall time between them."""

    def __init__(self, workers: dict[str, int], router: int, etcd: int | None) -> None:
        self.workers, self.router, self.etcd = workers, router, etcd

    def snapshot(self) -> Snapshot:
        own = os.times()
        return Snapshot(
            time.monotonic(), _machine(),
            sum(tree_cpu_seconds(p, unniced_only=True) for p in self.workers.values()),
            {w: tree_cpu_seconds(p) for w, p in self.workers.items()},
            process_cpu_seconds(self.router) or 0.0,
            (process_cpu_seconds(self.etcd) or 0.0) if self.etcd else 0.0,
            own.user + own.system)

    @staticmethod
    def worker_cores(a: Snapshot, b: Snapshot) -> dict[str, float]:
        """Cores each worker's process tree used between snapshots ``a`` and ``b``."""
        wall = max(b.wall - a.wall, 1e-9)
        return {w: (b.workers[w] - a.workers[w]) / wall for w in b.workers}

    @staticmethod
    def shares(a: Snapshot, b: Snapshot) -> dict[str, float]:
        """Cores used between snapshots ``a`` and ``b`` by each part (1.0 = one core busy)."""
        wall = max(b.wall - a.wall, 1e-9)
        busy = b.machine[0] - a.machine[0]
        workers = sum(b.workers.values()) - sum(a.workers.values())
        parts = {"tracking": b.tracking - a.tracking,
                 "background": workers - (b.tracking - a.tracking),
                 "router": b.router - a.router, "etcd": b.etcd - a.etcd,
                 "bench": b.bench - a.bench}
        out = {k: v / wall for k, v in parts.items()}
        out["other"] = (busy - sum(parts.values())) / wall
        out["steal"] = (b.machine[1] - a.machine[1]) / wall
        out["idle"] = ((b.machine[2] - a.machine[2]) - busy) / wall
        return out


def speed_probe_ms(repeats: int = 3) -> float:
    """The least of ``repeats`` timings of a fixed piece of single-threaded work (15-24 ms
    on this project's 2-core machine, between a fleet's phases)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((20000, 3))
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(20):
            np.sort(a @ a[:3].T, axis=0)
        sum(i * i for i in range(200_000))
        best = min(best, time.perf_counter() - start)
    return best * 1000.0
