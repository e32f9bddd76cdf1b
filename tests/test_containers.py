"""The two images a lab deploys (docs/deployment.md "Containers"): Dockerfile (the cloud and
the operator's tools, with etcd) and Dockerfile.robot (base install and the ros extra only),
built and run with the container engine found, docker or podman. Skipped, saying why, where
none can run a container: the suite runs them wherever it can (CI included) rather than
behind a switch nobody sets; once built, a rebuild after a source change redoes only the
wheel's layer (the dependencies' layer changes with pyproject.toml alone).

FLEETSLAM_CONTAINER_BASE: a base image to build from instead of python:3.11-slim-bookworm
(a machine that cannot reach Docker Hub; any image with Python 3.11 as python and pip).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
from conftest import HANG_S, PROJECT

from fleetslam.launch import free_endpoint

CLOUD, ROBOT = "fleetslam-cloud:test", "fleetslam-robot:test"
DEFAULT_BASE = "docker.io/library/python:3.11-slim-bookworm"  # the Dockerfiles' own
# A cold build downloads the cloud extra's wheels (GTSAM, faiss, ...): minutes, not a hang.
BUILD_S = 30 * 60
# What only the cloud side imports (pyproject's import contract for the robot).
CLOUD_ONLY = ("gtsam", "faiss", "small_gicp", "scipy", "octomap", "matplotlib", "cryptography")


def _engine() -> list[str]:
    """The engine's command (with the options every run needs), or a skip saying why."""
    tried = []
    for name in ("docker", "podman"):
        path = shutil.which(name)
        if path is None:
            tried.append(f"{name}: not on PATH")
            continue
        info = subprocess.run([path, "info"], capture_output=True, text=True, timeout=HANG_S)
        if info.returncode != 0:
            last = (info.stderr.strip().splitlines() or ["no reason given"])[-1]
            tried.append(f"{name}: cannot run containers here ({last})")
            continue
        return [path]
    pytest.skip("no container engine: " + "; ".join(tried))


def _run_options(engine: list[str]) -> list[str]:
    """Run as this user (the test's folders are its own), on the host's network."""
    options = ["--network", "host", "--user", f"{os.getuid()}:{os.getgid()}"]
    if Path(engine[0]).name == "podman" and os.getuid() != 0:
        options.append("--userns=keep-id")  # rootless: this user inside as outside
    return options


def _base(engine: list[str]) -> str:
    """The base image, pulled if missing, or a skip saying why (no registry in reach)."""
    base = os.environ.get("FLEETSLAM_CONTAINER_BASE", DEFAULT_BASE)
    there = subprocess.run([*engine, "image", "inspect", base], capture_output=True,
                           timeout=HANG_S)
    if there.returncode != 0:
        pulled = subprocess.run([*engine, "pull", base], capture_output=True, text=True,
                                timeout=BUILD_S)
        if pulled.returncode != 0:
            last = (pulled.stderr.strip().splitlines() or ["no reason given"])[-1]
            pytest.skip(f"cannot pull the base image {base} ({last}); "
                        f"FLEETSLAM_CONTAINER_BASE names another")
    return base


@pytest.fixture(scope="module")
def images():
    engine = _engine()
    build_args = ["--build-arg", f"BASE={_base(engine)}"]
    for tag, dockerfile in ((CLOUD, "Dockerfile"), (ROBOT, "Dockerfile.robot")):
        built = subprocess.run([*engine, "build", "-f", str(PROJECT / dockerfile), "-t", tag,
                                *build_args, str(PROJECT)],
                               capture_output=True, text=True, timeout=BUILD_S)
        assert built.returncode == 0, f"{dockerfile}:\n{built.stdout[-3000:]}{built.stderr[-3000:]}"
    return engine


