"""Place recognition, geometric verification, the robust pose graph, and relocalisation:
each part checked with a bound that fails when the part is removed."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import SEVEN_SCENES, require
from fleetslam.config import Config, PlaceRecognitionConfig
from fleetslam.datasets.recording import open_source
from fleetslam.evaluation.ate import absolute_trajectory_error
from fleetslam.backend.geometric_verification import ransac_rigid
from fleetslam.backend.loop_closing import LoopDetection, correct
from fleetslam.backend.place_recognition import (
    ApproximateKeyframeDatabase,
    KeyframeDatabase,
    snapshot,
)
from fleetslam.backend.pose_graph import PoseEdge, optimise_pose_graph
from fleetslam.system import track_robot
from fleetslam.registration.metrics import random_perturbation
from fleetslam.transforms import invert, make_T, rotation_angle_deg


def _flip_bits(rng: np.random.Generator, d: np.ndarray, n_bits: int) -> np.ndarray:
    bits = np.unpackbits(d, axis=1)
    for row in bits:
        row[rng.choice(256, n_bits, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


def test_place_recognition_finds_the_keyframe_that_shares_the_features():
    rng = np.random.default_rng(0)
    db = KeyframeDatabase(PlaceRecognitionConfig())
    places = [rng.integers(0, 256, (300, 32), dtype=np.uint8) for _ in range(6)]
    for k, d in enumerate(places):
        db.add(f"kf{k}", d)
    # A new view of place 3: half its features again, each with 10 bits of noise, plus
    # features of nowhere.
    query = np.vstack([_flip_bits(rng, places[3][:150], 10),
                       rng.integers(0, 256, (150, 32), dtype=np.uint8)])
    found = db.query(query)
    assert found and found[0].key == "kf3" and found[0].votes >= 140
    # Entries that may not be matched are never returned.
    allowed = np.ones(6, bool)
    allowed[3] = False
    assert all(c.key != "kf3" for c in db.query(query, allowed))
    assert db.query(query, np.zeros(6, bool)) == []
    # A snapshot (what an asynchronous query searches) does not see later keyframes.
    frozen = snapshot(db)
    db.add("kf6", places[3])
    assert len(frozen) == 6 and frozen.query(query)[0].key == "kf3"
    assert len(db) == 7 and "kf6" in [c.key for c in db.query(query)]


def test_the_approximate_place_index_votes_as_the_exact_one():
    """The merger's index, exact for its first 10 keyframes, then a graph grown keyframe by
    keyframe: the same best place and nearly the same votes as the exact search."""
    rng = np.random.default_rng(1)
    cfg = PlaceRecognitionConfig()
    exact, approximate = KeyframeDatabase(cfg), ApproximateKeyframeDatabase(cfg, 10, 16, 64)
    places = [rng.integers(0, 256, (300, 32), dtype=np.uint8) for _ in range(40)]
    for k, d in enumerate(places):
        exact.add(f"kf{k}", d)
        approximate.add(f"kf{k}", d)
        if k == 5:  # still exact: the same answer to the letter
            query = _flip_bits(rng, places[3][:150], 10)
            assert approximate.query(query) == exact.query(query)
    assert approximate.exact is None and approximate.index is not None
    for k in (0, 17, 39):
        query = np.vstack([_flip_bits(rng, places[k][:150], 10),
                           rng.integers(0, 256, (150, 32), dtype=np.uint8)])
        a, b = exact.query(query), approximate.query(query)
        assert a[0].key == b[0].key == f"kf{k}"
        assert b[0].votes >= 0.9 * a[0].votes
    assert approximate.query(np.zeros((0, 32), np.uint8)) == []
    with pytest.raises(ValueError, match="restrict"):
        approximate.query(query, np.ones(40, bool))


def test_ransac_rigid_recovers_the_transform_among_outliers():
    rng = np.random.default_rng(1)
    T = random_perturbation(rng, 30.0, 0.5)
    src = rng.uniform(-1, 1, (120, 3)) + [0, 0, 2]
    dst = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.003, (120, 3))
    dst[:50] = rng.uniform(-1, 1, (50, 3)) + [0, 0, 2]  # 42 % wrong matches
    found = ransac_rigid(src, dst, np.full(120, 0.02), 300, 30, np.random.default_rng(2))
    assert found is not None
    assert found.inliers[50:].all() and found.inliers[:50].sum() <= 2
    assert rotation_angle_deg(found.T_target_source[:3, :3].T @ T[:3, :3]) < 0.5
    assert np.linalg.norm(found.T_target_source[:3, 3] - T[:3, 3]) < 0.01
    # Too few agreeing matches: no answer rather than a guess.
    assert ransac_rigid(src[:40], dst[:40], np.full(40, 0.02), 300, 30,
                        np.random.default_rng(2)) is None


def _chain(n: int, drift_deg: float
           ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray], list[PoseEdge]]:
    """A camera going round a circle of n keyframes; odometry drifts a little each step."""
    truth = {k: make_T(np.array(_rot_z(2 * np.pi * k / n)), np.array(
        [np.cos(2 * np.pi * k / n), np.sin(2 * np.pi * k / n), 0.0])) for k in range(n)}
    drift = make_T(np.array(_rot_z(np.deg2rad(drift_deg))), np.zeros(3))
    poses = {0: truth[0]}
    edges = []
    for k in range(1, n):
        step = invert(truth[k - 1]) @ truth[k] @ drift
        edges.append(PoseEdge(k - 1, k, step, "odometry"))
        poses[k] = poses[k - 1] @ step
    return truth, poses, edges


def _rot_z(a: float) -> list[list[float]]:
    return [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]


def test_pose_graph_keeps_a_true_loop_and_switches_off_a_false_one():
    truth, poses, edges = _chain(20, 0.1)
    true_loop = PoseEdge(0, 19, invert(truth[0]) @ truth[19], "loop")
    # A look-alike: keyframe 10 said to be at keyframe 0's place.
    false_loop = PoseEdge(0, 10, np.eye(4), "loop")
    result = optimise_pose_graph(poses, edges + [true_loop, false_loop], 0,
                                 np.deg2rad(0.3), 0.005)
    assert result.loop_inliers == [True, False]
    # The true loop removed the drift at the end of the chain ...
    end_before = np.linalg.norm(poses[19][:3, 3] - truth[19][:3, 3])
    end_after = np.linalg.norm(result.poses[19][:3, 3] - truth[19][:3, 3])
    assert end_after < 0.2 * end_before
    # ... and the false one did not pull keyframe 10 (1 m from keyframe 0 ... 2 m) to it.
    assert np.linalg.norm(result.poses[10][:3, 3] - truth[10][:3, 3]) < 0.05


@pytest.fixture(scope="module")
def kitchen_run():
    seq = open_source(f"{require(SEVEN_SCENES)}:0-199")
    config = Config().with_values({"loop_closing.global_ba": False})
    from fleetslam.backend.robot_slam import RobotSlam
    from fleetslam.pipeline.states import CapturedFrame
    pipeline = RobotSlam.new(config, seq.camera)
    out = [pipeline.track(CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m)) for f in seq]
    return seq, pipeline.state, out


def _final_ate(seq, session, out) -> float:
    poses = session.final_poses([o.reference_keyframe for o in out],
                                [o.T_reference_camera for o in out],
                                [o.T_world_camera for o in out])
    return absolute_trajectory_error(poses, seq.gt_poses).rmse_m


@pytest.mark.realdata
def test_a_false_loop_forced_into_the_graph_is_rejected(kitchen_run):
    seq, session, out = kitchen_run
    ate_before = _final_ate(seq, session, out)
    kfs = session.map.keyframes
    query, candidate = kfs[-1], kfs[len(kfs) // 3]
    # Claim the newest keyframe stands where an old one stood: a wrong pair, far apart.
    far = np.linalg.norm(query.T_world_camera[:3, 3] - candidate.T_world_camera[:3, 3])
    assert far > 0.3
    wrong = LoopDetection(query.id, candidate.id, candidate.T_world_camera.copy(),
                          candidate.T_world_camera @ invert(query.T_world_camera), 1.0, 100,
                          200, (np.zeros(0, np.int64), np.zeros(0, np.int64)))
    poses_before = session.map.keyframe_poses().copy()
    assert correct(session, [wrong]) is False
    assert session.loops.events[-1]["accepted"] is False
    np.testing.assert_array_equal(session.map.keyframe_poses(), poses_before)
    assert _final_ate(seq, session, out) <= 1.05 * ate_before


@pytest.mark.realdata
def test_relocalisation_recovers_after_30_frames_cut_out():
    folder = require(SEVEN_SCENES)
    config = Config()
    whole = track_robot("whole", "", open_source(f"{folder}:0-199"), config, False)
    cut = track_robot("cut", "", open_source(f"{folder}:0-99,130-199"), config, False)
    assert cut.loop_closing["relocalisations"] >= 1
    assert cut.lost_frames == 0 and cut.resets == 0
    # After the gap, the trajectory is as good as without the gap.
    after = 100
    gt = cut.sequence.gt_poses[after:]
    ate_cut = absolute_trajectory_error(cut.poses[after:], gt).rmse_m
    ate_whole = absolute_trajectory_error(whole.poses[130:], whole.sequence.gt_poses[130:]).rmse_m
    assert ate_cut <= ate_whole + 0.01


@pytest.mark.realdata
def test_without_relocalisation_the_cut_is_lost():
    """The bound above fails when relocalisation is switched off (it is what recovers)."""
    config = Config().with_values({"relocalisation.enabled": False})
    cut = track_robot("cut", "", open_source(f"{require(SEVEN_SCENES)}:0-99,130-199"), config,
                      False)
    assert cut.lost_frames > 0
