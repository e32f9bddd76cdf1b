"""Live sources run on the camera's clock: the one-frame slot, a recording replayed as a
camera, a RealSense recording played through pyrealsense2's playback device, and a robot
slower than its camera that skips frames, holds one at most and still tracks."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from conftest import HANG_S, SEVEN_SCENES, TUM_RPY, require

from fleetslam.config import Config
from fleetslam.datasets.live import LiveSource, NewestFrame, take_numbered
from fleetslam.datasets.replay import ReplaySource
from fleetslam.datasets.source import Frame
from fleetslam.datasets.recording import open_source


def frame(stamp: float) -> Frame:
    return Frame(99, stamp, np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.uint16),
                 np.zeros((2, 2), np.float32))


def test_the_newest_frame_wins_and_the_overwritten_ones_are_counted():
    slot = NewestFrame()
    for stamp in (1.0, 2.0, 3.0):
        slot.put(frame(stamp))
    assert slot.waiting == 1
    taken = take_numbered(slot, 0.1)
    assert taken.timestamp == 3.0 and taken.index == 0  # indices count taken frames
    assert (slot.delivered, slot.taken, slot.skipped, slot.waiting) == (3, 1, 2, 0)
    slot.put(frame(4.0))
    assert take_numbered(slot, 0.1).index == 1 and slot.skipped == 2


def test_the_slot_times_out_ends_and_passes_the_cameras_error_on():
    slot = NewestFrame()
    start = time.monotonic()
    with pytest.raises(TimeoutError, match="no frame from the camera in 0.1 s"):
        slot.take(0.1)
    assert time.monotonic() - start >= 0.09  # it waited its timeout
    slot.put(frame(1.0))
    slot.close()
    assert slot.take(0.1).timestamp == 1.0  # the last frame is still taken
    assert slot.take(0.1) is None  # then the end
    slot.put(frame(2.0))  # a camera thread still running after the end is ignored
    assert slot.take(0.1) is None and slot.delivered == 1
    broken = NewestFrame()
    threading.Timer(0.05, broken.close, (OSError("USB gone"),)).start()
    with pytest.raises(OSError, match="USB gone"):
        broken.take(5.0)  # a waiting take wakes with the camera's error


def test_a_replay_delivers_on_its_clock_and_a_slow_taker_skips():
    recording = open_source(f"{require(TUM_RPY)}:0-44")  # 45 frames
    # At 15 fps: a frame's colour and depth PNGs decode in well under a period (66 ms) even
    # beside the other test worker; at 30 fps they did not always (12 of 45 late, once).
    fast = ReplaySource(recording, "fr1_rpy", 15.0)
    assert isinstance(fast, LiveSource)
    start, stamps = time.monotonic(), []  # before the camera's clock starts
    fast.start(10.0)
    while (f := fast.take(HANG_S)) is not None:
        stamps.append(f.timestamp)
    elapsed = time.monotonic() - start
    fast.close()
    # Not as fast as it can read: the last frame comes 44 periods after the first. (How many
    # frames were decoded too late or overwritten depends on the machine's load: counted.)
    assert elapsed >= 44 / 15
    assert fast.delivered + fast.late == 45
    assert len(stamps) == fast.delivered - fast.skipped
    assert stamps == sorted(stamps)  # recorded timestamps, kept for evaluation

    slow = ReplaySource(recording, "fr1_rpy", 30.0)
    slow.start(10.0)
    order = {float(stamp): i for i, stamp in enumerate(recording.timestamps)}
    taken = []
    while (f := slow.take(HANG_S)) is not None:
        taken.append(order[f.timestamp])
        # A robot slower than its camera: two more frames come before it takes the next (or
        # the stream ends).
        more = slow.delivered + 2
        while slow.delivered < more and slow.delivered + slow.late < 45:
            time.sleep(0.01)
    slow.close()
    assert slow.skipped == slow.delivered - len(taken)  # every frame taken or overwritten
    assert slow.skipped >= len(taken) - 2 > 0
    # The newest frame each time: two or more recording frames on from the one before.
    assert all(b - a >= 2 for a, b in zip(taken[:-2], taken[1:-1])), taken
    assert slow.waiting == 0


def test_a_replay_at_recorded_timestamps_takes_the_recordings_time():
    recording = open_source(f"{require(TUM_RPY)}:0-29")
    span = float(recording.timestamps[-1] - recording.timestamps[0])
    replay = ReplaySource(recording, "fr1_rpy", None)
    assert "recorded timestamps" in replay.description
    start, n = time.monotonic(), 0  # before the camera's clock starts
    replay.start(10.0)
    while replay.take(HANG_S) is not None:
        n += 1
    replay.close()
    # The recording's span at least (its last frame is due then), not as fast as it reads.
    assert time.monotonic() - start >= span and n + replay.skipped + replay.late == 30


def test_bad_replays_say_what_is_wrong():
    recording = open_source(str(require(TUM_RPY)))
    with pytest.raises(ValueError, match="replay of x: rate -1.0 is not frames per second"):
        ReplaySource(recording, "x", -1.0)


def test_a_realsense_asked_for_without_the_extra_says_which_extra(monkeypatch):
    import sys

    from fleetslam.datasets.live_sources import open_live

    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import raises ImportError
    with pytest.raises(ValueError, match=r"--source realsense: needs the realsense extra: "
                                         r"pip install 'fleetslam\[realsense\]'"):
        open_live("realsense", Config())
    assert open_live(str(TUM_RPY), Config()) is None  # a recording is no live spec
    with pytest.raises(ValueError, match="no such RealSense recording"):
        open_live("realsense:/nonexistent/x.db3", Config())


def test_realsense_lens_models_map_to_opencv_coefficients():
    import cv2

    from fleetslam.camera import Camera
    from fleetslam.datasets.realsense import opencv_distortion

    camera = Camera(615.0, 615.0, 320.0, 240.0)
    coeffs = [0.12, -0.25, 0.001, -0.002, 0.1]
    assert opencv_distortion("brown_conrady", coeffs, camera) == (tuple(coeffs), 0.0)
    assert opencv_distortion("inverse_brown_conrady", [0.0] * 5, camera) == ((), 0.0)
    with pytest.raises(ValueError, match="kannala_brandt4 is not one fleetslam maps"):
        opencv_distortion("kannala_brandt4", coeffs, camera)
    # Inverse Brown-Conrady: the polynomial undistorts. Distorted pixels, undistorted by
    # librealsense's formula, re-distorted by OpenCV with the fitted coefficients.
    inverse = [0.05, -0.02, 0.0005, -0.0004, 0.0]
    fitted, worst_px = opencv_distortion("inverse_brown_conrady", inverse, camera)
    assert worst_px < 0.5
    u, v = np.meshgrid(np.linspace(20, 620, 9), np.linspace(20, 460, 7))
    xd, yd = (u.ravel() - 320.0) / 615.0, (v.ravel() - 240.0) / 615.0
    k1, k2, p1, p2, k3 = inverse
    r2 = xd ** 2 + yd ** 2
    f = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    x = xd * f + 2 * p1 * xd * yd + p2 * (r2 + 2 * xd ** 2)
    y = yd * f + 2 * p2 * xd * yd + p1 * (r2 + 2 * yd ** 2)
    points = np.stack([x, y, np.ones_like(x)], 1)
    uv, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), camera.K, np.array(fitted))
    assert np.abs(uv.reshape(-1, 2) - np.stack([u.ravel(), v.ravel()], 1)).max() < 0.5


@pytest.mark.parametrize("suffix", [".db3", ".bag"])
def test_a_realsense_recording_plays_through_pyrealsense2_as_a_camera(tmp_path, suffix):
    """TUM frames as a RealSense recording (.db3 by librealsense's own recorder from a software
    device; a ROS 1 .bag in librealsense's layout by rosbags), played by pyrealsense2's
    playback device in real time, aligned to colour."""
    pytest.importorskip("pyrealsense2")
    from realsense_recording import write_realsense_recording, write_realsense_ros1_bag

    from fleetslam.datasets.live_sources import open_live

    recording = open_source(f"{require(TUM_RPY)}:0-29")
    frames = [recording[i] for i in range(len(recording))]
    path = tmp_path / f"fr1_rpy{suffix}"
    write = write_realsense_recording if suffix == ".db3" else write_realsense_ros1_bag
    write(path, frames, recording.camera)
    source = open_live(f"realsense:{path}", Config())
    assert isinstance(source, LiveSource)
    span = float(recording.timestamps[-1] - recording.timestamps[0])
    start = time.monotonic()
    source.start(10.0)
    camera = source.camera
    assert (camera.fx, camera.cy, camera.width) == pytest.approx(
        (recording.camera.fx, recording.camera.cy, 640), abs=1e-3)
    assert camera.distortion == pytest.approx(recording.camera.distortion, abs=1e-6)
    assert camera.depth_scale == pytest.approx(5000.0, rel=1e-6)  # 1 / metres per unit
    assert "Brown Conrady" in source.camera_source or "brown_conrady" in source.camera_source
    by_stamp = {round(f.timestamp * 1000): f for f in frames}
    taken = []
    while (f := source.take(5.0)) is not None:
        taken.append(f)
    elapsed = time.monotonic() - start
    source.close()
    # Real time: the recording's span from the playback's start, not as fast as it reads.
    assert elapsed > 0.8 * span, (elapsed, span)
    assert len(taken) + source.skipped == source.delivered >= 25
    assert [f.index for f in taken] == list(range(len(taken)))
    for f in taken:  # each frame as recorded: the same colour, depth and time
        original = by_stamp[round(f.timestamp * 1000)]
        assert np.array_equal(f.rgb, original.rgb)
        # Depth went through rs.align (reprojected into colour by the same intrinsics, lens
        # distortion included): the same readings, a few moved by a pixel.
        valid = original.depth_raw > 0
        assert np.mean(f.depth_raw[valid] == original.depth_raw[valid]) > 0.97


def test_a_robot_slower_than_its_camera_skips_frames_holds_one_and_tracks(tmp_path):
    """150 frames at 30 fps on a robot held back by a 2 Mbit/s link: it takes the newest
    frame each time, counts the rest, never holds more than one, and the cloud still tracks
    (ATE read after the run)."""
    from fleetslam.cloud.server import CloudServer
    from fleetslam.edge.robot import Robot
    from fleetslam.evaluation.fleet import trajectory_ate
    from fleetslam.launch import CloudClient, free_endpoint

    spec = f"{require(SEVEN_SCENES)}:0-149"
    config = Config().with_values({"link.bandwidth_mbps": 2.0})
    endpoint = free_endpoint()
    server = CloudServer(Config(), tmp_path / "cloud", endpoint).start()
    try:
        replay = ReplaySource(open_source(spec), spec, 30.0)
        replay.start(10.0)
        robot = Robot("r1", replay, spec, 3, config, endpoint, show_progress=False)
        held, done = [], threading.Event()

        def watch() -> None:
            while not done.wait(0.05):
                held.append(replay.waiting)

        threading.Thread(target=watch, daemon=True).start()
        report = robot.run()
        done.set()
        client = CloudClient(endpoint, 30.0)
        try:
            summary = client.merge()
        finally:
            client.close()
    finally:
        server.close()
    assert report.camera_skipped > 20 and report.live_source == replay.description
    assert report.camera_taken == report.frames == len(report.frame_cpu_ms)
    # Those the camera delivered while the robot connected are told apart from the pace's.
    assert 0 <= report.camera_skipped_at_start <= report.camera_skipped
    assert report.camera_taken + report.camera_skipped <= replay.delivered <= 150
    # Every frame of the recording is counted: delivered, or never delivered (late).
    assert replay.delivered + replay.undelivered == 150
    assert report.camera_undelivered == replay.undelivered == replay.late
    assert max(held) <= 1  # one waiting frame at most, however far behind
    entry = json.loads((tmp_path / "cloud" / "summary.json").read_text())["robots"][0]
    assert entry["name"] == "r1" and summary["robots"][0]["live_camera"] == entry["live_camera"]
    assert entry["live_camera"]["undelivered"] == replay.late
    assert entry["live_camera"]["skipped"] == report.camera_skipped
    assert entry["live_camera"]["taken"] == report.camera_taken == entry["frames"]
    assert entry["lost_frames"] <= 0.1 * entry["frames"]
    ate = trajectory_ate(tmp_path / "cloud" / "r1" / "trajectory.tum", open_source(spec))
    assert ate is not None and ate["rmse_m"] < 0.1


def test_a_live_robot_keeps_keyframe_uploads_until_acknowledged_and_names_lost_ones():
    """Without a recording to read again: a keyframe's upload stays after it left the frame
    buffer, until the cloud acknowledges it; one the robot never kept (feedback after the
    buffer moved on, a restart) is unavailable at once, never sent, never waited for."""
    from fleetslam.edge.report import RobotReport
    from fleetslam.edge.uploader import KeyframeUploader
    from fleetslam.wire.messages import decode_keyframe

    config = Config().with_values({"transport.keyframe_buffer_frames": 2})
    report = RobotReport("r1", 3)
    uploader = KeyframeUploader("r1", None, 3, config, report)
    sent = []

    def send(key: str, data: bytes) -> bool:
        index = decode_keyframe(data)[1].frame_index
        sent.append(index)
        uploader.acknowledged(index)
        return True

    image = np.zeros((48, 64, 3), np.uint8)
    depth = np.full((48, 64), 1000, np.uint16)
    uploader.keep(Frame(0, 0.0, image, depth, depth / 1000.0), 3)
    uploader.keyframe(0)  # queued; the uploader starts only once the buffer moved on
    for i in range(1, 5):
        uploader.keep(Frame(i, i / 30, image, depth, depth / 1000.0), 3)
    uploader.keyframe(0)  # already queued: once only
    uploader.queue(1)  # fell out of the buffer before its feedback: gone
    uploader.start(send)
    uploader.wait()
    uploader.stop()
    assert sent == [0] and report.acknowledged == [0]
    assert uploader.unavailable == {1} and report.keyframes_unavailable == 1
    assert uploader._pinned == {}  # acknowledged: no longer held


def test_a_resumed_live_robot_numbers_on_and_drops_what_the_session_has():
    """A camera cannot go back to a frame index: after a restart the robot numbers its frames
    on from the cloud's next index and drops frames not after the session's last timestamp
    (a replay restarted from its beginning)."""
    import threading

    from fleetslam.edge.pacing import live_frames
    from fleetslam.edge.report import RobotReport
    from fleetslam.edge.robot import Robot

    recording = open_source(f"{require(TUM_RPY)}:0-29")
    replay = ReplaySource(recording, "fr1_rpy", 30.0)
    replay.start(10.0)
    with pytest.raises(ValueError, match="delivers frames at its own rate"):
        Robot("r2", replay, "fr1_rpy", 3, Config(), rate="30", show_progress=False)
    report = RobotReport("r1", 3)
    # The session's last frame was the recording's 10th; it resumes at index 57.
    frames = list(live_frames(replay, 57, Config().source.live_frame_timeout_s,
                              threading.Event(), report, float(recording.timestamps[9]), "r1"))
    replay.close()
    assert [f.index for f in frames] == list(range(57, 57 + len(frames)))
    assert frames and frames[0].timestamp > recording.timestamps[9]
    assert report.camera_before_resume >= 1
    assert report.camera_taken == len(frames)
    assert report.camera_skipped == replay.skipped
