"""Joining robots' maps with no ground truth in the run: the consistency rule, GNC against a
wrong inter-robot edge, real robots that share a place (and ones that do not), the same
outputs with ground truth deleted, and the OctoMap written."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from conftest import SEVEN_SCENES, TUM_RPY, require
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.datasets.recording import open_source
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.mapping.octomap_export import read_octomap
from fleetslam.merging.inter_robot import PlaceMatch
from fleetslam.wire.merger_keyframes import KeyframeSummary
from fleetslam.merging.merger import MapMerger
from fleetslam.merging.proximity import near_keyframes
from fleetslam.pipeline.split import run_stages
from fleetslam.pipeline.states import CapturedFrame, FeatureFrame
from fleetslam.system import run_fleet
from fleetslam.registration.metrics import random_perturbation
from fleetslam.transforms import invert, make_T, rotation_angle_deg

CAMERA = Camera(525.0, 525.0, 319.5, 239.5)


def _path(n: int, rng: np.random.Generator, step: float = 0.1) -> np.ndarray:
    """A smooth-ish camera path of n keyframe poses (the robot's own map frame)."""
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ random_perturbation(rng, 3.0, step))
    return np.array(poses)


def _summary(robot: str, k: int, T: np.ndarray) -> KeyframeSummary:
    empty = FeatureFrame(k, float(k), np.zeros((0, 7), np.float32), np.zeros((0, 32), np.uint8),
                         np.zeros(0, np.float32), np.zeros((0, 2)))
    return KeyframeSummary(robot, k, k, float(k), empty, T)


def _merger_with_two_robots(seed: int = 0):
    """Two robots (keyframes only, no features) whose map frames are ``T_a_b`` apart."""
    rng = np.random.default_rng(seed)
    merger = MapMerger(Config())
    poses = {"a": _path(12, rng), "b": _path(12, rng)}
    for name in poses:
        merger.add_robot(name, CAMERA)
        merger.robots[name].keyframes = [_summary(name, k, T) for k, T in enumerate(poses[name])]
        merger.update_poses(name, poses[name])
    T_a_b = random_perturbation(rng, 40.0, 2.0)
    return merger, poses, T_a_b


def _match(merger, poses, T_a_b, qa: int, pb: int, noise: np.ndarray | None = None):
    """Robot b's keyframe qa seen in robot a's keyframe pb, exactly (or spoiled by noise)."""
    T_place_query = invert(poses["a"][pb]) @ T_a_b @ poses["b"][qa]
    if noise is not None:
        T_place_query = T_place_query @ noise
    return PlaceMatch(merger.robots["b"].keyframes[qa], merger.robots["a"].keyframes[pb],
                      T_place_query, 1.0, 80, 80)


def test_robots_join_only_when_two_matches_agree():
    merger, poses, T_a_b = _merger_with_two_robots()
    assert merger._consider(_match(merger, poses, T_a_b, 3, 5)) is None  # one match: no join
    assert merger.robots["b"].anchor == "b"
    # A second match that implies another transform (8 deg off): still no join.
    wrong = make_T(random_perturbation(np.random.default_rng(1), 8.0, 0.0)[:3, :3], [0, 0, 0])
    assert merger._consider(_match(merger, poses, T_a_b, 4, 6, wrong)) is None
    assert merger.robots["b"].anchor == "b"
    event = merger._consider(_match(merger, poses, T_a_b, 6, 7))
    assert event is not None and event["anchor"] == "a" and event["matches"] == 2
    found = invert(merger.solve_T_global_map("a")) @ merger.solve_T_global_map("b")
    assert rotation_angle_deg(found[:3, :3].T @ T_a_b[:3, :3]) < 1e-3
    assert np.linalg.norm(found[:3, 3] - T_a_b[:3, 3]) < 1e-5
    assert merger.status()["robots"]["b"]["joined"]["frames"] == {"b": 6, "a": 7}


def test_a_wrong_inter_robot_edge_after_the_join_is_rejected_by_gnc():
    merger, poses, T_a_b = _merger_with_two_robots(seed=3)
    merger._consider(_match(merger, poses, T_a_b, 3, 5))
    merger._consider(_match(merger, poses, T_a_b, 6, 7))
    before = invert(merger.solve_T_global_map("a")) @ merger.solve_T_global_map("b")
    wrong = random_perturbation(np.random.default_rng(4), 25.0, 0.5)
    merger._consider(_match(merger, poses, T_a_b, 9, 2, wrong))
    after = invert(merger.solve_T_global_map("a")) @ merger.solve_T_global_map("b")
    assert [c.kept for c in merger.constraints] == [True, True, False]
    assert rotation_angle_deg(after[:3, :3].T @ before[:3, :3]) < 0.05
    assert np.linalg.norm(after[:3, 3] - before[:3, 3]) < 0.002


def _copy_without_ground_truth(folder, to):
    to.mkdir()
    for item in folder.iterdir():
        if item.name != "groundtruth.txt":
            (to / item.name).symlink_to(item)
    return to


