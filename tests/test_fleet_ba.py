"""The fleet-wide bundle adjustment (merging/fleet_ba.py) on a synthetic scene whose truth is
known: two robots see the same landmarks; the graph put the second robot's map a little off
(a rigid map-to-map error) and the adjustment takes it back, without moving the anchor."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.merging.fleet_ba import FleetRobot, candidate_pairs, fleet_bundle_adjustment
from fleetslam.pipeline.states import FeatureFrame
from fleetslam.registration.metrics import transform_error
from fleetslam.transforms import invert
from fleetslam.wire.merger_keyframes import KeyframeSummary

CAMERA = Camera(525.0, 525.0, 319.5, 239.5, 640, 480)


def _pose(x: float, yaw_deg: float) -> np.ndarray:
    a = np.deg2rad(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [x, 0.0, 0.0]
    return T


def _offset(rotation_deg: float, translation: tuple[float, float, float]) -> np.ndarray:
    a = np.deg2rad(rotation_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = translation
    return T


def _scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks on a wall 2-3 m ahead, each with its own descriptor."""
    xyz = np.column_stack([rng.uniform(-1.5, 2.5, 600), rng.uniform(-1.0, 1.0, 600),
                           rng.uniform(2.0, 3.0, 600)])
    return xyz, rng.integers(0, 256, (600, 32), dtype=np.uint8)


def _keyframe(robot: str, k: int, T_world_camera: np.ndarray, T_map_world: np.ndarray,
              xyz: np.ndarray, descriptors: np.ndarray, rng: np.random.Generator
              ) -> KeyframeSummary:
    P = (xyz - T_world_camera[:3, 3]) @ T_world_camera[:3, :3]  # in the camera
    uv = CAMERA.project(P)
    seen = (P[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) \
        & (uv[:, 1] < 480)
    uv = uv[seen] + rng.normal(0, 0.5, (int(seen.sum()), 2))
    keypoints = np.zeros((len(uv), 7), np.float32)
    keypoints[:, :2] = uv
    features = FeatureFrame(k, float(k), keypoints, descriptors[seen],
                            P[seen, 2].astype(np.float32), uv)
    return KeyframeSummary(robot, k, k, float(k), features, T_map_world @ T_world_camera)


def _robots(map_to_map: np.ndarray) -> tuple[list[FleetRobot], dict[str, np.ndarray]]:
    """Robot a at x 0..1 m, robot b at x 0.5..1.5 m, both looking at the wall; b's graph
    poses carry ``map_to_map`` (its own relative poses are exact)."""
    rng = np.random.default_rng(3)
    xyz, descriptors = _scene(rng)
    truth = {"a": np.array([_pose(0.2 * k, 2.0 * k) for k in range(6)]),
             "b": np.array([_pose(0.5 + 0.2 * k, -2.0 * k) for k in range(6)])}
    robots = []
    for name, T_map_world in (("a", np.eye(4)), ("b", invert(truth["b"][0]))):
        kfs = [_keyframe(name, k, T, T_map_world, xyz, descriptors, rng)
               for k, T in enumerate(truth[name])]
        own = np.array([kf.T_map_keyframe for kf in kfs])
        placed = truth[name] if name == "a" else map_to_map @ truth[name]
        robots.append(FleetRobot(name, CAMERA, kfs, placed.copy(), own))
    return robots, truth


def _config(**merge: object) -> Config:
    config = Config()
    return dataclasses.replace(config, merge=dataclasses.replace(config.merge, **merge))


def _worst(poses: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    errors = [transform_error(P, T) for P, T in zip(poses, truth)]
    return max(e.rotation_deg for e in errors), max(e.translation_m for e in errors)


def test_the_adjustment_takes_a_map_to_map_error_back():
    off = _offset(1.0, (0.03, -0.02, 0.02))
    robots, truth = _robots(off)
    before = _worst(robots[1].poses, truth["b"])
    assert before[1] > 0.03
    adjusted, report = fleet_bundle_adjustment(robots, _config())
    assert report.skipped is None and report.pairs_between_robots > 0
    assert report.shared_landmarks > 50
    # The anchor's first keyframe stays where it was.
    np.testing.assert_array_equal(adjusted["a"][0], truth["a"][0])
    rotation, translation = _worst(adjusted["b"], truth["b"])
    assert rotation < 0.1 and translation < 0.005, (before, rotation, translation)
    rotation_a, translation_a = _worst(adjusted["a"], truth["a"])
    assert rotation_a < 0.1 and translation_a < 0.005


def test_a_fit_far_from_the_graph_is_no_association():
    # The graph has robot b 30 cm and 8 deg off: every pair between the robots disagrees
    # with its fit by more than the bounds, so nothing ties them and b stays put.
    robots, truth = _robots(_offset(8.0, (0.3, 0.0, 0.0)))
    adjusted, report = fleet_bundle_adjustment(robots, _config(proximity_distance_m=1.0))
    assert report.pairs_between_robots == 0
    assert report.shared_landmarks == 0
    # b's keyframes moved rigidly at most (its own landmarks hold them together), never
    # towards a: relative poses within the robot unchanged.
    for k in range(1, 6):
        rel_before = invert(robots[1].poses[0]) @ robots[1].poses[k]
        rel_after = invert(adjusted["b"][0]) @ adjusted["b"][k]
        assert transform_error(rel_after, rel_before).translation_m < 0.005


def test_one_robot_is_nothing_to_adjust():
    robots, _ = _robots(np.eye(4))
    adjusted, report = fleet_bundle_adjustment(robots[:1], _config())
    assert report.skipped == "fewer than two robots with keyframes"
    np.testing.assert_array_equal(adjusted["a"], robots[0].poses)


@pytest.mark.parametrize("nearest", [0, 2])
def test_candidate_pairs(nearest):
    poses = np.array([_pose(0.1 * k, 0.0) for k in range(4)] * 2)
    robot_of = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    index_of = np.array([0, 1, 2, 3, 0, 1, 2, 3])
    pairs = {tuple(p) for p in candidate_pairs(poses, robot_of, index_of, 1, nearest, 0.5,
                                               30.0).tolist()}
    sequential = {(0, 1), (1, 2), (2, 3), (4, 5), (5, 6), (6, 7)}
    assert sequential <= pairs
    between = pairs - sequential
    assert all(robot_of[i] != robot_of[j] for i, j in between)
    if nearest == 0:
        assert not between
    else:
        assert (0, 4) in between and (3, 7) in between
