"""The back-end's heavy work off the tracking thread, for the cloud: worker processes that
solve local bundle adjustments and answer the loop closer's database queries.

A process, not a thread: gtsam holds Python's GIL while it optimises (measured: a thread
spinning beside ``optimize`` got 0.5 % of its normal rate) and so does faiss's search, so a
thread would stall tracking as much as running in-line does.

``LocalMappingPool`` is the pool a cloud's sessions share; ``SessionWorkers`` is one
session's use of it, pinned to one of its processes: that process keeps the session's
keyframe database, so each loop query sends only the keyframes added since the last one
(backend/worker_places.py; the whole database when the process's copy is missing), and
forgets it at the session's end. If a worker dies, the sessions pinned to it run local BA
and loop queries in-line from then on, and say so. What is sent, when, and what happens to
an answer is the local mapper's and the loop closer's business (backend/local_mapping.py,
backend/loop_closing.py, each with one latest-only job slot: backend/jobs.py).

The poses then depend on when each answer lands, so a run is not repeatable bit for bit;
``tracking.local_mapping = "inline"`` is the deterministic mode (the exactness tests, the
one-process ``fleetslam run``, a robot tracking at point 6).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import time
import uuid
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable

import numpy as np

from fleetslam.backend import worker_places
from fleetslam.backend.local_ba import LocalBAProblem, solve_local_ba
from fleetslam.config import LoopClosingConfig

log = logging.getLogger(__name__)
# How often a worker checks that the cloud process that started it is still there.
PARENT_POLL_S = 1.0


def start_background(parent_pid: int, nice: int) -> None:
    """In each of the cloud's background processes (these workers, the merger's place
    search): Ctrl-C is the cloud's to handle (a terminal sends SIGINT to the whole
    process group; a worker interrupted on its queue printed a traceback while the cloud
    shut its pool down cleanly), a lower priority than tracking (``nice``), and exit with
    the cloud."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if nice > 0 and hasattr(os, "nice"):
        os.nice(nice)
    _exit_with_parent(parent_pid)


def end_process(process: Any, grace_s: float) -> bool:
    """Wait up to ``grace_s`` for a background process told to end; kill it past that.
    Whether it ended on its own."""
    process.join(grace_s)
    if not process.is_alive():
        return True
    process.kill()
    process.join(2.0)
    return False


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
    """A keyframe database query (candidates, seconds): in-line, where the worker's answer
    is taken back."""
    start = time.perf_counter()
    return database.query(descriptors, allowed), time.perf_counter() - start


def start_worker(parent_pid: int, nice: int, databases: int) -> None:
    """A local-mapping worker's initialiser: a background process that keeps at most
    ``databases`` sessions' keyframe databases (backend/worker_places.py)."""
    start_background(parent_pid, nice)
    worker_places.keep_databases(databases)


def _warm_up() -> bool:
    # Importing gtsam takes about a second: pay it when the cloud starts, not at the first
    # keyframe.
    import gtsam  # noqa: F401
    return True


class LocalMappingPool:
    """The worker processes that solve local BA problems and answer loop queries, shared by
    a cloud's sessions. Each process is a lane of its own (a one-process executor) and each
    session is pinned to one lane (``assign``): the lane keeps the session's keyframe
    database between queries, which a pool that hands each task to any process could not
    count on. A session's local BA goes to its lane too, so a session's jobs run in order."""

    def __init__(self, workers: int, nice: int = 0,
                 databases: int = LoopClosingConfig.worker_databases) -> None:
        if workers < 1:
            raise ValueError(f"tracking.local_mapping_workers is {workers}: at least 1")
        if not 0 <= nice <= 19:
            raise ValueError(f"tracking.local_mapping_nice is {nice}: 0 to 19")
        # spawn, not fork: the cloud process has Zenoh's and the sessions' threads.
        context = multiprocessing.get_context("spawn")
        self._lanes = [ProcessPoolExecutor(max_workers=1, mp_context=context,
                                           initializer=start_worker,
                                           initargs=(os.getpid(), nice, databases))
                       for _ in range(workers)]
        self._lock = threading.Lock()
        self._sessions = [0] * workers  # sessions pinned to each lane
        self._broken = [False] * workers
        for lane in self._lanes:
            lane.submit(_warm_up)

    def assign(self) -> int:
        """A lane for a new session: a live one with the fewest sessions."""
        with self._lock:
            lane = min(range(len(self._lanes)),
                       key=lambda i: (self._broken[i], self._sessions[i], i))
            self._sessions[lane] += 1
            return lane

    def release(self, lane: int) -> None:
        with self._lock:
            self._sessions[lane] -= 1

    def broke(self, lane: int) -> None:
        """A lane's process died: new sessions go to the others."""
        with self._lock:
            self._broken[lane] = True

    def submit(self, problem: LocalBAProblem, lane: int = 0) -> Future:
        return self._lanes[lane].submit(solve_local_ba, problem)

    def submit_query(self, request: bytes, lane: int) -> Future:
        return self._lanes[lane].submit(worker_places.answer, request)

    def forget(self, session: str, lane: int) -> None:
        """Drop a session's keyframe database from its lane (its session ended)."""
        try:
            self._lanes[lane].submit(worker_places.forget, session)
        except (BrokenProcessPool, RuntimeError):
            pass  # a dead or closed lane holds nothing

    def call(self, lane: int, work: Callable[..., Any], *args: Any) -> Future:
        """``work(*args)`` in a lane's process (tests look inside it)."""
        return self._lanes[lane].submit(work, *args)

    def pids(self) -> list[int]:
        """The worker processes' ids (tests stop and kill them)."""
        return [pid for lane in self._lanes for pid in lane._processes]

    def close(self) -> None:
        # Waits for the solve in flight (a fraction of a second): a pool left to shut down
        # at interpreter exit writes to closed pipes.
        for lane in self._lanes:
            lane.shutdown(wait=True, cancel_futures=True)


class SessionWorkers:
    """One session's use of the shared pool, on the lane it is pinned to. ``submit`` returns
    None once the lane failed (the caller then does the work in-line): a dead worker must
    not end a robot's session. ``close`` at the session's end frees the lane's copy of its
    keyframe database."""

    def __init__(self, pool: LocalMappingPool) -> None:
        self.pool = pool
        self.lane = pool.assign()
        # Names the session's keyframe database in its worker.
        self.session = uuid.uuid4().hex
        # Set when a worker died: the session's back-end runs in-line from then on.
        self.broken = False
        self.closed = False

    def submit(self, send: Callable[..., Future], *args: Any) -> Future | None:
        if self.broken:
            return None
        try:
            return send(*args)
        except (BrokenProcessPool, RuntimeError) as exc:
            self.fail(exc)
            return None

    def submit_local_ba(self, problem: LocalBAProblem) -> Future | None:
        return self.submit(self.pool.submit, problem, self.lane)

    def submit_query(self, request: bytes) -> Future | None:
        return self.submit(self.pool.submit_query, request, self.lane)

    def fail(self, exc: BaseException) -> None:
        if not self.broken:
            log.error("the local mapping worker failed (%s): local BA runs in-line from now "
                      "on", exc)
            if isinstance(exc, BrokenProcessPool):
                self.pool.broke(self.lane)
        self.broken = True

    def close(self) -> None:
        """The session ended: its lane forgets it (once)."""
        if self.closed:
            return
        self.closed = True
        if not self.broken:
            self.pool.forget(self.session, self.lane)
        self.pool.release(self.lane)
