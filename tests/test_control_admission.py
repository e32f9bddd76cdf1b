"""The control path against floods and hostile orders (issue 27, items 1, 7, 8): an end
before any frame is refused with a reason, ends and other control messages pass the same
admission as frames (rate limit, pause; no thread or traceback per message), a full cloud
is reported as full and frees the slots of sessions that never tracked a frame, and a
robot that tracks itself cannot record frame indices that go back or jump."""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import replace

import pytest
from conftest import exact_config, small_scene
from test_cloud import FakeRobot

from fleetslam.cloud.robot_session import RobotSession
from fleetslam.cloud.server import CloudServer
from fleetslam.cloud.store import CloudStore
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.edge.robot import Robot
from fleetslam.launch import free_endpoint
from fleetslam.transport import keys
from fleetslam.transport.protocol import PROTOCOL, Hello
from fleetslam.transport.zenoh_session import open_connecting
from fleetslam.wire.frames import encode_frame_message

N_FRAMES = 6


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return small_scene(tmp_path_factory, N_FRAMES)


def _session(tmp_path, camera, config=None, offload_at: int = 3):
    replies: list[dict] = []
    session = RobotSession.open(
        "r0", Hello(offload_at, camera, "test"), config or exact_config(),
        CloudStore(tmp_path), lambda k, d: replies.append(json.loads(d))
        if k == keys.reply("r0") else None)
    return session, replies


