"""The merger's place search in its own process gives the matches the in-line search gives,
on real keyframes of two robots; a process that dies or misses its deadline hands over to
the in-line search with nothing lost."""

from __future__ import annotations

import os

import numpy as np
import pytest

from conftest import SEVEN_SCENES, require
from fleetslam.backend.back_end import TrackingPipeline
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.merging.place_search import PlaceSearch, PlaceSearchProcess
from fleetslam.pipeline.split import run_stages
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.wire.merger_keyframes import KeyframeSummary


@pytest.fixture(scope="module")
def keyframes():
    """Robot a: redkitchen frames 0, 12, ... 84; robot b: 6, 18, ... 90 (same place, other
    views). Poses are not searched, so identity."""
    seq = RgbdSequence(require(SEVEN_SCENES), first=0, last=90)
    pipeline = TrackingPipeline(Config(), seq.camera)
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


def _run(search, camera, keyframes) -> list[tuple]:
    """a's keyframes indexed, then each of b's searched in a; the matches found."""
    for name in keyframes:
        search.add_robot(name, camera)
    for kf in keyframes["a"]:
        assert search.add_keyframe(kf, []) == []
    found = []
    for kf in keyframes["b"]:
        for m in search.add_keyframe(kf, ["a"]):
            assert m.query is kf and m.place is keyframes["a"][m.place.keyframe]
            found.append((m.query.keyframe, m.place.robot, m.place.keyframe, m.score,
                          m.ransac_inliers, m.inliers, m.T_place_query.round(9).tobytes()))
    return found


def test_the_search_process_finds_what_the_inline_search_finds(keyframes):
    camera, kfs = keyframes
    inline = _run(PlaceSearch(Config()), camera, kfs)
    assert len(inline) >= len(kfs["b"]) // 2  # neighbouring views of one kitchen
    search = PlaceSearchProcess(Config(), nice=5, timeout_s=60.0)
    try:
        assert _run(search, camera, kfs) == inline
        assert not search.inline
        own = os.getpriority(os.PRIO_PROCESS, 0)
        assert os.getpriority(os.PRIO_PROCESS, search._process.pid) - own == 5
    finally:
        search.close()


@pytest.mark.parametrize("failure", ["killed", "deadline"])
def test_a_failed_search_process_hands_over_to_the_inline_search(keyframes, failure, caplog):
    camera, kfs = keyframes
    inline = _run(PlaceSearch(Config()), camera, kfs)
    search = PlaceSearchProcess(Config(), nice=0, timeout_s=60.0)
    try:
        for name in kfs:
            search.add_robot(name, camera)
        for kf in kfs["a"][:3]:
            search.add_keyframe(kf, [])
        assert not search.inline
        if failure == "killed":
            search._process.kill()
            search._process.join(5)
        else:
            search.timeout_s = 1e-4  # no search answers this fast
        for kf in kfs["a"][3:]:
            search.add_keyframe(kf, [])
        found = [(m.query.keyframe, m.place.robot, m.place.keyframe, m.score,
                  m.ransac_inliers, m.inliers, m.T_place_query.round(9).tobytes())
                 for kf in kfs["b"] for m in search.add_keyframe(kf, ["a"])]
        assert search.inline
        assert found == inline
        assert "searching in-line from now on" in caplog.text
    finally:
        search.close()


def test_a_closed_search_answers_nothing_and_says_nothing(keyframes, caplog):
    """The cloud stopping while the merger's thread still searches: no fallback, no error."""
    camera, kfs = keyframes
    search = PlaceSearchProcess(Config(), nice=0, timeout_s=60.0)
    for name in kfs:
        search.add_robot(name, camera)
    search.add_keyframe(kfs["a"][0], [])
    search.close()
    assert search.add_keyframe(kfs["b"][0], ["a"]) == []
    assert not search.inline and "in-line" not in caplog.text
