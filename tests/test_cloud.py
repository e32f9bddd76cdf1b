"""The cloud against bad and unlucky input: garbage, truncated, wrong-version, wrong-checksum,
duplicated and out-of-order messages are rejected with a logged reason, and neither the
cloud nor any other robot's session is harmed. Runs a real CloudServer over Zenoh in this
process, with a hand-driven robot that sends exactly the bytes each case needs."""

from __future__ import annotations

import json
import logging
import queue
import socket
import struct
import threading
import time
from contextlib import contextmanager
from dataclasses import replace
from types import SimpleNamespace
from typing import Any, Iterator

import numpy as np
import pytest
from conftest import exact_config, small_scene, wait_for

from fleetslam.cloud.server import CloudServer
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.launch import free_endpoint
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.pipeline.split import run_stages
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.transport import keys, protocol
from fleetslam.transport.protocol import PROTOCOL, Code, Hello
from fleetslam.transport.zenoh_session import open_connecting, open_router, put
from fleetslam.wire.envelope import FORMAT_VERSION, Kind, open_message
from fleetslam.wire.frames import encode_frame_message
from fleetslam.wire.inter import InterEncoder, reference_of
from fleetslam.wire.messages import decode_feedback

K = 3  # the paper's offloading point
N_FRAMES = 12


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return small_scene(tmp_path_factory, N_FRAMES)


def robot_messages(scene, k: int) -> dict:
    """Per robot: the frame messages a robot offloading at ``k`` sends, and the poses the
    whole pipeline gives in memory (the reference every cloud run must reproduce)."""
    out = {}
    for name, folder in zip(("r0", "r1"), scene):
        seq = RgbdSequence(folder)
        robot = RobotSlam.new(exact_config(), seq.camera)
        reference = RobotSlam.new(exact_config(), seq.camera)
        msgs, poses = [], []
        for seq_no, f in enumerate(seq):
            frame = CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m)
            state = run_stages(robot.split(k)[0], frame, robot.sides)
            msgs.append(encode_frame_message(state, k, name, seq_no, seq.camera, exact_config().wire))
            poses.append(reference.track(frame).T_world_camera)
        out[name] = (seq, msgs, np.array(poses))
    return out


@pytest.fixture(scope="module")
def messages(scene):
    return robot_messages(scene, K)


class FakeRobot:
    """Talks to the cloud with raw bytes on one robot's keys."""

    def __init__(self, session, robot_id: str, camera, offload_at: int = K,
                 adaptive: bool = False) -> None:
        self.z = session
        self.adaptive = adaptive
        self.id = robot_id
        self.camera = camera
        self.offload_at = offload_at
        self.feedback: queue.Queue = queue.Queue()
        self.replies: queue.Queue = queue.Queue()
        self.subs = [
            session.declare_subscriber(keys.feedback(robot_id),
                                       lambda s: self.feedback.put(s.payload.to_bytes())),
            session.declare_subscriber(keys.reply(robot_id),
                                       lambda s: self.replies.put(json.loads(
                                           s.payload.to_bytes()))),
        ]

    def reply(self, kind: str, timeout: float = 10.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                message = self.replies.get(timeout=0.1)
            except queue.Empty:
                continue
            if message["type"] == kind:
                return message
        raise AssertionError(f"no {kind} reply for {self.id}")

    def hello(self) -> dict:
        message = {"type": "hello", "protocol": PROTOCOL, "offload_at": self.offload_at,
                   "camera": self.camera.to_dict(), "source": "test",
                   "adaptive": self.adaptive}
        for _ in range(20):
            self.z.put(keys.control(self.id), json.dumps(message).encode())
            try:
                return self.reply("welcome", timeout=0.5)
            except AssertionError:
                continue
        raise AssertionError("cloud never welcomed")

    def send(self, data: bytes) -> None:
        put(self.z, keys.frame(self.id), data)

    def poses(self, n: int, timeout: float = 30.0) -> list:
        out = []
        deadline = time.monotonic() + timeout
        while len(out) < n and time.monotonic() < deadline:
            try:
                out.append(decode_feedback(self.feedback.get(timeout=0.2))[1])
            except queue.Empty:
                pass
        return out

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


@contextmanager
def one_robot_cloud(config, tmp_path, camera) -> Iterator[tuple[CloudServer, Any, FakeRobot]]:
    """A lone cloud with ``config``, a client session and robot r0 on it; all closed after."""
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    client = open_connecting(endpoint)
    robot = FakeRobot(client, "r0", camera)
    try:
        yield server, client, robot
    finally:
        robot.close()
        client.close()
        server.close()


@pytest.fixture()
def cloud(tmp_path):
    endpoint = free_endpoint()
    server = CloudServer(exact_config(), tmp_path / "cloud", endpoint).start()
    client = open_connecting(endpoint)
    yield server, client
    client.close()
    server.close()


def _damaged(message: bytes) -> dict[str, bytes]:
    flipped = bytearray(message)
    flipped[-5] ^= 0xFF
    wrong_version = bytearray(message)
    wrong_version[4:6] = struct.pack("<H", FORMAT_VERSION + 1)
    return {
        "garbage": bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8)),
        "empty": b"",
        "truncated": message[: len(message) // 2],
        "wrong version": bytes(wrong_version),
        "wrong checksum": bytes(flipped),
    }


@pytest.mark.parametrize("k", [0, 1, 2])
def test_the_cloud_runs_the_front_end_when_the_robot_offloads_early(cloud, scene, k):
    """At points 0-2 the cloud also runs front-end stages (their state lives in the cloud
    then): the poses are the in-memory ones."""
    server, client = cloud
    seq, msgs, reference = robot_messages(scene, k)["r0"]
    robot = FakeRobot(client, "r0", seq.camera, offload_at=k)
    robot.hello()
    for data in msgs:
        robot.send(data)
    got = robot.poses(N_FRAMES)
    assert [fb.frame_index for fb in got] == list(range(N_FRAMES))
    np.testing.assert_array_equal(np.array([fb.T_world_camera for fb in got]), reference)
    assert server.sessions["r0"].state.counts["errors"] == 0


