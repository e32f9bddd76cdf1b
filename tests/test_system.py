"""End to end on a small synthetic scene: track, map, merge, outputs other tools open."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fleetslam.cli import main
from fleetslam.io.ply import read_ply
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.mapping.octomap_export import read_octomap
from fleetslam.outputs import summary_table


@pytest.fixture(scope="module")
def scene(synthetic_scene):
    return synthetic_scene


@pytest.fixture(scope="module")
def run(synthetic_run):
    return synthetic_run


def test_run_writes_standard_outputs(run):
    out, summary = run
    assert json.loads((out / "summary.json").read_text()) == json.loads(json.dumps(summary))
    for robot in summary["robots"]:
        times, poses = read_tum_trajectory(out / robot["trajectory"])
        assert len(times) == robot["frames"] == 30
        np.testing.assert_allclose(poses[0], np.eye(4), atol=1e-9)  # own map frame
        points, colors = read_ply(out / robot["map"])
        assert len(points) == robot["map_points"] > 10000 and colors is not None
    points, colors = read_ply(out / "global_map.ply")
    assert len(points) > 10000
    for robot in summary["robots"]:
        times, poses = read_tum_trajectory(out / "global" / f"{robot['name']}.tum")
        assert len(times) == robot["frames"]
    assert read_octomap(out / "global_map.bt").getNumLeafNodes() > 1000


def test_tracking_and_merge_are_accurate_on_synthetic_data(run):
    _, summary = run
    for robot in summary["robots"]:
        assert robot["lost_frames"] == 0
        assert robot["ate"]["rmse_m"] < 0.02
        assert set(robot["stage_ms"]) == {"extract", "describe", "associate_depth", "match",
                                          "estimate_pose", "decide_keyframe"}
    # The robots start apart and find each other with no ground truth in the run.
    merge = summary["merge"]
    assert merge["members"] == ["r0", "r1"] and merge["joins"]
    rel = merge["evaluation"]["relative_poses"][0]
    assert rel["final_rotation_error_deg"] < 0.5 and rel["final_translation_error_m"] < 0.01
    assert merge["evaluation"]["joint_ate"]["rmse_m"] < 0.02
    assert "ATE RMSE cm" in summary_table(summary)


def test_cli_run_names_a_bad_folder(tmp_path, capsys):
    code = main(["--quiet", "run", "--robot", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")])
    assert code == 2
    assert "nowhere: no such sequence folder" in capsys.readouterr().err


def test_cli_refuses_to_overwrite_a_run(tmp_path, scene, capsys):
    _, folders = scene
    (tmp_path / "o").mkdir()
    code = main(["--quiet", "run", "--robot", f"{folders[0]}:0-4", "--out", str(tmp_path / "o")])
    assert code == 2
    assert "exists" in capsys.readouterr().err
