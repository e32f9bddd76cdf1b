"""Local mapping off the tracking thread (ORB-SLAM's LocalMapping thread), for the cloud.

At a keyframe the tracker still inserts the keyframe in-line (fuse, new landmarks, cull:
a few ms), but the local bundle adjustment, 100-200 ms, would hold up every frame queued
behind it. Here it runs elsewhere: the problem is copied out of the map
(``local_ba_problem``), solved in a worker process, and the solution is written back at
the start of a later frame (``poll``), on the tracking thread, so the map is only ever
changed by one thread and between frames.

A process, not a thread: gtsam holds Python's GIL while it optimises (measured: a thread
spinning beside ``optimize`` got 0.5 % of its normal rate), so a thread would stall
tracking as much as running in-line does.

At most one solve per session is in flight. A keyframe that arrives meanwhile waits, and a
newer one replaces it (its window overlaps the older one's): when the cloud falls behind,
local mapping does less rather than queueing, as ORB-SLAM aborts its BA for new keyframes.
A solution computed on a map that a loop correction has moved since (``LocalMap.epoch``) is
dropped. If the worker dies, the session goes on with local BA in-line and says so.

The poses then depend on when each solution lands, so a run is not repeatable bit for bit;
``tracking.local_mapping = "inline"`` is the deterministic mode (the exactness tests, the
one-process ``fleetslam run``, a robot tracking at point 6).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from fleetslam.config import TrackingConfig
from fleetslam.pipeline.local_ba import LocalBAProblem, LocalBASolution, solve_local_ba
from fleetslam.pipeline.place_recognition import snapshot

if TYPE_CHECKING:
    from fleetslam.pipeline.session import CloudSession

log = logging.getLogger(__name__)
# How often a worker checks that the cloud process that started it is still there.
PARENT_POLL_S = 1.0


def _exit_with_parent(parent_pid: int) -> None:
    """In each worker: exit when the cloud process is gone (a SIGKILLed cloud cannot shut its
    pool down, and its workers would wait for work forever)."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_POLL_S)
        os._exit(0)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def query_places(database, descriptors: np.ndarray, allowed: np.ndarray
                 ) -> tuple[list, float]:
    """In a worker: a keyframe database query (candidates, seconds)."""
    start = time.perf_counter()
    return database.query(descriptors, allowed), time.perf_counter() - start


def _warm_up() -> bool:
    # Importing gtsam takes about a second: pay it when the cloud starts, not at the first
    # keyframe.
    import gtsam  # noqa: F401
    return True


class LocalMappingPool:
    """The worker processes that solve local BA problems, shared by a cloud's sessions."""

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise ValueError(f"tracking.local_mapping_workers is {workers}: at least 1")
        # spawn, not fork: the cloud process has Zenoh's and the sessions' threads.
        self._executor = ProcessPoolExecutor(
            max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
            initializer=_exit_with_parent, initargs=(os.getpid(),))
        self._executor.submit(_warm_up)

    def submit(self, problem: LocalBAProblem) -> Future:
        return self._executor.submit(solve_local_ba, problem)

    def submit_query(self, database, descriptors: np.ndarray, allowed: np.ndarray) -> Future:
        return self._executor.submit(query_places, database, descriptors, allowed)

    def close(self) -> None:
        # Waits for the solve in flight (a fraction of a second): a pool left to shut down
        # at interpreter exit writes to closed pipes.
        self._executor.shutdown(wait=True, cancel_futures=True)


@dataclass
class _InFlight:
    future: Future
    problem: LocalBAProblem
    submitted: float


@dataclass
class _LoopQuery:
    future: Future
    kf_id: int
    epoch: int
    submitted: float


