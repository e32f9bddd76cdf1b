"""The cloud process, alone or as one of many workers: keeps one RobotSession per robot it
serves, merges the finished maps on request and writes the run folder (the store).

Alone, it listens on an endpoint as the Zenoh router robots connect to. As a worker, it
connects to the routers (``--connect``) beside other workers sharing the same store folder;
which worker serves which robot is agreed through liveliness tokens (``placement.py``), and
a worker hears a robot's frames only while it serves that robot. Zenoh callbacks only check
the key and enqueue; each robot's work happens on its session's own threads. A worker that
starts (a restart, a new worker) or sees a worker die bids for the robots nobody serves and
restores the winner's sessions from their checkpoints in the store.

The server is the composition root: it builds its parts in dependency order, each given
the objects it uses, and runs their lifecycle:

    sessions.py     SessionTable: the robots' sessions (open, restore, read from the store)
    worker_load.py  CpuMeter: this worker's load, as placement weighs it
    placement_protocol.py  Placement: which worker serves which robot, one of
      placement.py        LivelinessPlacement: decided by Zenoh liveliness bids
      fenced_placement.py FencedPlacement: decided by etcd with fencing
                    (``placement.coordination``; its store is fenced_store.py)
    merge_role.py   MergeRole: which worker merges; the keyframes its merger gets (the table
                    hands them over: SessionTable.hand_to)
    fleet_merge.py  FleetMerge, MergeRequests: the merge a client asks for, once per request
    operator_requests.py  OperatorRequests: the status and merge requests
    routing.py      Router: each message to its session, the status or the merge; the
                    robots the placement hands this worker (its Served)
    idle_reaper.py  IdleReaper: checkpoint and close the sessions of quiet robots
"""

from __future__ import annotations

import gc
import logging
import os
import socket
import threading
from pathlib import Path
from typing import Any

import zenoh

from fleetslam.backend.workers import LocalMappingPool
from fleetslam.cloud.coordination.etcd_gateway import EtcdClient, EtcdTls
from fleetslam.cloud.coordination.fenced_placement import FencedPlacement, wait_for_etcd
from fleetslam.cloud.coordination.fenced_store import FencedStore
from fleetslam.cloud.coordination.ownership import Ownership
from fleetslam.cloud.coordination.placement import LivelinessPlacement
from fleetslam.cloud.coordination.placement_protocol import Placement
from fleetslam.cloud.coordination.worker_load import CpuMeter
from fleetslam.cloud.merge.fleet_frames import FleetFrames
from fleetslam.cloud.merge.fleet_merge import FleetMerge, MergeRequests
from fleetslam.cloud.merge.merge_role import MergeRole
from fleetslam.cloud.operator_requests import OperatorRequests
from fleetslam.cloud.routing import Router
from fleetslam.cloud.session.idle_reaper import IdleReaper
from fleetslam.cloud.session.sessions import SessionTable
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.merging.saved_map import LoadedMap
from fleetslam.transport import keys
from fleetslam.transport.zenoh_session import open_connecting, open_listening, put
from fleetslam.visualisation.live_view import NullView

log = logging.getLogger("fleetslam.cloud")


def default_worker_id() -> str:
    host = "".join(c if c.isalnum() or c in "-_" else "-" for c in socket.gethostname())
    return f"w-{host[:40]}-{os.getpid()}"


