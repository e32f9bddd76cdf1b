"""A worker's etcd lease, kept alive by a small process of its own.

Why a process: a lease renewed by a thread of the worker waits for the worker's interpreter,
and a loaded worker (many robots' threads) let its renewals slip past the fence: false
fences, robots failed over from a worker that was serving them. Here the renewals run in a
process that does nothing else, its own interpreter, its sockets marked expedited
(etcd_gateway: DSCP EF) so a link full of the robots' frames lets them ahead where the
network honours it.

Why several renewals in flight: on a congested link (a queue of hundreds of milliseconds each
way, packets dropped at its tail) one keepalive waits for its round trip, and for TCP's
retransmission of whatever was dropped, seconds. Renewals go out evenly,
``RENEWALS_PER_LEASE`` per lease, on ``CONNECTIONS`` connections (one waiting for its answer
does not hold up the next), each answer counted however late it comes: the lease is good
until ``sent + ttl - margin``, as etcd received the renewal no earlier than it was sent. The
worker is fenced only when no renewal comes back within ``ttl - margin`` of being sent.

Shared with the worker (one small struct behind a lock): the lease, the moment until which the
worker may serve under it (CLOCK_MONOTONIC, one clock for every process of the machine), and
the worker's heartbeat. The keeper never extends a lease past its moment (the worker may have
fenced its robots then; a lease that lapsed is revoked and a new one granted), stops renewing
when the worker has not beaten for ``stall_s`` (a stopped or frozen worker must not hold its
robots), and revokes the lease and ends when the worker ends or is gone.
"""

from __future__ import annotations

import ctypes
import logging
import multiprocessing
import os
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from fleetslam.backend.workers import end_process
from fleetslam.cloud.coordination.etcd_gateway import EtcdClient, EtcdError, EtcdTls, LeaseExpired

# Renewals sent per lease period, evenly (12 per 2 s lease: one every 0.17 s, ~500 bytes
# each way), and the connections they take turns on: renewals keep their spacing up to a
# round trip of CONNECTIONS spacings (1 s), and a dropped packet holds up one connection.
RENEWALS_PER_LEASE = 12
CONNECTIONS = 6
# How often the keeper looks at the worker and its lease (a lapsed lease is replaced then).
POLL_S = 0.05
# What the keeper tells the worker: ("log", level, text) or ("no-lease", text).
Message = tuple[Any, ...]


class Shared(ctypes.Structure):
    _fields_ = [("lease", ctypes.c_int64), ("ttl", ctypes.c_int64),
                ("valid_until", ctypes.c_double), ("beat", ctypes.c_double),
                ("closing", ctypes.c_int)]


class LeaseKeeper:
    """The worker's side: start the process, read the lease, beat, hear what it says."""

    def __init__(self, client: EtcdClient, worker_id: str, lease_s: int, stall_s: float
                 ) -> None:
        self.client = client
        self.worker_id = worker_id
        self.lease_s = lease_s
        self.stall_s = stall_s
        self._context = multiprocessing.get_context("spawn")
        self._shared: Any = None
        self._conn: Connection | None = None
        self._process: Any = None

    def start(self, deadline_s: float) -> tuple[int, int]:
        """Start the process and wait for its first lease: (lease, ttl). EtcdError if etcd
        granted none (the process is stopped again), TimeoutError past ``deadline_s``."""
        self.spawn()
        deadline = time.monotonic() + deadline_s
        while time.monotonic() < deadline:
            lease, ttl = self.granted()
            if lease:
                return lease, ttl
            for message in self.messages(0.02):
                if message[0] == "no-lease":
                    self.close(0.5)
                    raise EtcdError(message[1])
            if not self._process.is_alive():
                break
        self.close(0.5)
        raise TimeoutError(f"worker {self.worker_id}: its lease process "
                           f"{'ended' if self._process.exitcode is not None else 'has not'} "
                           f"granted a lease within {deadline_s:g} s")

    def spawn(self) -> None:
        """Start the process (it asks etcd for a lease until granted one)."""
        self._shared = self._context.Value(Shared, lock=True)
        self.beat()
        parent, child = self._context.Pipe(duplex=False)
        tls = self.client.tls
        self._process = self._context.Process(
            target=_keep, name=f"fleetslam-lease-{self.worker_id}", daemon=True,
            args=(self._shared, child, self.client.endpoint, self.client.timeout_s,
                  None if tls is None else str(tls.folder), self.worker_id, self.lease_s,
                  self.stall_s, os.getpid()))
        self._process.start()
        child.close()
        self._conn = parent

    def granted(self) -> tuple[int, int]:
        with self._shared.get_lock():
            return self._shared.lease, self._shared.ttl

    def read(self) -> tuple[int, float]:
        """(lease, monotonic moment until which it may be served under); (0, 0) before start."""
        if self._shared is None:
            return 0, 0.0
        with self._shared.get_lock():
            return self._shared.lease, self._shared.valid_until

    def beat(self) -> None:
        """The worker is alive (the keeper renews only while it hears this)."""
        with self._shared.get_lock():
            self._shared.beat = time.monotonic()

    def alive(self) -> bool:
        return self._process is not None and self._process.is_alive()

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    @property
    def exitcode(self) -> int | None:
        return None if self._process is None else self._process.exitcode

    def messages(self, wait_s: float = 0.0) -> list[Message]:
        """What the process said since last asked (waiting up to ``wait_s`` for a first)."""
        out: list[Message] = []
        conn = self._conn
        try:
            while conn is not None and conn.poll(wait_s if not out else 0):
                out.append(conn.recv())
        except (EOFError, OSError):
            pass
        return out

    def close(self, deadline_s: float) -> bool:
        """Stop the process (it revokes its lease first); whether it ended on its own."""
        if self._process is None:
            return True
        with self._shared.get_lock():
            self._shared.closing = 1
        ended = end_process(self._process, deadline_s)
        if self._conn is not None:
            self._conn.close()
        return ended


