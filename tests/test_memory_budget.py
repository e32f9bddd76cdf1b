"""A session's memory is bounded in bytes (transport.session_budget_mb): a robot sending
valid frames faster than its session tracks, ignoring flow control, has the frames beyond
its budget dropped unread, counted and is told so; an honest robot loses none."""

from __future__ import annotations

import dataclasses
import json
import threading
import time

import numpy as np
import pytest
from conftest import SHARED_DATA, exact_config, require, small_scene, wait_for

from fleetslam.cloud.session.robot_session import RobotSession
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.transport import keys, protocol
from fleetslam.transport.protocol import Hello
from fleetslam.wire.frames import encode_frame_message

OVER_BUDGET = "frames dropped unread (over memory budget)"
MB = 1 << 20


@pytest.fixture(scope="module")
def point0(tmp_path_factory):
    """(camera, point-0 frame messages of robot r0 with seqs and timestamps moving forward:
    valid frames, more than a session tracks at once)."""
    seq = RgbdSequence(small_scene(tmp_path_factory, 4)[0])
    frames = list(seq)
    out = []
    for i in range(24):
        f = frames[i % len(frames)]
        state = CapturedFrame(i, 0.1 + i / 30.0, f.rgb, f.depth_m)
        out.append(encode_frame_message(state, 0, "r0", i, seq.camera, exact_config().wire))
    return seq.camera, out


def _bytes_of(x: object) -> int:
    """What an inbox item really holds: raw messages and decoded arrays."""
    if isinstance(x, (bytes, bytearray)):
        return len(x)
    if isinstance(x, np.ndarray):
        return x.nbytes
    if isinstance(x, tuple):
        return sum(_bytes_of(y) for y in x)
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return sum(_bytes_of(getattr(x, f.name)) for f in dataclasses.fields(x))
    return 0


def queued_bytes(session: RobotSession) -> int:
    """Bytes of the frames waiting in the session's two inboxes, measured on the items."""
    return sum(_bytes_of(item.data) + _bytes_of(item.decoded)
               for item in session.queued_frames())


def _session(camera, config: Config, tmp_path, replies: list) -> RobotSession:
    return RobotSession.open("r0", Hello(0, camera, "test"), config, CloudStore(tmp_path),
                             lambda k, d: replies.append(json.loads(d))
                             if k == keys.reply("r0") else None)


def _hold_tracking(session: RobotSession) -> threading.Event:
    """The tracking thread waits until the returned event is set (a slow map)."""
    gate = threading.Event()
    session.run_in_order(gate.wait, before_decoding=True)
    return gate


def test_frames_beyond_the_budget_are_dropped_unread_counted_and_the_robot_told(point0,
                                                                                 tmp_path):
    camera, msgs = point0
    decoded = camera.width * camera.height * 7  # a point-0 frame decoded
    room = 4.5 * decoded / MB  # for 4 frames
    config = exact_config().with_values({"transport.session_budget_mb": room})
    replies: list[dict] = []
    session = _session(camera, config, tmp_path, replies)
    try:
        gate = _hold_tracking(session)
        for data in msgs[:20]:
            session.submit_frame(data, time.monotonic())
        time.sleep(0.5)  # decoded meanwhile: the charge is trued up, still 4 frames
        assert queued_bytes(session) <= config.transport.session_budget_mb * MB
        gate.set()
        session.drain()
        counts = session.counts()
        assert counts[OVER_BUDGET] == 16 and counts["frames"] == 4
        told = [r for r in replies if r.get("code") == protocol.Code.OVER_BUDGET.value]
        assert len(told) == 1  # at most once a second
        assert session.transport_counts()[OVER_BUDGET] == 16
    finally:
        session.close()


def test_under_the_budget_nothing_is_dropped(point0, tmp_path):
    camera, msgs = point0
    config = exact_config().with_values(
        {"transport.session_budget_mb": 25 * camera.width * camera.height * 7 / MB})
    replies: list[dict] = []
    session = _session(camera, config, tmp_path, replies)
    try:
        gate = _hold_tracking(session)
        for data in msgs[:20]:
            session.submit_frame(data, time.monotonic())
        gate.set()
        session.drain()
        counts = session.counts()
        assert counts["frames"] == 20
        assert session.transport_counts()[OVER_BUDGET] == 0
        assert not [r for r in replies if r.get("type") == "error"]
    finally:
        session.close()


