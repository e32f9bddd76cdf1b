"""The robot's command-line choices: offloading point and pace."""

from __future__ import annotations

import pytest

from fleetslam.edge.robot import parse_offload_point, parse_rate
from fleetslam.pipeline.stages import default_stages
from fleetslam.transport import keys

NAMES = [s.name for s in default_stages()]


def test_offloading_points():
    assert parse_offload_point("paper", NAMES) == 3
    assert parse_offload_point("match", NAMES) == 3  # the first stage in the cloud
    assert parse_offload_point("0", NAMES) == 0
    assert parse_offload_point("6", NAMES) == 6
    for k in ("4", "5", "estimate_pose"):
        with pytest.raises(ValueError, match="splits the tracking map"):
            parse_offload_point(k, NAMES)
    with pytest.raises(ValueError, match="give 0..6"):
        parse_offload_point("later", NAMES)


def test_rates():
    assert parse_rate("max") is None
    assert parse_rate("recorded") == 0.0
    assert parse_rate("12.5") == 12.5
    for bad in ("0", "-3", "fast"):
        with pytest.raises(ValueError, match="frames per second"):
            parse_rate(bad)


def test_robot_ids_are_one_key_chunk():
    assert keys.frame("r-1_a") == "fleet/r-1_a/frame"
    assert keys.robot_of("fleet/r7/keyframe") == "r7"
    for bad in ("a/b", "", "x" * 65, "cloud", "r 1", "r*"):
        with pytest.raises(ValueError):
            keys.check_robot_id(bad)
    with pytest.raises(ValueError):
        keys.robot_of("other/r1/frame")


def test_a_robot_with_no_cloud_says_so_and_gives_up_at_its_deadline(caplog):
    from fleetslam.launch import free_endpoint
    from fleetslam.transport.zenoh_session import wait_until_reachable

    endpoint = free_endpoint()
    with pytest.raises(RuntimeError, match="nothing answers at .* is the cloud running"):
        wait_until_reachable(endpoint, deadline_s=1.5, attempt_s=0.5)
    assert "retrying" in caplog.text