def run(engine: list[str], image: str, args: list[str], mounts: dict[Path, str] = {},
        timeout: float = 600) -> subprocess.CompletedProcess:
    volumes = [f"--volume={host}:{inside}" for host, inside in mounts.items()]
    return subprocess.run([*engine, "run", "--rm", *_run_options(engine), *volumes, image,
                           *args], capture_output=True, text=True, timeout=timeout)


def size_mb(engine: list[str], image: str) -> float:
    out = subprocess.run([*engine, "image", "inspect", "--format", "{{.Size}}", image],
                         capture_output=True, text=True, timeout=HANG_S, check=True).stdout
    return int(out.strip()) / 1e6


def test_the_robot_image_holds_nothing_of_the_cloud(images):
    probe = ("import importlib.util, json; print(json.dumps([m for m in %r "
             "if importlib.util.find_spec(m)]))" % (CLOUD_ONLY,))
    done = run(images, ROBOT, ["--help"])
    assert done.returncode == 0 and "robot" in done.stdout, done.stderr
    found = subprocess.run([*images, "run", "--rm", "--entrypoint", "python", ROBOT, "-c",
                            probe], capture_output=True, text=True, timeout=HANG_S)
    assert found.returncode == 0 and json.loads(found.stdout) == [], found.stdout + found.stderr
    # Above their common base, the robot's image holds less than half what the cloud's does.
    base = size_mb(images, _base(images))
    robot, cloud = size_mb(images, ROBOT) - base, size_mb(images, CLOUD) - base
    print(f"\nabove the base's {base:.0f} MB: robot {robot:.0f} MB, cloud {cloud:.0f} MB")
    assert robot < cloud / 2


def test_a_robot_container_tracks_against_a_cloud_container(images, tmp_path):
    (tmp_path / "scene.toml").write_text("[synthetic]\nframes_per_robot = 20\n")
    made = run(images, CLOUD, ["generate", "--quiet", "--config", "/data/scene.toml", "--out",
                               "/data/scene"], {tmp_path: "/data"})
    assert made.returncode == 0, made.stderr
    folder = sorted(p for p in (tmp_path / "scene").iterdir() if (p / "rgb.txt").is_file())[0]
    endpoint = free_endpoint()
    name = f"fleetslam-cloud-{tmp_path.name}"
    cloud = subprocess.Popen([*images, "run", "--rm", "--name", name, *_run_options(images),
                              f"--volume={tmp_path}:/data", CLOUD, "cloud", "--listen",
                              endpoint, "--out", "/data/store"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        robot = run(images, ROBOT, ["robot", "--connect", endpoint, "--id", "r1", "--source",
                                    f"/scene/{folder.name}", "--quiet"],
                    {tmp_path / "scene": "/scene:ro"})
        assert robot.returncode == 0, robot.stdout + robot.stderr
        merged = run(images, CLOUD, ["merge", "--connect", endpoint], {tmp_path: "/data"})
        assert merged.returncode == 0, merged.stdout + merged.stderr
    finally:
        subprocess.run([*images, "stop", "--time", "10", name], capture_output=True,
                       timeout=HANG_S)
        log = cloud.communicate(timeout=HANG_S)[0]
    assert "Traceback" not in log, log
    summary = json.loads((tmp_path / "store" / "summary.json").read_text())
    assert [r["source"] for r in summary["robots"]] == [f"/scene/{folder.name}"]


def test_the_demo_and_etcd_run_in_the_cloud_image(images, tmp_path):
    etcd = subprocess.run([*images, "run", "--rm", "--entrypoint", "etcd", CLOUD, "--version"],
                          capture_output=True, text=True, timeout=HANG_S)
    assert etcd.returncode == 0 and "etcd Version: 3." in etcd.stdout, etcd.stdout + etcd.stderr
    demo = run(images, CLOUD, ["demo", "--frames", "30", "--out", "/data/run"],
               {tmp_path: "/data"})
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr[-3000:]
    assert (tmp_path / "run" / "report" / "report.html").is_file()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert len(summary["robots"]) == 2
