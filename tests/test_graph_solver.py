"""The merger's pose graphs solved in a process of their own (merging/graph_solver.py): the same
answer as in-line, gtsam's refusals raised as in-line, and a process that ended or hangs
costs one solve in-line, said, never the answer."""

from __future__ import annotations

import logging
import os
import signal

import numpy as np
import pytest

from fleetslam.backend.pose_graph import PoseEdge
from fleetslam.cloud.merge.merger_service import SOLVE_SHARE, MergerService
from fleetslam.config import Config
from fleetslam.merging.graph_solver import FAILURES_INLINE, GraphSolver, GraphSolverProcess
from fleetslam.transforms import invert, make_T

from conftest import HANG_S


def _graph(n: int = 40) -> tuple[dict[int, np.ndarray], list[PoseEdge]]:
    """A circle of keyframes whose odometry drifts, one true loop and one false."""
    def at(k: int) -> np.ndarray:
        a = 2 * np.pi * k / n
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        return make_T(R, np.array([np.cos(a), np.sin(a), 0.0]))

    drift = make_T(np.eye(3), np.array([0.004, 0.0, 0.0]))
    poses, edges = {0: at(0)}, []
    for k in range(1, n):
        step = invert(at(k - 1)) @ at(k) @ drift
        edges.append(PoseEdge(k - 1, k, step, "odometry"))
        poses[k] = poses[k - 1] @ step
    edges += [PoseEdge(0, n - 1, invert(at(0)) @ at(n - 1), "loop"),
              PoseEdge(0, n // 2, np.eye(4), "loop")]
    return poses, edges


ARGS = (0, np.deg2rad(0.3), 0.005)


def _same(a, b) -> None:
    assert a.loop_inliers == b.loop_inliers
    for node, T in a.poses.items():
        np.testing.assert_allclose(b.poses[node], T, atol=1e-9)


@pytest.fixture
def solver():
    s = GraphSolverProcess(nice=0, timeout_s=HANG_S)
    yield s
    s.close()


def test_a_process_solves_the_graph_as_in_line(solver):
    poses, edges = _graph()
    inline = GraphSolver().solve(poses, edges, *ARGS)
    assert inline.loop_inliers == [True, False]
    _same(inline, solver.solve(poses, edges, *ARGS))
    pid = solver._process.pid
    assert pid != os.getpid() and solver.failures == 0
    # The process stays for the next graph.
    _same(inline, solver.solve(poses, edges, *ARGS))
    assert solver._process.pid == pid


def test_gtsam_refusing_a_graph_raises_as_in_line(solver):
    edge = [PoseEdge(0, 5, np.eye(4), "odometry")]  # node 5 has no value
    with pytest.raises(RuntimeError, match="does not exist"):
        solver.solve({0: np.eye(4)}, edge, *ARGS)
    assert solver.failures == 0


def test_a_process_that_ended_costs_one_solve_in_line(solver, caplog):
    poses, edges = _graph()
    expected = GraphSolver().solve(poses, edges, *ARGS)
    solver.solve(poses, edges, *ARGS)
    first = solver._process.pid
    os.kill(first, signal.SIGKILL)
    solver._process.join(HANG_S)
    with caplog.at_level(logging.ERROR, "fleetslam.merge"):
        _same(expected, solver.solve(poses, edges, *ARGS))
    assert solver.failures == 1
    assert "it ended" in caplog.text and "in-line this time" in caplog.text
    # The next solve has a fresh process.
    _same(expected, solver.solve(poses, edges, *ARGS))
    assert solver._process.pid != first


def test_a_process_that_hangs_is_given_up_after_its_timeout(caplog):
    poses, edges = _graph()
    expected = GraphSolver().solve(poses, edges, *ARGS)
    solver = GraphSolverProcess(nice=0, timeout_s=1.0)
    try:
        for failure in range(1, FAILURES_INLINE + 1):
            solver.solve(poses, edges, *ARGS)  # started (or started again)
            os.kill(solver._process.pid, signal.SIGSTOP)
            with caplog.at_level(logging.ERROR, "fleetslam.merge"):
                _same(expected, solver.solve(poses, edges, *ARGS))
            assert solver.failures == failure
        assert "no answer within 1 s (merge.solve_timeout_s)" in caplog.text
        # Given up for good: in-line, and no process left.
        assert solver.inline and solver._process is None
        assert "in-line from now on" in caplog.text
        _same(expected, solver.solve(poses, edges, *ARGS))
    finally:
        solver.close()


def test_placements_wait_longer_when_the_graph_takes_longer():
    """The merger re-solves the graph for placements at most SOLVE_SHARE of the time."""
    config = Config().with_values({"merge.search_process": False,
                                   "merge.solve_process": False})
    service = MergerService(config)
    try:
        assert service._every(1.0) == 1.0
        service.merger.graph_seconds.append(2.0)
        assert service._every(1.0) == pytest.approx(2.0 / SOLVE_SHARE)
        service.merger.graph_seconds.append(0.01)
        assert service._every(1.0) == 1.0
    finally:
        service.close()
