"""What both placements (placement.py, fenced_placement.py) share: which workers are up, by
their Zenoh liveliness tokens (this worker's declared while it runs), every worker's measured
load (worker_load.py) and how this worker's elections went. Each placement holds one.
"""

from __future__ import annotations

import threading
from collections import Counter
from typing import Any, Mapping, Protocol

import zenoh

from fleetslam.cloud.coordination.placement_protocol import Served
from fleetslam.cloud.coordination.worker_load import Holdings, LoadMeter, WorkerLoads
from fleetslam.config import PlacementConfig
from fleetslam.transport import keys


class OwnerTable(Holdings, Protocol):
    """A placement's robots as the load scores count them."""

    def table(self) -> dict[str, str]: ...


class WorkerDirectory:
    def __init__(self, worker_id: str, cfg: PlacementConfig, meter: LoadMeter,
                 placement: OwnerTable, outcomes: tuple[str, ...]) -> None:
        """``placement``: the one holding this directory (its robots weigh in the load
        reports and scores); ``outcomes``: what its elections count."""
        self.worker_id = keys.check_worker_id(worker_id)
        self._placement = placement
        self.loads = WorkerLoads(self.worker_id, cfg, meter, placement)
        # Zenoh calls back on its threads; elections, watches and leases count on theirs.
        self._lock = threading.Lock()
        self._workers: set[str] = set()
        self._elections = dict.fromkeys(outcomes, 0)
        self._token: Any = None
        self._subscriber: Any = None
        self._z: zenoh.Session | None = None  # set by bind
        self._served: Served | None = None

    # -- lifecycle ----------------------------------------------------------------------------

    def bind(self, z: zenoh.Session, served: Served) -> None:
        """The placement started: on ``z``, handing robots to ``served``."""
        self._z, self._served = z, served

    def started(self) -> tuple[zenoh.Session, Served]:
        """The placement's Zenoh session and whom it hands robots to; RuntimeError before
        it started."""
        if self._z is None or self._served is None:
            raise RuntimeError("the placement is not started")
        return self._z, self._served

    def start_loads(self, z: zenoh.Session) -> None:
        """Report this worker's load and hear the others'."""
        self.loads.start(z)

    def announce(self, z: zenoh.Session) -> None:
        """This worker's token, and the other workers' (which workers are up)."""
        live = z.liveliness()
        self._token = live.declare_token(keys.worker(self.worker_id))
        self._subscriber = live.declare_subscriber(f"{keys.WORKERS}/*", self._on_worker,
                                                   history=True)

    def close(self) -> None:
        self.loads.close()
        if self._subscriber is not None:
            self._subscriber.undeclare()
        if self._token is not None:
            self._token.undeclare()

    def _on_worker(self, sample: zenoh.Sample) -> None:
        (worker,) = keys.last_chunks(sample.key_expr, 1)
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._workers.add(worker)
            else:
                self._workers.discard(worker)

    # -- what the placements ask ---------------------------------------------------------------

    def live_workers(self) -> list[str]:
        with self._lock:
            return sorted(self._workers | {self.worker_id})

    def hears(self, worker: str) -> bool:
        """Whether ``worker``'s token is up (this worker's own always is)."""
        with self._lock:
            return worker == self.worker_id or worker in self._workers

    def count(self, outcome: str) -> None:
        with self._lock:
            self._elections[outcome] = self._elections.get(outcome, 0) + 1

    def elections(self) -> dict[str, int]:
        with self._lock:
            return dict(self._elections)

    def says_full(self) -> bool:
        """Whether this worker tells a new robot that the cloud is full: no live worker has
        room, as their load reports say, and this one's id sorts first among them (one
        answer, not one a worker)."""
        live = self.live_workers()
        return live[0] == self.worker_id and self.loads.all_full(live)

    def load_scores(self, workers: list[str], owned: Mapping[str, int] | None = None
                    ) -> dict[str, float]:
        """Cores each of ``workers`` has busy as measured, plus the robots granted to it
        since: ``owned``, robots granted to each worker (as the coordination service had
        them at one revision), or as the owner table says, read once (this worker's own as
        it holds them)."""
        if owned is None:
            counted = Counter(self._placement.table().values())
            counted[self.worker_id] = max(counted[self.worker_id], self._placement.held())
            owned = counted
        return {w: self.loads.score(w, owned.get(w, 0)) for w in workers}
