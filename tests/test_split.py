"""The central invariant: running stages[:k] on the robot, sending the state at k as a frame
message (wire/frames.py), then stages[k:] in the cloud gives exactly the poses of the unsplit
pipeline, for every offloading point k.

Robot and cloud are built as the two processes build them: the robot (edge/robot.Robot, no
network) holds only the state of the stages it runs, the cloud builds its own back-end (and a
front end where it runs front-end stages) from the robot's hello (as
cloud/session/robot_session.py); nothing passes between them but the hello, the welcome's
reference-ring size, the frame messages and the cloud's acknowledgements."""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import SEVEN_SCENES, require
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.edge.robot import Robot
from fleetslam.pipeline.split import (
    INTER_POINTS,
    ROBOT_TRACKS,
    SUPPORTED_POINTS,
    Sides,
    parse_offload_point,
    run_stages,
)
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.transport.protocol import Hello, Welcome
from fleetslam.wire.frames import decode_frame_message, encode_frame_message
from fleetslam.wire.inter import InterEncoder, ReferenceRing, reference_of

N_FRAMES = 20
ROBOT = "r0"
# The points no robot offloads at: the tracking map would be on both sides.
MAP_SPLITTING_POINTS = (4, 5)


@pytest.fixture(scope="module")
def frames():
    seq = RgbdSequence(require(SEVEN_SCENES), last=N_FRAMES - 1)
    captured = [CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m) for f in seq]
    return seq, captured


@pytest.fixture(scope="module")
def expected(frames):
    """Poses and keyframe decisions of the whole pipeline in one process."""
    sequence, captured = frames
    reference = RobotSlam.new(Config(), sequence.camera)
    assert len(reference.stages) == 6
    out = [reference.track(f) for f in captured]
    poses = np.array([t.T_world_camera for t in out])
    # Sanity: the reference actually tracked motion and made keyframes after the first.
    assert np.linalg.norm(poses[-1][:3, 3]) > 0.01
    assert sum(t.is_keyframe for t in out) >= 2
    return poses, [t.is_keyframe for t in out]


class RobotSide:
    """A robot offloading at ``k`` (edge/robot.Robot, no network): the stages it runs, the
    state they read and nothing else, and its inter-frame encoder."""

    def __init__(self, sequence: RgbdSequence, k: int) -> None:
        config = Config()
        # At point 6 the robot tracks by itself: the command line gives it the pipeline.
        onboard = RobotSlam.new(config, sequence.camera) if k == ROBOT_TRACKS else None
        self.robot = Robot(ROBOT, sequence, "test", k, config, show_progress=False,
                           onboard=onboard)
        self.k, self.camera = k, sequence.camera

    @property
    def sides(self) -> Sides:
        return self.robot.encoder.sides

    def hello(self) -> bytes:
        return json.dumps(Hello(self.k, self.camera, "test").message(N_FRAMES)).encode()

    def welcomed(self, reference_frames: int) -> None:
        """The cloud's welcome: how many frames it keeps to decode inter-coded ones."""
        self.robot.encoder.restart(Welcome(False, 0, 0, 0, reference_frames))

    def frame_message(self, frame: CapturedFrame, seq: int) -> bytes:
        """What the robot sends for a frame (its stages, then the message)."""
        return self.robot.encoder.encode(frame, self.k, seq)


class CloudSide:
    """The cloud's session for that robot, built from its hello alone (as
    cloud/session/robot_session.py): its own config, its own back-end, a front end only if it runs
    front-end stages, and the ring of frames inter-coded ones refer to."""

    def __init__(self, hello: bytes) -> None:
        self.hello = Hello.parse(json.loads(hello))
        self.config = Config()
        camera = self.hello.camera
        self.k = self.hello.offload_at
        self.tracks = self.k != ROBOT_TRACKS
        self.slam = RobotSlam(self.config, camera)
        self.references = ReferenceRing(self.config.wire.reference_frames)

    def track(self, data: bytes) -> tuple[int, object]:
        """(seq, the tracked frame) of one frame message."""
        header, state = decode_frame_message(data, self.hello.camera, self.references)
        assert header.robot_id == ROBOT and header.split_point == self.k
        self.references.put(header.seq, reference_of(state))
        # At point 6 the robot tracked: the cloud records the result it sent.
        out = self.slam.track(state, self.k) if self.tracks else state
        return header.seq, out


