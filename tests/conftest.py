from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

import fleetslam  # noqa: F401  (first: one BLAS thread a process, set before numpy loads)

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

PROJECT = Path(__file__).resolve().parents[1]
SHARED_DATA = PROJECT.parent / "shared" / "data"
SEVEN_SCENES = SHARED_DATA / "7scenes_redkitchen_seq01_f0000-0599"
TUM_RPY = SHARED_DATA / "tum_fr1_rpy_f000-149"
FRAGMENTS = SHARED_DATA / "3dmatch_7scenes-redkitchen_fragments"
# A bound on a measured duration fails only beyond this: far past anything expected, even on
# a loaded machine, so it catches a hang or a wrong deadline path, never a slow machine
# (tests/test_test_hygiene.py).
HANG_S = 60.0


def require(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"real data not present: {path}")
    return path


def small_scene(tmp_path_factory, frames_per_robot: int) -> list[Path]:
    """The built-in synthetic scene (2 robots) with this many frames each, in a temp dir."""
    from fleetslam.config import Config
    from fleetslam.datasets.synthetic import ensure_scene

    config = Config().with_values({"synthetic.frames_per_robot": frames_per_robot})
    return ensure_scene(tmp_path_factory.mktemp("scene") / "s", config.synthetic)


@pytest.fixture(scope="session")
def synthetic_scene(tmp_path_factory):
    """(config, folders): the synthetic scene, 2 robots of 30 frames."""
    from fleetslam.config import Config

    config = Config().with_values({"synthetic.frames_per_robot": 30})
    return config, small_scene(tmp_path_factory, 30)


@pytest.fixture(scope="session")
def synthetic_run(synthetic_scene, tmp_path_factory):
    """(run folder, summary) of the in-process run of the synthetic scene: the cheapest
    two-robot run that merges, shared by every test that reads a run's outputs."""
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.system import run_fleet

    config, folders = synthetic_scene
    out = tmp_path_factory.mktemp("runs") / "run"
    robots = [(f"r{i}", str(f), RgbdSequence(f)) for i, f in enumerate(folders)]
    return out, run_fleet(robots, config, out, show_progress=False)


def mcap_messages(path: Path) -> list[tuple[str, str, int, bytes]]:
    """(topic, schema name, log time, serialised message) of every message of an MCAP
    file, in the order the file has them, read with the mcap library alone."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(channel.topic, schema.name, message.log_time, message.data)
                for schema, channel, message in make_reader(f).iter_messages()]


def exact_config():
    """The defaults with local mapping in-line in the cloud too: the cloud's poses are then
    bit-identical to an in-memory run (with ``async`` they depend on when each local BA
    lands)."""
    from fleetslam.config import Config

    config = Config().with_values({"tracking.local_mapping": "inline"})
    return config


def tracked_by_itself(last: int, min_keyframes: int):
    """(camera, tracked frames) of a robot tracking redkitchen 0..``last`` by itself (point
    6's stages, exact_config), with at least ``min_keyframes`` keyframes."""
    from fleetslam.backend.robot_slam import RobotSlam
    from fleetslam.datasets.recording import open_source
    from fleetslam.pipeline.split import run_stages
    from fleetslam.pipeline.states import CapturedFrame

    sequence = open_source(f"{require(SEVEN_SCENES)}:0-{last}")
    pipeline = RobotSlam.new(exact_config(), sequence.camera)
    frames = [run_stages(pipeline.stages, CapturedFrame(f.index, f.timestamp, f.rgb,
                                                        f.depth_m), pipeline.sides)
              for f in sequence]
    assert sum(t.is_keyframe for t in frames) >= min_keyframes
    return sequence.camera, frames


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


# ---------------------------------------------------------------- a ROS 2 graph over Zenoh

@pytest.fixture(scope="module")
def etcd(tmp_path_factory):
    """One real etcd on loopback for a test module (each test keeps to a key prefix of its
    own); skip the module where the etcd program is missing."""
    from fleetslam.cloud.coordination.coordination_service import EtcdService

    with EtcdService(tmp_path_factory.mktemp("run") / "etcd") as service:
        yield service


@pytest.fixture
def keys(request):
    """A key prefix of the test's own in the module's etcd: no test sees another's robots."""
    from fleetslam.cloud.coordination.ownership import Keys

    return Keys(f"test/{request.node.name}/")


@pytest.fixture(scope="module")
def ros_router() -> Iterator[str]:
    """A Zenoh router on a free loopback port, standing in for the robot's rmw_zenohd."""
    from fleetslam.launch import free_endpoint
    from fleetslam.transport.zenoh_session import open_router

    endpoint = free_endpoint()
    router = open_router(endpoint)
    yield endpoint
    router.close()


@pytest.fixture
def sdk_session(ros_router) -> Iterator[str]:
    """zenoh-ros2-sdk's one shared session, on ``ros_router``, closed after the test (the
    SDK keeps it in a class attribute for the whole process otherwise)."""
    from zenoh_ros2_sdk.session import ZenohSession

    port = int(ros_router.rsplit(":", 1)[1])
    session = ZenohSession.get_instance("127.0.0.1", port)
    if session.router_port != port:  # left over from another router
        session.close()
        session = ZenohSession.get_instance("127.0.0.1", port)
    yield ros_router
    session.close()