@dataclass
class AsyncLocalMapping:
    """One session's local BA requests to the pool (see the module's docstring)."""

    pool: LocalMappingPool
    config: TrackingConfig
    in_flight: _InFlight | None = None
    waiting: int | None = None  # keyframe id whose BA waits for the one in flight
    # Set when the worker died: local BA runs in-line from then on.
    broken: bool = False
    counts: dict[str, int] = field(default_factory=lambda: {
        "submitted": 0, "applied": 0, "superseded": 0, "stale": 0, "abandoned": 0,
        "failed": 0, "inline": 0})
    # Seconds from request to the solution written into the map.
    lag_seconds: list[float] = field(default_factory=list)
    # The loop closer's database query in flight (one at a time) and the newest keyframe
    # whose query waits for it (with the database as it was then).
    loop_query: _LoopQuery | None = None
    loop_waiting: tuple[int, object, np.ndarray] | None = None
    loop_counts: dict[str, int] = field(default_factory=lambda: {
        "submitted": 0, "answered": 0, "superseded": 0, "stale": 0, "failed": 0})
    loop_lag_seconds: list[float] = field(default_factory=list)

    def request_loop_query(self, session: "CloudSession", kf_id: int,
                           allowed: np.ndarray) -> None:
        """Place recognition for keyframe ``kf_id`` in the worker, against the database as
        it is now; the answer is verified at the frame it lands (``poll``)."""
        # The live database grows while the query waits.
        frozen = snapshot(session.places)
        if self.loop_query is None:
            self._submit_query(session, kf_id, frozen, allowed)
        else:
            if self.loop_waiting is not None:
                self.loop_counts["superseded"] += 1
            self.loop_waiting = (kf_id, frozen, allowed)

    def request(self, session: "CloudSession", kf_id: int) -> None:
        """Local BA around keyframe ``kf_id``: submitted now, or after the one in flight."""
        self.poll(session)
        if self.in_flight is None:
            self._submit(session, kf_id)
        else:
            if self.waiting is not None:
                self.counts["superseded"] += 1
            self.waiting = kf_id

    def poll(self, session: "CloudSession") -> None:
        """Apply a finished solution and verify a finished loop query (never waits); then
        submit what waits."""
        self._poll_loop(session)
        job = self.in_flight
        if job is None:
            return
        if not job.future.done():
            if time.monotonic() - job.submitted > self.config.local_ba_timeout_s:
                log.warning("local BA of keyframe %d not back after %.0f s: dropped",
                            job.problem.kf_id, self.config.local_ba_timeout_s)
                self.counts["abandoned"] += 1
                self.in_flight = None
            return
        self.in_flight = None
        self._finish(session, job)
        if self.waiting is not None:
            kf_id, self.waiting = self.waiting, None
            self._submit(session, kf_id)

    def _poll_loop(self, session: "CloudSession", wait_s: float = 0.0) -> None:
        from fleetslam.pipeline.loop_closer import on_candidates

        job = self.loop_query
        if job is None:
            return
        try:
            candidates, query_s = job.future.result(timeout=wait_s)
        except TimeoutError:
            if time.monotonic() - job.submitted > self.config.local_ba_timeout_s:
                log.warning("loop query of keyframe %d not back after %.0f s: dropped",
                            job.kf_id, self.config.local_ba_timeout_s)
                self.loop_counts["failed"] += 1
                self.loop_query = None
            return
        except BrokenProcessPool as exc:
            self._break(exc)
            candidates, query_s = None, 0.0
        except Exception as exc:  # a bug in the query must not end the robot's session
            log.error("loop query of keyframe %d failed: %r", job.kf_id, exc)
            candidates, query_s = None, 0.0
        self.loop_query = None
        if candidates is None:
            self.loop_counts["failed"] += 1
        elif job.epoch != session.map.epoch:
            # A loop was corrected meanwhile: the candidates' place may be merged already.
            self.loop_counts["stale"] += 1
        else:
            self.loop_counts["answered"] += 1
            self.loop_lag_seconds.append(time.monotonic() - job.submitted)
            correction = on_candidates(session, job.kf_id, candidates, query_s)
            if correction is not None:
                session.correct_motion(correction)
        if self.loop_waiting is not None and not self.broken:
            kf_id, frozen, allowed = self.loop_waiting
            self.loop_waiting = None
            self._submit_query(session, kf_id, frozen, allowed)

    def _submit_query(self, session: "CloudSession", kf_id: int, frozen,
                      allowed: np.ndarray) -> None:
        try:
            future = self.pool.submit_query(
                frozen, session.map.keyframes[kf_id].features.descriptors, allowed)
        except (BrokenProcessPool, RuntimeError) as exc:
            self._break(exc)
            self.loop_counts["failed"] += 1
            return
        self.loop_counts["submitted"] += 1
        self.loop_query = _LoopQuery(future, kf_id, session.map.epoch, time.monotonic())

    def flush(self, session: "CloudSession", timeout_s: float | None = None,
              loops: bool = False) -> None:
        """Wait (at most ``timeout_s``, default the config's) for the solve in flight and the
        waiting one, and apply them: before a loop correction and at the end of a run; at
        the end (``loops``) also for the loop queries."""
        deadline = time.monotonic() + (self.config.local_ba_timeout_s if timeout_s is None
                                       else timeout_s)
        while loops and self.loop_query is not None:
            self._poll_loop(session, wait_s=max(deadline - time.monotonic(), 0.0))
            if time.monotonic() >= deadline and self.loop_query is not None:
                log.warning("loop query of keyframe %d not back in time: dropped",
                            self.loop_query.kf_id)
                self.loop_counts["failed"] += 1
                self.loop_query, self.loop_waiting = None, None
        while self.in_flight is not None:
            job = self.in_flight
            try:
                job.future.exception(timeout=max(deadline - time.monotonic(), 0.0))
            except TimeoutError:
                log.warning("local BA of keyframe %d not back in time: dropped",
                            job.problem.kf_id)
                self.counts["abandoned"] += 1
                self.in_flight, self.waiting = None, None
                return
            self.poll(session)

    def _submit(self, session: "CloudSession", kf_id: int) -> None:
        from fleetslam.pipeline.local_mapper import build_problem

        problem = build_problem(session, kf_id)
        if problem is None:
            return
        if not self.broken:
            try:
                future = self.pool.submit(problem)
            except (BrokenProcessPool, RuntimeError) as exc:
                self._break(exc)
            else:
                self.counts["submitted"] += 1
                self.in_flight = _InFlight(future, problem, time.monotonic())
                return
        self.counts["inline"] += 1
        self._land(session, problem, solve_local_ba(problem))

    def _finish(self, session: "CloudSession", job: _InFlight) -> None:
        try:
            solution: LocalBASolution | None = job.future.result()
        except BrokenProcessPool as exc:
            self._break(exc)
            self.counts["inline"] += 1
            solution = solve_local_ba(job.problem)
        except Exception as exc:  # a bug in the solve must not end the robot's session
            log.error("local BA of keyframe %d failed: %r", job.problem.kf_id, exc)
            self.counts["failed"] += 1
            return
        if job.problem.epoch != session.map.epoch:
            self.counts["stale"] += 1
            return
        self._land(session, job.problem, solution)
        self.counts["applied"] += 1
        self.lag_seconds.append(time.monotonic() - job.submitted)

    @staticmethod
    def _land(session: "CloudSession", problem: LocalBAProblem,
              solution: LocalBASolution | None) -> None:
        """Write a solution into the map. The frames tracked since moved with the map: so
        does the motion model; and the keyframe test's reference is counted again."""
        from fleetslam.pipeline.local_mapper import apply_solution, update_reference

        session.correct_motion(apply_solution(session, problem, solution))
        update_reference(session)

    def _break(self, exc: BaseException) -> None:
        if not self.broken:
            log.error("the local mapping worker failed (%s): local BA runs in-line from now "
                      "on", exc)
        self.broken = True
