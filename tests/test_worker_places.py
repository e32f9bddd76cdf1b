"""The loop closer's keyframe database kept in its worker: each query sends the keyframes
added since the last one, not the database, and answers as the in-line query does; a
worker that lost its copy is sent the whole database again; a session's end (or a full
worker) frees the copy; a worker killed mid-run leaves the session in-line."""

from __future__ import annotations

import os
import signal
from types import SimpleNamespace

import numpy as np
import pytest

from fleetslam.backend import worker_places
from fleetslam.backend.loop_closing import LoopCloser
from fleetslam.backend.place_recognition import KeyframeDatabase
from fleetslam.backend.workers import LocalMappingPool, SessionWorkers, query_places
from fleetslam.config import Config

N_KEYFRAMES = 60
FEATURES = 300
FIRST_QUERY = 10


@pytest.fixture(scope="module")
def pool():
    pool = LocalMappingPool(2, databases=3)
    yield pool
    pool.close()


def keyframe_descriptors(seed: int) -> list[np.ndarray]:
    """Keyframes that revisit places: each shares half its features with one 20 back."""
    rng = np.random.default_rng(seed)
    kfs: list[np.ndarray] = []
    for k in range(N_KEYFRAMES):
        d = rng.integers(0, 256, (FEATURES, 32), dtype=np.uint8)
        if k >= 20:
            d[: FEATURES // 2] = kfs[k - 20][: FEATURES // 2] ^ rng.integers(
                0, 2, (FEATURES // 2, 32), dtype=np.uint8)
        kfs.append(d)
    return kfs


def closer_for(pool: LocalMappingPool, descriptors: list[np.ndarray]
               ) -> tuple[LoopCloser, list]:
    """A loop closer on a back-end holding only what a query reads (the database and each
    keyframe's descriptors); the candidates it would verify are recorded, not verified."""
    config = Config()
    backend = SimpleNamespace(
        config=config, places=KeyframeDatabase(config.place_recognition),
        map=SimpleNamespace(epoch=0, keyframes=[
            SimpleNamespace(features=SimpleNamespace(descriptors=d)) for d in descriptors]))
    closer = LoopCloser(backend, lambda: None, SessionWorkers(pool))
    answers: list = []
    closer.on_candidates = lambda kf, candidates, s: answers.append((kf, candidates))
    return closer, answers


def run_keyframes(closer: LoopCloser, descriptors: list[np.ndarray], first: int, last: int
                  ) -> list:
    """Keyframes ``first`` to ``last`` as close_loops takes them: the query against the
    database as it is (each answer landing before the next keyframe), then the keyframe
    enters it. Returns the in-line answers to the same queries."""
    inline = []
    for k in range(first, last):
        if k >= FIRST_QUERY:
            allowed = np.ones(k, bool)
            allowed[k - 3:] = False
            closer.request(k, allowed)
            inline.append((k, query_places(closer.backend.places, descriptors[k], allowed)[0]))
            closer.flush(timeout_s=60)
        closer.remember(k, descriptors[k])
    return inline


def test_a_query_in_the_worker_equals_the_query_in_line_and_sends_only_what_is_new(pool):
    descriptors = keyframe_descriptors(0)
    closer, answers = closer_for(pool, descriptors)
    inline = run_keyframes(closer, descriptors, 0, N_KEYFRAMES)
    assert answers == inline
    assert any(c and c[0].entry == k - 20 for k, c in answers)  # the places were found
    counts = closer.summary()
    assert counts["answered"] == N_KEYFRAMES - FIRST_QUERY and counts["taken_back"] == 0
    assert counts["reseeded"] == 0 and counts["bytes_sent"]["full"] == 1
    # The first query sent the database whole; each later one its keyframe's descriptors,
    # the query's and the allowed flags: flat while the database grows sixfold.
    sent = closer.mirror.sent_bytes
    one_keyframe = FEATURES * 32
    assert all(b < 3 * one_keyframe for b in sent[1:]), sent
    assert max(sent[1:]) - min(sent[1:]) < 200, sent
    whole = len(worker_places.pickle.dumps(closer.backend.places))
    assert whole > 20 * one_keyframe > 6 * max(sent[1:])
    # The worker's copy is the database, entry for entry.
    lane, session = closer.workers.lane, closer.workers.session
    held = pool.call(lane, worker_places.held).result(timeout=60)
    assert held[session] == N_KEYFRAMES - 1  # the last keyframe entered after its query


def test_a_worker_without_the_copy_is_sent_the_whole_database(pool):
    descriptors = keyframe_descriptors(1)
    closer, answers = closer_for(pool, descriptors)
    inline = run_keyframes(closer, descriptors, 0, 30)
    # The worker lost the copy (dropped as the least recently used, a restart ...).
    pool.forget(closer.workers.session, closer.workers.lane)
    inline += run_keyframes(closer, descriptors, 30, N_KEYFRAMES)
    assert answers == inline
    assert closer.counts["reseeded"] == 1 and closer.mirror.full_sends == 2
    assert closer.counts["failed"] == 0


def test_a_session_end_frees_its_copy_and_a_worker_keeps_a_bounded_number(pool):
    descriptors = keyframe_descriptors(2)[:FIRST_QUERY + 2]
    closers = [closer_for(pool, descriptors)[0] for _ in range(8)]
    for closer in closers:
        run_keyframes(closer, descriptors, 0, len(descriptors))
    lanes = {c.workers.lane for c in closers}
    assert lanes == {0, 1}  # sessions spread over the processes
    for lane in lanes:  # at most ``databases`` (3) copies a process
        assert len(pool.call(lane, worker_places.held).result(timeout=60)) == 3
    ended = closers[-1]
    ended.release()
    held = pool.call(ended.workers.lane, worker_places.held).result(timeout=60)
    assert ended.workers.session not in held and len(held) == 2
    for closer in closers[:-1]:
        closer.release()
    for lane in lanes:
        assert pool.call(lane, worker_places.held).result(timeout=60) == {}


def test_a_worker_killed_mid_run_leaves_the_session_in_line():
    pool = LocalMappingPool(2)
    try:
        descriptors = keyframe_descriptors(3)
        closer, answers = closer_for(pool, descriptors)
        inline = run_keyframes(closer, descriptors, 0, 20)
        assert answers == inline
        lane = closer.workers.lane
        other = closer_for(pool, descriptors)[0]  # pinned to the other process
        assert other.workers.lane != lane
        os.kill(pool.pids()[lane], signal.SIGKILL)
        run_keyframes(closer, descriptors, 20, 22)
        assert closer.workers.broken and closer.counts["failed"] >= 1
        # In-line from now on: nothing more is kept for the worker ...
        closer.remember(22, descriptors[22])
        assert closer.mirror.log == []
        # ... and the session on the other process goes on there; a new one goes there.
        assert answers == inline
        run_keyframes(other, descriptors, 0, 15)
        assert other.counts["answered"] == 5 and not other.workers.broken
        assert SessionWorkers(pool).lane != lane
    finally:
        pool.close()