@pytest.mark.realdata
def test_two_robots_on_one_real_sequence_join_and_ground_truth_changes_nothing(tmp_path):
    folder = require(SEVEN_SCENES)
    blind = _copy_without_ground_truth(folder, tmp_path / "no_gt")
    runs = {}
    for label, source in (("gt", folder), ("blind", blind)):
        robots = [(f"r{i}", f"{source}:{r}", open_source(f"{source}:{r}"))
                  for i, r in enumerate(("0-59", "30-89"))]
        runs[label] = (tmp_path / label, run_fleet(robots, Config(), tmp_path / label, False))
    out, summary = runs["gt"]
    merge = summary["merge"]
    assert merge["members"] == ["r0", "r1"] and not merge["not_merged"]
    rel = merge["evaluation"]["relative_poses"][0]
    assert rel["final_rotation_error_deg"] < 3.0 and rel["final_translation_error_m"] < 0.06
    assert merge["evaluation"]["joint_ate"]["rmse_m"] < 0.04
    for c in merge["evaluation"]["constraints"]:
        assert c["rotation_error_deg"] < 5.0 and c["translation_error_m"] < 0.2
    # Every constraint was refined on the keyframes' depth, and the edges the graph used are
    # closer to ground truth than the feature estimates they began as.
    scored = merge["evaluation"]["constraints"]
    assert all(c["used"] == "dense" for c in scored), merge["constraints"]
    assert max(c["rotation_error_deg"] for c in scored) < 2.0
    featured = [c for c in scored if c["found"] == "features"]
    assert featured and max(c["rotation_error_deg"] for c in featured) < \
        max(c["feature_rotation_error_deg"] for c in featured)
    # The run never read ground truth: without it, the same joins and the same outputs.
    blind_out, blind_summary = runs["blind"]
    assert blind_summary["merge"]["joins"] == merge["joins"]
    assert blind_summary["merge"]["evaluation"]["joint_ate"] is None  # nothing to score
    for name in ("r0", "r1"):
        t1, p1 = read_tum_trajectory(out / "global" / f"{name}.tum")
        t2, p2 = read_tum_trajectory(blind_out / "global" / f"{name}.tum")
        np.testing.assert_array_equal(t1, t2)
        np.testing.assert_allclose(p1, p2, atol=1e-9)
    assert (out / "global_map.ply").stat().st_size == (blind_out / "global_map.ply").stat().st_size
    tree = read_octomap(out / "global_map.bt")
    assert tree.getResolution() == pytest.approx(Config().merge.octomap_resolution_m)
    assert merge["octomap"]["occupied"] > 1000 and merge["octomap"]["free"] > 1000
    assert json.loads((out / "summary.json").read_text())["merge"]["members"] == ["r0", "r1"]


@pytest.mark.realdata
def test_two_robots_join_whichever_starts_first():
    """Redkitchen 0-199 and 250-349 (bench/merge_fleet.py's rk-3, robots r0 and r1): their
    only shared place is near both starts, and before the catch-up and the two-way check they
    joined only when r1's keyframes were searched first. Poses come from the ground truth so
    that the test is about the search alone (tracking is tested elsewhere)."""
    seq = RgbdSequence(require(SEVEN_SCENES), first=0, last=349)
    pipeline = RobotSlam.new(Config(), seq.camera)
    stages = pipeline.split(3)[0]
    robots: dict[str, list[tuple[KeyframeSummary, np.ndarray]]] = {}
    for name, frames in {"r0": range(0, 200, 6), "r1": range(250, 350, 6)}.items():
        first = invert(seq.gt_poses[frames[0]])
        robots[name] = []
        for i in frames:
            f = seq[i]
            features = run_stages(stages, CapturedFrame(f.index, f.timestamp, f.rgb,
                                                        f.depth_m), pipeline.sides)
            robots[name].append((KeyframeSummary(name, len(robots[name]), f.index,
                                                 f.timestamp, features, np.eye(4)),
                                 first @ seq.gt_poses[i]))
    joins = []
    for order in (["r0", "r1"], ["r1", "r0"]):
        merger = MapMerger(Config())
        for name in order:
            merger.add_robot(name, seq.camera)
        for name in order:  # one robot's whole run, then the other's
            poses = np.array([T for _, T in robots[name]])
            for summary, _ in robots[name]:
                merger.add_keyframe(summary, poses[: summary.keyframe + 1])
        assert merger.components() == {"r0": ["r0", "r1"]}, order
        joins.append([(e["query_robot"], e["query_frame"], e["place_robot"], e["place_frame"])
                      for e in merger.events])
    assert joins[0] == joins[1]  # the same pair of keyframes joins them


@pytest.mark.realdata
def test_robots_in_different_places_never_join(tmp_path):
    kitchen, office = require(SEVEN_SCENES), require(TUM_RPY)
    robots = [("r0", "kitchen", open_source(f"{kitchen}:0-79")),
              ("r1", "office", open_source(f"{office}:0-79"))]
    summary = run_fleet(robots, Config(), tmp_path / "run", False)
    merge = summary["merge"]
    assert merge["components"] == {"r0": ["r0"], "r1": ["r1"]}
    assert merge["joins"] == [] and set(merge["not_merged"]) == {"r0", "r1"}
    assert not (tmp_path / "run" / "global" / "r1.tum").exists()