def test_an_adaptive_robot_switches_points_frame_by_frame(cloud, scene):
    """A robot that re-plans sends each frame at the point it chose then (0-3): the cloud
    tracks every frame, and as the front end keeps no state that matters here, the poses are
    the in-memory ones. A robot that did not say it adapts is held to its point."""
    server, client = cloud
    both = {k: robot_messages(scene, k) for k in (0, 1, 3)}
    by_k = {k: both[k]["r0"] for k in both}
    seq, _, reference = by_k[3]
    robot = FakeRobot(client, "r0", seq.camera, offload_at=3, adaptive=True)
    robot.hello()
    plan = [3, 3, 1, 1, 0, 3, 3, 1, 0, 0, 3, 3][:N_FRAMES]
    for i, k in enumerate(plan):
        robot.send(by_k[k][1][i])
    got = robot.poses(N_FRAMES)
    assert [fb.frame_index for fb in got] == list(range(N_FRAMES))
    np.testing.assert_array_equal(np.array([fb.T_world_camera for fb in got]), reference)
    assert server.sessions["r0"].state.counts["errors"] == 0
    seq1, _, _ = both[3]["r1"]
    fixed = FakeRobot(client, "r1", seq1.camera, offload_at=3)
    fixed.hello()
    fixed.send(both[1]["r1"][1][0])  # its own frame 0, at point 1: refused ...
    assert "split point 1, but the session offloads at 3" in fixed.reply("error")["reason"]
    fixed.send(both[3]["r1"][1][1])  # ... its frame 1 at point 3 is tracked
    assert [fb.frame_index for fb in fixed.poses(1)] == [1]
    counts = server.sessions["r1"].state.counts
    assert counts["rejected frame"] == 1 and counts["frames"] == 1
    fixed.close()


def test_bad_messages_are_rejected_and_no_session_is_harmed(cloud, messages, caplog):
    server, client = cloud
    caplog.set_level(logging.WARNING, logger="fleetslam.cloud")
    seq0, msgs0, ref0 = messages["r0"]
    seq1, msgs1, ref1 = messages["r1"]
    r0, r1 = FakeRobot(client, "r0", seq0.camera), FakeRobot(client, "r1", seq1.camera)
    r0.hello()
    r1.hello()
    bad = _damaged(msgs0[1])
    # r1's messages are interleaved with everything r0 does wrong; r0 also tries to pass
    # its frame off as r1's (robot id in the header differs from the key).
    for i in range(N_FRAMES):
        r1.send(msgs1[i])
        if i == 1:
            for data in bad.values():
                r0.send(data)
            put(client, keys.frame("r1"), msgs0[1])  # BLOCK: Zenoh must not drop it
        r0.send(msgs0[i])
        if i == 3:
            r0.send(msgs0[3])  # duplicate
            r0.send(msgs0[2])  # out of order (older than the last accepted)
    got0, got1 = r0.poses(N_FRAMES), r1.poses(N_FRAMES)
    # Every good frame tracked, bit for bit as in memory, for both robots.
    assert [fb.frame_index for fb in got0] == list(range(N_FRAMES))
    assert [fb.frame_index for fb in got1] == list(range(N_FRAMES))
    np.testing.assert_array_equal(np.array([fb.T_world_camera for fb in got0]), ref0)
    np.testing.assert_array_equal(np.array([fb.T_world_camera for fb in got1]), ref1)
    counts0 = server.sessions["r0"].state.counts
    counts1 = server.sessions["r1"].state.counts
    assert counts0["rejected frame"] == len(bad) + 2
    assert counts1["rejected frame"] == 1  # r0's frame on r1's key
    text = caplog.text
    for reason in ("magic", "truncated", "version", "checksum", "duplicate", "out of order",
                   "header names robot 'r0'"):
        assert reason in text, reason
    r0.close()
    r1.close()


def test_frames_without_a_session_and_bad_control_get_a_clear_error(cloud, messages):
    server, client = cloud
    seq0, msgs0, _ = messages["r0"]
    robot = FakeRobot(client, "r0", seq0.camera)
    time.sleep(0.3)
    robot.send(msgs0[0])
    assert "hello" in robot.reply("error")["reason"]
    client.put(keys.control("r0"), b"{not json")
    assert "not JSON" in robot.reply("error")["reason"]
    client.put(keys.control("r0"), json.dumps({"type": "hello", "protocol": PROTOCOL,
                                               "offload_at": 4, "camera": {}}).encode())
    assert "not supported" in robot.reply("error")["reason"]
    client.put("fleet/bad id!/frame", msgs0[0])  # not a valid robot id: dropped, logged
    robot.hello()
    robot.send(msgs0[0])
    assert robot.poses(1)[0].frame_index == 0
    assert server.unrouted >= 1
    robot.close()


def test_every_reply_that_asks_for_a_hello_carries_the_no_session_code(cloud, messages):
    """A robot says hello again on Code.NO_SESSION, not on a reply's words: a frame or a
    control message before any hello, and a frame at another point than its session's."""
    server, client = cloud
    seq0, msgs0, _ = messages["r0"]
    robot = FakeRobot(client, "r0", seq0.camera, offload_at=1)
    time.sleep(0.3)
    robot.send(msgs0[0])  # no session yet
    replies = [robot.reply("error")]
    client.put(keys.control("r0"), json.dumps({"type": "end", "last_seq": 0}).encode())
    replies.append(robot.reply("error"))
    robot.hello()  # a session at point 1
    robot.send(msgs0[0])  # a frame at point 3
    replies.append(robot.reply("error"))
    assert [r["code"] for r in replies] == [Code.NO_SESSION.value] * 3, replies
    assert all("send a hello" in r["reason"] for r in replies), replies
    assert "split point 3" in replies[-1]["reason"]
    robot.close()


def test_an_end_that_overtakes_the_last_frames_waits_for_them(messages, tmp_path):
    from fleetslam.cloud.session.robot_session import RobotSession
    from fleetslam.cloud.session.store import CloudStore
    from fleetslam.transport.protocol import Hello

    seq0, msgs0, _ = messages["r0"]
    replies: list[dict] = []
    holder: list[RobotSession] = []

    def publish(key: str, data: bytes) -> None:
        if key == keys.reply("r0"):  # with the number of frames tracked when it was sent
            replies.append({**json.loads(data), "frames": holder[0].state.counts["frames"]})

    hello = Hello(K, seq0.camera, "test")
    session = RobotSession.open("r0", hello, exact_config(), CloudStore(tmp_path), publish)
    holder.append(session)
    now = time.monotonic()
    for data in msgs0[:-3]:
        session.submit_frame(data, now)
    # The end arrives before the last three frames it follows (another key, another path).
    session.submit_control({"type": "end", "last_seq": N_FRAMES - 1}, now)
    time.sleep(0.2)
    for data in msgs0[-3:]:
        session.submit_frame(data, time.monotonic())
    deadline = time.monotonic() + 30
    while not any(r["type"] in ("need", "ended") for r in replies):
        assert time.monotonic() < deadline, replies
        time.sleep(0.05)
    session.close()
    # Keyframe uploads are still missing, so the cloud asks for them — after all frames.
    assert replies[-1]["type"] == "need" and replies[-1]["frames"] == N_FRAMES


