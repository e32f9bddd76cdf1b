"""Point 6's keyframe poses as deltas (wire/pose_deltas.py): whatever the link loses and
however late the feedback comes, every table the cloud applies is the robot's table of that
message, bit for bit; a delta on a base the cloud did not apply is refused and the robot
sends its table whole; on real frames the session ends with the poses whole tables give."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest
from conftest import exact_config, tracked_by_itself
from scipy.spatial.transform import Rotation

from fleetslam.cloud.session.robot_session import RobotSession
from fleetslam.cloud.session.store import CloudStore
from fleetslam.transport.protocol import Hello
from fleetslam.wire.binary import Reader, Writer
from fleetslam.wire.envelope import WireError
from fleetslam.wire.frames import _get_pose_delta, decode_frame_message, encode_frame_message
from fleetslam.wire.pose_deltas import PoseDelta, PoseDeltaEncoder, PoseTable

ROBOT = "r0"


def _pose(rng: np.random.Generator) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T[:3, 3] = rng.normal(size=3)
    return T


def test_every_applied_table_is_the_robots_whatever_is_lost_or_late():
    """A robot adds a keyframe a message and moves a few recent poses (sometimes one back to
    an earlier value exactly); the link loses 20 % of messages and of feedback, feedback comes
    up to 5 messages late; the cloud restarts twice (its table gone)."""
    rng = np.random.default_rng(3)
    robot, cloud = PoseDeltaEncoder(), PoseTable()
    robot.restart(enabled=True)
    table = np.zeros((0, 4, 4))
    history: dict[int, np.ndarray] = {}
    feedback: list[tuple[int, int]] = []  # (due at message, seq)
    applied = refused = 0
    for seq in range(400):
        table = np.concatenate([table, _pose(rng)[None]])
        for i in rng.choice(len(table), size=min(len(table), 4), replace=False):
            if rng.random() < 0.1 and seq - 3 in history and i < len(history[seq - 3]):
                table[i] = history[seq - 3][i]  # back to what it was three messages ago
            elif i >= len(table) - 10:
                table[i] = _pose(rng)
        history[seq] = table.copy()
        delta = robot.choose(table)
        robot.sent(seq, table, delta)
        if seq in (150, 290):
            cloud = PoseTable()  # restored from a checkpoint: no table
            if seq == 290:
                robot.lost()  # told at once (a takeover's welcome); at 150 by refusals only
        if rng.random() < 0.2:
            continue  # lost on the link
        if delta is None:
            got = cloud.whole(seq, table)
        elif cloud.refusal(delta) is not None:
            refused += 1
            robot.lost()  # reference_missing
            continue
        else:
            got = cloud.apply(seq, delta)
        applied += 1
        assert got.tobytes() == history[seq].tobytes(), seq
        if rng.random() < 0.8:
            feedback.append((seq + int(rng.integers(0, 6)), seq))
        for item in [f for f in feedback if f[0] <= seq]:
            feedback.remove(item)
            robot.tracked(item[1])
    assert applied > 250 and 1 <= refused <= 5
    counts = robot.counts
    assert counts.delta_tables > 300 and counts.whole_tables >= 3
    # 400 keyframes, each moving 4 poses: deltas carry a few percent of the whole tables.
    assert counts.poses_sent < 0.1 * counts.poses_in_tables


def test_a_delta_the_cloud_cannot_apply_is_refused_with_why():
    rng = np.random.default_rng(4)
    table = np.stack([_pose(rng) for _ in range(5)])
    cloud = PoseTable()
    assert "holds no table" in cloud.refusal(PoseDelta(3, 6, np.array([5]), table[:1]))
    cloud.whole(10, table)
    assert "did not apply" in cloud.refusal(PoseDelta(9, 6, np.array([5]), table[:1]))
    assert "did not apply" in cloud.refusal(PoseDelta(11, 6, np.array([5]), table[:1]))
    assert "the session holds 5" in cloud.refusal(PoseDelta(10, 4, np.array([3]), table[:1]))
    assert "are new" in cloud.refusal(PoseDelta(10, 7, np.array([6]), table[:1]))
    assert cloud.refusal(PoseDelta(10, 7, np.array([2, 5, 6]), table[:3])) is None
    # A robot whose welcome did not offer deltas (an older cloud) sends whole tables.
    robot = PoseDeltaEncoder()
    robot.restart(enabled=False)
    robot.sent(0, table, None)
    robot.tracked(0)
    assert robot.choose(table) is None


@pytest.fixture(scope="module")
def tracked():
    """The camera and the tracked frames of a robot tracking redkitchen 0-59 by itself."""
    return tracked_by_itself(59, 5)


@pytest.mark.realdata
def test_a_delta_on_the_wire_decodes_exactly_and_a_bad_one_is_rejected(tracked):
    camera, frames = tracked
    keyframes = [t for t in frames if t.is_keyframe]
    state = keyframes[-1]
    table = np.asarray(state.keyframe_poses)
    ids = np.array([0, len(table) - 1])
    data = encode_frame_message(state, 6, ROBOT, 9, camera, exact_config().wire,
                                pose_delta=PoseDelta(4, len(table), ids, table[ids]))
    _, decoded = decode_frame_message(data, camera)
    assert decoded.keyframe_poses is None and decoded.pose_delta.base_seq == 4
    assert decoded.pose_delta.ids.tolist() == ids.tolist()
    assert decoded.pose_delta.poses.tobytes() == table[ids].tobytes()
    whole = encode_frame_message(state, 6, ROBOT, 9, camera, exact_config().wire)
    assert len(data) < len(whole)
    with pytest.raises(ValueError, match="the newest not among its rows"):
        encode_frame_message(state, 6, ROBOT, 9, camera, exact_config().wire,
                             pose_delta=PoseDelta(4, len(table), ids[:1], table[:1]))


@pytest.mark.realdata
def test_a_session_fed_deltas_ends_with_the_poses_whole_tables_give(tracked, tmp_path):
    """One robot's 60 frames into a real session twice: whole tables, then deltas (with the
    feedback the session's tracking gives, two keyframe messages lost on the link, and once
    a delta whose base the session never had, after which the robot sends its table whole):
    the same keyframes, less those, at the same poses."""
    camera, frames = tracked
    keyframe_seqs = [seq for seq, t in enumerate(frames) if t.is_keyframe]
    lost = {keyframe_seqs[2], keyframe_seqs[3]}
    bad_base = keyframe_seqs[-2]
    results = []
    for use_deltas in (False, True):
        store = CloudStore(tmp_path / str(use_deltas))
        session = RobotSession.open(ROBOT, Hello(6, camera, "test"), exact_config(), store,
                                    lambda k, d: None)
        robot = PoseDeltaEncoder()
        robot.restart(enabled=use_deltas)
        try:
            for seq, state in enumerate(frames):
                delta = None
                if state.sends_keyframe:
                    table = np.asarray(state.keyframe_poses)
                    delta = robot.choose(table)
                    if use_deltas and seq == bad_base:
                        assert delta is not None
                        delta = replace(delta, base_seq=seq + 1000)  # no message of it
                    robot.sent(seq, table, delta)
                if use_deltas and seq in lost:
                    continue
                rejected = session.counts().get("rejected frame", 0)
                session.submit_frame(encode_frame_message(
                    state, 6, ROBOT, seq, camera, exact_config().wire, pose_delta=delta),
                    time.monotonic())
                session.drain()
                if session.state.last_seq == seq:
                    robot.tracked(seq)  # its feedback
                elif session.counts().get("rejected frame", 0) > rejected:
                    robot.lost()  # reference_missing
            results.append((session.keyframes.poses().copy(),
                            [kf.frame_index for kf in session.keyframes.all()],
                            session.counts().get("rejected frame", 0)))
        finally:
            session.close()
    (poses_whole, kfs_whole, rejected_whole), (poses_delta, kfs_delta, rejected_delta) = results
    assert rejected_whole == 0 and rejected_delta == 1 and robot.counts.delta_tables >= 2
    missing = {frames[s].index for s in lost | {bad_base}}
    keep = [i for i, f in enumerate(kfs_whole) if f not in missing]
    assert kfs_delta == [kfs_whole[i] for i in keep]
    # The last message's table (whole, after the refusal) placed every keyframe.
    assert poses_delta.tobytes() == poses_whole[keep].tobytes()


def test_a_malformed_pose_delta_is_rejected_with_the_reason():
    w = Writer()
    w.pack("qI", 3, 4)
    w.bits(np.array([True, False, True, False]))
    with pytest.raises(WireError, match="without the newest keyframe"):
        _get_pose_delta(Reader(w.getvalue(), "test"), 3)
    w = Writer()
    w.pack("qI", -1, 4)
    with pytest.raises(WireError, match="coded against message -1"):
        _get_pose_delta(Reader(w.getvalue(), "test"), 3)
    w = Writer()
    w.pack("qI", 3, 5)
    with pytest.raises(WireError, match="5 keyframe poses, but keyframe 3"):
        _get_pose_delta(Reader(w.getvalue(), "test"), 3)
