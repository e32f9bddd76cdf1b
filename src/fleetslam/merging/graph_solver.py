"""Where the merger's pose graphs are solved: in-line (``GraphSolver``) or in a process of
their own (``GraphSolverProcess``, the cloud's).

Why a process: gtsam holds Python's GIL while it optimises (backend/workers.py measured it),
and the fleet's graph grows with every robot and keyframe. In the worker that merged 20
robots (bench/worker_scaling.py) one solve held that worker's interpreter for seconds:
every robot it served waited, and so did the beat its lease process listens for, which let
the lease go ("no sign of life") and failed all its robots over. Here the merger's thread
sends the graph over a pipe and waits for the answer without the GIL, and the process runs
at a lower priority than tracking (``merge.solve_nice``), as the place search does.

A process that ended, or a solve not answered within ``merge.solve_timeout_s``, is said and
that graph is solved in-line; the next solve starts a fresh process, and after
``FAILURES_INLINE`` failures every graph is solved in-line.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from fleetslam.backend.pose_graph import PoseEdge, PoseGraphResult, optimise_pose_graph
from fleetslam.backend.workers import end_process, start_background

log = logging.getLogger("fleetslam.merge")

# Failed processes (ended, or too slow) after which graphs are solved in-line for good.
FAILURES_INLINE = 3
# How often a wait for an answer looks whether the process is still there.
POLL_S = 0.5

# One solve: optimise_pose_graph's arguments.
Request = tuple[dict[int, np.ndarray], list[PoseEdge], "int | list[int]", float, float]


class GraphSolver:
    """Solves in the calling thread (a run in one process, the tests)."""

    def solve(self, poses: dict[int, np.ndarray], edges: list[PoseEdge],
              fixed: int | list[int], sigma_rotation_rad: float,
              sigma_translation_m: float) -> PoseGraphResult:
        return optimise_pose_graph(poses, edges, fixed, sigma_rotation_rad,
                                   sigma_translation_m)

    def close(self) -> None:
        pass


class GraphSolverProcess(GraphSolver):
    """Solves in a process started at the first solve (a worker that never merges never
    starts one). One solve at a time; ``close`` from any thread."""

    def __init__(self, nice: int, timeout_s: float) -> None:
        self.nice = nice
        self.timeout_s = timeout_s
        self.failures = 0
        self._lock = threading.Lock()
        self._conn: Connection | None = None
        self._process: multiprocessing.process.BaseProcess | None = None
        self._closed = False

    @property
    def inline(self) -> bool:
        return self.failures >= FAILURES_INLINE or self._closed

    def solve(self, poses: dict[int, np.ndarray], edges: list[PoseEdge],
              fixed: int | list[int], sigma_rotation_rad: float,
              sigma_translation_m: float) -> PoseGraphResult:
        request: Request = (poses, edges, fixed, sigma_rotation_rad, sigma_translation_m)
        with self._lock:
            answer = None if self.inline else self._ask(request)
        if answer is None:
            return optimise_pose_graph(*request)
        kind, value = answer
        if kind == "error":  # gtsam refused the graph: as it would have in-line
            raise value
        return value

    def _ask(self, request: Request) -> tuple[str, Any] | None:
        """The process's answer, or None (said) when it could not give one."""
        try:
            conn, process = self._started()
        except OSError as exc:
            return self._failed(f"it could not be started ({exc})")
        try:
            conn.send(request)
        except (OSError, ValueError) as exc:
            return self._failed(f"it ended (exit {process.exitcode})" if not process.is_alive()
                                else f"it could not be reached ({exc!r})")
        deadline = time.monotonic() + self.timeout_s
        while True:
            try:
                if conn.poll(min(POLL_S, max(deadline - time.monotonic(), 0.0))):
                    return conn.recv()
            except (EOFError, OSError) as exc:
                return self._failed(f"it ended ({exc!r})")
            if not process.is_alive():
                return self._failed(f"it ended (exit {process.exitcode})")
            if time.monotonic() >= deadline:
                return self._failed(f"no answer within {self.timeout_s:g} s "
                                    f"(merge.solve_timeout_s)")

    def _started(self) -> tuple[Connection, multiprocessing.process.BaseProcess]:
        if self._conn is not None and self._process is not None:
            return self._conn, self._process
        context = multiprocessing.get_context("spawn")
        parent, child = context.Pipe()
        process = context.Process(target=_serve, args=(child, os.getpid()),
                                  name="fleetslam-graph-solver", daemon=True)
        process.start()
        child.close()
        try:  # niced from its start, as the place search (its imports are tracking's too)
            os.setpriority(os.PRIO_PROCESS, process.pid,
                           min(19, os.getpriority(os.PRIO_PROCESS, 0) + self.nice))
        except (AttributeError, OSError):
            pass
        self._conn, self._process = parent, process
        return parent, process

    def _failed(self, reason: str) -> None:
        if self._closed:  # closed under a solve: nothing failed
            return None
        self.failures += 1
        then = "in-line from now on" if self.inline else "in-line this time"
        log.error("the merger's graph solver process: %s; the graph is solved %s", reason,
                  then)
        self._stop()
        return None

    def _stop(self) -> None:
        conn, process, self._conn, self._process = self._conn, self._process, None, None
        if conn is not None:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
        if process is not None:
            end_process(process, 1.0)
        if conn is not None:
            conn.close()

    def close(self) -> None:
        self._closed = True
        # A solve in progress ends with the process (its caller solves in-line).
        self._stop()


def _serve(conn: Connection, parent_pid: int) -> None:
    """The process: one graph per request, until None or the cloud is gone."""
    start_background(parent_pid, 0)  # niced by the cloud as it started (see _started)
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if request is None:
            return
        try:
            answer: tuple[str, Any] = ("ok", optimise_pose_graph(*request))
        except Exception as exc:  # gtsam's refusal goes back to be raised there
            answer = ("error", exc)
        try:
            conn.send(answer)
        except (OSError, ValueError):
            return
