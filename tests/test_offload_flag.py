"""A wrong ``--offload-at`` is one line naming the flag and what it may be, before anything
starts: no cloud, no robot, no synthetic scene, no run folder with a lab's TLS keys."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"


def fleetslam(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(SRC))
    return subprocess.run([sys.executable, "-m", "fleetslam.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("point, told", [
    ("7", "there are 6 stages"),
    ("4", "splits the tracking map"),
    ("banana", "give one of 0, 1, 2, 3, 6, 'paper'"),
])
def test_demo_refuses_a_bad_point_before_starting_anything(tmp_path, point, told):
    done = fleetslam(["demo", "--offload-at", point, "--out", "run", "--scene", "scene",
                      "--frames", "3"], tmp_path)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1
    assert done.stderr.startswith(f"fleetslam: error: --offload-at {point}: ") \
        and told in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no run folder, no scene


@pytest.mark.parametrize("point", ["7", "4", "banana"])
def test_robot_refuses_a_bad_point_before_opening_its_source(tmp_path, point):
    # The source does not exist: the point is what is told (a camera would not be started).
    done = fleetslam(["robot", "--id", "r1", "--source", "nowhere", "--offload-at", point],
                     tmp_path)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1
    assert done.stderr.startswith(f"fleetslam: error: --offload-at {point}: ")
    assert list(tmp_path.iterdir()) == []
