"""A worker's lease kept by a process of its own (cloud/coordination/lease_keeper.py), through a
real etcd: a slow link to etcd (answers later than a renewal period) and a worker whose interpreter
is busy for longer than the fence leave the worker's robots with it; a worker frozen past
``stall_s`` lets them go; a killed keeper is replaced; the keeper's packets are marked expedited."""

from __future__ import annotations

import logging
import os
import signal
import socket
import sys
import time

import pytest
from conftest import wait_for
from link_cutter import LinkCutter

from fleetslam.cloud.coordination.coordination_service import etcd_binary
from fleetslam.cloud.coordination.etcd_gateway import EXPEDITED_TOS, EtcdClient
from fleetslam.cloud.coordination.ownership import Keys, Ownership
from fleetslam.config import PlacementConfig

pytestmark = pytest.mark.skipif(
    etcd_binary() is None,
    reason="the etcd program is not installed (scripts/setup-system.sh installs etcd-server)")

LEASE_S = PlacementConfig.lease_s


def _worker(endpoint: str, keys: Keys, fenced: list, stall_s: float = PlacementConfig.stall_s
            ) -> Ownership:
    return Ownership(EtcdClient(endpoint), "wa", LEASE_S, fenced.append, keys,
                     stall_s=stall_s).start()


def _hold_the_interpreter(seconds: float) -> None:
    """No other thread of this process runs meanwhile (a worker's lease thread starved)."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(seconds * 2)
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pass
    finally:
        sys.setswitchinterval(interval)


def test_a_slow_link_to_etcd_does_not_fence_the_worker(etcd, keys):
    """Every answer arrives 0.9 s after its renewal was sent (a queue on a congested link),
    longer than a renewal period: the answers still count, from when each was sent."""
    link = LinkCutter(etcd.client_port)
    fenced: list = []
    a = _worker(link.endpoint, keys, fenced)
    try:
        epoch = a.grant("r1")
        assert epoch is not None
        link.delay_s = 0.45
        time.sleep(LEASE_S * 3)
        assert not fenced and a.epoch("r1") == epoch
        owner = EtcdClient(etcd.endpoint).get(keys.owner("r1"))
        assert owner is not None and owner.create_revision == epoch
    finally:
        a.close()
        link.close()


def test_a_busy_worker_keeps_its_lease(etcd, keys):
    fenced: list = []
    a = _worker(etcd.endpoint, keys, fenced)
    try:
        epoch = a.grant("r1")
        _hold_the_interpreter(LEASE_S * 1.5)  # twice the fence's 3/4 of the lease
        time.sleep(0.3)
        assert not fenced and a.epoch("r1") == epoch and a.fences == 0
    finally:
        a.close()


def test_a_frozen_worker_lets_its_robots_go(etcd, keys, caplog):
    caplog.set_level(logging.INFO, "fleetslam.ownership")
    fenced: list = []
    a = _worker(etcd.endpoint, keys, fenced, stall_s=1.0)
    b = _worker(etcd.endpoint, Keys(keys.prefix), [])
    try:
        epoch = a.grant("r1")
        _hold_the_interpreter(LEASE_S * 2)
        # The keeper stopped renewing after 1 s without a beat and revoked the lease at its
        # fence: the robot is free at etcd, and the worker, awake again, knows it lost it.
        assert EtcdClient(etcd.endpoint).get(keys.owner("r1")) is None
        wait_for(lambda: fenced, 2.0, "the frozen worker's fence")
        assert fenced[0] == [("r1", epoch)] and a.epoch("r1") is None
        assert any("no sign of life" in r.message for r in caplog.records)
        assert b.grant("r1") > epoch
        wait_for(a.live, LEASE_S * 3, "the worker's new lease")
    finally:
        a.close()
        b.close()


def test_a_killed_lease_process_is_replaced(etcd, keys, caplog):
    fenced: list = []
    a = _worker(etcd.endpoint, keys, fenced)
    try:
        epoch = a.grant("r1")
        pid = a._keeper.pid
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: fenced, LEASE_S * 2, "the fence of the lease nobody renews")
        assert fenced[0] == [("r1", epoch)]
        wait_for(a.live, LEASE_S * 5, "a new keeper's lease")
        assert a._keeper.pid != pid
        # The old lease's key expires with it; then the robot is this worker's again.
        wait_for(lambda: a.grant("r1") is not None, LEASE_S * 3, "the robot granted again")
        assert a.epoch("r1") > epoch
    finally:
        a.close()


def test_the_keepers_packets_are_marked_expedited(etcd):
    client = EtcdClient(etcd.endpoint, expedited=True)
    client.get("k")
    sock = client._connection().sock
    assert sock.getsockopt(socket.IPPROTO_IP, socket.IP_TOS) == EXPEDITED_TOS
    plain = EtcdClient(etcd.endpoint)
    plain.get("k")
    assert plain._connection().sock.getsockopt(socket.IPPROTO_IP, socket.IP_TOS) == 0