def test_frames_are_held_as_references_when_decoded_not_when_tracked(messages, tmp_path):
    """Inter-frame coding refers to frames the cloud holds. The session says it holds a
    frame as soon as it is decoded: a tracker that lags (here: stopped) must not hold back
    what the robot may code against, or a busy cloud gets intra frames only."""
    from fleetslam.cloud.session.robot_session import RobotSession
    from fleetslam.cloud.session.store import CloudStore
    from fleetslam.transport.protocol import Hello

    seq0, msgs0, _ = messages["r0"]
    sent: list[tuple[str, bytes]] = []
    session = RobotSession.open("r0", Hello(K, seq0.camera, "test"), exact_config(),
                                CloudStore(tmp_path), lambda key, data: sent.append((key, data)))
    gate = threading.Event()
    session.run_in_order(lambda: gate.wait(30))  # the tracker is busy
    now = time.monotonic()
    for data in msgs0:
        session.submit_frame(data, now)
    deadline = time.monotonic() + 30
    held = []
    while len(held) < len(msgs0):
        assert time.monotonic() < deadline, held
        time.sleep(0.02)
        held = [json.loads(d)["seq"] for k, d in list(sent)
                if k == keys.reply("r0") and json.loads(d)["type"] == "held"]
    assert held == list(range(len(msgs0)))
    assert not [k for k, _ in sent if k == keys.feedback("r0")]  # nothing tracked yet
    assert all(i in session.references for i in held)
    gate.set()
    session.drain()
    assert len([k for k, _ in sent if k == keys.feedback("r0")]) == len(msgs0)
    session.close()


def test_hostile_frames_that_decode_are_rejected_with_a_reason_and_tracking_goes_on(cloud,
                                                                                   scene):
    """Messages that are well formed but carry what no camera produces: each is rejected
    before any stage runs, the robot hears why, and its good frames track as before."""
    server, client = cloud
    seq = RgbdSequence(scene[0])
    camera, config = seq.camera, exact_config()
    robot_side, reference = RobotSlam.new(config, camera), RobotSlam.new(config, camera)
    states, expected = [], []
    for f in seq:
        frame = CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m)
        states.append(run_stages(robot_side.split(K)[0], frame, robot_side.sides))
        expected.append(reference.track(frame).T_world_camera)
    good = states[1]
    n = len(good.keypoints)
    nan_kp = good.keypoints.copy()
    nan_kp[0, 0] = np.nan
    outside = good.keypoints.copy()
    outside[:, 0] += camera.width
    many = 50
    hostile = {
        "NaN keypoints": replace(good, keypoints=nan_kp),
        "keypoints outside": replace(good, keypoints=outside),
        "uv disagrees": replace(good, uv=good.uv + [300.0, 0.0]),
        "too many keypoints": replace(
            good, keypoints=np.tile(good.keypoints, (many, 1)),
            descriptors=np.tile(good.descriptors, (many, 1)), depth=np.tile(good.depth, many),
            uv=np.tile(good.uv, (many, 1))),
    }
    assert many * n > 20_000
    robot = FakeRobot(client, "r0", camera)
    robot.hello()
    robot.send(encode_frame_message(states[0], K, "r0", 0, camera, config.wire))
    seq_no = 1
    for name, state in hostile.items():
        robot.send(encode_frame_message(state, K, "r0", seq_no, camera, config.wire))
        reason = robot.reply("error", timeout=5.0)["reason"]
        assert reason.startswith("frame rejected"), (name, reason)
        seq_no += 1
        time.sleep(1.05)  # the cloud tells a robot why at most once a second
    # A far-future seq, and a frame from the past: rejected too.
    robot.send(encode_frame_message(states[1], K, "r0", 2**63, camera, config.wire))
    assert "seq jumps" in robot.reply("error", timeout=5.0)["reason"]
    time.sleep(1.05)
    for i in range(1, N_FRAMES):
        robot.send(encode_frame_message(states[i], K, "r0", seq_no, camera, config.wire))
        seq_no += 1
        if i == 3:
            time.sleep(0.3)  # let frame 3 be tracked before its stale twin arrives
            robot.send(encode_frame_message(states[2], K, "r0", seq_no, camera, config.wire))
            seq_no += 1
    got = robot.poses(N_FRAMES)
    assert [fb.frame_index for fb in got] == list(range(N_FRAMES))
    np.testing.assert_array_equal(np.array([fb.T_world_camera for fb in got]),
                                  np.array(expected))
    counts = server.sessions["r0"].state.counts
    assert counts["rejected frame"] == len(hostile) + 2 and counts["errors"] == 0
    assert "is not after" in robot.reply("error", timeout=5.0)["reason"]


def test_a_sessions_inbox_drops_its_oldest_frames_never_a_control_message():
    from fleetslam.cloud.session.inbox import ControlItem, FrameItem, WorkQueue

    q = WorkQueue(max_frames=3)
    for i in range(3):
        q.put(FrameItem(bytes([i]), 0.0, 1))
    q.put(ControlItem({"type": "end"}, 0.0))
    q.put(FrameItem(b"\x03", 0.0, 1))
    q.put(FrameItem(b"\x04", 0.0, 1))
    got = [q.get() for _ in range(4)]
    assert [getattr(x, "data", None) or x.message["type"] for x in got] == \
        [b"\x02", "end", b"\x03", b"\x04"] and q.dropped == 2


def test_bad_hellos_and_too_many_robots_are_refused_with_a_reason(tmp_path, scene, messages):
    config = exact_config().with_values({"transport.max_sessions": 1})
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    client = open_connecting(endpoint)
    try:
        camera = RgbdSequence(scene[0]).camera
        first = FakeRobot(client, "r0", camera)
        first.hello()
        first.send(messages["r0"][1][0])  # a robot that sent a frame keeps its slot
        wait_for(lambda: server.sessions.live("r0").heard_frame, 10.0, "r0's frame")
        second = FakeRobot(client, "r1", camera)
        second.z.put(keys.control("r1"), json.dumps(
            {"type": "hello", "protocol": PROTOCOL, "offload_at": K,
             "camera": camera.to_dict()}).encode())
        assert "at most 1 robots" in second.reply("error")["reason"]
        bad = {**camera.to_dict(), "fx": "abc"}
        first.z.put(keys.control("r2"), json.dumps(
            {"type": "hello", "protocol": PROTOCOL, "offload_at": K, "camera": bad}).encode())
        deep = ("[" * 100_000 + "]" * 100_000).encode()
        first.z.put(keys.control("r0"), deep)
        time.sleep(0.5)
        assert set(server.sessions) == {"r0"}
        first.hello()  # the cloud still answers
    finally:
        client.close()
        server.close()


