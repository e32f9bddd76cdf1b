"""The offloading planner: the paper's own numbers give the paper's choice and energies; the
objectives choose what they say; a measured profile round-trips through JSON; the robot's
side is measured with the base install and planned beside the cloud's profile."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from conftest import HANG_S, PROJECT, small_scene
from fleetslam.cli import main
from fleetslam.config import Config, PlannerConfig
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.planner.model import Link, candidates, choose, offloading_ratios
from fleetslam.planner.profile import Profile, RobotSideProfile, paper_profile
from fleetslam.planner.profiling import measure_profile

PAPER_ENERGY = [6.64, 6.79, 4.30, 3.43, 4.48, 4.81, 5.12]
PAPER_T_TR = [5.04, 5.04, 3.04, 2.32, 2.96, 3.20, 3.36]


def _paper_config() -> PlannerConfig:
    return PlannerConfig(c_total_g=1.0)


def test_the_papers_numbers_choose_eta_0484_with_the_papers_energies():
    cands = candidates(paper_profile(), Link(10.0), _paper_config())
    assert [round(c.energy_j, 2) for c in cands] == PAPER_ENERGY
    assert [round(c.t_tr_unit_s, 2) for c in cands] == PAPER_T_TR
    chosen = choose(cands, _paper_config())
    assert chosen.k == 3 and round(chosen.eta, 3) == 0.484
    # eq. 31 with the paper's stated total: its printed candidates.
    assert [round(e, 2) for e in offloading_ratios(paper_profile())] == \
        [0.0, 0.22, 0.4, 0.48, 0.82, 0.85, 1.0]


def test_objectives_choose_what_they_say():
    cfg = _paper_config()
    cands = candidates(paper_profile(), Link(10.0, latency_ms=5.0), cfg)
    assert choose(cands, cfg, "latency").latency_s == min(c.latency_s for c in cands)
    assert choose(cands, cfg, "fps").fps == max(c.fps for c in cands)
    # A point the system does not offer is never chosen, however cheap.
    limited = candidates(paper_profile(), Link(10.0), cfg, offered=(0, 1, 6))
    assert choose(limited, cfg).k == 6
    with pytest.raises(ValueError, match="objective"):
        choose(cands, cfg, "cheapest")
    with pytest.raises(ValueError, match="bandwidth"):
        Link(0.0)


def test_a_faster_link_never_costs_more_energy():
    cfg = _paper_config()
    slow = candidates(paper_profile(), Link(1.0), cfg)
    fast = candidates(paper_profile(), Link(100.0), cfg)
    assert all(f.energy_j < s.energy_j for f, s in zip(fast, slow))
    # With almost free transmission (10 Gbit/s) the robot's own computation dominates:
    # offload it all.
    assert choose(candidates(paper_profile(), Link(10_000.0), cfg), cfg).k == 0


def test_a_measured_profile_round_trips_and_a_bad_one_is_named(tmp_path_factory, tmp_path):
    folder = small_scene(tmp_path_factory, 12)[0]
    profile = measure_profile(RgbdSequence(folder), str(folder), Config(), 12)
    assert len(profile.stage_ms) == 6 and len(profile.frame_bytes) == 7
    assert profile.frame_bytes[0] > profile.frame_bytes[3] > 0
    assert profile.keyframe_bytes > 0 and 0 < profile.keyframe_fraction <= 1
    # Point 6's payload is the real message: its keyframes carry their features (about a
    # point-3 frame each), so the merger gets them and the planner counts them.
    assert profile.frame_bytes[6] > 0.8 * profile.keyframe_fraction * profile.frame_bytes[3]
    path = tmp_path / "profile.json"
    profile.save(path)
    assert Profile.load(path) == profile
    path.write_text(json.dumps({"version": 1, "stages": []}))
    with pytest.raises(ValueError, match="profile.json: not a profile"):
        Profile.load(path)


def test_cli_plan_paper_writes_the_plan_and_plots(tmp_path, capsys):
    assert main(["--quiet", "plan", "--paper", "--out", str(tmp_path / "plan")]) == 0
    out = capsys.readouterr().out
    assert "choice: k = 3, eta = 0.484" in out and "3.43" in out
    plan = json.loads((tmp_path / "plan" / "plan.json").read_text())
    assert plan["links"][0]["chosen_k"] == 3
    for name in ("energy.png", "transmission_time.png"):
        assert (tmp_path / "plan" / name).stat().st_size > 1000


def test_whole_system_energy_is_power_times_measured_time():
    from fleetslam.planner.energy_report import whole_system, whole_system_table

    cfg = PlannerConfig()
    summary = {"wall_time_s": 100.0, "merge_wall_time_s": 10.0, "robots": [
        {"name": "r0", "offload_at": 3, "cloud_s_total": 20.0,
         "robot": {"robot_compute_s": 12.0, "link_busy_s": 30.0}}]}
    w = whole_system(summary, cfg)
    robot_s = 12.0 * 3.3 / 1.2  # the robot's slower CPU
    assert w["E_localization"] == pytest.approx(0.9 * robot_s + 1.3 * 30.0 + 0.3 * 20.0)
    assert w["E_mapping"] == pytest.approx(3.0) and w["T_total_s"] == 100.0
    assert "540.35" in whole_system_table({"run": w})  # the paper's row beside ours
    with pytest.raises(ValueError, match="no robot report"):
        whole_system({"wall_time_s": 1.0, "robots": [{"name": "r0"}]}, cfg)


# A robot's install: what the cloud extra brings cannot be imported (a finder first on
# sys.meta_path refuses it, as a missing package would be refused), then the command runs.
ROBOT_INSTALL = """
import sys
from fleetslam.cli import CLOUD_EXTRA_MODULES


