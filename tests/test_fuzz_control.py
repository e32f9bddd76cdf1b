"""A short run of bench/fuzz_control.py: hostile control messages and orders through a real
cloud process raise nothing in it (only clean rejections) and it keeps answering."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from conftest import small_scene

from fleetslam.datasets.tum import RgbdSequence
from fleetslam.launch import CloudClient, free_endpoint, start_cloud, stop

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import fuzz_control  # noqa: E402

# Every order of the end and a sample of hostile fields, unknown types and JSON.
SMOKE = ("end before", "end twice", "end for frames", "end, hello, end", "end last_seq",
         "end keyframe_poses nan", "end camera list", "end unavailable NaN", "hello twice",
         "hello then a changed point", "ack for unknown", "need (frames)",
         "nonsense (hostile)", "control deep nesting in a session",
         "control over 1 MB in a session", "control NaN type", "cloud unknown request",
         "hello offload_at 2^64", "hello camera fx NaN", "flood of 500 ends")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return small_scene(tmp_path_factory, 2)


def test_hostile_control_messages_raise_nothing_in_a_cloud_process(scene, tmp_path):
    camera = RgbdSequence(scene[0]).camera.to_dict()
    chosen = [c for c in fuzz_control.cases(camera) if c[0].startswith(SMOKE)]
    assert len(chosen) >= 35
    endpoint = free_endpoint()
    log_path = tmp_path / "cloud.log"
    cloud = start_cloud(endpoint, tmp_path / "cloud", log_path)
    try:
        client = CloudClient(endpoint, 60.0)
        client.status(timeout=60.0)
        client.close()
        results = fuzz_control.run_cases(endpoint, cloud.pid, chosen, settle_s=0.02)
    finally:
        stop(cloud)
    assert [r["case"] for r in results if r["status_s"] is None] == []
    found = fuzz_control.exceptions_in(log_path.read_text(errors="replace"))
    assert found == [], found[:5]