@pytest.mark.parametrize("freed_by", ["a hello", "idleness"])
def test_a_finished_session_gives_its_slot_to_the_next_robot(tmp_path, messages, freed_by):
    """A worker holding transport.max_sessions (1) sessions: a robot that ended leaves its
    slot to the next robot's hello (it stayed full for good before), or leaves the table
    once idle for transport.idle_session_s, yet it is merged from the store, and a hello
    under its id is still refused as ended."""
    seq0, msgs0, _ = messages["r0"]
    values = {"transport.max_sessions": 1}
    if freed_by == "idleness":
        values["transport.idle_session_s"] = 3.0
    config = exact_config().with_values(values)
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    client = open_connecting(endpoint)
    first, second = FakeRobot(client, "r0", seq0.camera), FakeRobot(client, "r1", seq0.camera)
    try:
        first.hello()
        for m in msgs0:
            first.send(m)
        assert len(first.poses(len(msgs0))) == len(msgs0)
        client.put(keys.control("r0"), json.dumps(
            {"type": "end", "last_seq": len(msgs0) - 1,
             "unavailable": list(range(len(msgs0)))}).encode())
        first.reply("ended", timeout=60.0)
        if freed_by == "idleness":
            wait_for(lambda: "r0" not in server.sessions, 30.0, "r0's finished session to go")
        assert second.hello()["type"] == "welcome"
        assert set(server.sessions) == {"r1"}
        merged = server.merge()["merge"]
        assert "r0" in merged["robots"], merged
        client.put(keys.control("r0"), json.dumps(
            {"type": "hello", "protocol": PROTOCOL, "offload_at": K,
             "camera": seq0.camera.to_dict()}).encode())
        assert first.reply("error")["code"] == Code.SESSION_ENDED.value
    finally:
        first.close()
        second.close()
        client.close()
        server.close()


@contextmanager
def two_workers_of_one_robot_each(tmp_path):
    """Two workers ("wa", "wb", transport.max_sessions 1 each) behind a router, and a client
    session on it; yields (servers, client, robots): the FakeRobots put in ``robots`` are
    closed at the end."""
    endpoint = free_endpoint()
    router = open_router(endpoint)
    servers = [CloudServer(exact_config().with_values({"transport.max_sessions": 1,
                                                       "placement.worker_id": name}),
                           tmp_path / "store", connect=endpoint).start() for name in ("wa", "wb")]
    client = open_connecting(endpoint)
    robots: list[FakeRobot] = []
    try:
        yield servers, client, robots
    finally:
        for robot in robots:
            robot.close()
        client.close()
        for server in servers:
            server.close()
        router.close()


def test_workers_full_of_sessions_they_may_close_still_take_the_next_robot(tmp_path,
                                                                           messages):
    """Two workers behind a router, each holding transport.max_sessions (1) session it would
    close for a new robot (here a hello with no frame; a finished one alike): the next
    robot's hello is still placed and welcomed. A full worker did not bid, so with every
    worker full nobody answered (bench/worker_scaling.py: 9 robots heard nothing after 130
    sessions had filled both workers)."""
    camera = messages["r0"][0].camera
    with two_workers_of_one_robot_each(tmp_path) as (servers, client, robots):
        # Hellos until both workers hold a session (where each goes is the placement's).
        for i in range(10):
            robots.append(FakeRobot(client, f"h{i}", camera))
            assert robots[-1].hello()["type"] == "welcome"
            if all(s.sessions.full() for s in servers):
                break
        assert all(s.sessions.full() for s in servers), "the hellos never filled both workers"
        robots.append(FakeRobot(client, "next", camera))
        assert robots[-1].hello()["type"] == "welcome"
        assert "next" in [r for s in servers for r in s.sessions]


def test_a_robot_hears_that_every_worker_is_full(tmp_path, messages):
    """Two workers behind a router, each holding transport.max_sessions (1) robot at work
    (its frames tracked: no session either may close): a new robot's hello is refused as
    full, by one of them, saying every worker is full. Before, a full worker did not bid
    and nobody answered: the robot gave up saying the cloud was silent."""
    seq = messages["r0"][0]
    with two_workers_of_one_robot_each(tmp_path) as (servers, client, robots):
        # One robot a worker: the first fills one worker, which then does not bid.
        for name in ("r0", "r1"):
            robots.append(FakeRobot(client, name, messages[name][0].camera))
            assert robots[-1].hello()["type"] == "welcome"
            robots[-1].send(messages[name][1][0])
            assert len(robots[-1].poses(1)) == 1
        assert not any(s.sessions.has_room() for s in servers), "not both workers busy"
        late = FakeRobot(client, "late", seq.camera)
        robots.append(late)
        hello = json.dumps({"type": "hello", "protocol": PROTOCOL, "offload_at": K,
                            "camera": seq.camera.to_dict(), "source": "test"}).encode()
        refusal = None
        deadline = time.monotonic() + 20.0  # the workers' load reports come every 0.5 s
        while refusal is None and time.monotonic() < deadline:
            client.put(keys.control("late"), hello)
            try:
                refusal = late.reply("error", timeout=1.0)
            except AssertionError:
                continue
        assert refusal is not None, "nobody answered the hello of a robot no worker can take"
        assert refusal["code"] == Code.REFUSED.value and refusal["full"], refusal
        assert refusal["answer_to"] == "hello" and refusal["max_sessions"] == 1
        assert "each of its 2 workers (wa, wb)" in refusal["reason"], refusal
        assert "late" not in [r for s in servers for r in s.sessions]


def test_an_idle_session_is_checkpointed_closed_and_restored_by_its_next_frame(messages,
                                                                                tmp_path):
    """A robot that goes quiet frees its session's threads and memory; nothing it sent is
    lost: its next frame restores the session from the checkpoint and tracking goes on with
    the same poses as a session that never closed."""
    seq0, msgs0, poses0 = messages["r0"]
    config = exact_config().with_values({"transport.idle_session_s": 0.4})
    with one_robot_cloud(config, tmp_path, seq0.camera) as (server, _, robot):
        robot.hello()
        half = len(msgs0) // 2
        for m in msgs0[:half]:
            robot.send(m)
        first = robot.poses(half)
        deadline = time.monotonic() + 10.0
        while "r0" in server.sessions and time.monotonic() < deadline:
            time.sleep(0.05)
        assert "r0" not in server.sessions, "the idle session was not closed"
        assert (tmp_path / "cloud" / "r0" / "session.ckpt").is_file()
        for m in msgs0[half:]:
            robot.send(m)
        rest = robot.poses(len(msgs0) - half)
        assert np.array_equal(np.array([f.T_world_camera for f in first + rest]), poses0)
        # Every frame counted once, by the live session or (on a loaded machine the last
        # feedback can come 0.4 s after the last frame, and the session goes idle again) by
        # the checkpoint it was closed with.
        with server.sessions.lock:
            live = server.sessions.get("r0")
            counts = live.counts() if live is not None else server.store.load_checkpoint(
                "r0").counts
        assert counts["frames"] == len(msgs0)


