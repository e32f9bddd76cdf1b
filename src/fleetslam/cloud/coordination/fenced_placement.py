"""Which cloud worker serves which robot, decided by etcd with fencing (``placement.coordination``).

The same questions as placement.py (serves, owner, claim, release), answered by the
coordination service instead of liveliness tokens, so a partition can never leave a robot
with two owners:

- A worker serves a robot only while it holds the robot's grant (ownership.py): an etcd key
  attached to the worker's lease, whose create revision is the grant's epoch. ``serves`` asks
  the local lease clock, so a worker cut off from etcd stops serving by itself, a quarter of
  the lease before etcd may expire the lease and grant the robot to another worker; the
  fence then drops the robot's session unsaved (``give_up``), and the store
  (fenced_store.py) refuses any write of the old epoch that was still under way.
- A claim is one transaction (the first asker wins). Every worker ranks the live workers
  for a new robot by their measured load (worker_load.py: cores busy, plus the robots
  granted since each measured, counted on the owner table read from etcd) and asks at once
  if it ranks first; one ranked later asks only once ``settle_s`` per worker before it has
  passed with no grant (the wait starts again at every grant), so the least loaded asks and
  a slow one is not waited for long. The grant of a new robot is conditioned on the owner
  table it was ranked on (ownership.py: no grant since that revision), so two workers
  never both take robots on the same counts: the second decides again on the new table.
  Robots that arrive together are ranked one at a time as grants land, so they spread (a
  worker ranked second used to take every robot left once ``settle_s`` had passed since
  the hellos, the others' grants or not: 16 robots went 4 + 12 when one worker was slow to
  reach etcd, tests/test_fenced_placement.py); a robot whose owner went (a takeover) is
  asked for at once.
- Every worker watches the owner keys: a key gone (its worker's lease expired, a release)
  is a robot to take over if the store has its checkpoint, and the merger's key gone is a
  merger to become. Zenoh liveliness still says which workers are up (the status; the
  WorkerDirectory of worker_directory.py, as placement.py has one), never who owns.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

import zenoh

from fleetslam.cloud.coordination.coordination_service import CoordinationServiceError
from fleetslam.cloud.coordination.etcd_gateway import EtcdError, Event, Watch
from fleetslam.cloud.coordination.ownership import MERGER, Owners, Ownership, StaleCounts
from fleetslam.cloud.coordination.placement_protocol import Placement, Served
from fleetslam.cloud.coordination.worker_directory import WorkerDirectory
from fleetslam.cloud.coordination.worker_load import LoadMeter
from fleetslam.config import PlacementConfig
from fleetslam.transport import keys, protocol

log = logging.getLogger("fleetslam.placement")

# A robot's owner in etcd that no worker has heard (its Zenoh token) for this many leases
# serves nobody: its robot is taken over. Tokens reach every worker within the routers'
# round trip; a worker starting up is heard before it is granted anything.
UNHEARD_OWNER_LEASES = 2

OUTCOMES = ("won", "lost", "failovers", "given_up", "fenced")


class FencedPlacement(Placement):
    def __init__(self, worker_id: str, cfg: PlacementConfig, meter: LoadMeter,
                 ownership: Ownership) -> None:
        """``meter``: this worker's load now (cores busy, measured: worker_load.CpuMeter);
        ``ownership``: this worker's lease and grants (not started: ``start`` starts it)."""
        self.worker_id = keys.check_worker_id(worker_id)
        self.cfg = cfg
        self.directory = WorkerDirectory(self.worker_id, cfg, meter, self, OUTCOMES)
        self.ownership = ownership
        ownership.on_fenced = self._on_fenced
        ownership.on_lost = self._on_lost
        self._lock = threading.Lock()
        # robot -> (worker, epoch, mod revision) as etcd last said; the merger under MERGER.
        self._owners: dict[str, tuple[str, int, int]] = {}
        self._electing: set[str] = set()
        self._closed = threading.Event()
        # Robots asked for, one election at a time (ranked in _run_elections).
        self._bids: queue.Queue = queue.Queue()
        self._elector = threading.Thread(target=self._run_elections, name="placement",
                                         daemon=True)
        self._watch: Watch | None = None
        # Robots claimed because their owner went (a takeover): claimed at once, not after
        # the load's wait (failover time counts; a new robot's placement does not).
        self._takeovers: set[str] = set()
        # robot -> (epoch, since): its owner in etcd is a worker nobody hears (below).
        self._unheard: dict[str, tuple[int, float]] = {}
        # ((newest grant's revision, grants), when first seen so) of the owner table.
        self._table_seen: tuple[tuple[int, int], float] = ((0, 0), time.monotonic())

    # -- lifecycle ------------------------------------------------------------------------

    def start(self, z: zenoh.Session, served: Served) -> "FencedPlacement":
        self.directory.bind(z, served)
        self.ownership.start()
        self.directory.start_loads(z)
        prefix = self.ownership.keys.owner("")
        client = self.ownership.client
        self._watch = Watch(client.endpoint, prefix, self._on_events, tls=client.tls,
                            on_reset=self._reread).start()
        if not self._watch.created.wait(self.ownership.ttl_s * 2):
            log.warning("the etcd watch of owners at %s is not open yet; retrying",
                        self.ownership.client.endpoint)
        self._reread(clear=False)
        self.directory.announce(z)
        self._elector.start()
        self.claim(MERGER)
        return self

    def close(self) -> None:
        """Give every robot and the merger back at once (revoking the lease)."""
        self._closed.set()
        self._bids.put(None)
        self.ownership.close()
        if self._watch is not None:
            self._watch.close()
        self.directory.close()

    # -- what the worker asks ---------------------------------------------------------------

    @property
    def elections(self) -> dict[str, int]:
        return self.directory.elections()

    def live_workers(self) -> list[str]:
        return self.directory.live_workers()

    def load_scores(self, workers: list[str]) -> dict[str, float]:
        return self.directory.load_scores(workers)

    def says_full(self) -> bool:
        return self.directory.says_full()

    def serves(self, robot: str) -> bool:
        # The local lease clock, not the table: a worker cut off stops serving on time.
        return self.ownership.epoch(robot) is not None

    def merges(self) -> bool:
        return self.ownership.epoch(MERGER) is not None

    def held(self) -> int:
        return sum(1 for robot in self.ownership.robots() if robot != MERGER)

    def unavailable(self) -> str | None:
        if self.ownership.live():
            return None
        return (f"the cloud's workers cannot reach their coordination service (etcd at "
                f"{self.ownership.client.endpoint}): robots are served again once it answers")

    def owner(self, robot: str) -> str | None:
        with self._lock:
            held = self._owners.get(robot)
            return held[0] if held and not self._owner_unheard(robot, held) else None

    def _owner_unheard(self, robot: str, held: tuple[str, int, int]) -> bool:
        """Whether ``robot``'s owner in etcd is a worker no one has heard on Zenoh (no
        worker token) for ``UNHEARD_OWNER_LEASES`` leases since it was first asked about: a
        grant written with a worker's certificate for a worker that does not exist, or a
        worker cut off from the robots. It serves nobody, so it counts as no owner and the
        robot's hello is claimed (``_elect`` deletes that grant first). Called with the lock."""
        worker, epoch, _ = held
        if robot == MERGER or self.directory.hears(worker):
            self._unheard.pop(robot, None)
            return False
        now = time.monotonic()
        since = self._unheard.get(robot)
        if since is None or since[0] != epoch:
            self._unheard[robot] = (epoch, now)
            return False
        return now - since[1] >= UNHEARD_OWNER_LEASES * self.ownership.ttl_s

    def table(self) -> dict[str, str]:
        with self._lock:
            return {r: w for r, (w, _, _) in self._owners.items() if r != MERGER}

    def claim(self, robot: str) -> None:
        with self._lock:
            held = self._owners.get(robot)
            if self._closed.is_set() or robot in self._electing or (
                    held and not self._owner_unheard(robot, held)):
                return
            self._electing.add(robot)
        self._bids.put(robot)

    def release(self, robot: str) -> None:
        epoch = self.ownership.robots().get(robot)
        if epoch is None:
            return
        try:
            self.ownership.release(robot, epoch)
        except EtcdError as exc:  # the grant goes with the lease, or at the next fence
            log.warning("robot %s: not released (%s); it goes with this worker's lease",
                        robot, exc)

    # -- etcd's answers ---------------------------------------------------------------------

    def _reread(self, clear: bool = True) -> None:
        """What etcd holds now (a watch event of the same key and a newer revision wins);
        ``clear``: after etcd's history was reset, the owners known before are void."""
        prefix = self.ownership.keys.owner("")
        if clear:
            with self._lock:
                self._owners.clear()
        for kv in self.ownership.client.get_prefix(prefix):
            self._apply(kv.key.decode()[len(prefix):], False, kv)

    def _on_events(self, events: list[Event]) -> None:
        prefix = self.ownership.keys.owner("")
        for event in events:
            self._apply(event.kv.key.decode()[len(prefix):], event.deleted, event.kv)

    def _apply(self, robot: str, deleted: bool, kv: Any) -> None:
        _, served = self.directory.started()
        if not deleted and kv.lease == 0:
            # No grant is without a lease (ownership.py): not an owner; the next grant of
            # the robot removes the key.
            log.error("robot %s: owner key %r without a lease (not a grant): no owner",
                      robot, kv.value.decode(errors="replace"))
            deleted = True
        with self._lock:
            known = self._owners.get(robot)
            if known is not None and known[2] >= kv.mod_revision:
                return  # older than what the table has (the snapshot and the watch overlap)
            if deleted:
                self._owners.pop(robot, None)
            else:
                self._owners[robot] = (kv.value.decode(), kv.create_revision, kv.mod_revision)
        mine = self.ownership.robots().get(robot)
        if not deleted and mine is not None and mine != kv.create_revision:
            # Another grant of a robot this worker believes it holds: only possible if this
            # process stood still past its own fence. The newer grant rules.
            log.error("robot %s: granted to %s epoch %d while this worker held epoch %d: "
                      "giving it up", robot, kv.value.decode(), kv.create_revision, mine)
            self.directory.count("given_up")
            self.release(robot)  # out of this worker's grants too: serves() says no from now
            served.give_up(robot)
            return
        if not deleted or self._closed.is_set() or mine is not None:
            return
        if robot == MERGER:
            self.claim(MERGER)
        elif self.ownership.was_lost(robot):
            pass  # this worker dropped it and told it to say hello again (_on_lost)
        elif served.worth_serving(robot):
            log.info("robot %s lost its owner: claiming it", robot)
            self.directory.count("failovers")
            with self._lock:
                self._takeovers.add(robot)
            self.claim(robot)

    def _on_fenced(self, robots: list[tuple[str, int]]) -> None:
        """The lease was not renewed in time: stop serving every robot at once (their
        sessions go unsaved: the store would refuse their writes anyway)."""
        _, served = self.directory.started()
        for robot, _epoch in robots:
            if robot == MERGER:
                continue  # merges() says no from now on
            self.directory.count("fenced")
            served.give_up(robot)

    def _on_lost(self, robot: str, epoch: int, why: str) -> None:
        """etcd no longer has this worker's grant (its key changed or went; this worker is
        in touch with etcd, and so, likely, with the robot): stop serving it, and tell the
        robot at once, so it says hello again now instead of after its wait for answers."""
        self._on_fenced([(robot, epoch)])
        if robot == MERGER:
            return
        reason = (f"worker {self.worker_id} no longer serves robot {robot} (its grant, epoch "
                  f"{epoch}, is gone from the coordination service: {why}); say hello again")
        z, _ = self.directory.started()
        try:
            z.put(keys.reply(robot), protocol.encode(protocol.Error.of(
                protocol.Code.NO_SESSION, reason)))
        except zenoh.ZError as exc:  # the robot waits for answers, then says hello anyway
            log.warning("robot %s: not told it lost its worker (%s)", robot, exc)

    # -- the election ---------------------------------------------------------------------------

    def _run_elections(self) -> None:
        # Robots asked for and not yet claimed: when each was first asked for.
        asked: dict[str, float] = {}
        while not self._closed.is_set():
            try:
                robot = self._bids.get(timeout=self.cfg.settle_s / 4 if asked
                                       else self.ownership.ttl_s)
            except queue.Empty:
                # A merger's key deleted while the watch was broken would otherwise wait for
                # the next event: look now and then.
                if not asked and self.owner(MERGER) is None and not self.merges():
                    self.claim(MERGER)
            else:
                if robot is None:
                    return
                asked.setdefault(robot, time.monotonic())
            if asked:
                self._place(asked)

    def _place(self, asked: dict[str, float]) -> None:
        """Decide on the robots asked for, one at a time, oldest first (each grant changes
        the next ranking): the merger and a takeover at once, a new robot by the owner
        table as etcd has it now and the workers' measured loads. A grant finding the table
        changed since it was read (another worker's grant) is decided again on a new one."""
        table: Owners | None = None
        for robot, since in sorted(asked.items(), key=lambda item: item[1]):
            if self._closed.is_set():
                return
            if robot != MERGER and self.owner(robot):
                del asked[robot]
                self._done(robot)
                continue
            with self._lock:
                takeover = robot in self._takeovers
            if robot == MERGER or takeover:
                del asked[robot]
                self._elect(robot)
                continue
            for _ in range(self.cfg.max_rounds):
                if table is None and (table := self._read_owners()) is None:
                    return  # etcd does not answer: asked again at the next round
                holder = table.workers.get(robot)
                if holder is not None and self.directory.hears(holder):
                    del asked[robot]  # granted meanwhile; the watch brings it to owner()
                    self._done(robot)
                    break
                if not self._my_turn(robot, since, table):
                    break
                try:
                    epoch = self._elect(robot, table.revision)
                except StaleCounts:
                    table = None  # read again and decide again
                    continue
                del asked[robot]
                if epoch is not None:  # the table as it is now: this grant is its newest
                    table = Owners(epoch, {**table.workers, robot: self.worker_id}, epoch)
                    self._note_table(table)
                break

    def _read_owners(self) -> Owners | None:
        """The owner table from etcd now (None, said, if etcd does not answer)."""
        try:
            table = self.ownership.owners()
        except EtcdError as exc:
            log.warning("robots waiting for a worker: etcd's owner table not read (%s); "
                        "again in %g s", exc, self.cfg.settle_s / 4)
            return None
        self._note_table(table)
        return table

    def _note_table(self, table: Owners) -> None:
        """When the owner table last changed by a grant (a worker ranked later waits from
        then: it takes a robot only if those ranked before it let ``settle_s`` pass)."""
        signature = (table.latest, len(table.workers))
        if signature != self._table_seen[0]:
            self._table_seen = (signature, time.monotonic())

    def _my_turn(self, robot: str, since: float, table: Owners) -> bool:
        """Whether this worker asks for the new robot ``robot`` now: at once if it ranks
        first on ``table``'s grants and the measured loads, else after ``settle_s`` per live
        worker ranked before it with no grant in between (each grant starts the wait
        again: a worker ranked later takes robots only from a worker too slow to ask)."""
        scores = self._scores_on(table)
        place = self.directory.loads.ranking(robot, scores).index(self.worker_id)
        if place == 0:
            return True
        quiet = time.monotonic() - max(since, self._table_seen[1])
        return quiet >= self.cfg.settle_s * place

    def _scores_on(self, table: Owners) -> dict[str, float]:
        """Each live worker's measured load plus its robots granted since it measured, as
        ``table`` counts them."""
        return self.directory.load_scores(self.live_workers(), table.counts())

    def _done(self, robot: str) -> None:
        with self._lock:
            self._electing.discard(robot)
            self._takeovers.discard(robot)

    def _elect(self, robot: str, basis: int | None = None) -> int | None:
        """Ask etcd for ``robot``; ``basis``: the owner table's revision the decision was taken
        on (a new robot). The epoch won, or None (another worker owns it; etcd not asked;
        done either way). StaleCounts: the table changed since ``basis``, decide again."""
        settled = True
        try:
            return self._ask(robot, basis)
        except StaleCounts:
            settled = False
            raise
        except Exception:
            log.exception("robot %s: claim failed", robot)
            return None
        finally:
            if settled:
                self._done(robot)

    def _ask(self, robot: str, basis: int | None) -> int | None:
        _, served = self.directory.started()
        for attempt in range(self.cfg.max_rounds):
            with self._lock:
                held = self._owners.get(robot)
                unheard = held is not None and self._owner_unheard(robot, held)
            if self._closed.is_set() or (robot != MERGER and held and not unheard):
                return None
            try:
                if unheard:
                    self.ownership.evict(robot, held[1], f"its owner {held[0]!r} is a "
                                         f"worker nobody hears: taken over")
                epoch = self.ownership.grant(robot, basis=basis)
            except EtcdError as exc:
                log.warning("robot %s: etcd not asked (%s); again in %g s (round %d)",
                            robot, exc, self.cfg.settle_s, attempt + 1)
                self._closed.wait(self.cfg.settle_s)
                continue
            if epoch is None:
                self.directory.count("lost")
                return None
            if robot == MERGER:
                log.info("worker %s merges (epoch %d)", self.worker_id, epoch)
                return epoch
            self.directory.count("won")
            log.info("worker %s serves robot %s (epoch %d)", self.worker_id, robot, epoch)
            served.take(robot)
            return epoch
        return None


def wait_for_etcd(ownership: Ownership, deadline_s: float) -> None:
    """Until etcd answers ``ownership``'s client (a worker may start before it), or a
    ConnectionError naming the endpoint and the setting."""
    deadline = time.monotonic() + deadline_s
    while True:
        try:
            ownership.client.get(ownership.keys.owner(MERGER))
            return
        except EtcdError as exc:
            if time.monotonic() > deadline:
                raise CoordinationServiceError(
                    f"placement.coordination {ownership.client.endpoint}: etcd does not answer "
                    f"after {deadline_s:.0f} s ({exc}); start it (`fleetslam demo --workers N` "
                    f"starts one) or fix the endpoint") from None
            time.sleep(0.2)
