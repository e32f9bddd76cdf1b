"""A new user is told what a command does while it does it: `plan` says how many frames it
measures of how many, and shows progress while it makes the synthetic scene; `status` and
`merge` document --connect and its default."""

from __future__ import annotations

import os
import subprocess
import sys


def _cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fleetslam.cli", *args], capture_output=True,
                          text=True, timeout=120, env=env)


def test_plan_shows_the_scene_setup_and_the_frames_it_measures(tmp_path):
    config = tmp_path / "small.toml"
    config.write_text("[synthetic]\nframes_per_robot = 6\n")
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}  # a scene made here
    result = _cli("--config", str(config), "plan", "--frames", "3", "--out",
                  str(tmp_path / "plan"), env=env)
    assert result.returncode == 0, result.stderr
    scene = tmp_path / "cache" / "fleetslam" / "synthetic-seed1-r2-f6"
    assert f"synthetic scene {scene}: 12/12 frames" in result.stderr
    robot = scene / "robot_0"
    assert (f"profile: measuring the first 3 of the 6 frames of {robot} (--frames N, or "
            f"[planner] profile_frames)") in result.stderr
    assert (f"profile: {robot} (measured on the first 3 of its 6 frames: --frames)"
            in result.stdout.splitlines())


def test_status_and_merge_document_connect():
    for command in ("status", "merge"):
        result = _cli(command, "--help")
        assert result.returncode == 0
        text = " ".join(result.stdout.split())
        assert ("--connect ENDPOINT the cloud's Zenoh endpoint, as its --listen, or a router of "
                "several workers (default from config [transport] endpoint: "
                "tcp/127.0.0.1:7450)") in text, text


def test_version_is_the_packages():
    import tomllib
    from pathlib import Path

    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml")
                            .read_text())["project"]
    result = _cli("--version")
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"fleetslam {project['version']}\n"


def test_a_robot_named_after_a_run_folder_is_refused_before_anything_is_written(tmp_path):
    """A robot's files are <run>/<name>/: a name that is a folder the run keeps beside them
    (global/, map/, report/) or that is no robot id is refused, naming the flag."""
    for name, reason in (("map", "robot id 'map' is reserved"),
                         ("../x", "--name '../x'")):
        out = tmp_path / f"run-{len(name)}"
        result = _cli("--quiet", "run", "--robot", str(tmp_path / "nowhere"), "--name", name,
                      "--out", str(out))
        assert result.returncode != 0 and reason in result.stderr, result.stderr
        assert not out.exists()
