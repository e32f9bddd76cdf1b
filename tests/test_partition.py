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


@pytest.fixture
def namespaces() -> None:
    why = unavailable()
    if why:
        pytest.skip(f"partition test: {why}")
    remove_leftovers()


@pytest.mark.realdata
def test_lost_machine_fails_over_with_one_owner(namespaces: None, tmp_path: Path) -> None:
    from fleetslam.cloud.coordination.coordination_service import etcd_binary

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


def test_the_ownership_check_finds_two_owners_at_once(tmp_path: Path) -> None:
    """The checker the partition test trusts: w1's grant of r0 while w0 still holds it (no
    fence yet) is an overlap; w0's fence before w2's grant, and a re-grant to w0 itself, are
    not."""
    import ownership_log

    (tmp_path / "w0.log").write_text(
        "2026-12-02 10:00:00,000 fleetslam.ownership INFO grant robot r0 to worker w0 epoch 5 "
        "(lease 1)\n"
        "Traceback (not a log line)\n"
        "2026-12-02 10:00:03,000 fleetslam.ownership INFO fence robot r0 on worker w0 epoch 5\n"
        "2026-12-02 10:00:09,000 fleetslam.ownership INFO grant robot r1 to worker w0 epoch 9 "
        "(lease 2)\n")
    (tmp_path / "w1.log").write_text(
        "2026-12-02 10:00:02,500 fleetslam.ownership INFO grant robot r0 to worker w1 epoch 7 "
        "(lease 3)\n"
        "2026-12-02 10:00:04,000 fleetslam.ownership INFO release robot r0 by worker w1 epoch 7\n")
    (tmp_path / "w2.log").write_text(
        "2026-12-02 10:00:04,001 fleetslam.ownership INFO grant robot r0 to worker w2 epoch 8 "
        "(lease 4)\n")
    ivs = [iv for w in ("w0", "w1", "w2")
           for iv in ownership_log.intervals(tmp_path / f"{w}.log", w, ends=None)]
    found = ownership_log.overlaps(ivs)
    assert [(o.robot, o.first.worker, o.second.worker) for o in found] == [("r0", "w0", "w1")]
    assert abs(found[0].seconds - 0.5) < 1e-6
    assert ownership_log.owner_at(ivs, "r0", ownership_log.stamp("2026-12-02 10:00:03,500")) \
        == ["w1"]
    # An ownership never ended (a worker still running) counts as going on.
    assert [iv.end for iv in ivs if iv.robot == "r1"] == [None]


def test_the_service_also_listens_where_it_is_told(tmp_path: Path) -> None:
    """A worker in a namespace reaches etcd at the veth's host address: here 127.0.0.2 (every
    127/8 address is loopback on Linux), beside 127.0.0.1."""
    from fleetslam.cloud.coordination.coordination_service import EtcdService, etcd_binary
    from fleetslam.cloud.coordination.etcd_gateway import EtcdClient

    if etcd_binary() is None:
        pytest.skip("etcd is not installed (scripts/setup-system.sh)")
    with EtcdService(tmp_path / "etcd", also_listen=("127.0.0.2",)) as etcd:
        EtcdClient(etcd.endpoint).put("k", "v")
        kv = EtcdClient(f"http://127.0.0.2:{etcd.client_port}").get("k")
        assert kv is not None and kv.value == b"v"
