"""The robot's front end (pipeline/front_end.py) on real frames: Describe's keypoint table is
exactly what OpenCV's ORB returned, whether Describe reused the detected table (ORB kept
every keypoint) or converted ORB's keypoints again (ORB dropped some)."""

from __future__ import annotations

import numpy as np

from conftest import SEVEN_SCENES, require
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.pipeline.front_end import (
    Describe,
    Extract,
    FrontEndState,
    _array_to_keypoints,
    _keypoints_to_array,
)
from fleetslam.pipeline.states import CapturedFrame, DetectedFrame


def _detected(n: int = 4) -> tuple[list[DetectedFrame], FrontEndState]:
    seq = RgbdSequence(require(SEVEN_SCENES))
    session = FrontEndState(Config(), seq.camera)
    out = []
    for i in range(0, 40, 40 // n):
        f = seq[i]
        out.append(Extract()(CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m), session))
    return out, session


def _orb_table(detected: DetectedFrame, session: FrontEndState) -> tuple[np.ndarray, np.ndarray]:
    kps, desc = session.orb.compute(detected.gray, _array_to_keypoints(detected.keypoints))
    return _keypoints_to_array(kps), desc


def test_describe_gives_orbs_keypoints_and_descriptors():
    frames, session = _detected()
    for detected in frames:
        table, desc = _orb_table(detected, session)
        described = Describe()(detected, session)
        assert len(table) > 500
        assert np.array_equal(described.keypoints, table)
        assert np.array_equal(described.descriptors, desc)


def test_describe_follows_orb_when_it_drops_keypoints():
    frames, session = _detected(1)
    detected = frames[0]
    # Two keypoints moved onto the image's edge: ORB cannot describe them there.
    moved = detected.keypoints.copy()
    moved[[3, 10], 0] = 1.0
    detected = DetectedFrame(detected.index, detected.timestamp, detected.gray,
                             detected.depth_m, moved)
    table, desc = _orb_table(detected, session)
    described = Describe()(detected, session)
    assert len(table) == len(moved) - 2
    assert np.array_equal(described.keypoints, table)
    assert np.array_equal(described.descriptors, desc)