class CloudServer:
    def __init__(self, config: Config, out_dir: Path, endpoint: str | None = None,
                 view: NullView | None = None, connect: str | None = None,
                 loaded: LoadedMap | None = None) -> None:
        """``endpoint``: listen there as the router (a lone cloud); ``connect``: a worker
        connecting to the routers there instead. ``out_dir`` is the store every worker of
        the fleet shares. ``loaded``: a saved map, the fleet's first group."""
        self.config = config
        # The live view (visualisation/live_view.py; off: a NullView). The server closes it.
        self.view = view or NullView()
        self.out_dir = Path(out_dir)
        self.connect = connect
        self.endpoint = connect or endpoint or config.transport.endpoint
        self.worker_id = keys.check_worker_id(config.placement.worker_id or default_worker_id())
        self.stopped = threading.Event()
        self._zenoh: zenoh.Session | None = None
        self._placing = False  # the placement started (it takes part on the Zenoh session)
        self.local_mapping: LocalMappingPool | None = None
        # With a coordination service, etcd decides ownership and whose checkpoint is
        # current (fenced); without, the store is plain and liveliness decides.
        self.ownership: Ownership | None = None
        if config.placement.coordination:
            certs = config.placement.coordination_certs
            client = EtcdClient(config.placement.coordination,
                                tls=EtcdTls.from_folder(certs) if certs else None)
            self.ownership = Ownership(client, self.worker_id, config.placement.lease_s,
                                       stall_s=config.placement.stall_s)
            self.store: CloudStore = FencedStore(self.out_dir, self.ownership,
                                                 config.transport.max_checkpoint_bytes)
        else:
            self.store = CloudStore(self.out_dir, config.transport.max_checkpoint_bytes)
        self.sessions = SessionTable(config, self.store, self.publish, self.view)
        # This worker's load as placement weighs it: the cores it keeps busy for the robots
        # at work, at its own priority (its niced local BA and place search yield).
        cpu = CpuMeter(os.getpid(), config.placement.load_window_s, self.sessions,
                       config.placement.robot_cost_cores)
        self.placement: Placement = (
            FencedPlacement(self.worker_id, config.placement, cpu, self.ownership)
            if self.ownership is not None
            else LivelinessPlacement(self.worker_id, config.placement, cpu))
        self.merging = MergeRole(config, self.view, self.worker_id, self.sessions,
                                 self.publish_droppable, self.placement,
                                 FleetFrames(config.merge, self.publish), loaded)
        # The table hands the merge role each new keyframe and robot; the role reads the table.
        self.sessions.hand_to(self.merging)
        self.merger = self.merging.merger
        self.fleet_merge = FleetMerge(config, self.out_dir, self.sessions, self.merger,
                                      self.placement)
        self.operator = OperatorRequests(self.worker_id, self.sessions, self.placement,
                                         self.merging,
                                         MergeRequests(self.fleet_merge, self.publish))
        self.router = Router(self.sessions, self.placement, self.merging, self.operator,
                             self.publish, self.stopped)
        self._reaper = IdleReaper(self.sessions, config.transport, self.stopped)

    @property
    def unrouted(self) -> int:
        """Messages on keys that name no valid robot."""
        return self.router.unrouted

    # -- lifecycle ----------------------------------------------------------------------

    def start(self) -> "CloudServer":
        tracking = self.config.tracking
        if tracking.local_mapping not in ("async", "inline"):
            raise ValueError(f"tracking.local_mapping is {tracking.local_mapping!r}: "
                             f"'async' or 'inline'")
        if tracking.local_mapping == "async" and tracking.local_ba:
            self.local_mapping = LocalMappingPool(
                tracking.local_mapping_workers, tracking.local_mapping_nice,
                self.config.loop_closing.worker_databases)
            self.sessions.local_mapping = self.local_mapping
        try:
            z = self._zenoh = self._open_zenoh()
        except BaseException:
            self.close()  # its workers end quietly, not as failures
            raise
        # Placement first: a hello heard before it existed was served at once, unowned, and
        # the robot's next frames were dropped while this worker then bid for it (seen in
        # test_processes when a robot's hello met a cloud starting).
        if self.ownership is not None:
            wait_for_etcd(self.ownership, self.config.placement.coordination_start_s)
        self.placement.start(z, self.router)
        self._placing = True
        if isinstance(self.store, FencedStore) and (old := self.store.unfenced_checkpoints()):
            log.warning("the store %s holds checkpoints written without a coordination service "
                        "(robots %s): they are not read with one; run those robots' workers "
                        "without --coordination to finish them", self.out_dir, ", ".join(old))
        self.router.listen(z, every_robot=not self.connect)
        self._reaper.start()
        threading.Thread(target=self._claim_orphans, name="cloud-orphans", daemon=True).start()
        # What start-up made (modules, classes, the libraries' objects: ~60k) lives as long
        # as the worker: frozen, a full collection no longer walks it, while every robot's
        # thread waits (bench/worker_scaling: a worker's full collections 10-58 ms, then 4-6).
        gc.freeze()
        log.info("cloud worker %s %s %s, store %s%s", self.worker_id,
                 "connected to" if self.connect else "listening on", self.endpoint,
                 self.out_dir, f", ownership by etcd at {self.config.placement.coordination}"
                 if self.ownership is not None else "")
        return self

    def _open_zenoh(self) -> zenoh.Session:
        transport = self.config.transport
        if self.connect:
            return open_connecting(self.connect, transport.reach_deadline_s,
                                   transport.zenoh_config or None,
                                   self.config.placement.zenoh_lease_s)
        return open_listening(self.endpoint, transport.zenoh_config or None,
                              transport.router_block_s)

    def close(self) -> None:
        """Stop; every session's state goes to the store first, then this worker's robots
        are given back (another worker restores them from there)."""
        self.stopped.set()
        self._reaper.join(30.0)
        for _, session in self.sessions.now():
            session.close(final_checkpoint=True)
        if self._placing:
            self.placement.close()
        self.router.close_robots()
        self.merger.close()
        if self.local_mapping is not None:
            self.local_mapping.close()
        self.view.close()
        self.router.close()
        if self._zenoh is not None:
            self._zenoh.close()
            self._zenoh = None

    def publish(self, key: str, data: bytes) -> None:
        if self._zenoh is not None:
            put(self._zenoh, key, data)

    def publish_droppable(self, key: str, data: bytes) -> None:
        """To another worker, what it recovers otherwise (a keyframe for the merger, which
        fills a gap from the store): never waited for behind an unreachable worker's queue
        (measured: every robot of the live worker silent ~10 s after the merging worker's
        machine was cut off)."""
        if self._zenoh is not None:
            put(self._zenoh, key, data, droppable=True)

    # -- placement (which worker serves which robot) ----------------------------------------

    def _claim_orphans(self) -> None:
        """Bid for every robot of the store that nobody serves: a restarted (or a new)
        worker takes over the sessions a dead worker left, finished ones too (the merge
        needs them). Once the liveliness history has arrived."""
        if self.stopped.wait(self.config.placement.settle_s):
            return
        for robot_id in self.store.robots_with_checkpoints():
            if self.placement.owner(robot_id) is None:
                self.placement.claim(robot_id)

    # -- the operator's requests ------------------------------------------------------------

    def merge(self, timeout_s: float = 300.0) -> dict[str, Any]:
        """Write the global outputs of the finished robots (global trajectories, map, OctoMap)
        and summary.json; return the summary."""
        return self.fleet_merge.merge(timeout_s)
