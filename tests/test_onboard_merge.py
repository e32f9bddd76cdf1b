"""A robot that tracks itself (point 6) joins the global map: each keyframe's message carries
its features and the robot's keyframe poses (wire/frames.py), checked on the cloud, kept in
the session's checkpoint and handed to the merger once that checkpoint is on disk."""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from conftest import SEVEN_SCENES, exact_config, require, tracked_by_itself

from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.cloud.server import CloudServer
from fleetslam.cloud.session.memory_budget import held_bytes
from fleetslam.cloud.session.robot_session import RobotSession
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.datasets.recording import open_source
from fleetslam.edge.robot import Robot
from fleetslam.launch import free_endpoint
from fleetslam.pipeline.states import TrackedFrame
from fleetslam.transport.protocol import Hello
from fleetslam.wire.envelope import Kind, WireError, seal
from fleetslam.wire.frames import decode_frame_message, encode_frame_message, encode_state

N_FRAMES = 30
ROBOT = "r0"


@pytest.fixture(scope="module")
def tracked():
    """The camera and the tracked frames of a robot tracking redkitchen 0-29 by itself."""
    return tracked_by_itself(N_FRAMES - 1, 3)


def _message(camera, state: TrackedFrame, seq: int) -> bytes:
    return encode_frame_message(state, 6, ROBOT, seq, camera, exact_config().wire)


@pytest.mark.realdata
def test_a_keyframe_carries_its_features_and_the_keyframe_poses(tracked):
    camera, frames = tracked
    sizes = {True: [], False: []}
    for seq, state in enumerate(frames):
        data = _message(camera, state, seq)
        _, decoded = decode_frame_message(data, camera)
        sizes[state.is_keyframe].append(len(data))
        if not state.is_keyframe:  # only keyframes carry features: bytes stay small
            assert decoded.features is None and decoded.keyframe_poses is None
            continue
        sent = state.posed.matched.features
        # The session's memory budget charges a keyframe's features too.
        assert held_bytes(decoded) > sent.descriptors.nbytes + sent.keypoints.nbytes
        assert decoded.reference_keyframe == len(state.keyframe_poses) - 1
        np.testing.assert_array_equal(decoded.keyframe_poses, state.keyframe_poses)
        assert decoded.features.descriptors.tobytes() == sent.descriptors.tobytes()
        assert decoded.features.depth.tobytes() == sent.depth.tobytes()
        assert decoded.features.uv.tobytes() == sent.uv.tobytes()
        # x, y, size, octave, class id exact (angle quantised, response dropped, as at k=3)
        exact = [0, 1, 2, 5, 6]
        assert decoded.features.keypoints[:, exact].tobytes() == \
            sent.keypoints[:, exact].tobytes()
    assert max(sizes[False]) < 400 < 10_000 < min(sizes[True])


def _payload(camera, state: TrackedFrame) -> bytearray:
    return bytearray(encode_state(state, 6, camera, exact_config().wire))


def _sealed(payload: bytes, state: TrackedFrame) -> bytes:
    return seal(Kind.FRAME, ROBOT, 1, state.timestamp, 6, bytes(payload), compress=False)


@pytest.mark.realdata
def test_a_malformed_keyframe_message_is_rejected_with_the_reason(tracked):
    camera, frames = tracked
    state = next(t for t in frames[1:] if t.is_keyframe)
    # Payload: camera digest, index, timestamp (20 bytes), pose (128), tracked, keyframe.
    keyframe_flag = 20 + 128 + 1
    reference = keyframe_flag + 1 + 4
    not_a_keyframe = _payload(camera, state)
    not_a_keyframe[keyframe_flag] = 0
    other_reference = _payload(camera, state)
    other_reference[reference] -= 1
    bent = state.keyframe_poses.copy()
    bent[0, :3, :3] *= 1.1
    nan_depth = replace(state.posed.matched.features,
                        depth=np.full_like(state.posed.matched.features.depth, np.nan))
    cases = {
        "no keyframe": (_sealed(not_a_keyframe, state), "on a frame that is no keyframe"),
        "reference": (_sealed(other_reference, state), "keyframe poses, but keyframe"),
        "bent pose": (_message(camera, replace(state, keyframe_poses=bent), 1),
                      "not all rigid transforms"),
        "NaN depth": (_message(camera, replace(state, posed=replace(
            state.posed, matched=replace(state.posed.matched, features=nan_depth))), 1),
                      "keypoint depths outside"),
    }
    for name, (data, reason) in cases.items():
        with pytest.raises(WireError, match=reason):
            decode_frame_message(data, camera)


