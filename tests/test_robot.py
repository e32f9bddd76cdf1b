"""The robot's command-line choices: offloading point and pace."""

from __future__ import annotations

import pytest

from fleetslam.edge.pacing import parse_rate
from fleetslam.pipeline.split import parse_offload_point
from fleetslam.transport import keys


def test_offloading_points():
    assert parse_offload_point("paper") == 3
    assert parse_offload_point("match") == 3  # the first stage in the cloud
    assert parse_offload_point("0") == 0
    assert parse_offload_point("6") == 6
    for k in ("4", "5", "estimate_pose"):
        with pytest.raises(ValueError, match="splits the tracking map"):
            parse_offload_point(k)
    for k in ("later", "7", "-1"):  # a clear error, never an IndexError
        with pytest.raises(ValueError, match="give one of 0, 1, 2, 3, 6, 'paper'"):
            parse_offload_point(k)


def test_rates():
    assert parse_rate("max") is None
    assert parse_rate("recorded") == 0.0
    assert parse_rate("12.5") == 12.5
    for bad in ("0", "-3", "fast"):
        with pytest.raises(ValueError, match="frames per second"):
            parse_rate(bad)


def test_robot_ids_are_one_key_chunk():
    assert keys.frame("r-1_a") == "fleet/r-1_a/frame"
    assert keys.robot_of("fleet/r7/keyframe") == "r7"
    for bad in ("a/b", "", "x" * 65, "cloud", "r 1", "r*"):
        with pytest.raises(ValueError):
            keys.check_robot_id(bad)
    with pytest.raises(ValueError):
        keys.robot_of("other/r1/frame")


def test_a_robot_with_no_cloud_says_so_and_gives_up_at_its_deadline(caplog):
    from fleetslam.launch import free_endpoint
    from fleetslam.transport.zenoh_session import wait_until_reachable

    endpoint = free_endpoint()
    with pytest.raises(RuntimeError, match="nothing answers at .* is the cloud running"):
        wait_until_reachable(endpoint, deadline_s=1.5, attempt_s=0.5)
    assert "retrying" in caplog.text