def test_frames_without_a_keyframe_are_checkpointed_too(messages, tmp_path):
    """transport.checkpoint_every_s: a robot making no keyframe (a place already mapped) is
    still checkpointed, so a restarted cloud resumes it near where it was. Here every frame
    is older than the setting, so each is checkpointed, keyframe or not."""
    seq0, msgs0, _ = messages["r0"]
    config = exact_config().with_values({"transport.checkpoint_every_s": 1e-6,
                                         "transport.checkpoint_interval_s": 0.0})
    with one_robot_cloud(config, tmp_path, seq0.camera) as (server, _, robot):
        robot.hello()
        for m in msgs0:
            robot.send(m)
        feedback = robot.poses(len(msgs0))
        assert len(feedback) == len(msgs0)
        session = server.sessions.get("r0")
        assert session.checkpoints.wait_for_frame(len(msgs0) - 1, 10.0)
        keyframes = sum(f.is_keyframe for f in feedback)
        assert keyframes < len(msgs0)  # frames without a keyframe were there to checkpoint
        # One asked for by each frame (writes of several asked together coalesce).
        assert session.checkpoints.asked == len(msgs0)
        assert server.store.load_checkpoint("r0").last_index == len(msgs0) - 1


def test_a_robot_flooding_bad_frames_is_paused_and_then_heard_again(messages, tmp_path):
    """Hundreds of rejected frames in a second: the session stops reading the robot's frames
    for a while (cheap drops instead of decoding), says so once, and tracks its good frames
    once the pause is over."""
    from fleetslam.cloud.session.robot_session import RobotSession
    from fleetslam.cloud.session.store import CloudStore
    from fleetslam.transport.protocol import Hello

    seq0, msgs0, poses0 = messages["r0"]
    config = exact_config().with_values({"transport.max_rejections_per_s": 20,
                                         "transport.misbehaving_pause_s": 0.5})
    replies: list[dict] = []
    session = RobotSession.open("r0", Hello(K, seq0.camera, "test"), config,
                                CloudStore(tmp_path), lambda k, d: replies.append(json.loads(d))
                                if k == keys.reply("r0") else None)
    try:
        for _ in range(30):  # decoded and rejected: trips the pause
            session.submit_frame(msgs0[0][: len(msgs0[0]) // 2], time.monotonic())
        session.drain()
        for _ in range(200):  # dropped unread
            session.submit_frame(msgs0[0][: len(msgs0[0]) // 2], time.monotonic())
        session.drain()
        counts = session.counts()
        assert counts["pauses (too many rejected)"] == 1
        assert counts["dropped unread (too many rejected)"] == 200
        assert counts["rejected frame"] == 30 and len(replies) == 1  # one reason per second
        time.sleep(0.6)
        for data in msgs0:
            session.submit_frame(data, time.monotonic())
        session.drain()
        assert session.counts()["frames"] == len(msgs0)
        np.testing.assert_array_equal(np.array([r.T_world_camera for r in session.state.rows]),
                                      poses0)
    finally:
        session.close()


def test_a_resent_merge_request_merges_once_and_replies_carry_its_id(cloud):
    """A client resends its request until answered; the cloud merges once per request id
    and sends the same reply again to a resend that comes after the merge (here the refusal
    of a cloud with no finished robot; the reply to a real merge is remembered alike)."""
    from fleetslam.launch import CloudClient
    from fleetslam.transport import protocol

    server, _ = cloud
    calls = []
    real_merge = server.fleet_merge.merge

    def slow_merge():
        calls.append(time.monotonic())
        time.sleep(0.5)
        return real_merge()

    server.fleet_merge.merge = slow_merge
    client = CloudClient(server.endpoint, reach_deadline_s=10.0)
    try:
        # No robot has finished here: the merge's answer is that one-line refusal, and a
        # resend of the same request gets it again from memory, without merging again.
        request = protocol.Request("merge")
        for _ in range(2):
            with pytest.raises(RuntimeError, match="no robot has finished yet"):
                client.request(request, protocol.Merged, timeout=30.0, resend_s=0.1)
        assert len(calls) == 1
        assert client.status(timeout=10.0)["type"] == "status"
        # An unknown request is an error naming it, with the request's id.
        with pytest.raises(RuntimeError, match="unknown request 'dance'"):
            dance = SimpleNamespace(id="x1", message=lambda: {"type": "dance", "id": "x1"})
            client.request(dance, protocol.Merged, timeout=10.0)
    finally:
        client.close()


def test_a_busy_session_still_waits_for_the_last_frame_after_the_end(messages, tmp_path):
    """The race of a quiet run that lost its last pose: the end had waited behind a backlog
    longer than the grace period, so the cloud gave up on a frame that was just arriving.
    The grace now runs from when the session gets to the end."""
    from fleetslam.cloud.session.robot_session import RobotSession
    from fleetslam.cloud.session.store import CloudStore
    from fleetslam.transport.protocol import Hello

    seq0, msgs0, _ = messages["r0"]
    config = exact_config().with_values({"transport.end_grace_s": 0.5})
    replies: list[dict] = []
    holder: list[RobotSession] = []

    def publish(key: str, data: bytes) -> None:
        if key == keys.reply("r0"):
            replies.append({**json.loads(data), "frames": holder[0].state.counts["frames"]})

    session = RobotSession.open("r0", Hello(K, seq0.camera, "test"), config,
                                CloudStore(tmp_path), publish)
    holder.append(session)
    for data in msgs0[:-1]:
        session.submit_frame(data, time.monotonic())
    # The end arrived long ago as far as its arrival time goes (a backlog held it up).
    session.submit_control({"type": "end", "last_seq": N_FRAMES - 1}, time.monotonic() - 10)
    session.drain()
    time.sleep(0.1)
    session.submit_frame(msgs0[-1], time.monotonic())
    deadline = time.monotonic() + 30
    while not any(r["type"] in ("need", "ended") for r in replies):
        assert time.monotonic() < deadline, replies
        time.sleep(0.05)
    session.close()
    assert replies[-1]["frames"] == N_FRAMES


def test_keyframe_uploads_must_be_keyframes_of_the_session_at_the_cameras_size(messages,
                                                                               tmp_path):
    from fleetslam.cloud.session.robot_session import RobotSession
    from fleetslam.cloud.session.store import CloudStore
    from fleetslam.transport.protocol import Hello
    from fleetslam.wire.messages import KeyframeUpload, encode_keyframe

    seq0, msgs0, _ = messages["r0"]
    replies: list[dict] = []
    session = RobotSession.open("r0", Hello(K, seq0.camera, "test"), exact_config(),
                                CloudStore(tmp_path), lambda k, d: replies.append(json.loads(d))
                                if k == keys.reply("r0") else None)
    for data in msgs0:
        session.submit_frame(data, time.monotonic())
    session.drain()
    rows = session.state.rows
    keyframe = next(r.index for r in rows if r.is_keyframe)
    other = next(r.index for r in rows if not r.is_keyframe)
    frame = seq0[other]
    stride = exact_config().map.pixel_stride
    forged = KeyframeUpload.from_frame(other, frame.timestamp, frame.rgb, frame.depth_raw, stride)
    session.submit_keyframe(encode_keyframe("r0", 0, forged, exact_config().wire), time.monotonic())
    time.sleep(0.3)
    assert "is not a keyframe of this session" in replies[-1]["reason"]
    # Said so that the robot stops resending it (its own test: test_robot.py).
    assert replies[-1]["code"] == "not_a_keyframe" and replies[-1]["frame_index"] == other
    time.sleep(1.0)  # one rejection reason per second
    small = KeyframeUpload(keyframe, frame.timestamp, stride, frame.rgb[:10, :10],
                           frame.depth_raw[:10, :10])
    session.submit_keyframe(encode_keyframe("r0", 1, small, exact_config().wire), time.monotonic())
    time.sleep(0.3)
    session.close()
    # Refused before its images are decoded (decode_keyframe knows the camera).
    assert "keyframe colour is 10 x 10, expected 320 x 240" in replies[-1]["reason"]
    assert session.state.counts["rejected keyframe"] == 2
    assert not CloudStore(tmp_path).keyframe_indices("r0")


def test_the_cloud_starts_from_a_labs_zenoh_config_file(tmp_path):
    """A lab's own Zenoh settings (here: the cloud as a Zenoh router) come from a config
    file; robots and clients reach it as before. A file Zenoh cannot read is named."""
    from fleetslam.launch import CloudClient
    from fleetslam.transport.zenoh_session import open_listening

    router = tmp_path / "cloud.json5"
    router.write_text('{ mode: "router", scouting: { multicast: { enabled: false } } }')
    config = exact_config().with_values({"transport.zenoh_config": str(router)})
    endpoint = free_endpoint()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    try:
        client = CloudClient(endpoint, reach_deadline_s=10.0)
        try:
            assert client.status(timeout=10.0)["type"] == "status"
        finally:
            client.close()
    finally:
        server.close()
    broken = tmp_path / "broken.json5"
    broken.write_text("{ mode: ")
    with pytest.raises(ValueError, match="broken.json5: not a Zenoh config file"):
        open_listening(free_endpoint(), str(broken))


def test_a_tls_cloud_refuses_clients_without_the_labs_ca(tmp_path, capsys):
    """`fleetslam certs` makes a lab (and adds robots to it); its cloud speaks mutual TLS:
    the operator with a certificate of the lab is answered; a client without TLS, with
    another lab's certificate, or with the lab's CA but no certificate of its own never
    reaches it; a robot's certificate does not let it ask for the status."""
    from fleetslam.cli import main
    from fleetslam.launch import CloudClient

    lab = tmp_path / "lab"
    assert main(["certs", "--out", str(lab), "--robot", "r1"]) == 0
    assert "robot r1:" in capsys.readouterr().out
    assert main(["certs", "--out", str(lab)]) == 2  # one CA per lab
    assert main(["certs", "--out", str(lab), "--robot", "r1"]) == 2  # r1 is in it
    assert main(["certs", "--out", str(lab), "--robot", "r2"]) == 0  # added with its CA
    assert json.loads((lab / "lab.json").read_text())["robots"] == ["r1", "r2"]
    assert main(["certs", "--out", str(tmp_path / "other")]) == 0
    config = exact_config().with_values({"transport.zenoh_config": str(lab / "cloud.json5")})
    endpoint = free_endpoint().replace("tcp/127.0.0.1", "tls/localhost")
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    try:
        client = CloudClient(endpoint, 10.0, str(lab / "client.json5"))
        try:
            assert client.status(timeout=10.0)["type"] == "status"
        finally:
            client.close()
        client = CloudClient(endpoint, 10.0, str(lab / "robot-r2.json5"))
        try:
            with pytest.raises(TimeoutError):  # the ACL: only the operator asks
                client.status(timeout=2.0)
        finally:
            client.close()
        ca_only = tmp_path / "ca_only.json5"
        ca_only.write_text(json.dumps({"mode": "peer", "transport": {"link": {"tls": {
            "root_ca_certificate": str(lab / "ca.pem")}}}}))
        with pytest.raises(ValueError, match="tls needs a Zenoh config file"):  # no TLS: told
            CloudClient(endpoint, 1.0, None)
        for outsider in (str(tmp_path / "other" / "client.json5"), str(ca_only)):
            with pytest.raises(RuntimeError, match="nothing answers"):
                CloudClient(endpoint, 1.0, outsider)
    finally:
        server.close()


def test_a_robot_can_use_only_its_own_keys(messages, tmp_path):
    """Access control by certificate: r2, authenticated, forges an end, frames and keyframe
    uploads for r1 and listens to r1's poses. None of it reaches the cloud or r2: r1 tracks
    every frame with the poses of a quiet run, and r2 still has its own session."""
    from fleetslam.transport.certs import make_lab

    seq1, r1_msgs, poses1 = messages["r1"]
    lab = make_lab(tmp_path / "lab", ["localhost"], ["r1", "r2"])
    config = exact_config().with_values({"transport.zenoh_config": str(lab["cloud"])})
    endpoint = free_endpoint().replace("tcp/127.0.0.1", "tls/localhost")
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    z1 = open_connecting(endpoint, 10.0, str(lab["r1"]))
    z2 = open_connecting(endpoint, 10.0, str(lab["r2"]))
    overheard: list[str] = []
    spy = z2.declare_subscriber("fleet/**", lambda s: overheard.append(str(s.key_expr)))
    try:
        r1 = FakeRobot(z1, "r1", seq1.camera)
        r1.hello()
        r2 = FakeRobot(z2, "r2", seq1.camera)
        r2.hello()
        for m in r1_msgs:
            put(z2, keys.control("r1"), json.dumps({"type": "end", "last_seq": 0}).encode())
            put(z2, keys.frame("r1"), r1_msgs[-1])
            put(z2, keys.keyframe("r1"), b"FSKF" + bytes(100))
            r1.send(m)
        got = r1.poses(len(r1_msgs))
        assert np.array_equal(np.array([f.T_world_camera for f in got]), poses1)
        counts = server.sessions["r1"].counts()
        assert counts["frames"] == len(r1_msgs) and not any(
            k.startswith("rejected") for k in counts)
        assert server.sessions["r1"].finished is None and server.unrouted == 0
        # (r2's session hears its own forgeries locally; never what the cloud sends r1.)
        assert keys.feedback("r1") not in overheard and keys.reply("r1") not in overheard
        assert keys.reply("r2") in overheard  # the spy works: it hears r2's welcome
        r2.hello()  # r2's own keys still work
        r1.close()
        r2.close()
    finally:
        spy.undeclare()
        z1.close()
        z2.close()
        server.close()


class Relay:
    """A TCP relay on loopback that records every byte both ways: a packet capture's view of
    the link between a client and the cloud."""

    def __init__(self, target_port: int) -> None:
        self.captured = bytearray()
        self.first_bytes = b""
        self._server = socket.socket()
        self._server.bind(("127.0.0.1", 0))
        self._server.listen()
        self.port = self._server.getsockname()[1]
        self._target = target_port
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._server.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self._target))
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, src, dst) -> None:
        while True:
            try:
                data = src.recv(65536)
            except OSError:
                return
            if not data:
                return
            if not self.captured:
                self.first_bytes = data[:8]
            self.captured.extend(data)
            try:
                dst.sendall(data)
            except OSError:
                return

    def close(self) -> None:
        self._server.close()


@pytest.mark.parametrize("secure", [True, False])
def test_the_link_is_encrypted(messages, tmp_path, secure):
    """What a capture on the wire sees: with the lab's TLS, neither the robot's hello (its
    id, its source) nor a frame's header or key appears in the bytes; over plain TCP all of
    them do (so the capture would see them if they were there)."""
    from fleetslam.transport.certs import make_lab

    seq1, msgs1, poses1 = messages["r1"]
    config, robot_config = exact_config(), None
    port = int(free_endpoint().rsplit(":", 1)[1])
    if secure:
        lab = make_lab(tmp_path / "lab", ["localhost"], ["r1"])
        config = config.with_values({"transport.zenoh_config": str(lab["cloud"])})
        robot_config = str(lab["r1"])
    scheme = "tls/localhost" if secure else "tcp/127.0.0.1"
    server = CloudServer(config, tmp_path / "cloud", f"{scheme}:{port}").start()
    relay = Relay(port)
    z = open_connecting(f"{scheme}:{relay.port}", 10.0, robot_config)
    marker = "plaintext-marker-7f3a9c"
    try:
        robot = FakeRobot(z, "r1", seq1.camera)
        hello = {"type": "hello", "protocol": PROTOCOL, "offload_at": K,
                 "camera": seq1.camera.to_dict(), "source": marker}
        put(z, keys.control("r1"), json.dumps(hello).encode())
        robot.reply("welcome")
        robot.send(msgs1[0])
        assert len(robot.poses(1)) == 1
        robot.close()
    finally:
        z.close()
        relay.close()
        server.close()
    wire = bytes(relay.captured)
    seen = [s for s in (marker.encode(), b"fleet/r1", b"FSLM") if s in wire]
    if secure:
        assert relay.first_bytes[:1] == b"\x16" and not seen  # a TLS handshake, then ciphertext
    else:
        assert len(seen) == 3


def test_a_missing_reference_is_refused_and_the_robot_falls_back_to_intra(cloud, scene):
    """Inter-coded frames (wire/inter.py) refer to frames the cloud acknowledged. When the
    cloud lacks one (here its ring is emptied, as a restart empties it), it refuses the frame
    with REFERENCE_MISSING; the robot's encoder then sends an intra frame, and inter-codes
    again once that one is acknowledged. Every frame the cloud takes is tracked exactly."""
    server, client = cloud
    seq = RgbdSequence(scene[0])
    robot = FakeRobot(client, "r0", seq.camera)
    welcome = robot.hello()
    assert welcome["reference_frames"] == exact_config().wire.reference_frames
    config = exact_config()
    encoder = InterEncoder(config.wire, welcome["reference_frames"])
    pipeline = RobotSlam.new(config, seq.camera)
    frames = [CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m) for f in seq]
    kinds, tracked = [], []
    for seq_no, frame in enumerate(frames):
        state = run_stages(pipeline.split(K)[0], frame, pipeline.sides)
        refs = encoder.choose(seq_no)
        data = encode_frame_message(state, K, "r0", seq_no, seq.camera, config.wire, refs)
        encoder.sent(seq_no, reference_of(state), len(refs))
        kinds.append(open_message(data)[0].kind)
        if seq_no == 5:
            server.sessions["r0"].references.clear()
        robot.send(data)
        if seq_no == 5:
            error = robot.reply("error")
            assert error["code"] == Code.REFERENCE_MISSING.value, error
            assert error["seq"] == 5 and error["missing"] and "does not hold" in error["reason"]
            encoder.refused(seq_no + 1)
            continue
        header, fb = decode_feedback(robot.feedback.get(timeout=30))
        assert header.seq == seq_no
        encoder.acked(header.seq)
        tracked.append(fb.T_world_camera)
    assert kinds[0] == Kind.FRAME and kinds[6] == Kind.FRAME  # first, and after the refusal
    assert all(k == Kind.FRAME_INTER for k in kinds[1:6] + kinds[7:]), kinds
    reference = RobotSlam.new(exact_config(), seq.camera)
    expected = [reference.track(f).T_world_camera for i, f in enumerate(frames) if i != 5]
    np.testing.assert_array_equal(np.array(tracked), np.array(expected))
    counts = server.sessions["r0"].state.counts
    assert counts["rejected frame"] == 1 and counts["errors"] == 0
    robot.close()