def test_octomap_reports_a_missing_file(tmp_path):
    with pytest.raises(ValueError, match="no such OctoMap file"):
        read_octomap(tmp_path / "nowhere.bt")


def test_near_keyframes_pairs_each_keyframe_with_its_nearest_facing_the_same_way():
    a = np.array([make_T(np.eye(3), [x, 0.0, 0.0]) for x in (0.0, 1.0, 2.0)])
    turned = make_T(random_perturbation(np.random.default_rng(0), 10.0, 0.0)[:3, :3], [0, 0, 0])
    facing_back = make_T(np.diag([-1.0, 1.0, -1.0]), [0.9, 0.0, 0.0])
    b = np.array([make_T(np.eye(3), [1.2, 0.1, 0.0]) @ turned,  # nearest: a's keyframe 1
                  facing_back,  # near a's keyframe 1 but looking the other way
                  make_T(np.eye(3), [5.0, 0.0, 0.0])])  # near nothing
    assert near_keyframes(a, b, 0.5, 30.0) == [(1, 0)]
    assert near_keyframes(a, b, 0.1, 30.0) == []


def _room(rng: np.random.Generator) -> np.ndarray:
    """Points on a floor, two walls and some boxes: a scene GICP can lock onto."""
    n = 6000
    floor = np.c_[rng.uniform(-2, 2, n), np.full(n, 1.2), rng.uniform(0, 5, n)]
    back = np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.2, n), np.full(n, 4.0)]
    side = np.c_[np.full(n, -1.8), rng.uniform(-1.5, 1.2, n), rng.uniform(0, 5, n)]
    boxes = np.vstack([c + rng.uniform(-0.2, 0.2, (n // 4, 3)) for c in
                       ([0.5, 0.8, 2.5], [-0.8, 0.5, 3.0], [1.0, -0.5, 3.5])])
    return np.vstack([floor, back, side, boxes])


def _view(room: np.ndarray, T_world_camera: np.ndarray) -> np.ndarray:
    local = (room - T_world_camera[:3, 3]) @ T_world_camera[:3, :3]
    z = local[:, 2]
    seen = (z > 0.3) & (z < 4.5) & (np.abs(local[:, 0]) < 0.6 * z) \
        & (np.abs(local[:, 1]) < 0.45 * z)
    return local[seen]


@pytest.mark.parametrize("on", [True, False])
def test_joined_robots_gain_depth_edges_where_the_graph_puts_them_near(on):
    """Two robots walking side by side, joined by two exact matches: with
    merge.proximity_constraints every other keyframe pair the graph puts near gets a depth
    edge (found "proximity"), each near the true relative pose; without it, none."""
    rng = np.random.default_rng(5)
    room = _room(rng)
    walk = [make_T(np.eye(3), [0.0, 0.0, 0.0])]
    for _ in range(9):
        step = random_perturbation(rng, 2.0, 0.0)[:3, :3]
        walk.append(walk[-1] @ make_T(step, [0.05, 0.0, 0.04]))
    beside = make_T(random_perturbation(rng, 3.0, 0.0)[:3, :3], [0.08, 0.02, 0.05])
    world = {"a": np.array(walk), "b": np.array([T @ beside for T in walk])}
    T_world_b = random_perturbation(rng, 30.0, 1.0)  # b's map frame in the world (= a's)
    config = Config()
    config = replace(config, merge=replace(config.merge, proximity_constraints=on))
    merger = MapMerger(config)
    own = {"a": world["a"], "b": np.array([invert(T_world_b) @ T for T in world["b"]])}
    for name in own:
        merger.add_robot(name, CAMERA)
        merger.robots[name].keyframes = [_summary(name, k, T) for k, T in enumerate(own[name])]
        merger.update_poses(name, own[name])
    for qa, pb in ((2, 2), (6, 6)):
        T = invert(world["a"][pb]) @ world["b"][qa]
        merger._consider(PlaceMatch(merger.robots["b"].keyframes[qa],
                                    merger.robots["a"].keyframes[pb], T, 1.0, 80, 80))
    assert merger.robots["b"].anchor == "a"
    clouds = {(name, k): _view(room, world[name][k]) for name in world for k in range(10)}
    merger.refine_constraints(lambda robot, k: clouds[robot, k])
    found = [c for c in merger.constraints if c.proximity]
    if not on:
        assert not found
        return
    assert len(found) >= 10 and {c.match.query.robot for c in found} == {"a", "b"}
    for c in found:
        place, query = c.match.place, c.match.query
        true = invert(world[place.robot][place.keyframe]) @ world[query.robot][query.keyframe]
        err = invert(true) @ c.T_place_query
        assert rotation_angle_deg(err[:3, :3]) < 0.5 and np.linalg.norm(err[:3, 3]) < 0.02
    merger.solve_keyframe_poses()
    assert all(c.kept for c in found)
