"""Local mapping off the tracking thread: a local BA solved in the worker process gives the
same numbers as in-line, a result computed on a map that a loop correction moved since is
dropped, a dead worker leaves the session with in-line BA, the worker's handle is never
checkpointed, and on real data the asynchronous cloud (local BA and the loop closer's
database queries in the worker) tracks as well as the in-line one."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import signal

import numpy as np
import pytest
from conftest import TUM_RPY, require
from test_local_ba import CAMERA, N_KEYFRAMES, build_scene

from fleetslam.cloud.robot_session import SessionState
from fleetslam.cloud.store import CHECKPOINT, CloudStore, snapshot
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.evaluation.fleet import run_ate
from fleetslam.pipeline.local_ba import solve_local_ba
from fleetslam.pipeline.local_mapper import apply_solution, build_problem
from fleetslam.pipeline.local_mapping_worker import AsyncLocalMapping, LocalMappingPool
from fleetslam.pipeline.session import CloudSession
from fleetslam.system import RobotTracker
from fleetslam.transport.protocol import Hello

NEWEST = N_KEYFRAMES - 1


@pytest.fixture(scope="module")
def pool():
    pool = LocalMappingPool(1)
    yield pool
    pool.close()


def scene_session(seed: int) -> CloudSession:
    session = CloudSession(Config(), CAMERA)
    session.map, _, _ = build_scene(seed)
    return session


def test_a_solve_in_the_worker_equals_the_solve_in_line(pool):
    problem = build_problem(scene_session(1), NEWEST)
    here = solve_local_ba(problem)
    there = pool.submit(problem).result(timeout=60)
    np.testing.assert_array_equal(there.poses, here.poses)
    np.testing.assert_array_equal(there.xyz, here.xyz)
    np.testing.assert_array_equal(there.outlier, here.outlier)


def test_the_worker_result_lands_in_the_map_as_in_line_would(pool):
    inline, worker = scene_session(2), scene_session(2)
    problem = build_problem(inline, NEWEST)
    apply_solution(inline, problem, solve_local_ba(problem))
    mapping = AsyncLocalMapping(pool, worker.config.tracking)
    worker.local_mapping = mapping
    mapping.request(worker, NEWEST)
    assert mapping.in_flight is not None  # submitted, not solved on this thread
    mapping.flush(worker, timeout_s=60)
    assert mapping.counts["applied"] == 1 and mapping.in_flight is None
    np.testing.assert_array_equal(worker.map.keyframe_poses(), inline.map.keyframe_poses())
    np.testing.assert_array_equal(worker.map.xyz, inline.map.xyz)


def test_a_result_for_a_map_moved_since_is_dropped(pool):
    session = scene_session(3)
    before = session.map.keyframe_poses().copy()
    mapping = AsyncLocalMapping(pool, session.config.tracking)
    mapping.request(session, NEWEST)
    session.map.epoch += 1  # a loop correction moved the map meanwhile
    mapping.flush(session, timeout_s=60)
    assert mapping.counts == {**mapping.counts, "stale": 1, "applied": 0}
    np.testing.assert_array_equal(session.map.keyframe_poses(), before)


def test_a_newer_keyframe_replaces_the_one_waiting(pool):
    session = scene_session(4)
    mapping = AsyncLocalMapping(pool, session.config.tracking)
    mapping.request(session, NEWEST - 2)
    mapping.request(session, NEWEST - 1)  # waits for the one in flight ...
    mapping.request(session, NEWEST)  # ... and is replaced by this one
    mapping.flush(session, timeout_s=60)
    assert mapping.counts["submitted"] == 2 and mapping.counts["superseded"] == 1
    assert mapping.counts["applied"] == 2


def test_a_dead_worker_leaves_local_ba_in_line():
    pool = LocalMappingPool(1)
    try:
        session, inline = scene_session(5), scene_session(5)
        mapping = AsyncLocalMapping(pool, session.config.tracking)
        session.local_mapping = mapping
        assert pool.submit(build_problem(session, NEWEST)).result(timeout=60) is not None
        for pid in list(pool._executor._processes):  # the worker dies (OOM killer, a crash)
            os.kill(pid, signal.SIGKILL)
        mapping.request(session, NEWEST)
        mapping.flush(session, timeout_s=60)
        assert mapping.broken and mapping.counts["inline"] == 1
        problem = build_problem(inline, NEWEST)
        apply_solution(inline, problem, solve_local_ba(problem))
        np.testing.assert_array_equal(session.map.keyframe_poses(), inline.map.keyframe_poses())
        assert session.local_mapping_summary()["mode"] == "inline (worker failed)"
    finally:
        pool.close()


def _objects(tree, name: str) -> list[dict]:
    """The saved attributes of every ``name`` object in a checkpoint's JSON tree."""
    found = []
    if isinstance(tree, dict):
        if tree.get("__obj__") == name:
            found.append(tree["attributes"])
        for value in tree.values():
            found += _objects(value, name)
    elif isinstance(tree, list):
        for value in tree:
            found += _objects(value, name)
    return found


