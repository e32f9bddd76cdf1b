"""The fleet's map as a folder that outlives its run (merging/saved_map.py): a merging run
writes map/, and loading it gives back every keyframe, pose and dense cloud; a damaged map
is refused with the file and the reason, nothing loaded and the folder unchanged."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import SEVEN_SCENES, require
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.merging.saved_map import (MANIFEST, MAP_VERSION, LoadedMap, MapError, read_map,
                                         write_map)
from fleetslam.system import run_fleet


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """Two robots on 7-Scenes (frames 0-99 and 60-159 of one recording) merged in one
    process: the run's map/."""
    folder = require(SEVEN_SCENES)
    out = tmp_path_factory.mktemp("saved") / "run"
    robots = [(f"r{i}", str(folder), RgbdSequence(folder, first=a, last=b))
              for i, (a, b) in enumerate(((0, 99), (60, 159)))]
    run_fleet(robots, Config(), out, show_progress=False)
    return out


def _tree_digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_merging_run_saves_its_map_and_it_loads_whole(run):
    summary = json.loads((run / "summary.json").read_text())
    saved = read_map(run / "map")
    members = summary["merge"]["members"]
    assert sorted(saved.robots) == sorted(members) and saved.anchor in members
    assert summary["map"]["keyframes"] == saved.keyframes > 0
    for name, robot in saved.robots.items():
        global_kfs = np.loadtxt(run / "global" / f"{name}.tum")  # a frame per row
        assert len(robot.keyframes) == len(robot.poses) == len(robot.clouds)
        assert [k.keyframe for k in robot.keyframes] == list(range(len(robot.keyframes)))
        assert sum(len(p) for p, _ in robot.clouds) > 0
        assert len(global_kfs) >= len(robot.keyframes)
    # The inter-robot constraints of the group, as its graph held them.
    assert saved.constraints and all(c["query"][0] != c["place"][0] for c in saved.constraints)


def test_a_map_is_written_whole_and_replaces_only_a_map(run, tmp_path):
    folder = tmp_path / "not-a-map"
    folder.mkdir()
    (folder / "notes.txt").write_text("mine")
    from fleetslam.merging.global_map import GlobalMap
    from fleetslam.merging.merger import MapMerger

    with pytest.raises(FileExistsError, match="not a map fleetslam wrote"):
        write_map(folder, MapMerger(Config()), GlobalMap([], "r0", {}, {}, {}, {}))
    assert (folder / "notes.txt").read_text() == "mine"


