"""The back-end's heavy work off the tracking thread, for the cloud: worker processes that
solve local bundle adjustments and answer the loop closer's database queries.

A process, not a thread: gtsam holds Python's GIL while it optimises (measured: a thread
spinning beside ``optimize`` got 0.5 % of its normal rate) and so does faiss's search, so a
thread would stall tracking as much as running in-line does.

``LocalMappingPool`` is the pool a cloud's sessions share; ``SessionWorkers`` is one
session's use of it. If a worker dies, that session's local BA and loop queries run in-line
from then on, and it says so. What is sent, when, and what happens to an answer is the local
mapper's and the loop closer's business (backend/local_mapping.py, backend/loop_closing.py,
each with one latest-only job slot: backend/jobs.py).

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
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable

import numpy as np

from fleetslam.backend.local_ba import LocalBAProblem, solve_local_ba

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

    def __init__(self, workers: int, nice: int = 0) -> None:
        if workers < 1:
            raise ValueError(f"tracking.local_mapping_workers is {workers}: at least 1")
        if not 0 <= nice <= 19:
            raise ValueError(f"tracking.local_mapping_nice is {nice}: 0 to 19")
        # spawn, not fork: the cloud process has Zenoh's and the sessions' threads.
        self._executor = ProcessPoolExecutor(
            max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
            initializer=start_background, initargs=(os.getpid(), nice))
        self._executor.submit(_warm_up)

    def submit(self, problem: LocalBAProblem) -> Future:
        return self._executor.submit(solve_local_ba, problem)

    def submit_query(self, database, descriptors: np.ndarray, allowed: np.ndarray) -> Future:
        return self._executor.submit(query_places, database, descriptors, allowed)

    def close(self) -> None:
        # Waits for the solve in flight (a fraction of a second): a pool left to shut down
        # at interpreter exit writes to closed pipes.
        self._executor.shutdown(wait=True, cancel_futures=True)


class SessionWorkers:
    """One session's use of the shared pool. ``submit`` returns None once the pool failed
    (the caller then does the work in-line): a dead worker must not end a robot's session."""

    def __init__(self, pool: LocalMappingPool) -> None:
        self.pool = pool
        # Set when a worker died: the session's back-end runs in-line from then on.
        self.broken = False

    def submit(self, send: Callable[..., Future], *args: Any) -> Future | None:
        if self.broken:
            return None
        try:
            return send(*args)
        except (BrokenProcessPool, RuntimeError) as exc:
            self.fail(exc)
            return None

    def submit_local_ba(self, problem: LocalBAProblem) -> Future | None:
        return self.submit(self.pool.submit, problem)

    def submit_query(self, database, descriptors: np.ndarray, allowed: np.ndarray
                     ) -> Future | None:
        return self.submit(self.pool.submit_query, database, descriptors, allowed)

    def fail(self, exc: BaseException) -> None:
        if not self.broken:
            log.error("the local mapping worker failed (%s): local BA runs in-line from now "
                      "on", exc)
        self.broken = True