class CloudExtraMissing:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in CLOUD_EXTRA_MODULES:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None


sys.meta_path.insert(0, CloudExtraMissing())
for name in CLOUD_EXTRA_MODULES:  # none of them loaded before the finder was in place
    assert not any(m == name or m.startswith(name + ".") for m in sys.modules), name
from fleetslam.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _on_a_robot(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(PROJECT / "src")}
    return subprocess.run([sys.executable, "-c", ROBOT_INSTALL, "--quiet", *args],
                          capture_output=True, text=True, env=env, timeout=HANG_S * 5)


def test_the_robots_side_is_measured_with_the_base_install_and_planned_elsewhere(
        tmp_path_factory, tmp_path):
    """`fleetslam plan --robot-side` measures the robot's stages and payloads where none of
    the cloud extra can be imported; the whole profile there says what is missing and what
    to do; the decision takes the robot's file beside a profile measured where the cloud
    runs (and writes plan.json, without the plots that need matplotlib)."""
    folder = small_scene(tmp_path_factory, 8)[0]
    robot_file = tmp_path / "robot.json"
    measured = _on_a_robot("plan", "--robot-side", "--source", str(folder), "--frames", "6",
                           "--save-profile", str(robot_file))
    assert measured.returncode == 0, measured.stderr
    robot = RobotSideProfile.load(robot_file)
    assert robot.stages == ["extract", "describe", "associate_depth"] and robot.frames == 6
    assert all(ms > 0 for ms in robot.stage_ms) and len(robot.frame_bytes) == 4
    assert robot.frame_bytes[0] > robot.frame_bytes[3] > 0 and robot.keyframe_bytes > 0
    assert f"--robot-profile {robot_file}" in measured.stdout

    whole = _on_a_robot("plan", "--source", str(folder), "--frames", "6")
    assert whole.returncode == 2
    assert "pip install 'fleetslam[cloud]'" in whole.stderr and "--robot-side" in whole.stderr
    assert "No module named" in whole.stderr  # which module it missed

    cloud_file = tmp_path / "cloud.json"
    measure_profile(RgbdSequence(folder), str(folder), Config(), 6).save(cloud_file)
    with pytest.raises(ValueError, match="--robot-profile"):
        Profile.load(robot_file)  # not a whole profile: said how to use it
    planned = _on_a_robot("plan", "--profile", str(cloud_file), "--robot-profile",
                          str(robot_file), "--out", str(tmp_path / "plan"))
    assert planned.returncode == 0, planned.stderr
    assert "plots not drawn: they need matplotlib" in planned.stdout
    used = json.loads((tmp_path / "plan" / "plan.json").read_text())["profile"]
    assert used["robot_stage_ms"] == [*robot.stage_ms, None, None, None]
    assert used["frame_bytes"][:4] == robot.frame_bytes
    assert used["keyframe_bytes"] == robot.keyframe_bytes
