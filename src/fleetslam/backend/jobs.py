"""A latest-only job slot: at most one job in flight, the newest request waiting behind it.

When the cloud falls behind, the back-end does less rather than queueing, as ORB-SLAM's
local mapper aborts its bundle adjustment for new keyframes: a request that arrives while
one waits replaces it (counted "superseded"). A job that does not come back within its
deadline is dropped; one that comes back after the map moved under it (its epoch is not the
map's) is the caller's to drop as stale. When the caller needs the answer now (a flush) and
the worker is late, the caller does the job itself (``take_back``): the workers run below
tracking's priority, so on a busy machine the thread that waits is the one starving them.
Used twice by the back-end (backend/workers.py): local bundle adjustment and the loop
closer's database query.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future
from concurrent.futures import wait as wait_for_futures
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class Job:
    future: Future
    request: Any  # what the caller asked for (a keyframe id, a query, ...)
    payload: Any  # what was sent (kept for a fallback or for applying the answer)
    epoch: int  # the map's epoch when the job left
    submitted: float  # time.monotonic()


class LatestOnly:
    """One job slot (see the module's docstring). ``counts`` holds "submitted" and
    "superseded" kept here, and ``overdue``: the name a job dropped at its deadline is
    counted under; callers add their own outcomes."""

    def __init__(self, what: str, timeout_s: float, counts: dict[str, int],
                 overdue: str = "abandoned", wait_s: float = 0.0) -> None:
        self.what = what
        self.timeout_s = timeout_s
        self.counts = counts
        self.overdue = overdue
        self.wait_s = wait_s  # how long ``settle`` waits for a worker by default
        self.in_flight: Job | None = None
        self.waiting: Any = None
        # Set while ``settle`` is past its wait: what the caller submits is done here.
        self._late = False
        # Seconds from submission to the answer put to use (the caller says when).
        self.lag_seconds: list[float] = []

    @property
    def idle(self) -> bool:
        return self.in_flight is None

    def pending(self, request: Any) -> bool:
        """Whether ``request`` is in flight or waiting (its answer has not landed)."""
        job = self.in_flight
        return self.waiting == request or (job is not None and job.request == request)

    def wait(self, request: Any) -> None:
        """Keep ``request`` until the job in flight is done (replacing an older one)."""
        if self.waiting is not None:
            self.counts["superseded"] += 1
        self.waiting = request

    def take_waiting(self) -> Any:
        request, self.waiting = self.waiting, None
        return request

    def started(self, future: Future, request: Any, payload: Any, epoch: int) -> None:
        self.counts["submitted"] += 1
        self.in_flight = Job(future, request, payload, epoch, time.monotonic())

    def wait_done(self, wait_s: float) -> bool:
        """Wait at most ``wait_s`` for the job in flight; whether it is done."""
        job = self.in_flight
        if job is None:
            return True
        if not job.future.done():
            wait_for_futures([job.future], timeout=wait_s)
        return job.future.done()

    def finished(self, wait_s: float = 0.0) -> Job | None:
        """The job in flight, taken out of the slot, when it is done (waiting at most
        ``wait_s``); None while it runs. A job past its deadline is dropped and counted."""
        job = self.in_flight
        if job is None:
            return None
        if self.wait_done(wait_s):
            self.in_flight = None
            return job
        if time.monotonic() - job.submitted > self.timeout_s:
            log.warning("%s of keyframe %s not back after %.0f s: dropped", self.what,
                        job.request, self.timeout_s)
            self.counts[self.overdue] += 1
            self.in_flight = None
        return None

    def take_back(self, work: Callable[[Any], Any]) -> None:
        """Do the job in flight here, ``work(payload)``, instead of waiting for its worker
        (counted "taken_back"); it then lands as if the worker had answered."""
        job = self.in_flight
        if job is None or job.future.done():
            return
        job.future = done_future(work, job.payload)
        self.counts["taken_back"] += 1

    def here_if_late(self, work: Callable[[Any], Any], payload: Any) -> Future | None:
        """While ``settle`` is past its wait: ``work(payload)`` done here, as a done future
        (counted "taken_back"); otherwise None, and the caller submits to its worker."""
        if not self._late:
            return None
        self.counts["taken_back"] += 1
        return done_future(work, payload)

    def settle(self, work: Callable[[Any], Any], poll: Callable[[], None],
               wait_s: float | None = None) -> None:
        """Until the slot is idle: ``poll`` (the caller's: land a done job, submit the waiting
        request). A job not done within ``wait_s`` (default: the slot's) is taken back (done
        here with ``work``), and so is what the caller submits from then on
        (``here_if_late``)."""
        deadline = time.monotonic() + (self.wait_s if wait_s is None else wait_s)
        try:
            while not self.idle:
                if not self.wait_done(max(deadline - time.monotonic(), 0.0)):
                    self._late = True
                    self.take_back(work)
                poll()
        finally:
            self._late = False

    def landed(self, job: Job) -> None:
        self.lag_seconds.append(time.monotonic() - job.submitted)


def done_future(work: Callable[[Any], Any], payload: Any) -> Future:
    """A future holding ``work(payload)``, done here and now (its exception, if it raised)."""
    future: Future = Future()
    try:
        future.set_result(work(payload))
    except Exception as exc:  # delivered where a worker's would be
        future.set_exception(exc)
    return future


def duration_stats(seconds: list[float]) -> dict:
    """Count, median and p95 (ms) of durations in seconds, for summary.json."""
    ms = 1000.0 * np.asarray(seconds)
    return {"n": len(ms), "median_ms": float(np.median(ms)) if len(ms) else None,
            "p95_ms": float(np.percentile(ms, 95)) if len(ms) else None}
