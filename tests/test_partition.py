"""A lost machine under etcd ownership (bench/partition.py, one short case): worker B is cut
off in its network namespace for good; its robot fails over to worker A, no keyframe the
cloud acknowledged is lost, and no robot ever had two owners at once (from the workers'
ownership log lines).

The case chosen is "machine lost": it fits in well under a minute (the heal cases wait out a
15 s partition), and it fails under the liveliness placement (FLEETSLAM_PARTITION_PLACEMENT=
liveliness): the isolated worker, which hears no one, keeps believing it owns its robot, and
bids for the others', while A takes it over, so the one-owner check fails there."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from conftest import PROJECT, SEVEN_SCENES, require

sys.path.insert(0, str(PROJECT / "bench"))
sys.path.insert(0, str(PROJECT / "tests"))

from netns_link import remove_leftovers, unavailable  # noqa: E402

pytestmark = pytest.mark.realdata


@pytest.fixture
def namespaces() -> None:
    why = unavailable()
    if why:
        pytest.skip(f"partition test: {why}")
    remove_leftovers()


def test_lost_machine_fails_over_with_one_owner(namespaces: None, tmp_path: Path) -> None:
    from fleetslam.cloud.coordination_service import etcd_binary

    placement = os.environ.get("FLEETSLAM_PARTITION_PLACEMENT", "etcd")
    if placement == "etcd" and etcd_binary() is None:
        pytest.skip("etcd is not installed (scripts/setup-system.sh)")
    require(SEVEN_SCENES)
    import partition

    timing = partition.Timing(cut_at_s=3.0, frames=60, robots=2, start_deadline_s=60.0,
                              run_deadline_s=90.0, merge_deadline_s=60.0)
    result = partition.Run(partition.CASES["lost"], placement, timing,
                           tmp_path / "run").execute()
    print(partition.table(result))
    robots = result["robots"]
    assert result["one_owner"], f"two owners at once: {result['overlaps']}"
    lost = {r: v["acknowledged_lost"] for r, v in robots.items() if v["acknowledged_lost"]}
    assert not lost, f"acknowledged keyframes lost: {lost}"
    assert all(v["acknowledged"] > 0 for v in robots.values()), robots
    cut_off = [r for r, v in robots.items() if v["on_b_at_cut"]]
    assert cut_off, f"B served no robot at the cut: nothing failed over ({result['ownership']})"
    for r in cut_off:
        assert robots[r]["failover_s"] is not None, f"robot {r} was never answered by A again"
