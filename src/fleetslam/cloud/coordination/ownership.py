"""Which worker owns which robot, decided by etcd (not by who is reachable), with fencing tokens.

Each worker holds one etcd lease of ``placement.lease_s`` seconds, renewed by a process of its own
(``lease_keeper.py``: no renewal waits for the worker's busy interpreter). A robot's owner is the
key ``<prefix>owner/<robot>`` = worker id, attached to that lease:

- ``grant(robot)`` is one transaction: it succeeds only if the robot has no owner key (a dead
  worker's key went with its lease), and writes the key. A new robot's grant also names the
  revision of the owner table it was decided on (``owners()``, ``basis``): it fails
  (``StaleCounts``) if any grant was written since, so no worker takes a robot on counts that
  another's grant has made stale. Its **epoch** (the fencing token) is
  the key's create revision: etcd's revisions only grow, so every later grant of the robot,
  by any worker, has a larger epoch. Writes that matter (``fenced_store.py``) are
  transactions conditioned on the owner key still having this epoch and this lease.
- A worker that has not renewed its lease for ``lease_s - margin`` (``margin`` = a quarter
  of the lease) fences itself: it drops every robot and calls ``on_fenced`` so the worker
  stops serving them, before etcd can expire the lease and grant them to anyone else. etcd
  expires a lease no earlier than ``lease_s`` after the renewal it last received, which was
  sent after the time this worker counts from; so the fence comes at least ``margin`` first.
- Fenced, the worker gets a new lease (its robots are gone: they are granted again, to
  whoever asks, with new epochs). A worker that stops beating (stopped, frozen) for
  ``placement.stall_s`` has its lease let go the same way.

The merger is granted the same way, under the name ``MERGER``: one at a time, fenced alike.
Every grant, release and fence is logged with its epoch (the partition tests check them).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable

from fleetslam.cloud.coordination.etcd_gateway import (EtcdClient, EtcdError, compare, delete_op,
                                                       prefix_end, put_op, range_op)
from fleetslam.cloud.coordination.lease_keeper import LeaseKeeper
from fleetslam.config import PlacementConfig

log = logging.getLogger("fleetslam.ownership")

# Told which (robot, epoch) this worker may no longer serve; called on the lease's thread, must
# return quickly (stop serving; the store refuses the rest anyway).
Fenced = Callable[[list[tuple[str, int]]], None]
Lost = Callable[[str, int, str], None]


# The merger is granted like a robot (one at a time, with an epoch); robot ids are
# [A-Za-z0-9_-] (validation/names.py), so this name is never a robot's.
MERGER = "@merger"
# The lease's thread beats for its keeper this often (and fences at the lease's moment).
BEAT_S = 0.1
# A keeper's process starts within this (spawned: a fresh interpreter and its imports).
START_S = 10.0


@dataclass(frozen=True)
class Keys:
    """Where ownership and the checkpoint pointers live in etcd (one prefix per fleet)."""

    prefix: str = "fleetslam/"

    def owner(self, robot: str) -> str:
        return f"{self.prefix}owner/{robot}"

    def current(self, robot: str) -> str:
        return f"{self.prefix}current/{robot}"

    def ended(self, robot: str) -> str:
        return f"{self.prefix}ended/{robot}"

    def currents(self) -> str:
        return f"{self.prefix}current/"


@dataclass(frozen=True)
class Owner:
    worker: str
    epoch: int
    lease: int


@dataclass(frozen=True)
class Owners:
    """The owner table as etcd held it at one revision: each granted robot's worker (the
    merger under MERGER; keys without a lease are no grants and left out)."""

    revision: int
    workers: dict[str, str]
    # The newest grant's revision (0: none): it changes with every grant, not with a release.
    latest: int

    def counts(self) -> dict[str, int]:
        """Robots granted to each worker (the merger not counted)."""
        out: dict[str, int] = {}
        for robot, worker in self.workers.items():
            if robot != MERGER:
                out[worker] = out.get(worker, 0) + 1
        return out


class StaleCounts(Exception):
    """A grant decided on an owner table that another grant has changed since."""


class Ownership:
    def __init__(self, client: EtcdClient, worker_id: str, lease_s: int,
                 on_fenced: Fenced | None = None, keys: Keys = Keys(),
                 stall_s: float = PlacementConfig.stall_s) -> None:
        self.client = client
        self.worker_id = worker_id
        self.lease_s = lease_s
        self.keys = keys
        # Public: the placement that serves the robots sets it once it exists. ``on_lost``
        # (robot, epoch, why): a grant etcd no longer has while this worker is in touch
        # with it (None: as at a fence).
        self.on_fenced: Fenced = on_fenced or (lambda robots: None)
        self.on_lost: Lost | None = None
        self._keeper = LeaseKeeper(client, worker_id, lease_s, stall_s)
        self._lock = threading.Lock()
        self._lease = 0  # the lease this worker's robots are granted under; 0: none yet
        self._mine: dict[str, int] = {}  # robot -> epoch
        # Robots whose grant went from under this worker (``lost``) until it is granted one
        # again: told to say hello again, not taken back by this worker as a failover.
        self._lost: set[str] = set()
        self._closed = threading.Event()
        self._thread: threading.Thread | None = None
        self.fences = 0

    @property
    def ttl_s(self) -> float:
        return float(self.lease_s)

    # -- lifecycle ----------------------------------------------------------------------------

    def start(self) -> "Ownership":
        """The first lease (EtcdError if etcd grants none), then the thread that beats for
        the keeper and fences this worker when its lease lapses."""
        # Starting the keeper's process takes a fraction of a second; etcd's own timeout on top.
        lease, ttl = self._keeper.start(START_S + self.client.timeout_s)
        self._adopt(lease, ttl)
        self._thread = threading.Thread(target=self._watch_lease,
                                        name=f"lease-{self.worker_id}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Give every robot back at once (revoking the lease deletes their owner keys)."""
        self._closed.set()
        if self._thread is not None:
            self._thread.join(self.ttl_s)
        lease, _ = self._keeper.read()
        with self._lock:
            self._lease, self._mine = 0, {}
        if not self._keeper.close(self.ttl_s + self.client.timeout_s) and lease:
            try:  # the keeper did not end on its own: its lease is revoked from here
                self.client.lease_revoke(lease)
            except EtcdError as exc:  # it expires by itself
                log.warning("worker %s: lease %x not revoked (%s); it expires within %g s",
                            self.worker_id, lease, exc, self.ttl_s)
        self._log_keeper()

    def _adopt(self, lease: int, ttl: int) -> None:
        with self._lock:
            self._lease = lease
        log.info("worker %s: lease %x of %d s", self.worker_id, lease, ttl)

    @property
    def _valid_until(self) -> float:
        """Until when (monotonic) this worker may serve under its lease; 0: not at all."""
        lease, valid_until = self._keeper.read()
        return valid_until if lease and lease == self._lease else 0.0

    def _serving_lease(self) -> int:
        """The lease this worker's robots are served under, if it is alive now (else 0);
        called with ``_lock`` held."""
        lease, valid_until = self._keeper.read()
        if lease == 0 or lease != self._lease or time.monotonic() >= valid_until:
            return 0
        return lease

    # -- what the worker asks -------------------------------------------------------------------

    @property
    def lease(self) -> int:
        return self._lease

    def live(self) -> bool:
        """Whether this worker's lease is surely alive at etcd now (not fenced)."""
        with self._lock:
            return self._serving_lease() != 0

    def epoch(self, robot: str) -> int | None:
        """This worker's epoch for ``robot`` if it owns it now (None: it does not)."""
        with self._lock:
            if not self._serving_lease():
                return None
            return self._mine.get(robot)

    def holding(self, robot: str) -> tuple[int, int] | None:
        """(epoch, lease) under which this worker owns ``robot`` now; None if it does not
        (the fenced store conditions its writes on both)."""
        with self._lock:
            lease = self._serving_lease()
            epoch = self._mine.get(robot) if lease else None
            return None if epoch is None else (epoch, lease)

    def robots(self) -> dict[str, int]:
        with self._lock:
            return dict(self._mine)

    def was_lost(self, robot: str) -> bool:
        """Whether this worker's last grant of ``robot`` went from under it (``lost``)."""
        with self._lock:
            return robot in self._lost

    def owner(self, robot: str) -> Owner | None:
        """The robot's owner as etcd has it now (None: nobody)."""
        kv = self.client.get(self.keys.owner(robot))
        return None if kv is None else Owner(kv.value.decode(), kv.create_revision, kv.lease)

    def owners(self) -> Owners:
        """The owner table now, read from etcd in one request (EtcdError if it cannot be)."""
        prefix = self.keys.owner("")
        kvs, revision = self.client.get_prefix_at(prefix)
        granted = [kv for kv in kvs if kv.lease != 0]
        return Owners(revision, {kv.key.decode()[len(prefix):]: kv.value.decode()
                                 for kv in granted},
                      max((kv.mod_revision for kv in granted), default=0))

    def grant(self, robot: str, retry: bool = True, basis: int | None = None) -> int | None:
        """Own ``robot``: its new epoch, or None if another worker (or this one, under an
        older lease) owns it or this worker is fenced. ``basis``: the revision of the owner
        table the grant was decided on (``owners()``); StaleCounts if a grant was written
        since. EtcdError if etcd cannot be asked."""
        with self._lock:
            lease = self._serving_lease()
            if not lease:
                return None
            if robot in self._mine:
                return self._mine[robot]
        key = self.keys.owner(robot)
        compares = [compare(key, "CREATE", 0)]
        if basis is not None:
            # No owner key written after the table was read: etcd orders the grants, and
            # of two decided on the same counts only the first is written.
            prefix = self.keys.owner("").encode()
            compares.append(compare(prefix, "MOD", basis + 1, "LESS", prefix_end(prefix)))
        try:
            result = self.client.txn(compares,
                                     [put_op(key, self.worker_id, lease), range_op(key)],
                                     [range_op(key)])
        except EtcdError as exc:
            if "lease not found" in str(exc):  # expired at etcd: fenced meanwhile
                return None
            raise
        if result.succeeded:
            epoch = result.ranged(1)[0].create_revision
        else:
            held = result.ranged(0)
            if held and held[0].lease == 0 and retry:
                # No grant is ever without a lease: written outside fleetslam (by hand, or by
                # someone holding a worker's credentials). Not an owner: said, removed (only
                # that very key), and the grant asked again.
                log.error("robot %s: its owner key names %r without a lease (not a grant): "
                          "refused and deleted", robot, held[0].value.decode(errors="replace"))
                self.client.txn([compare(key, "CREATE", held[0].create_revision),
                                 compare(key, "LEASE", 0)], [delete_op(key)])
                return self.grant(robot, retry=False, basis=basis)
            if not held and basis is not None:
                raise StaleCounts(f"robot {robot}: the owner table changed after revision "
                                  f"{basis}")
            if not held or held[0].lease != lease:
                if held:
                    log.debug("robot %s: owned by %s (epoch %d)", robot,
                              held[0].value.decode(), held[0].create_revision)
                return None
            # Our own key under our lease (a grant whose answer was lost, then repeated):
            # ours, or the robot would stay owned and unserved as long as the lease lives.
            epoch = held[0].create_revision
        with self._lock:
            if self._lease != lease:  # fenced while asking: it is not ours to serve
                return None
            self._mine[robot] = epoch
            self._lost.discard(robot)
        log.info("grant robot %s to worker %s epoch %d (lease %x)", robot, self.worker_id,
                 epoch, lease)
        return epoch

    def release(self, robot: str, epoch: int) -> bool:
        """Give ``robot`` up (only the grant of ``epoch`` under this worker's lease is
        deleted); whether it was still ours at etcd."""
        with self._lock:
            if self._mine.get(robot) == epoch:
                del self._mine[robot]
            lease = self._lease
        key = self.keys.owner(robot)
        result = self.client.txn([compare(key, "CREATE", epoch), compare(key, "LEASE", lease)],
                                 [delete_op(key)])
        log.info("release robot %s by worker %s epoch %d%s", robot, self.worker_id, epoch,
                 "" if result.succeeded else " (it was no longer ours)")
        return result.succeeded

    def evict(self, robot: str, epoch: int, why: str) -> bool:
        """Delete another's grant of ``robot`` (``epoch``: only that very key) that serves
        nobody (``why``); whether it was still there. Its holder, if any, is refused its
        next checkpoint (fenced_store.py) and stops serving (``lost``)."""
        key = self.keys.owner(robot)
        result = self.client.txn([compare(key, "CREATE", epoch)], [delete_op(key)])
        log.error("robot %s: grant epoch %d %s (%s)", robot, epoch,
                  "deleted" if result.succeeded else "already gone", why)
        return result.succeeded

    def lost(self, robot: str, epoch: int, why: str) -> None:
        """etcd no longer has this worker's grant of ``robot`` (``epoch``): its key changed or
        went (not by a fence of this worker's lease). The robot is dropped as at a fence, so
        it says hello again and is granted afresh, instead of being served with every
        checkpoint refused."""
        with self._lock:
            if self._mine.get(robot) != epoch:
                return
            del self._mine[robot]
            self._lost.add(robot)  # in the same hold: the key's deletion may be heard now
        log.error("robot %s: worker %s lost its grant epoch %d (%s): stops serving it",
                  robot, self.worker_id, epoch, why)
        try:
            if self.on_lost is not None:
                self.on_lost(robot, epoch, why)
            else:
                self.on_fenced([(robot, epoch)])
        except Exception:
            log.exception("worker %s: the fence callback failed", self.worker_id)

    # -- the lease ----------------------------------------------------------------------------

    def _watch_lease(self) -> None:
        """Beat for the keeper; fence at the lease's moment without a renewal; adopt the
        keeper's next lease; start a keeper again if its process died."""
        while not self._closed.is_set():
            self._keeper.beat()
            self._log_keeper()
            lease, valid_until = self._keeper.read()
            with self._lock:
                mine = self._lease
            now = time.monotonic()
            if mine and (lease != mine or now >= valid_until):
                self._fence(mine, valid_until if lease == mine else now)
                mine = 0
            if not mine and lease and now < valid_until:
                self._adopt(lease, self._keeper.granted()[1])
            if not self._keeper.alive() and not self._closed.is_set():
                self._restart_keeper()
            self._closed.wait(max(0.0, min(BEAT_S, valid_until - now) if lease else BEAT_S))

    def _log_keeper(self) -> None:
        for message in self._keeper.messages():
            if message[0] == "log":
                log.log(message[1], message[2])
            else:  # no new lease yet: said once it is granted, or by placement's status
                log.debug(message[1])

    def _restart_keeper(self) -> None:
        log.error("worker %s: its lease process ended (exit %s); starting another",
                  self.worker_id, self._keeper.exitcode)
        self._keeper.close(0.0)
        self._keeper = LeaseKeeper(self.client, self.worker_id, self.lease_s,
                                   self._keeper.stall_s)
        self._keeper.spawn()  # its lease is adopted here once granted

    def _fence(self, lease: int, valid_until: float) -> None:
        with self._lock:
            if self._lease != lease:
                return
            robots = sorted(self._mine.items())
            self._lease, self._mine = 0, {}
            self.fences += 1
        log.warning("worker %s fenced: lease %x not renewed by its deadline (%.2f s late); "
                    "stops serving %s", self.worker_id, lease, time.monotonic() - valid_until,
                    ", ".join(f"{r} (epoch {e})" for r, e in robots) or "no robot")
        for robot, epoch in robots:
            log.info("fence robot %s on worker %s epoch %d", robot, self.worker_id, epoch)
        try:
            self.on_fenced(robots)
        except Exception:
            log.exception("worker %s: the fence callback failed", self.worker_id)
