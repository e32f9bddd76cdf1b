from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

PROJECT = Path(__file__).resolve().parents[1]
SHARED_DATA = PROJECT.parent / "shared" / "data"
SEVEN_SCENES = SHARED_DATA / "7scenes_redkitchen_seq01_f0000-0599"
TUM_RPY = SHARED_DATA / "tum_fr1_rpy_f000-149"
FRAGMENTS = SHARED_DATA / "3dmatch_7scenes-redkitchen_fragments"


def require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data not present: {path}")
    return path


def small_scene(tmp_path_factory, frames_per_robot: int) -> list[Path]:
    """The built-in synthetic scene (2 robots) with this many frames each, in a temp dir."""
    from fleetslam.config import Config
    from fleetslam.datasets.synthetic import ensure_scene

    config = Config()
    config.synthetic.frames_per_robot = frames_per_robot
    return ensure_scene(tmp_path_factory.mktemp("scene") / "s", config.synthetic)


def exact_config():
    """The defaults with local mapping in-line in the cloud too: the cloud's poses are then
    bit-identical to an in-memory run (with ``async`` they depend on when each local BA
    lands)."""
    from fleetslam.config import Config

    config = Config()
    config.tracking.local_mapping = "inline"
    return config


def wait_for(predicate, timeout: float, what: str, interval: float = 0.1):
    """The predicate's first true value, polled; AssertionError naming ``what`` at the
    deadline."""
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out waiting for {what}")


def secure_endpoint() -> str:
    """A free loopback endpoint as a lab's TLS endpoint (its cloud certificate names
    localhost)."""
    from fleetslam.launch import free_endpoint

    return free_endpoint().replace("tcp/127.0.0.1", "tls/localhost")