def _damage(folder: Path, how: str) -> str:
    manifest = json.loads((folder / MANIFEST).read_text())
    robot_file = folder / manifest["robots"][0]["file"]
    if how == "no manifest":
        (folder / MANIFEST).unlink()
        return "no manifest: not a map folder fleetslam wrote"
    if how == "a changed byte":
        data = bytearray(robot_file.read_bytes())
        data[len(data) // 2] ^= 0xFF
        robot_file.write_bytes(bytes(data))
        return "SHA-256 is not the manifest's"
    if how == "a truncated file":
        robot_file.write_bytes(robot_file.read_bytes()[:-100])
        return "truncated or changed"
    if how == "a newer format":
        manifest["version"] = MAP_VERSION + 1
        (folder / MANIFEST).write_text(json.dumps(manifest))
        return f"map format version {MAP_VERSION + 1}; this fleetslam reads up to"
    if how == "a truncated constraints file":
        constraints = folder / manifest["constraints"]
        constraints.write_bytes(constraints.read_bytes()[:-10])
        return "truncated or changed"
    if how == "a camera edited in the manifest":
        manifest["robots"][0]["camera"]["fx"] += 10
        (folder / MANIFEST).write_text(json.dumps(manifest))
        return "camera is not the one its file"
    if how == "a missing robot file":
        robot_file.unlink()
        return "missing (the manifest lists it)"
    raise AssertionError(how)


@pytest.mark.parametrize("how", ["no manifest", "a changed byte", "a truncated file",
                                 "a newer format", "a missing robot file",
                                 "a camera edited in the manifest",
                                 "a truncated constraints file"])
def test_a_damaged_map_is_refused_in_one_line_and_left_as_it_is(run, tmp_path, how):
    folder = tmp_path / "map"
    shutil.copytree(run / "map", folder)
    reason = _damage(folder, how)
    before = _tree_digest(folder)
    with pytest.raises(MapError, match=re.escape(reason)) as refused:
        read_map(folder)
    assert "\n" not in str(refused.value) and str(folder) in str(refused.value)
    assert _tree_digest(folder) == before


def test_a_version_1_map_with_its_constraints_in_the_manifest_still_loads(run, tmp_path):
    folder = tmp_path / "map"
    shutil.copytree(run / "map", folder)
    manifest = json.loads((folder / MANIFEST).read_text())
    constraints = folder / manifest["constraints"]
    manifest.update(version=1, constraints=json.loads(constraints.read_text()))
    del manifest["files"][constraints.name]
    constraints.unlink()
    (folder / MANIFEST).write_text(json.dumps(manifest))
    old, new = read_map(folder), read_map(run / "map")
    assert old.constraints == new.constraints and old.keyframes == new.keyframes


def test_a_loaded_map_is_searched_and_a_robot_that_finds_it_tracks_in_its_frame(run,
                                                                                 tmp_path):
    """The next day: a new run loads the map, and a robot on frames the map covers part of
    (120-219) joins it by itself; its global trajectory is in the map's frame (scored with
    one alignment together with the map's robots', as one session's would be), the map's
    anchor stays where it was, and the run writes the extended map (the loaded one is
    never changed)."""
    from fleetslam.evaluation.ate import absolute_trajectory_error
    from fleetslam.io.trajectory import read_tum_trajectory

    folder = require(SEVEN_SCENES)
    before = _tree_digest(run / "map")
    saved = read_map(run / "map")
    out = tmp_path / "day2"
    robots = [("r0", str(folder), RgbdSequence(folder, first=120, last=219))]
    summary = run_fleet(robots, Config(), out, show_progress=False, loaded=LoadedMap(saved))
    assert _tree_digest(run / "map") == before
    merge = summary["merge"]
    assert sorted(merge["members"]) == sorted(["r0", *(f"map-{n}" for n in saved.robots)])
    assert merge["map_frame"]["source"] == "the loaded map's frame"
    # Scored afterwards, the map's robots are not (their sources are not this run's).
    assert merge["loaded_map"] == sorted(f"map-{n}" for n in saved.robots)
    rows = merge["evaluation"]["constraints"]
    assert rows and all("ground truth is not this run's" in r["note"] for r in rows
                        if r["place_robot"].startswith("map-"))
    # It starts where the map was made: placed in it within the 30 frames.
    assert merge["entered_map"]["r0"]["frames"] <= 30
    anchor_then = read_tum_trajectory(run / "global" / f"{saved.anchor}.tum")[1]
    anchor_now = read_tum_trajectory(out / "global" / f"map-{saved.anchor}.tum")[1]
    np.testing.assert_allclose(anchor_now[0], saved.robots[saved.anchor].poses[0], atol=1e-9)
    assert len(anchor_then) >= len(anchor_now)
    # One alignment for yesterday's robots and today's: today's is in the map's frame.
    gt_times, gt_poses = read_tum_trajectory(folder / "groundtruth.txt")
    estimated, truth = [], []
    for path in (run / "global" / "r0.tum", run / "global" / "r1.tum",
                 out / "global" / "r0.tum"):
        times, poses = read_tum_trajectory(path)
        nearest = np.abs(gt_times[None, :] - times[:, None]).argmin(axis=1)
        found = np.abs(gt_times[nearest] - times) < 1e-3
        estimated.append(poses[found])
        truth.append(gt_poses[nearest[found]])
    joint = absolute_trajectory_error(np.concatenate(estimated), np.concatenate(truth))
    assert joint.rmse_m < 0.05, joint
    extended = read_map(out / "map")
    assert extended.keyframes > saved.keyframes
    # Names stay short however often a map is loaded and extended: the map's robots keep
    # theirs, today's r0 is numbered on.
    assert sorted(extended.robots) == sorted([*saved.robots, "r0-2"])
    assert extended.anchor == saved.anchor


def test_a_robot_from_another_room_never_joins_the_map(run, tmp_path):
    """TUM fr1_rpy (another building) against the 7-Scenes map: searched, never joined; it
    stays in its own frame and the run says so."""
    from conftest import TUM_RPY

    saved = read_map(run / "map")
    folder = require(TUM_RPY)
    robots = [("r0", str(folder), RgbdSequence(folder, last=59))]
    # Another camera too: refused unless the run says the camera is new to the map.
    with pytest.raises(MapError, match="is none of the map's cameras"):
        run_fleet(robots, Config(), tmp_path / "refused", show_progress=False,
                  loaded=LoadedMap(saved))
    assert not (tmp_path / "refused").exists()
    summary = run_fleet(robots, Config(), tmp_path / "elsewhere", show_progress=False,
                        loaded=LoadedMap(saved, new_cameras=True))
    merge = summary["merge"]
    assert "r0" not in merge["members"]
    assert "never found the loaded map" in merge["not_merged"]["r0"]


def test_localise_only_places_the_robot_in_the_map_and_leaves_the_map_as_it_was(run,
                                                                                  tmp_path):
    """--localise-only: the robot joins the map and its trajectory is in the map's frame,
    the map's keyframes keep their poses (to the graph's prior, 1e-6), and no new map is
    written (nothing extends it)."""
    from fleetslam.io.trajectory import read_tum_trajectory

    folder = require(SEVEN_SCENES)
    saved = read_map(run / "map")
    out = tmp_path / "localised"
    robots = [("r0", str(folder), RgbdSequence(folder, first=120, last=219))]
    summary = run_fleet(robots, Config(), out, show_progress=False,
                        loaded=LoadedMap(saved, localise_only=True))
    assert "r0" in summary["merge"]["members"]
    assert not (out / "map").exists() and "map" not in summary
    for name, robot in saved.robots.items():
        now = read_tum_trajectory(out / "global" / f"map-{name}.tum")[1]
        np.testing.assert_allclose(now, robot.poses, atol=1e-5)


def test_a_cloud_loads_a_map_and_a_robot_over_the_link_joins_it(run, tmp_path):
    """fleetslam cloud --map: a robot streaming over Zenoh (point 3) finds the loaded map,
    the merge places it in the map's frame, and the store's map/ is the extended map."""
    import threading

    from fleetslam.cloud.server import CloudServer
    from fleetslam.datasets.recording import open_source
    from fleetslam.edge.robot import Robot
    from fleetslam.launch import free_endpoint

    folder = require(SEVEN_SCENES)
    saved = read_map(run / "map")
    endpoint = free_endpoint()
    config = Config().with_values({"transport.endpoint": endpoint})
    server = CloudServer(config, tmp_path / "store", endpoint, loaded=LoadedMap(saved)).start()
    try:
        robot = Robot("r0", open_source(f"{folder}:120-219"), "r0", 3, config,
                      show_progress=False)
        thread = threading.Thread(target=robot.run, daemon=True)
        thread.start()
        thread.join(300)
        assert not thread.is_alive(), "the robot did not finish"
        assert server.merger.drain(120), "the merger did not take the robot's keyframes"
        live = server.merger.placements()  # what robots hear while they run (map -> r0/map)
        summary = server.merge()
    finally:
        server.close()
    merge = summary["merge"]
    assert sorted(merge["members"]) == sorted(["r0", *(f"map-{n}" for n in saved.robots)])
    assert merge["map_frame"]["source"] == "the loaded map's frame"
    assert read_map(tmp_path / "store" / "map").keyframes > saved.keyframes
    # The robot was placed in the map's own frame while it ran (no levelling of its own: the
    # map's frame is level already), where the merge then put it, to FS-HICP's refinement.
    assert live["r0"][0] == f"map-{saved.anchor}"
    T_live, T_merged = live["r0"][1], np.array(merge["T_global_map"]["r0"])
    assert np.linalg.norm(T_live[:3, 3] - T_merged[:3, 3]) < 0.10
    cos = (np.trace(T_live[:3, :3].T @ T_merged[:3, :3]) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 3.0


def test_a_map_whose_features_this_run_could_never_match_is_refused_before_the_run(run,
                                                                                   tmp_path):
    saved = read_map(run / "map")
    folder = require(SEVEN_SCENES)
    config = Config().with_values({"orb.scale_factor": 1.3})
    out = tmp_path / "never"
    with pytest.raises(MapError, match=r"orb_scale_factor 1\.2 \(this run: 1\.3\)"):
        run_fleet([("r0", str(folder), RgbdSequence(folder, last=9))], config, out,
                  show_progress=False, loaded=LoadedMap(saved))
    assert not out.exists()


def _serve(config: Config, store: Path, loaded: LoadedMap | None):
    from fleetslam.cloud.server import CloudServer

    return CloudServer(config, store, config.transport.endpoint, loaded=loaded).start()


def test_a_cloud_refuses_a_robot_it_cannot_place_and_says_why(run, tmp_path):
    """A hello the loaded map cannot take is refused with the reason, before a session
    opens: a camera that is none of the map's (unless the cloud says --new-camera), and a
    robot asking to localise only in a cloud without a map."""
    from fleetslam.datasets.recording import open_source
    from fleetslam.edge.robot import Robot
    from conftest import TUM_RPY
    from fleetslam.launch import free_endpoint

    saved = read_map(run / "map")
    tum = require(TUM_RPY)
    for loaded, localise_only, reason in (
            (LoadedMap(saved), False, "is none of the map's cameras"),
            (None, True, "this cloud has no saved map loaded")):
        config = Config().with_values({"transport.endpoint": free_endpoint(),
                                       "transport.max_attempts": 3})
        server = _serve(config, tmp_path / f"store-{localise_only}", loaded)
        try:
            robot = Robot("r0", open_source(f"{tum}:0-4"), "r0", 3, config,
                          show_progress=False, localise_only=localise_only)
            with pytest.raises(RuntimeError, match=f"refused it: .*{reason}"):
                robot.run()
            assert "r0" not in server.sessions
        finally:
            server.close()


def test_a_robot_localising_only_is_placed_in_the_map_and_never_moves_it(run, tmp_path):
    """fleetslam robot --localise-only against cloud --map: the robot joins the map and the
    merge places it in the map's frame, the map's keyframes keep their poses, and the store
    writes no new map (the robot did not extend it)."""
    import threading

    from fleetslam.datasets.recording import open_source
    from fleetslam.edge.robot import Robot
    from fleetslam.io.trajectory import read_tum_trajectory
    from fleetslam.launch import free_endpoint

    folder = require(SEVEN_SCENES)
    saved = read_map(run / "map")
    config = Config().with_values({"transport.endpoint": free_endpoint()})
    store = tmp_path / "store"
    server = _serve(config, store, LoadedMap(saved))
    try:
        robot = Robot("r0", open_source(f"{folder}:120-219"), "r0", 3, config,
                      show_progress=False, localise_only=True)
        thread = threading.Thread(target=robot.run, daemon=True)
        thread.start()
        thread.join(300)
        assert not thread.is_alive(), "the robot did not finish"
        summary = server.merge()
    finally:
        server.close()
    assert "r0" in summary["merge"]["members"]
    assert not (store / "map").exists() and "map" not in summary
    for name, saved_robot in saved.robots.items():
        now = read_tum_trajectory(store / "global" / f"map-{name}.tum")[1]
        np.testing.assert_allclose(now, saved_robot.poses, atol=1e-5)