def test_a_hostile_flood_of_valid_frames_keeps_the_sessions_bytes_within_budget(point0,
                                                                                 tmp_path):
    """Over Zenoh, against a CloudServer: frames as fast as the link takes them; the bytes
    waiting in the session, sampled all along, never exceed its budget."""
    from test_cloud import FakeRobot

    from fleetslam.cloud.server import CloudServer
    from fleetslam.launch import free_endpoint
    from fleetslam.transport.zenoh_session import open_connecting

    camera, msgs = point0
    config = exact_config().with_values({"transport.session_budget_mb": 16.0})
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    client = open_connecting(endpoint)
    robot = FakeRobot(client, "r0", camera, offload_at=0)
    try:
        robot.hello()
        session = server.sessions["r0"]
        samples: list[int] = []
        done = threading.Event()

        def sample() -> None:
            while not done.is_set():
                samples.append(queued_bytes(session))
                time.sleep(0.002)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        for data in msgs:
            robot.send(data)
        time.sleep(1.0)
        done.set()
        sampler.join()
        session.drain()
        assert max(samples) <= 16 * MB, f"{max(samples) / MB:.1f} MB waiting"
        assert session.counts()[OVER_BUDGET] > 0
        assert robot.reply("error")["code"] == protocol.Code.OVER_BUDGET.value
    finally:
        robot.close()
        client.close()
        server.close()


def test_an_honest_robot_at_point_0_loses_no_frame_to_the_budget(tmp_path):
    """Real frames, the default config: the robot's window (max_frames_in_flight) fits its
    session's budget, however fast it sends."""
    from fleetslam.cloud.server import CloudServer
    from fleetslam.datasets.recording import open_source
    from fleetslam.edge.robot import Robot
    from fleetslam.launch import free_endpoint

    source = f"{require(SHARED_DATA / '7scenes_redkitchen_seq01_f0000-0599')}:0-39"
    config = Config()
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    try:
        robot = Robot("r1", open_source(source), source, 0, config, endpoint,
                      show_progress=False)
        robot.run()
        session = server.sessions["r1"]
        transport = session.transport_counts()
        assert transport[OVER_BUDGET] == 0
        assert transport["frames"] == 40
        assert session.budget.peak <= config.transport.session_budget_mb * MB
    finally:
        server.close()


def test_hellos_beyond_the_cloud_budget_are_refused_with_the_reason(point0, tmp_path):
    """Each session reserves its budget: a cloud of 32 MB with sessions of 16 MB opens two
    (a flood in one never takes the room of the other)."""
    from test_cloud import FakeRobot

    from fleetslam.cloud.server import CloudServer
    from fleetslam.launch import free_endpoint
    from fleetslam.transport.zenoh_session import open_connecting

    camera, messages = point0
    config = exact_config().with_values({"transport.session_budget_mb": 16.0,
                                         "transport.cloud_budget_mb": 32.0})
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    client = open_connecting(endpoint)
    robots = [FakeRobot(client, r, camera, offload_at=0) for r in ("r0", "r1", "r2")]
    try:
        for robot in robots[:2]:
            robot.hello()
            # A frame arrived: the session is no longer one that only said hello (whose
            # slot a full cloud gives to the next hello).
            robot.send(messages[0])
            wait_for(lambda: server.sessions.live(robot.id).heard_frame, 10.0,
                     f"{robot.id}'s frame")
        client.put(keys.control("r2"), json.dumps(
            {"type": "hello", "protocol": protocol.PROTOCOL, "offload_at": 0,
             "camera": camera.to_dict()}).encode())
        error = robots[2].reply("error")
        assert error["code"] == protocol.Code.REFUSED.value
        assert "transport.cloud_budget_mb" in error["reason"]
        assert set(server.sessions) == {"r0", "r1"}
    finally:
        for r in robots:
            r.close()
        client.close()
        server.close()


def test_uploads_beyond_the_budget_are_dropped_unread_under_it_read(point0, tmp_path):
    """An upload larger than the room left is dropped before decoding (the robot resends
    it); one that fits is read (here: rejected as garbage, after decoding)."""
    camera, _ = point0
    config = exact_config().with_values({"transport.session_budget_mb": 1.0})
    replies: list[dict] = []
    session = _session(camera, config, tmp_path, replies)
    try:
        session.submit_keyframe(bytes(2 * MB), time.monotonic())
        session.submit_keyframe(bytes(MB // 2), time.monotonic())
        deadline = time.monotonic() + 10.0
        while session.counts()["rejected keyframe"] < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        counts = session.transport_counts()
        assert counts["keyframes dropped unread (over memory budget)"] == 1
        assert counts["rejected keyframe"] == 1
        assert session.budget.used == 0  # the read upload's bytes are released
        assert any(r.get("code") == protocol.Code.OVER_BUDGET.value for r in replies)
    finally:
        session.close()