def test_keyframes_a_live_robot_no_longer_holds_are_mapped_without_images(cloud, messages):
    """A live camera keeps no recording: keyframes the robot cannot upload are named in its
    end message and the session ends without them (never asked for again); its camera's
    counts reach the summary."""
    _, client = cloud
    seq0, msgs0, _ = messages["r0"]
    robot = FakeRobot(client, "r0", seq0.camera)
    robot.hello()
    for data in msgs0:
        robot.send(data)
    keyframes = [fb.frame_index for fb in robot.poses(N_FRAMES) if fb.is_keyframe]
    assert keyframes
    robot.z.put(keys.control("r0"), protocol.encode(protocol.End(N_FRAMES - 1)))
    assert sorted(robot.reply("need", timeout=30.0)["frames"]) == keyframes
    camera = {"source": "replay of test at 30 fps", "delivered": 40, "taken": N_FRAMES,
              "skipped": 40 - N_FRAMES}
    bad = {**protocol.End(N_FRAMES - 1, camera=camera).message(), "unavailable": ["x"]}
    robot.z.put(keys.control("r0"), protocol.encode(bad))
    assert "bad unavailable keyframes" in robot.reply("error")["reason"]
    robot.z.put(keys.control("r0"), protocol.encode(
        protocol.End(N_FRAMES - 1, camera=camera, unavailable=frozenset(keyframes))))
    summary = robot.reply("ended", timeout=60.0)["summary"]
    assert summary["live_camera"] == camera
    assert summary["keyframes_without_images"] == len(keyframes) == summary["keyframes"]
    assert summary["map_points"] == 0
    robot.close()