def _wait_for(predicate, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def test_an_end_before_any_frame_is_refused_with_a_reason(scene, tmp_path, caplog):
    session, replies = _session(tmp_path, RgbdSequence(scene[0]).camera)
    try:
        with caplog.at_level(logging.WARNING, "fleetslam.cloud"):
            session.submit_control({"type": "end", "last_seq": -1}, time.monotonic())
            _wait_for(lambda: any(r["type"] == "error" for r in replies))
        refusal = next(r for r in replies if r["type"] == "error")
        assert refusal["answer_to"] == "end" and "no frame" in refusal["reason"]
        assert session.counts()["errors"] == 0 and session.finished is None
        assert not any(r.exc_info for r in caplog.records)
    finally:
        session.close()


def test_a_flood_of_ends_is_one_end_no_thread_or_traceback_each(scene, tmp_path, caplog):
    """7,500 ends at 500/s took the cloud from 27 to 257 threads: here 2,000 ends waiting
    for a last frame that never comes (the grace period) start no thread, and the robot
    hears one answer for them."""
    config = exact_config()
    config.transport.end_grace_s = 1.0
    session, replies = _session(tmp_path, RgbdSequence(scene[0]).camera, config)
    before = threading.active_count()
    peak = before
    try:
        with caplog.at_level(logging.WARNING, "fleetslam.cloud"):
            for _ in range(2000):
                session.submit_control({"type": "end", "last_seq": 5}, time.monotonic())
                peak = max(peak, threading.active_count())
            deadline = time.monotonic() + 3.0
            while time.monotonic() < deadline:
                peak = max(peak, threading.active_count())
                time.sleep(0.01)
        assert peak <= before + 1, (before, peak)
        answers = [r for r in replies if r.get("answer_to") == "end"]
        assert len(answers) == 1, replies
        counts = session.counts()
        # Over transport.max_control_per_s, then paused: dropped unread.
        assert counts["pauses (too many rejected)"] >= 1
        assert counts["rejected control"] + counts["dropped unread (too many rejected)"] \
            >= 1900
        assert sum(bool(r.exc_info) for r in caplog.records) == 0
        assert len(caplog.records) < 20, [r.getMessage() for r in caplog.records]
    finally:
        session.close()


def test_a_failing_control_message_logs_one_traceback_per_interval(scene, tmp_path, caplog,
                                                                   monkeypatch):
    session, _ = _session(tmp_path, RgbdSequence(scene[0]).camera)
    monkeypatch.setattr(session, "_on_control", lambda m, a: 1 / 0)
    try:
        with caplog.at_level(logging.WARNING, "fleetslam.cloud"):
            for _ in range(15):
                session.submit_control({"type": "hello"}, time.monotonic())
            session.drain()
        assert session.counts()["errors"] == 15
        assert sum(bool(r.exc_info) for r in caplog.records) == 1
    finally:
        session.close()


def test_a_robot_paused_for_flooding_control_is_dropped_unread(scene, tmp_path):
    config = exact_config()
    config.transport.max_control_per_s = 5
    config.transport.max_rejections_per_s = 10
    config.transport.misbehaving_pause_s = 30.0
    session, _ = _session(tmp_path, RgbdSequence(scene[0]).camera, config)
    try:
        taken = [session.submit_control({"type": "hello"}, time.monotonic())
                 for _ in range(100)]
        session.drain()
        counts = session.counts()
        assert sum(taken) == 5
        assert counts["pauses (too many rejected)"] == 1
        assert counts["dropped unread (too many rejected)"] > 0
        session.reject_control("garbage")  # bad control messages count as rejections too
        assert session.counts()["rejected control"] == counts["rejected control"] + 1
    finally:
        session.close()


def test_a_full_cloud_says_so_and_empty_sessions_free_their_slots(scene, tmp_path):
    config = exact_config()
    config.transport.max_sessions = 2
    config.transport.idle_empty_session_s = 1.0
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    client = open_connecting(endpoint)
    camera = RgbdSequence(scene[0]).camera
    robots = [FakeRobot(client, f"fake{i}", camera) for i in range(2)]
    genuine = FakeRobot(client, "r0", camera)
    try:
        for r in robots:
            r.hello()
        client.put(keys.control("r0"), json.dumps(
            {"type": "hello", "protocol": PROTOCOL, "offload_at": 3,
             "camera": camera.to_dict()}).encode())
        refusal = genuine.reply("error")
        assert refusal["full"] is True and refusal["answer_to"] == "hello"
        assert "full" in refusal["reason"]
        # The made-up robots say hello again but never send a frame: their slots free.
        for r in robots:
            client.put(keys.control(r.id), json.dumps(
                {"type": "hello", "protocol": PROTOCOL, "offload_at": 3,
                 "camera": camera.to_dict()}).encode())
        _wait_for(lambda: not {"fake0", "fake1"} & set(server.sessions))
        genuine.hello()
    finally:
        for r in robots + [genuine]:
            r.close()
        client.close()
        server.close()


def test_a_robot_refused_by_a_full_cloud_says_the_cloud_is_full(scene, tmp_path):
    config = exact_config()
    config.transport.max_sessions = 0
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    robot_config = exact_config()
    robot_config.transport.connect_timeout_s = 0.5
    robot_config.transport.max_attempts = 4
    robot_config.transport.full_retries = 1
    robot_config.transport.full_retry_s = 0.1
    robot = Robot("r0", RgbdSequence(scene[0]), str(scene[0]), 3, robot_config, endpoint,
                  show_progress=False)
    try:
        start = time.monotonic()
        with pytest.raises(RuntimeError,
                           match=r"is full \(0 sessions\), refused 2 times: .*at most 0 robots"):
            robot.run()
        assert time.monotonic() - start < 10.0
    finally:
        server.close()


@pytest.fixture(scope="module")
def point6(scene):
    """The camera and the tracked states of a robot that tracks itself (point 6)."""
    from fleetslam.backend.back_end import TrackingPipeline
    from fleetslam.pipeline.split import run_stages
    from fleetslam.pipeline.states import CapturedFrame

    seq = RgbdSequence(scene[0])
    robot = TrackingPipeline(exact_config(), seq.camera)
    return seq.camera, [run_stages(robot.split(6)[0],
                                   CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m),
                                   robot.sides) for f in seq]


def test_a_robot_tracking_itself_cannot_send_indices_that_go_back_or_jump(point6, tmp_path):
    camera, states = point6
    session, replies = _session(tmp_path, camera, offload_at=6)
    wire = exact_config().wire

    def message(i: int, index: int | None = None) -> bytes:
        """Frame ``i`` (its seq and timestamp in order), with another index if given."""
        state = states[i]
        if index is not None:  # the index lives in the features the pose was tracked from
            posed = state.posed
            features = replace(posed.matched.features, index=index)
            state = replace(state, posed=replace(
                posed, matched=replace(posed.matched, features=features)))
        return encode_frame_message(state, 6, "r0", i, camera, wire)

    msgs = [message(i) for i in range(len(states))]

    def forged(i: int, index: int) -> bytes:
        return message(i, index)

    try:
        session.submit_frame(msgs[0], time.monotonic())
        session.submit_frame(msgs[1], time.monotonic())
        for i, index in ((2, -5), (3, 2 ** 62), (4, 0)):
            session.submit_frame(forged(i, index), time.monotonic())
        session.drain()
        assert [r.index for r in session.state.rows] == [0, 1]
        assert session.counts()["rejected frame"] == 3
        session.submit_frame(msgs[5], time.monotonic())
        session.drain()
        assert [r.index for r in session.state.rows] == [0, 1, 5]
    finally:
        session.close()
