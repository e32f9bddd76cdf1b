"""The merger's place search in its own process gives the matches the in-line search gives,
on real keyframes of two robots; a process that dies or misses its deadline hands over to
the in-line search with nothing lost; a stopped search process holds up neither the
merger's status nor its keyframes."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from conftest import HANG_S, SEVEN_SCENES, require
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.cloud.merge.merger_service import MergerService
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.merging import place_search
from fleetslam.merging.place_search import PlaceSearch, PlaceSearchProcess, Searched
from fleetslam.pipeline.split import run_stages
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.wire.merger_keyframes import KeyframeSummary


@pytest.fixture(scope="module")
def keyframes():
    """Robot a: redkitchen frames 0, 12, ... 84; robot b: 6, 18, ... 90 (same place, other
    views). Poses are not searched, so identity."""
    seq = RgbdSequence(require(SEVEN_SCENES), first=0, last=90)
    pipeline = RobotSlam.new(Config(), seq.camera)
    stages = pipeline.split(3)[0]
    out: dict[str, list[KeyframeSummary]] = {"a": [], "b": []}
    for f in seq:
        if f.index % 6:
            continue
        robot = "a" if f.index % 12 == 0 else "b"
        features = run_stages(stages, CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m),
                              pipeline.sides)
        out[robot].append(KeyframeSummary(robot, len(out[robot]), f.index, f.timestamp,
                                          features, np.eye(4)))
    return seq.camera, out


def _results(search, n: int, timeout: float = 60.0) -> list[Searched]:
    """The next ``n`` searches' results (the process answers in its own time)."""
    out: list[Searched] = []
    deadline = time.monotonic() + timeout
    while len(out) < n:
        assert time.monotonic() < deadline, f"{len(out)} of {n} searches answered"
        search.idle()  # in-line: a put-off search now (the process does them itself)
        out += search.take_results()
        time.sleep(0.01)
    return out


def _found(results: list[Searched], kfs) -> list[tuple]:
    found = []
    for s in results:
        assert s.searched
        for m in s.matches:
            assert m.query is kfs[m.query.robot][m.query.keyframe]
            assert m.place is kfs[m.place.robot][m.place.keyframe]
            # Its own search's, or the catch-up's: another robot's keyframe searched again
            # in the map it joined.
            assert m.query is s.summary or m.place.robot == s.summary.robot
            found.append((m.query.robot, m.query.keyframe, m.place.robot, m.place.keyframe,
                          m.score, m.ransac_inliers, m.inliers,
                          m.T_place_query.round(9).tobytes()))
    return found


def _run(search, camera, keyframes) -> list[tuple]:
    """a's keyframes indexed, then each of b's searched in a, and a's searched again in b
    as b's map doubles (the catch-up); the matches found."""
    for name in keyframes:
        search.add_robot(name, camera)
    for kf in keyframes["a"]:
        search.submit(kf, ["b"], time.monotonic(), ["b"])
    assert all(not s.matches for s in _results(search, len(keyframes["a"])))
    for kf in keyframes["b"]:
        search.submit(kf, ["a"], time.monotonic(), ["a"])
    return _found(_results(search, len(keyframes["b"])), keyframes)


def test_the_search_process_finds_what_the_inline_search_finds(keyframes):
    camera, kfs = keyframes
    inline = _run(PlaceSearch(Config()), camera, kfs)
    assert len(inline) >= len(kfs["b"]) // 2  # neighbouring views of one kitchen
    assert {q for q, *_ in inline} == {"a", "b"}  # b's searches and a's catch-up found some
    search = PlaceSearchProcess(Config(), nice=5, timeout_s=60.0)
    try:
        assert _run(search, camera, kfs) == inline
        assert not search.inline and search.pending == 0
        own = os.getpriority(os.PRIO_PROCESS, 0)
        assert os.getpriority(os.PRIO_PROCESS, search._process.pid) - own == 5
    finally:
        search.close()