def test_a_robot_with_no_cloud_says_so_first_naming_its_wait_and_no_faiss_lines(tmp_path):
    """A robot may start before its cloud: its first line says none answers yet and how long
    it keeps trying, by the setting's name. A robot that tracks itself (point 6) has loaded
    faiss by then, whose loader's INFO lines (7 of them) are not shown."""
    import subprocess
    import sys

    from conftest import TUM_RPY, require

    from fleetslam.launch import free_endpoint

    config = tmp_path / "short.toml"
    config.write_text("[transport]\nreach_deadline_s = 1.0\n")
    endpoint = free_endpoint()
    result = subprocess.run(
        [sys.executable, "-m", "fleetslam.cli", "--config", str(config), "robot", "--connect",
         endpoint, "--id", "r1", "--source", f"{require(TUM_RPY)}:0-9", "--offload-at", "6"],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.splitlines()
    assert lines[0].endswith(
        f"WARNING no cloud answers at {endpoint} yet; retrying for up to 1 s "
        f"(transport.reach_deadline_s): nothing listens at {endpoint.partition('/')[2]} "
        f"(connection refused): is the cloud running, and is this its endpoint (--connect)?"
    ), result.stderr
    assert lines[-1].startswith(f"fleetslam: error: nothing answers at {endpoint} after ")
    assert "faiss" not in result.stderr


def test_an_upload_the_cloud_no_longer_needs_is_not_resent(tmp_path_factory):
    """A cloud restarted from a checkpoint older than a keyframe's feedback lost that
    keyframe: it says so (not_a_keyframe) and the robot's upload ends there instead of being
    resent until the robot gives up."""

    from conftest import small_scene

    from fleetslam.config import Config
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot
    from fleetslam.transport import protocol

    folder = small_scene(tmp_path_factory, 2)[0]
    robot = Robot("r1", RgbdSequence(folder), str(folder), 3, Config(), show_progress=False)
    robot.uploader.queue(14)

    def reply(message: protocol.Reply) -> None:
        robot.replies.take(protocol.encode(message))

    reply(protocol.Error.of(protocol.Code.REJECTED, "keyframe rejected: too big",
                            frame_index=14))
    assert not robot.uploader.settled(14)  # another reason: resending may help
    reply(protocol.Error.of(protocol.Code.NOT_A_KEYFRAME, "keyframe rejected: frame 14 is "
                            "not a keyframe of this session", frame_index=14))
    assert robot.uploader.settled(14) and robot.report.uploads_not_needed == 1


def test_a_robot_ahead_of_its_cloud_waits_for_feedback_then_goes_on(tmp_path_factory):
    """Flow control: with transport.max_frames_in_flight frames unanswered the robot waits;
    feedback for a frame frees it and every older frame (feedback comes in order, so those
    were lost); a cloud that does not answer at all holds it up at most in_flight_wait_s."""
    import threading
    import time

    import numpy as np
    from conftest import small_scene

    from fleetslam.config import Config
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot
    from fleetslam.wire.messages import Feedback, encode_feedback

    folder = small_scene(tmp_path_factory, 2)[0]
    config = Config().with_values({"transport.max_frames_in_flight": 4,
                                   "transport.in_flight_wait_s": 30.0})
    robot = Robot("r1", RgbdSequence(folder), str(folder), 3, config, show_progress=False)
    for seq in range(4):
        robot.window.sent(seq)
    waiter = threading.Thread(target=robot.window.wait_for_room)
    waiter.start()
    time.sleep(0.3)
    assert waiter.is_alive()  # 4 in flight: the next frame waits
    data = encode_feedback("r1", 2, Feedback(2, 0.0, True, False, 100, np.eye(4), 5.0))
    robot.take_feedback(data)
    waiter.join(5)
    assert not waiter.is_alive() and robot.window.in_flight() == [3]
    assert robot.report.flow_timeouts == 0

    # Now the cloud goes silent, and the robot waits for it less.
    robot.window.config = config.with_values({"transport.in_flight_wait_s": 0.2})
    for seq in range(4, 7):
        robot.window.sent(seq)
    start = time.monotonic()
    assert not robot.window.wait_for_room()  # the robot then says hello again
    assert time.monotonic() - start >= 0.2  # it waited in_flight_wait_s, then gave up
    assert robot.report.flow_timeouts == 1 and len(robot.window.in_flight()) < 4


def test_the_robot_says_hello_again_on_the_no_session_code_not_on_words(tmp_path_factory):
    """The cloud's error code, not its wording, makes the robot say hello again."""

    from conftest import small_scene

    from fleetslam.config import Config
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot
    from fleetslam.transport import protocol

    folder = small_scene(tmp_path_factory, 2)[0]
    robot = Robot("r1", RgbdSequence(folder), str(folder), 3, Config(), show_progress=False)

    def reply(message: protocol.Reply) -> None:
        robot.replies.take(protocol.encode(message))

    reply(protocol.Error.of(protocol.Code.REJECTED, "frame rejected: send a hello, or not"))
    assert not robot.replies.need_hello.is_set()
    reply(protocol.Error.of(protocol.Code.NO_SESSION, "frame rejected: no session"))
    assert robot.replies.need_hello.is_set()
    # Both reached whoever awaits a reply (a hello fails on an error).
    assert [robot.replies.await_reply((protocol.Error,), 1.0).code for _ in range(2)] == \
        ["rejected", "no_session"]


def test_a_robot_whose_end_is_refused_says_why_at_once(tmp_path_factory):
    """The cloud refuses an end before any frame (nothing to write): the robot reports the
    cloud's reason at once instead of waiting END_TIMEOUT_S for an 'ended'."""
    import threading
    from types import SimpleNamespace

    from conftest import small_scene

    from fleetslam.config import Config
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot
    from fleetslam.transport import protocol

    folder = small_scene(tmp_path_factory, 2)[0]
    robot = Robot("r1", RgbdSequence(folder), str(folder), 3, Config(), show_progress=False)

    def reply(message: protocol.Reply) -> None:
        robot.replies.take(protocol.encode(message))

    def control(message: dict) -> None:  # the cloud's answers to the robot's end
        reply(protocol.Ending())
        reply(protocol.Error.of(protocol.Code.REFUSED, "nothing to end: no frame tracked",
                                answer_to="end"))

    robot.sender = SimpleNamespace(control=control)
    raised: list[BaseException] = []

    def finish() -> None:
        try:
            robot.end_session(-1)
        except BaseException as exc:  # noqa: BLE001 (what the robot raises is the test)
            raised.append(exc)

    thread = threading.Thread(target=finish, daemon=True)
    thread.start()
    thread.join(5.0)  # not END_TIMEOUT_S
    assert not thread.is_alive(), "the robot still waits for an answer to its end"
    assert isinstance(raised[0], RuntimeError)
    assert "refused its end: nothing to end" in str(raised[0])


def test_a_session_the_cloud_lost_mid_run_is_said_and_reported(tmp_path,
                                                                  synthetic_scene):
    """A cloud replaced mid-run by one that never had the robot's session (a restart on an
    empty store): the robot's report and exit status say what the cloud kept (it had said
    "N frames sent" and exited 0)."""
    import threading
    import time

    from fleetslam.cloud.server import CloudServer
    from fleetslam.config import Config
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot
    from fleetslam.launch import free_endpoint

    _, folders = synthetic_scene
    endpoint = free_endpoint()
    config = Config()
    server = CloudServer(config, tmp_path / "first", endpoint).start()
    robot = Robot("r0", RgbdSequence(folders[0]), str(folders[0]), 3, config, endpoint,
                  rate="10", show_progress=False)
    reports: list = []
    thread = threading.Thread(target=lambda: reports.append(robot.run()), daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 60
        while robot.report.feedback < 8:
            assert time.monotonic() < deadline and thread.is_alive()
            time.sleep(0.05)
        server.close()
        server = CloudServer(config, tmp_path / "second", endpoint).start()
        thread.join(180)
    finally:
        server.close()
    assert not thread.is_alive() and reports
    report = reports[0]
    assert any("no longer had this robot's session" in why for why in report.incomplete)
    assert report.cloud_frames is not None
    assert report.cloud_frames < report.first_index + report.frames
    assert any(f"holds {report.cloud_frames} of the" in why for why in report.incomplete)


def test_the_robot_reports_its_cpu_time_for_every_frame_it_sends(tmp_path, synthetic_scene):
    """bench/robot_cpu.py reads each frame's CPU time (stages and encoding) from the report:
    one value per frame sent, in order, and the process's CPU while it streamed."""
    from fleetslam.cloud.server import CloudServer
    from fleetslam.config import Config
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot
    from fleetslam.launch import free_endpoint

    _, folders = synthetic_scene
    endpoint = free_endpoint()
    config = Config()
    server = CloudServer(config, tmp_path / "cloud", endpoint).start()
    try:
        robot = Robot("r0", RgbdSequence(folders[0]), str(folders[0]), 3, config, endpoint,
                      show_progress=False)
        report = robot.run()
    finally:
        server.close()
    assert report.frames == 30
    assert len(report.frame_cpu_ms) == report.frames
    assert all(ms > 0 for ms in report.frame_cpu_ms)
    # Each frame's CPU is part of its stages' and encoding's wall time (the robot's total).
    assert sum(report.frame_cpu_ms) / 1000 <= report.robot_compute_s * 1.05 + 0.01
    assert report.streaming_cpu_s >= sum(report.frame_cpu_ms) / 1000 * 0.95


def test_the_inter_coders_search_is_warmed_up_before_the_stream(monkeypatch):
    """A robot that inter-codes its frames (points 2-5, or an adaptive robot) pays the
    search's imports up front (`fleetslam robot` does so before its camera starts), so its
    first inter-coded frame does not; one that cannot inter-code warms up nothing."""
    from fleetslam.config import Config
    from fleetslam.edge import encoder

    calls: list[int] = []
    monkeypatch.setattr(encoder, "warm_up", lambda: calls.append(1))
    config = Config()
    for point in (2, 3, None):
        encoder.prepare(config, point)
    assert len(calls) == 3
    for point in (0, 1, 6):
        encoder.prepare(config, point)
    encoder.prepare(config.with_values({"wire.inter_frame": False}), 3)
    assert len(calls) == 3
