"""The central invariant: running stages[:k], passing the state through serialisation, then
stages[k:] gives exactly the poses of the unsplit pipeline, for every offloading point k."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from conftest import SEVEN_SCENES, require
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.backend.back_end import TrackingPipeline
from fleetslam.pipeline.split import run_stages
from fleetslam.pipeline.states import CapturedFrame

N_FRAMES = 20


@pytest.fixture(scope="module")
def frames():
    seq = RgbdSequence(require(SEVEN_SCENES), last=N_FRAMES - 1)
    return seq.camera, [CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m) for f in seq]


def run_split(camera, frames, k: int) -> np.ndarray:
    pipeline = TrackingPipeline(Config(), camera)
    robot, cloud = pipeline.split(k)
    poses = []
    for frame in frames:
        state = run_stages(robot, frame, pipeline.sides)
        state = pickle.loads(pickle.dumps(state))  # what crosses the wire
        poses.append(run_stages(cloud, state, pipeline.sides).T_world_camera)
    return np.array(poses)


def test_every_split_point_gives_identical_poses(frames):
    camera, frames = frames
    reference = TrackingPipeline(Config(), camera)
    expected = np.array([reference.track(f).T_world_camera for f in frames])
    assert len(reference.stages) == 6
    # Sanity: the reference actually tracked motion.
    assert np.linalg.norm(expected[-1][:3, 3]) > 0.01
    for k in range(len(reference.stages) + 1):
        np.testing.assert_array_equal(run_split(camera, frames, k), expected, err_msg=f"k={k}")


def test_split_point_out_of_range(frames):
    camera, _ = frames
    with pytest.raises(ValueError, match="offloading point"):
        TrackingPipeline(Config(), camera).split(7)