def _answering(camera, kfs) -> PlaceSearchProcess:
    """A search process that has answered robot a's first three keyframes."""
    search = PlaceSearchProcess(Config(), nice=0, timeout_s=60.0)
    for name in kfs:
        search.add_robot(name, camera)
    for kf in kfs["a"][:3]:
        search.submit(kf, ["b"], time.monotonic(), ["b"])
    _results(search, 3)
    return search


@pytest.mark.parametrize("failure", ["killed", "deadline"])
def test_a_failed_search_process_hands_over_to_the_inline_search(keyframes, failure, caplog):
    camera, kfs = keyframes
    inline = _run(PlaceSearch(Config()), camera, kfs)
    search = _answering(camera, kfs)
    try:
        assert not search.inline
        if failure == "killed":
            search._process.kill()
            search._process.join(5)
        else:
            os.kill(search._process.pid, signal.SIGSTOP)  # alive, and answers nothing
            search.timeout_s = 0.5
        # Asked of the process, and searched in-line once it is found to have failed.
        for kf in kfs["a"][3:]:
            search.submit(kf, ["b"], time.monotonic(), ["b"])
        for kf in kfs["b"]:
            search.submit(kf, ["a"], time.monotonic(), ["a"])
        results = _results(search, len(kfs["a"]) - 3 + len(kfs["b"]))
        assert search.inline and search.pending == 0
        assert _found(results[len(kfs["a"]) - 3:], kfs) == inline
        assert "searching in-line from now on" in caplog.text
    finally:
        search.close()


def test_a_search_process_that_answers_is_not_given_up_for_its_backlog(keyframes, caplog):
    """Silence, not the age of the oldest request, fails the process: a niced search behind
    20 robots answers all along while its backlog's oldest waits minutes."""
    camera, kfs = keyframes
    search = _answering(camera, kfs)
    try:
        os.kill(search._process.pid, signal.SIGSTOP)  # this request stays unanswered
        search.submit(kfs["b"][0], ["a"], time.monotonic(), ["a"])
        next(iter(search._requests.values())).sent -= 120.0  # asked two minutes ago ...
        search._answered_at = time.monotonic()  # ... and the process answered just now
        assert search.take_results() == [] and not search.inline
        search._answered_at -= 120.0  # silent for two minutes
        search.take_results()
        assert search.inline
        assert "no answer for 120 s (merge.search_timeout_s 60 s)" in caplog.text
    finally:
        search.close()


def test_a_silent_search_process_that_works_is_starved_not_hung(keyframes, caplog,
                                                                 monkeypatch):
    """A niced search behind robots that fill the cores answers nothing for a while but
    uses the CPU meanwhile: it is waited for, and given up only once it stops working, or
    stays silent for BUSY_SILENCE_TIMEOUTS timeouts."""
    camera, kfs = keyframes
    search = _answering(camera, kfs)
    cpu = [search._cpu_mark]  # the process's CPU seconds as /proc would say (here: set)
    monkeypatch.setattr(place_search, "process_cpu_seconds", lambda pid: cpu[0])
    try:
        os.kill(search._process.pid, signal.SIGSTOP)  # silent from here on
        search.submit(kfs["b"][0], ["a"], time.monotonic(), ["a"])
        search._answered_at -= 120.0
        next(iter(search._requests.values())).sent -= 120.0
        cpu[0] += 3.0  # working meanwhile
        assert search.take_results() == [] and not search.inline
        assert "starved, waiting for it" in caplog.text
        search._excused_at -= 61.0  # another timeout, no more CPU: hung after all
        search.take_results()
        assert search.inline and "searching in-line from now on" in caplog.text
    finally:
        search.close()