# -- the process -----------------------------------------------------------------------------

class _Keeper:
    def __init__(self, shared: Any, conn: Connection, client: EtcdClient, worker_id: str,
                 lease_s: int, stall_s: float, parent_pid: int) -> None:
        self.shared, self.conn, self.client = shared, conn, client
        self.worker_id, self.lease_s, self.stall_s = worker_id, lease_s, stall_s
        self.parent_pid = parent_pid
        self.spacing = lease_s / RENEWALS_PER_LEASE
        self.margin = lease_s / 4  # the fence comes this long before etcd may expire it
        self._slot_lock = threading.Lock()
        self._slot = 0.0  # when the last renewal taken was (or is) due
        self.stop = threading.Event()
        self._said_lock = threading.Lock()
        self._said: dict[str, float] = {}

    def say(self, level: int, text: str, every_s: float = 0.0, topic: str = "") -> None:
        """To the worker's log; at most once per ``every_s`` per ``topic``."""
        if every_s:
            now = time.monotonic()
            with self._said_lock:
                if now - self._said.get(topic, -every_s) < every_s:
                    return
                self._said[topic] = now
        try:
            self.conn.send(("log", level, text))
        except (OSError, ValueError):
            pass

    def state(self) -> tuple[int, int, float, float, int]:
        with self.shared.get_lock():
            s = self.shared
            return s.lease, s.ttl, s.valid_until, s.beat, s.closing

    def run(self) -> None:
        renewers = [threading.Thread(target=self.renew, daemon=True, name=f"renew-{i}")
                    for i in range(CONNECTIONS)]
        for thread in renewers:
            thread.start()
        stalled = False
        try:
            while True:
                lease, _, valid_until, beat, closing = self.state()
                if closing or os.getppid() != self.parent_pid:
                    self.drop(lease, "the worker ended" if closing else "the worker is gone")
                    return
                now = time.monotonic()
                if now - beat > self.stall_s and not stalled:
                    self.say(logging.ERROR, f"worker {self.worker_id}: no sign of life for "
                                            f"{now - beat:.1f} s (placement.stall_s "
                                            f"{self.stall_s:g}): its lease is let go")
                stalled = now - beat > self.stall_s
                if lease and now >= valid_until:
                    self.drop(lease, "it lapsed")
                elif not lease and not stalled:
                    self.grant()
                time.sleep(POLL_S)
        finally:
            self.stop.set()

    def grant(self) -> None:
        sent = time.monotonic()
        try:
            lease, ttl = self.client.lease_grant(self.lease_s)
        except EtcdError as exc:
            try:
                self.conn.send(("no-lease", f"worker {self.worker_id}: no lease ({exc})"))
            except (OSError, ValueError):
                pass
            time.sleep(self.lease_s / 3)
            return
        with self.shared.get_lock():
            self.shared.lease, self.shared.ttl = lease, ttl
            self.shared.valid_until = sent + ttl - self.margin

    def drop(self, lease: int, why: str) -> None:
        """The lease is not served under any more: revoke it (its robots are free at once)."""
        with self.shared.get_lock():
            if self.shared.lease == lease:
                self.shared.lease, self.shared.valid_until = 0, 0.0
        if not lease:
            return
        try:
            self.client.lease_revoke(lease)
        except EtcdError as exc:
            if "not found" not in str(exc):
                self.say(logging.WARNING, f"worker {self.worker_id}: lease {lease:x} not "
                                          f"revoked after {why} ({exc}); it expires within "
                                          f"{self.lease_s} s")

    def next_slot(self) -> float:
        """When the next renewal is due: ``spacing`` after the last one taken, or now."""
        with self._slot_lock:
            self._slot = max(self._slot + self.spacing, time.monotonic())
            return self._slot

    def renew(self) -> None:
        """One connection's renewals, each at the next free slot."""
        while not self.stop.is_set():
            self.stop.wait(max(0.0, self.next_slot() - time.monotonic()))
            lease, ttl, valid_until, beat, closing = self.state()
            sent = time.monotonic()
            if not lease or closing or sent >= valid_until or sent - beat > self.stall_s:
                continue
            try:
                # However late, an answer extends the lease from when it was sent.
                got = self.client.lease_keepalive(lease, timeout_s=float(max(ttl, 1)))
            except LeaseExpired as exc:  # gone at etcd already: no use serving under it
                self.say(logging.WARNING, f"worker {self.worker_id}: {exc}")
                with self.shared.get_lock():
                    if self.shared.lease == lease:
                        self.shared.valid_until = 0.0
                continue
            except EtcdError as exc:
                left = max(0.0, self.state()[2] - time.monotonic())
                self.say(logging.WARNING, f"worker {self.worker_id}: lease {lease:x} not "
                                          f"renewed ({exc}); fenced in {left:.2f} s without "
                                          f"a renewal", every_s=self.lease_s / 3,
                         topic="renew")
                continue
            with self.shared.get_lock():
                # Never past its moment: the worker may have fenced its robots by then.
                if self.shared.lease == lease and time.monotonic() < self.shared.valid_until:
                    self.shared.valid_until = max(self.shared.valid_until,
                                                  sent + got - self.margin)


def _keep(shared: Any, conn: Connection, endpoint: str, timeout_s: float, tls: str | None,
          worker_id: str, lease_s: int, stall_s: float, parent_pid: int) -> None:
    client = EtcdClient(endpoint, timeout_s, None if tls is None else EtcdTls(Path(tls)),
                        expedited=True)
    _Keeper(shared, conn, client, worker_id, lease_s, stall_s, parent_pid).run()
