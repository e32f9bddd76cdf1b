"""The control path against floods and hostile orders (issue 27, items 1, 7, 8): an end
before any frame is refused with a reason, ends and other control messages pass the same
admission as frames (rate limit, pause; no thread or traceback per message), a full cloud
is reported as full and gives the slots of sessions that only said hello to the next hello, and a
robot that tracks itself cannot record frame indices that go back or jump."""

from __future__ import annotations

import json
import logging
import threading
import time
from dataclasses import replace

import pytest
from conftest import HANG_S, exact_config, small_scene
from test_cloud import FakeRobot

from fleetslam.cloud.server import CloudServer
from fleetslam.cloud.session.robot_session import RobotSession
from fleetslam.cloud.session.store import CloudStore
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
    config = exact_config().with_values({"transport.end_grace_s": 1.0})
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
    config = exact_config().with_values({"transport.max_control_per_s": 5,
                                         "transport.max_rejections_per_s": 10,
                                         "transport.misbehaving_pause_s": 30.0})
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


def _first_frame(folder, robot_id: str) -> bytes:
    """The first frame message a robot at point 3 sends."""
    from fleetslam.backend.robot_slam import RobotSlam
    from fleetslam.pipeline.split import run_stages
    from fleetslam.pipeline.states import CapturedFrame

    seq = RgbdSequence(folder)
    f = seq[0]
    pipeline = RobotSlam.new(exact_config(), seq.camera)
    state = run_stages(pipeline.split(3)[0], CapturedFrame(f.index, f.timestamp, f.rgb,
                                                           f.depth_m), pipeline.sides)
    return encode_frame_message(state, 3, robot_id, 0, seq.camera, exact_config().wire)


def test_hellos_alone_never_keep_a_robot_out_and_a_full_cloud_says_so(scene, tmp_path,
                                                                      caplog):
    """On plain TCP anyone may say hello under made-up ids: a session that only said hello
    gives its slot to the next hello of a cloud that is full (oldest first), so a flood of
    them churns among themselves while the robots that sent frames keep theirs. Full of
    robots that sent frames, the cloud refuses and says why."""
    config = exact_config().with_values({"transport.max_sessions": 2})
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    client = open_connecting(endpoint)
    camera = RgbdSequence(scene[0]).camera
    fakes = [FakeRobot(client, f"fake{i}", camera) for i in range(2)]
    robots = [FakeRobot(client, f"r{i}", camera, offload_at=3) for i in range(2)]
    try:
        with caplog.at_level(logging.WARNING, "fleetslam.cloud"):
            for fake in fakes:
                fake.hello()
            for robot in robots:
                robot.hello()  # welcomed: the oldest made-up session made room
                robot.send(_first_frame(scene[0], robot.id))
                _wait_for(lambda: server.sessions.live(robot.id) is not None
                          and server.sessions.live(robot.id).heard_frame)
        assert set(server.sessions) == {"r0", "r1"}
        assert any("fake0: its session (a hello" in r.getMessage()
                   and "closed for robot r0's hello" in r.getMessage() for r in caplog.records)
        for _ in range(20):  # the flood goes on: nothing of the robots' is given up
            client.put(keys.control("fake0"), json.dumps(
                {"type": "hello", "protocol": PROTOCOL, "offload_at": 3,
                 "camera": camera.to_dict()}).encode())
        refusal = fakes[0].reply("error")
        assert refusal["full"] is True and refusal["answer_to"] == "hello"
        assert "full" in refusal["reason"]
        assert set(server.sessions) == {"r0", "r1"}
    finally:
        for r in fakes + robots:
            r.close()
        client.close()
        server.close()


def test_a_session_that_never_tracks_a_frame_is_closed(scene, tmp_path, caplog):
    config = exact_config().with_values({"transport.idle_empty_session_s": 0.5})
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    client = open_connecting(endpoint)
    fake = FakeRobot(client, "fake0", RgbdSequence(scene[0]).camera)
    try:
        with caplog.at_level(logging.INFO, "fleetslam.cloud"):
            fake.hello()
            # Logged once it is closed (out of the table first).
            _wait_for(lambda: any(r.getMessage().startswith(
                "robot fake0: session closed, no frame") for r in caplog.records))
        assert "fake0" not in set(server.sessions)
    finally:
        fake.close()
        client.close()
        server.close()


def test_a_robot_refused_by_a_full_cloud_says_the_cloud_is_full(scene, tmp_path):
    # A cloud that admits no robot: below the setting's range, so made past its check.
    config = exact_config()
    config = replace(config, transport=replace(config.transport, max_sessions=0))
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    robot_config = exact_config().with_values({"transport.connect_timeout_s": 0.5,
                                               "transport.max_attempts": 4,
                                               "transport.full_retries": 1,
                                               "transport.full_retry_s": 0.1})
    robot = Robot("r0", RgbdSequence(scene[0]), str(scene[0]), 3, robot_config, endpoint,
                  show_progress=False)
    try:
        start = time.monotonic()
        with pytest.raises(RuntimeError,
                           match=r"is full \(0 sessions\), refused 2 times: .*at most 0 robots"):
            robot.run()
        assert time.monotonic() - start < HANG_S  # not transport.reach_deadline_s (600 s)
    finally:
        server.close()


@pytest.fixture(scope="module")
def point6(scene):
    """The camera and the tracked states of a robot that tracks itself (point 6)."""
    from fleetslam.backend.robot_slam import RobotSlam
    from fleetslam.pipeline.split import run_stages
    from fleetslam.pipeline.states import CapturedFrame

    seq = RgbdSequence(scene[0])
    robot = RobotSlam.new(exact_config(), seq.camera)
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