def test_a_search_process_silent_for_too_long_is_given_up_however_busy(keyframes,
                                                                        monkeypatch):
    camera, kfs = keyframes
    search = _answering(camera, kfs)
    cpu = [search._cpu_mark]
    monkeypatch.setattr(place_search, "process_cpu_seconds", lambda pid: cpu[0])
    try:
        os.kill(search._process.pid, signal.SIGSTOP)
        search.submit(kfs["b"][0], ["a"], time.monotonic(), ["a"])
        silent = (place_search.BUSY_SILENCE_TIMEOUTS + 1) * search.timeout_s
        search._answered_at -= silent
        next(iter(search._requests.values())).sent -= silent
        cpu[0] += 30.0
        search.take_results()
        assert search.inline
    finally:
        search.close()


@pytest.mark.parametrize("where", ["inline", "process"])
def test_a_search_asked_too_long_ago_is_put_off(keyframes, where):
    """A starved search catches up: a keyframe that waited beyond merge.search_behind_s is
    indexed at once (and found by those after it), and searched once nothing newer waits."""
    camera, kfs = keyframes
    search = PlaceSearch(Config()) if where == "inline" else \
        PlaceSearchProcess(Config(), nice=0, timeout_s=60.0)
    try:
        for name in kfs:
            search.add_robot(name, camera)
        behind = Config().merge.search_behind_s
        search.submit(kfs["a"][0], [], time.monotonic() - 2 * behind)
        search.submit(kfs["b"][0], ["a"], time.monotonic() - 2 * behind)
        search.submit(kfs["b"][1], ["a"], time.monotonic())
        results = _results(search, 4)
        assert search.pending == 0
        first, late = [s for s in results if not s.late], [s for s in results if s.late]
        assert [s.searched for s in first] == [False, False, True]
        assert not first[1].matches and first[1].seconds is None
        assert [m.place for m in first[2].matches] == [kfs["a"][0]]  # b0 was not yet
        # b0's own search, put off: in a's map as it is now.
        assert [s.summary for s in late] == [kfs["b"][0]]
        assert [m.place for m in late[0].matches] == [kfs["a"][0]]
    finally:
        search.close()


def test_a_closed_search_answers_nothing_and_says_nothing(keyframes, caplog):
    """The cloud stopping while the merger's thread still searches: no fallback, no error."""
    camera, kfs = keyframes
    search = PlaceSearchProcess(Config(), nice=0, timeout_s=60.0)
    for name in kfs:
        search.add_robot(name, camera)
    search.submit(kfs["a"][0], [], time.monotonic())
    search.close()
    search.submit(kfs["b"][0], ["a"], time.monotonic())
    assert search.take_results() == [] and search.pending <= 1
    assert not search.inline and "in-line" not in caplog.text


def test_a_stopped_search_process_holds_up_neither_status_nor_keyframes(keyframes):
    """The merger's search process starved (here: stopped): the merger still takes every
    keyframe, and status answers at once; once the process runs again, the searches land
    and a drain waits for them."""
    camera, kfs = keyframes
    # A search timeout beyond the hang guard: a status that waited on the stopped search
    # would wait that long.
    config = Config().with_values({"merge.search_process": True,
                                   "merge.search_timeout_s": 2 * HANG_S})
    service = MergerService(config)
    try:
        for name in kfs:
            service.add_robot(name, camera)
        assert service.drain(60.0)
        pid = service.merger.search._process.pid
        os.kill(pid, signal.SIGSTOP)
        try:
            for robot in ("a", "b"):
                for kf in kfs[robot]:
                    service.submit(kf, np.stack([np.eye(4)] * (kf.keyframe + 1)))
            assert not service.drain(1.0)  # searches out: not merged yet
            start = time.monotonic()
            status = service.status()
            assert time.monotonic() - start < HANG_S
            assert {r: v["keyframes"] for r, v in status["robots"].items()} == \
                {r: len(v) for r, v in kfs.items()}
        finally:
            os.kill(pid, signal.SIGCONT)
        assert service.drain(60.0)
        status = service.status()
        assert status["constraints"] + sum(status["pending_matches"].values()) > 0 \
            or any(v["joined"] for v in status["robots"].values())
    finally:
        service.close()