def test_a_damaged_stored_keyframe_costs_its_images_not_the_robots_end(messages, tmp_path,
                                                                       caplog):
    """A keyframe file damaged on disk after it was acknowledged, read at the end by a
    session without the clouds made as the keyframes came (as a restored one): the session
    still ends (the robot answered 'ended', trajectory and map written), that keyframe left
    out of the dense map with one line naming it."""
    from fleetslam.cloud.session.robot_session import RobotSession
    from fleetslam.cloud.session.store import CloudStore
    from fleetslam.mapping.dense_map import KeyframeClouds
    from fleetslam.transport.protocol import Hello
    from fleetslam.wire.messages import KeyframeUpload, encode_keyframe

    seq0, msgs0, _ = messages["r0"]
    replies: list[dict] = []
    store = CloudStore(tmp_path)
    session = RobotSession.open("r0", Hello(K, seq0.camera, "test"), exact_config(), store,
                                lambda k, d: replies.append(json.loads(d))
                                if k == keys.reply("r0") else None)
    for data in msgs0:
        session.submit_frame(data, time.monotonic())
    session.drain()
    keyframes = [r.index for r in session.state.rows if r.is_keyframe]
    assert len(keyframes) >= 2
    stride = exact_config().map.pixel_stride
    for seq, index in enumerate(keyframes):
        frame = seq0[index]
        upload = KeyframeUpload.from_frame(index, frame.timestamp, frame.rgb, frame.depth_raw,
                                           stride)
        session.submit_keyframe(encode_keyframe("r0", seq, upload, exact_config().wire),
                                time.monotonic())
    deadline = time.monotonic() + 30
    while len(store.keyframe_indices("r0")) < len(keyframes):
        assert time.monotonic() < deadline, replies
        time.sleep(0.05)
    damaged = store.robot_dir("r0") / "keyframes" / f"{keyframes[0]:06d}.fskf"
    damaged.write_bytes(damaged.read_bytes()[:100])  # cut short on disk
    # Each keyframe's cloud is made after its upload is stored and acknowledged.
    while not all(session.outputs.clouds.get(i) is not None for i in keyframes):
        assert time.monotonic() < deadline, "keyframe clouds not made"
        time.sleep(0.05)
    # The keyframes' clouds made as they came are this process's: a session restored by
    # another worker has none, and reads the store at its end.
    session.outputs.clouds = KeyframeClouds(seq0.camera, exact_config().map)
    session.submit_control({"type": "end", "last_seq": N_FRAMES - 1}, time.monotonic())
    deadline = time.monotonic() + 60
    while not any(r["type"] == "ended" for r in replies):
        assert time.monotonic() < deadline, replies
        time.sleep(0.05)
    session.close()
    summary = next(r for r in replies if r["type"] == "ended")["summary"]
    assert summary["frames"] == N_FRAMES and summary["map_points"] > 0
    assert f"robot r0: stored keyframe {keyframes[0]} cannot be read" in caplog.text
    assert str(damaged) in caplog.text