def run_offloaded(sequence: RgbdSequence, frames: list[CapturedFrame], k: int
                  ) -> tuple[np.ndarray, list[bool], int]:
    """(poses, keyframe flags, inter-coded frames) of a robot offloading at ``k`` to its own
    cloud session, bytes between them."""
    robot = RobotSide(sequence, k)
    cloud = CloudSide(robot.hello())
    robot.welcomed(cloud.references.size)
    poses, keyframes = [], []
    for seq, frame in enumerate(frames):
        seq_back, out = cloud.track(robot.frame_message(frame, seq))
        robot.robot.encoder.held(seq_back)  # the cloud's "held" reply / feedback
        poses.append(out.T_world_camera)
        keyframes.append(out.is_keyframe)
    return np.array(poses), keyframes, robot.robot.encoder.inter.counts.inter_frames


@pytest.mark.parametrize("k", SUPPORTED_POINTS)
def test_every_offloading_point_gives_identical_poses(frames, expected, k):
    sequence, captured = frames
    poses, keyframes, inter_frames = run_offloaded(sequence, captured, k)
    np.testing.assert_array_equal(poses, expected[0], err_msg=f"k={k}")
    assert keyframes == expected[1]
    if k in INTER_POINTS:  # the descriptors went inter-coded against earlier frames
        assert inter_frames > N_FRAMES // 2


def test_where_the_robot_holds_what(frames):
    """Each process holds only the state its stages read: at points 0-3 the tracking map
    lives only in the cloud, at point 6 only on the robot; the cloud runs the front end (and
    holds its state) only where the robot does not."""
    sequence, captured = frames
    holds = {}
    for k in SUPPORTED_POINTS:
        robot = RobotSide(sequence, k)
        cloud = CloudSide(robot.hello())
        robot.welcomed(cloud.references.size)
        cloud.track(robot.frame_message(captured[0], 0))
        holds[k] = (robot.sides.edge is not None, robot.sides.cloud is not None,
                    cloud.slam.front_end is not None)
    assert holds == {0: (False, False, True), 1: (True, False, True), 2: (True, False, True),
                     3: (True, False, False), 6: (True, True, False)}


@pytest.mark.parametrize("k", MAP_SPLITTING_POINTS)
def test_the_codec_is_exact_where_the_map_would_be_split(frames, expected, k):
    """At points 4 and 5 the robot matches against the tracking map and the cloud updates
    it, so no robot offloads there (refused at start and in the hello). The frame messages
    are still exact: with the one map both sides read, the poses are the in-memory ones."""
    sequence, captured = frames
    camera = sequence.camera
    with pytest.raises(ValueError, match="splits the tracking map"):
        parse_offload_point(str(k))
    with pytest.raises(ValueError, match="splits the tracking map"):
        Robot(ROBOT, sequence, "test", k, config=Config(), show_progress=False)
    with pytest.raises(ValueError, match="not supported"):
        Hello.parse(json.loads(json.dumps(Hello(k, camera, "test").message(N_FRAMES))))
    config = Config()
    pipeline = RobotSlam.new(config, camera)
    robot_stages, cloud_stages = pipeline.split(k)
    cloud_sides = Sides(None, pipeline.state)  # the shared map, no front end
    references = ReferenceRing(config.wire.reference_frames)
    inter = InterEncoder(config.wire, references.size)
    poses = []
    for seq, frame in enumerate(captured):
        state = run_stages(robot_stages, frame, pipeline.sides)
        refs = inter.choose(seq)
        data = encode_frame_message(state, k, ROBOT, seq, camera, config.wire, refs)
        inter.sent(seq, reference_of(state), len(refs))
        header, state = decode_frame_message(data, camera, references)
        references.put(header.seq, reference_of(state))
        inter.acked(header.seq)
        poses.append(run_stages(cloud_stages, state, cloud_sides).T_world_camera)
    np.testing.assert_array_equal(np.array(poses), expected[0], err_msg=f"k={k}")
    assert inter.counts.inter_frames > N_FRAMES // 2


def test_split_point_out_of_range(frames):
    sequence, _ = frames
    with pytest.raises(ValueError, match="offloading point"):
        RobotSlam.new(Config(), sequence.camera).split(7)