@pytest.mark.realdata
def test_the_session_keeps_each_keyframe_and_hands_it_on_after_its_checkpoint(tracked,
                                                                             tmp_path):
    """The keyframes a point-6 robot sends reach the merger in order, each once the
    checkpoint holding it is on disk; a keyframe that does not follow the last one is
    rejected for this robot only; a restored session has them all."""
    camera, frames = tracked
    store = CloudStore(tmp_path)
    seen = []

    def sink(summary, poses) -> None:
        on_disk = store.load_checkpoint(ROBOT)
        seen.append((summary.keyframe, summary.frame_index, len(poses),
                     len(on_disk.robot_keyframes) if on_disk else 0))

    session = RobotSession.open(ROBOT, Hello(6, camera, "test"), exact_config(), store,
                                lambda k, d: None, sink)
    keyframes = [t for t in frames if t.is_keyframe]
    try:
        for seq, state in enumerate(frames):
            session.submit_frame(_message(camera, state, seq), time.monotonic())
        # A later keyframe naming an old keyframe id is refused with the reason.
        last = frames[-1]
        old = replace(last, is_keyframe=True, reference_keyframe=0,
                      keyframe_poses=last.keyframe_poses if last.is_keyframe
                      else keyframes[0].keyframe_poses[:1])
        old = replace(old, posed=replace(old.posed, matched=replace(
            old.posed.matched, features=replace(old.posed.matched.features,
                                                index=last.index + 1,
                                                timestamp=last.timestamp + 1))))
        session.submit_frame(_message(camera, old, len(frames)), time.monotonic())
        session.drain()
    finally:
        session.close()
    assert session.counts()["rejected frame"] == 1
    assert [s[:3] for s in seen] == [(i, t.index, i + 1) for i, t in enumerate(keyframes)]
    assert all(on_disk > kf for kf, _, _, on_disk in seen)
    restored = RobotSession(store.load_checkpoint(ROBOT), exact_config(), store,
                            lambda k, d: None)
    assert [kf.frame_index for kf in restored.keyframes.all()] == \
        [t.index for t in keyframes]
    np.testing.assert_array_equal(restored.keyframes.poses(), keyframes[-1].keyframe_poses)


def _run_robot(robot: Robot, errors: list) -> None:
    try:
        robot.run()
    except Exception as exc:  # noqa: BLE001 - the test reports it
        errors.append(exc)


@pytest.mark.realdata
@pytest.mark.parametrize("points", [(6, 6), (6, 3)])
def test_robots_that_track_themselves_are_merged(tmp_path, points):
    """Two robots on redkitchen 0-59 and 30-89 (they share places), at point 6 (or one at
    6, one at 3), through a real cloud over Zenoh: both are in the global map."""
    folder = require(SEVEN_SCENES)
    endpoint = free_endpoint()
    server = CloudServer(exact_config(), tmp_path / "cloud", endpoint).start()
    try:
        robots, errors = [], []
        for i, (span, k) in enumerate(zip(("0-59", "30-89"), points)):
            sequence = open_source(f"{folder}:{span}")
            config = Config()
            onboard = RobotSlam.new(config, sequence.camera) if k == 6 else None
            robots.append(Robot(f"r{i}", sequence, span, k, config, endpoint,
                                show_progress=False, onboard=onboard))
        threads = [threading.Thread(target=_run_robot, args=(r, errors)) for r in robots]
        for t in threads:
            t.start()
        for t in threads:
            t.join(300)
        assert not errors
        merge = server.merge()["merge"]
    finally:
        server.close()
    # Past its first, each keyframe's poses went as a delta (wire/pose_deltas.py), and the
    # merge below holds them.
    for robot, k in zip(robots, points):
        if k == 6:
            coded = robot.report.inter_coding
            assert coded["pose_tables_delta"] >= 2, coded
            assert coded["keyframe_poses_sent"] < coded["keyframe_poses_in_tables"], coded
    assert merge["members"] == ["r0", "r1"] and merge["not_merged"] == {}
    assert merge["robots"]["r0"]["keyframes"] >= 3 and merge["robots"]["r1"]["keyframes"] >= 3


@pytest.mark.realdata
def test_a_keyframe_lost_on_the_link_leaves_no_gap_in_the_merger(tracked, tmp_path):
    """The merger numbers a robot's keyframes 0, 1, ... as they come: a keyframe message
    lost on the link is left out, and the frames that refer to it (by the robot's own id)
    are placed with the robot's map frame, the later ones by their renumbered keyframes."""
    camera, frames = tracked
    keyframes = [i for i, t in enumerate(frames) if t.is_keyframe]
    lost = keyframes[1]
    session = RobotSession.open(ROBOT, Hello(6, camera, "test"), exact_config(),
                                CloudStore(tmp_path), lambda k, d: None)
    try:
        for seq, state in enumerate(frames):
            if seq != lost:
                session.submit_frame(_message(camera, state, seq), time.monotonic())
        session.drain()
    finally:
        session.close()
    kept = [i for i in keyframes if i != lost]
    assert [kf.frame_index for kf in session.keyframes.all()] == kept
    assert [kf.keyframe for kf in session.keyframes.all()] == list(range(len(kept)))
    robot_ids = [frames[i].reference_keyframe for i in kept]
    np.testing.assert_array_equal(session.keyframes.poses(),
                                  frames[kept[-1]].keyframe_poses[robot_ids])
    rows = [t for i, t in enumerate(frames) if i != lost]
    expected = [-1 if t.reference_keyframe == 1 else
                t.reference_keyframe - (t.reference_keyframe > 1) for t in rows]
    track = session.outputs.track(np.array([t.timestamp for t in rows]))
    assert track.references.tolist() == expected