def test_a_merge_names_each_robot_it_leaves_out_unfinished(cloud, messages):
    """r0 ended, r1 still streaming: the merge is r0's, and r1 is in not_merged with why
    (it was left out silently)."""
    server, client = cloud
    robots = {}
    for name in ("r0", "r1"):
        seq, msgs, _ = messages[name]
        robots[name] = FakeRobot(client, name, seq.camera)
        robots[name].hello()
        for data in msgs[:6] if name == "r1" else msgs:
            robots[name].send(data)
    try:
        robots["r1"].poses(6)
        robots["r0"].poses(N_FRAMES)
        robots["r0"].z.put(keys.control("r0"), protocol.encode(protocol.End(N_FRAMES - 1)))
        reply = robots["r0"].reply("need", timeout=30.0)
        robots["r0"].z.put(keys.control("r0"), protocol.encode(
            protocol.End(N_FRAMES - 1, unavailable=frozenset(reply["frames"]))))
        robots["r0"].reply("ended", timeout=60.0)
        summary = server.merge()
    finally:
        for robot in robots.values():
            robot.close()
    merge = summary["merge"]
    assert [r["name"] for r in summary["robots"]] == ["r0"]
    assert merge["not_merged"]["r1"] == ("not finished: its stream has not ended (6 frames "
                                         "tracked so far)")


def test_a_flood_of_status_requests_costs_one_build_per_interval(cloud):
    """Each request is answered with its own id; the answer is built at most every
    STATUS_EVERY_S (it was built for every request)."""
    from fleetslam.cloud.operator_requests import STATUS_EVERY_S

    server, _ = cloud
    before = server.operator.status_builds
    started = time.monotonic()
    answers = [server.operator.status(f"q{i}") for i in range(200)]
    took = time.monotonic() - started
    assert [a.id for a in answers] == [f"q{i}" for i in range(200)]
    assert all(a.robots == answers[0].robots for a in answers)
    assert server.operator.status_builds - before <= 1 + int(took / STATUS_EVERY_S)


def test_a_finished_session_is_never_resumed_a_new_run_is_refused_with_why(tmp_path,
                                                                          messages):
    """A robot id whose session ended: its next hello (a new run under the same id, before
    or after a cloud restart) is refused as ended, saying to use a new id, and nothing of
    the old session changes (it had been resumed past its end: '0 frames sent', exit 0)."""
    endpoint = free_endpoint()
    store = tmp_path / "cloud"
    server = CloudServer(exact_config(), store, endpoint).start()
    client = open_connecting(endpoint)
    seq0, msgs0, _ = messages["r0"]
    robot = FakeRobot(client, "r0", seq0.camera)
    try:
        robot.hello()
        for data in msgs0:
            robot.send(data)
        keyframes = [fb.frame_index for fb in robot.poses(N_FRAMES) if fb.is_keyframe]
        robot.z.put(keys.control("r0"), protocol.encode(
            protocol.End(N_FRAMES - 1, unavailable=frozenset(keyframes))))
        robot.reply("ended", timeout=60.0)
        written = (store / "r0" / "trajectory.tum").read_bytes()
        for restart in (False, True):
            if restart:
                server.close()
                server = CloudServer(exact_config(), store, endpoint).start()
            refusal = None
            for _ in range(40):  # resent until answered: the client reconnects after a restart
                robot.z.put(keys.control("r0"), protocol.encode(
                    Hello(K, seq0.camera, "test").message(N_FRAMES)))
                try:
                    refusal = robot.reply("error", timeout=1.0)
                    break
                except AssertionError:
                    continue
            assert refusal is not None, "no answer to the hello"
            assert (refusal["code"], refusal["answer_to"]) == ("session_ended", "hello")
            assert "never resumed: run the robot under a new --id" in refusal["reason"]
            assert (store / "r0" / "trajectory.tum").read_bytes() == written
    finally:
        robot.close()
        client.close()
        server.close()