def assert_same(a, b, where: str = "map") -> None:
    """Equal bit for bit: the same types, arrays of the same dtype, shape and bytes,
    dataclasses attribute by attribute."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, np.ndarray):
        assert (a.dtype, a.shape) == (b.dtype, b.shape), \
            f"{where}: {a.dtype} {a.shape} != {b.dtype} {b.shape}"
        assert a.tobytes() == b.tobytes(), f"{where}: values differ"
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{where}: {len(a)} != {len(b)} items"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{i}]")
    elif dataclasses.is_dataclass(a):
        assert vars(a).keys() == vars(b).keys(), f"{where}: attributes differ"
        for name in vars(a):
            assert_same(getattr(a, name), getattr(b, name), f"{where}.{name}")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def test_the_worker_handle_is_not_checkpointed(pool, tmp_path):
    """The cloud checkpoints a session as cloud/checkpoint.py data through its store (the
    snapshot the frame thread takes, written by the checkpoint writer): the worker handle is
    not in the file, the restored session has none, and its map is the original's."""
    session = scene_session(6)
    mapping = AsyncLocalMapping(pool, session.config.tracking)
    session.local_mapping = mapping
    state = SessionState("r0", Hello(3, CAMERA, "test"), session)
    store = CloudStore(tmp_path)
    store.write_checkpoint("r0", snapshot(state))
    assert session.local_mapping is mapping  # the live session keeps its worker

    blob = (store.robot_dir("r0") / CHECKPOINT).read_bytes()
    tree = json.loads(bytes(np.load(io.BytesIO(blob))["__tree__"]).decode())
    (saved,) = _objects(tree, "CloudSession")
    assert "map" in saved and saved.get("local_mapping") is None
    assert "LocalMapping" not in json.dumps(tree)

    restored = store.load_checkpoint("r0")
    assert restored.tracking.local_mapping is None
    assert restored.tracking.map.n_landmarks == session.map.n_landmarks > 0
    assert_same(restored.tracking.map, session.map)


def test_asynchronous_local_mapping_tracks_real_frames_as_well_as_in_line(pool):
    """TUM fr1_rpy 0-149: the same frames, once with local BA at each keyframe and once with
    it in the worker. The worker's solutions must land (nearly every keyframe's, none
    in-line) and late landing must not cost accuracy (ATE within +25 % of in-line)."""
    folder = require(TUM_RPY)
    ates = {}
    for mode in ("inline", "async"):
        config = Config()
        sequence = RgbdSequence(folder)
        tracker = RobotTracker("r", str(folder), sequence, config)
        if mode == "async":
            tracker.session.local_mapping = AsyncLocalMapping(pool, config.tracking)
        for i in range(len(sequence)):
            tracker.step(i)
        if mode == "async":
            tracker.session.local_mapping.flush(tracker.session, loops=True)
        run = tracker.finish()
        ates[mode] = run_ate(run)["rmse_m"]
        summary = run.loop_closing["local_mapping"]
        if mode == "async":
            assert summary["applied"] >= 0.8 * len(run.keyframe_indices) - 1, summary
            assert summary["inline"] == 0 and summary["failed"] == 0
            # The loop closer's database queries ran in the worker too, and every answer
            # was verified on the tracking thread.
            queries = summary["loop_queries"]
            searched = len(run.keyframe_indices) - config.loop_closing.min_keyframes
            assert queries["failed"] == 0 and queries["answered"] >= 0.5 * searched, queries
            assert run.loop_closing["loop_queries"] == queries["answered"]
    assert ates["async"] <= 1.25 * ates["inline"], ates
