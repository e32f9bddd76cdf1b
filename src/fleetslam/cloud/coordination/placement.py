"""Which cloud worker serves which robot, agreed through Zenoh liveliness tokens.

Several ``fleetslam cloud`` workers may hang off the same Zenoh routers; a robot never
knows which one serves it. A robot's session lives on exactly one worker at a time:

- A worker hearing of a robot nobody serves (its hello, or its owner's token vanishing
  when that worker died) bids for it: a claim token whose name carries the worker's load
  (measured: worker_load.py) and id. After ``placement.settle_s`` every bidder lists the
  bids; the lowest (least loaded, then a hash of robot and worker) wins, the others
  withdraw. So a new robot goes to the least-loaded worker, and two bidders that see the
  same bids never both win.
- The winner declares the owner token ``fleet/cloud/owners/<robot>/<worker>`` before it
  withdraws its bid, and a worker bids only for a robot without an owner token. The token
  lives as long as the worker's Zenoh session: when the worker dies (SIGKILL, a lost
  machine after Zenoh's lease), the token vanishes and the others bid for its robots.
- Should two owners ever show up for one robot (a worker slow to hear the other's token, a
  partition healing), the worker with the larger id gives the robot up.

No state of its own is shared: every worker sees the same tokens, and the sessions'
durable state lives in the shared store (``cloud/session/store.py``). Which workers are up and
their loads are the WorkerDirectory's (worker_directory.py), which fenced_placement.py shares.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any

import zenoh

from fleetslam.cloud.coordination.placement_protocol import Placement, Served
from fleetslam.cloud.coordination.worker_directory import WorkerDirectory
from fleetslam.cloud.coordination.worker_load import LoadMeter, spread
from fleetslam.config import PlacementConfig
from fleetslam.transport import keys

log = logging.getLogger("fleetslam.placement")

OUTCOMES = ("won", "lost", "failovers", "given_up")


def rank(load: float, robot_id: str, worker_id: str) -> str:
    """A bid's name: sorts by load (cores busy, in thousandths) first; equal loads by a hash
    of robot and worker (robots arriving together spread over the workers instead of all
    going to the first id), and the worker id last (unique)."""
    millicores = min(max(int(round(1000 * load)), 0), 999_999)
    return f"{millicores:06d}.{spread(robot_id, worker_id)}.{worker_id}"


class LivelinessPlacement(Placement):
    def __init__(self, worker_id: str, cfg: PlacementConfig, meter: LoadMeter) -> None:
        """``meter``: this worker's load now (cores busy, measured: worker_load.CpuMeter)."""
        self.worker_id = keys.check_worker_id(worker_id)
        self.cfg = cfg
        self.directory = WorkerDirectory(self.worker_id, cfg, meter, self, OUTCOMES)
        self._lock = threading.Lock()
        self.owners: dict[str, set[str]] = {}  # robot -> workers holding its owner token
        self._mine: dict[str, Any] = {}  # robot -> this worker's owner token
        self._electing: set[str] = set()
        self._closed = threading.Event()
        # One election at a time per worker: each bid's load counts the robots this worker
        # won just before, so robots arriving together tend to spread over the workers.
        self._bids: queue.Queue = queue.Queue()
        self._elector = threading.Thread(target=self._run_elections, name="placement",
                                         daemon=True)
        self._subscriber: Any = None

    # -- lifecycle ------------------------------------------------------------------------

    def start(self, z: zenoh.Session, served: Served) -> "LivelinessPlacement":
        self.directory.bind(z, served)
        self._elector.start()
        self.directory.start_loads(z)
        self.directory.announce(z)
        self._subscriber = z.liveliness().declare_subscriber(
            f"{keys.OWNERS}/**", self._on_owner, history=True)
        return self

    def close(self) -> None:
        """Give every robot back (the other workers take them from their checkpoints)."""
        self._closed.set()
        self._bids.put(None)
        with self._lock:
            tokens, self._mine = list(self._mine.values()), {}
        for token in tokens:
            token.undeclare()
        if self._subscriber is not None:
            self._subscriber.undeclare()
        self.directory.close()

    # -- what the worker asks ---------------------------------------------------------------

    @property
    def elections(self) -> dict[str, int]:
        return self.directory.elections()

    def serves(self, robot: str) -> bool:
        with self._lock:
            return robot in self._mine

    def held(self) -> int:
        """Robots this worker serves now."""
        with self._lock:
            return len(self._mine)

    def load_scores(self, workers: list[str]) -> dict[str, float]:
        return self.directory.load_scores(workers)

    def says_full(self) -> bool:
        return self.directory.says_full()

    def merges(self) -> bool:
        """Whether this worker runs the fleet's merger: the live worker whose id sorts first."""
        return self.live_workers()[0] == self.worker_id

    def owner(self, robot: str) -> str | None:
        """The worker serving ``robot`` as this worker last heard (None: nobody)."""
        with self._lock:
            owners = self.owners.get(robot)
            return min(owners) if owners else None

    def table(self) -> dict[str, str]:
        with self._lock:
            return {robot: min(ws) for robot, ws in self.owners.items() if ws}

    def unavailable(self) -> str | None:
        """Why this worker cannot be granted any robot now (None: it can); liveliness alone
        has nothing to wait for."""
        return None

    def live_workers(self) -> list[str]:
        return self.directory.live_workers()

    def claim(self, robot: str) -> None:
        """Bid for ``robot`` unless it is served or a bid of ours is queued or running
        (returns at once; elections run one after another on the placement thread)."""
        with self._lock:
            if self._closed.is_set() or robot in self._electing or self.owners.get(robot):
                return
            self._electing.add(robot)
        self._bids.put(robot)

    # -- liveliness events -------------------------------------------------------------------

    def _on_owner(self, sample: zenoh.Sample) -> None:
        _, served = self.directory.started()
        robot, worker = keys.last_chunks(sample.key_expr, 2)
        with self._lock:
            owners = self.owners.setdefault(robot, set())
            if sample.kind == zenoh.SampleKind.PUT:
                owners.add(worker)
                conflict = robot in self._mine and worker < self.worker_id
            else:
                owners.discard(worker)
                conflict = False
            orphaned = not owners and robot not in self._mine
        if conflict:
            log.warning("robot %s is also served by worker %s: giving it up", robot, worker)
            self.release(robot)
            self.directory.count("given_up")
            served.give_up(robot)
        elif orphaned and sample.kind == zenoh.SampleKind.DELETE \
                and served.worth_serving(robot):
            log.info("robot %s lost its worker %s: bidding to serve it", robot, worker)
            self.directory.count("failovers")
            self.claim(robot)

    def release(self, robot: str) -> None:
        with self._lock:
            token = self._mine.pop(robot, None)
        if token is not None:
            token.undeclare()

    # -- the election ------------------------------------------------------------------------

    def _listed(self, key: str) -> list[str]:
        """The tokens under ``key`` now, asked of the routers (not the cached table)."""
        z, _ = self.directory.started()
        replies = z.liveliness().get(key, timeout=self.cfg.query_timeout_s)
        return [str(r.ok.key_expr) for r in replies if r.ok is not None]

    def _run_elections(self) -> None:
        while (robot := self._bids.get()) is not None:
            self._elect(robot)

    def _elect(self, robot: str) -> None:
        try:
            z, served = self.directory.started()
            for attempt in range(self.cfg.max_rounds):
                if self._closed.is_set() or self._listed(f"{keys.OWNERS}/{robot}/*"):
                    return
                load = self.load_scores([self.worker_id])[self.worker_id]
                bid = rank(load, robot, self.worker_id)
                token = z.liveliness().declare_token(keys.claim(robot, bid))
                try:
                    time.sleep(self.cfg.settle_s)
                    bids = sorted({keys.last_chunks(k, 1)[0]
                                   for k in self._listed(f"{keys.CLAIMS}/{robot}/*")})
                    # Asked of the routers, and as this worker's subscription heard it: a
                    # winner's owner token may reach one before the other on a loaded host.
                    taken = self._listed(f"{keys.OWNERS}/{robot}/*") or self.owner(robot)
                    if not taken and bids and bids[0] == bid:
                        with self._lock:
                            self._mine[robot] = z.liveliness().declare_token(
                                keys.owner(robot, self.worker_id))
                            owners = self.owners.setdefault(robot, set())
                            owners.add(self.worker_id)
                            earlier = min(owners)
                        if earlier != self.worker_id:
                            # Another owner was heard while this one declared: the rule of
                            # _on_owner (the smaller id keeps the robot) applies at once.
                            log.warning("robot %s is also served by worker %s: not taking it",
                                        robot, earlier)
                            self.release(robot)
                            self.directory.count("given_up")
                            return
                        self.directory.count("won")
                        log.info("worker %s serves robot %s (bids: %s)", self.worker_id,
                                 robot, ", ".join(bids))
                        served.take(robot)
                        return
                finally:
                    token.undeclare()  # after the owner token is up: never a gap
                self.directory.count("lost")
                # Another bid won: it must show its owner token soon. If it does not (its
                # worker died mid-election), bid again.
                deadline = time.monotonic() + self.cfg.settle_s * 4
                while time.monotonic() < deadline and not self._closed.is_set():
                    if self.owner(robot) is not None:
                        return
                    time.sleep(self.cfg.settle_s / 4)
                log.warning("robot %s: the winning bid never took it (round %d); bidding "
                            "again", robot, attempt + 1)
        except Exception:
            log.exception("robot %s: election failed", robot)
        finally:
            with self._lock:
                self._electing.discard(robot)
