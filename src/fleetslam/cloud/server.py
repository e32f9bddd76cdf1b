"""The cloud process, alone or as one of many workers: keeps one RobotSession per robot it
serves, merges the finished maps on request and writes the run folder (the store).

Alone, it listens on an endpoint as the Zenoh router robots connect to. As a worker, it
connects to the routers (``--connect``) beside other workers sharing the same store folder;
which worker serves which robot is agreed through liveliness tokens (``placement.py``), and
a worker hears a robot's frames only while it serves that robot. Zenoh callbacks only check
the key and enqueue; each robot's work happens on its session's own threads. A worker that
starts (a restart, a new worker) or sees a worker die bids for the robots nobody serves and
restores the winner's sessions from their checkpoints in the store.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from fleetslam.backend.workers import LocalMappingPool
from fleetslam.cloud.fleet_merge import FleetMerge, MergeRequests
from fleetslam.cloud.idle_reaper import IdleReaper
from fleetslam.cloud.inbox import REJECTION_REPLY_INTERVAL_S
from fleetslam.cloud.merge_role import MergeRole
from fleetslam.cloud.placement import Placement
from fleetslam.cloud.sessions import SessionTable
from fleetslam.cloud.store import CloudStore
from fleetslam.config import Config
from fleetslam.transport import keys, protocol
from fleetslam.transport.protocol import Hello
from fleetslam.transport.zenoh_session import open_connecting, open_listening, put
from fleetslam.visualisation.live_view import NullView

log = logging.getLogger("fleetslam.cloud")

# Control messages of robots nobody serves yet, kept for the election's winner (per robot:
# the newest), and at most this many robots' at once.
PENDING_ROBOTS = 256


def _is_hello(data: bytes) -> bool:
    try:
        return protocol.parse_control(data)["type"] == "hello"
    except ValueError:
        return False


def default_worker_id() -> str:
    host = "".join(c if c.isalnum() or c in "-_" else "-" for c in socket.gethostname())
    return f"w-{host[:40]}-{os.getpid()}"


class Throttle:
    """Says whether something keyed (a reply key, a log topic) is due again: at most once
    per interval per key. The table forgets old keys, so a flood of made-up ids cannot grow
    it without bound."""

    MAX_KEYS = 4096

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._lock = threading.Lock()

    def due(self, key: str) -> bool:
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -float("inf")) < self.interval_s:
                return False
            if len(self._last) >= self.MAX_KEYS:
                self._last = {k: t for k, t in self._last.items()
                              if now - t < self.interval_s}
            self._last[key] = now
            return True


class CloudServer:
    def __init__(self, config: Config, out_dir: Path, endpoint: str | None = None,
                 view: NullView | None = None, connect: str | None = None) -> None:
        """``endpoint``: listen there as the router (a lone cloud); ``connect``: a worker
        connecting to the routers there instead. ``out_dir`` is the store every worker of
        the fleet shares."""
        self.config = config
        # The live view (visualisation/live_view.py; off: a NullView). The server closes it.
        self.view = view or NullView()
        self.out_dir = Path(out_dir)
        self.connect = connect
        self.endpoint = connect or endpoint or config.transport.endpoint
        self.worker_id = keys.check_worker_id(config.placement.worker_id or default_worker_id())
        self.placement: Placement | None = None
        self.store = CloudStore(self.out_dir)
        # The table hands the merge role each new keyframe and robot; the role reads the table.
        self.sessions = SessionTable(
            config, self.store, self.publish, self.view,
            keyframe_sink=lambda summary, poses: self.merging.keyframe_sink(summary, poses),
            joined=lambda robot, camera, restored: self.merging.joined(robot, camera, restored))
        self.merging = MergeRole(config, self.view, self.worker_id, self.sessions, self.publish,
                                 lambda: self.placement)
        self.merger = self.merging.merger
        self.fleet_merge = FleetMerge(config, self.out_dir, self.sessions, self.merger)
        # Through self.merge, whatever it is when a request comes (a test slows it down).
        self.merge_requests = MergeRequests(lambda: self.merge(), self.publish)
        # The session table's lock guards what the server keeps per robot too.
        self._lock = self.sessions.lock
        self._zenoh: zenoh.Session | None = None
        self._subscribers: list[Any] = []
        self._robot_subscribers: dict[str, list[Any]] = {}
        self._pending: dict[str, tuple[bytes, float]] = {}
        self.stopped = threading.Event()
        self.unrouted = 0  # messages on keys that name no valid robot
        self._throttle = Throttle(REJECTION_REPLY_INTERVAL_S)
        self._reaper = IdleReaper(self.sessions, config.transport, self.stopped)
        self.local_mapping: LocalMappingPool | None = None

    # -- lifecycle ----------------------------------------------------------------------

    def start(self) -> "CloudServer":
        tracking = self.config.tracking
        if tracking.local_mapping not in ("async", "inline"):
            raise ValueError(f"tracking.local_mapping is {tracking.local_mapping!r}: "
                             f"'async' or 'inline'")
        if tracking.local_mapping == "async" and tracking.local_ba:
            self.local_mapping = LocalMappingPool(tracking.local_mapping_workers)
            self.sessions.local_mapping = self.local_mapping
        transport = self.config.transport
        if self.connect:
            self._zenoh = open_connecting(self.connect, transport.reach_deadline_s,
                                          transport.zenoh_config or None)
        else:
            self._zenoh = open_listening(self.endpoint, transport.zenoh_config or None)
        z = self._zenoh
        self._subscribers = [
            z.declare_subscriber(keys.ALL_CONTROL, lambda s: self._route(s, "control")),
            z.declare_subscriber(f"{keys.MERGE_KEYFRAMES}/*", self._on_remote_keyframe),
        ]
        if not self.connect:
            # The router itself hears every robot's frames at no cost to the network (they
            # pass through it): it serves its own and tells a robot nobody serves to say
            # hello. A worker behind a router hears only the robots it serves (_take).
            self._subscribers += [
                z.declare_subscriber(keys.ALL_FRAMES, lambda s: self._route(s, "frame")),
                z.declare_subscriber(keys.ALL_KEYFRAMES, lambda s: self._route(s, "keyframe")),
            ]
        self.placement = Placement(z, self.worker_id, self.config.placement, self._load,
                                   self._take, self._give_up, self._worth_serving).start()
        self._reaper.start()
        threading.Thread(target=self._claim_orphans, name="cloud-orphans", daemon=True).start()
        log.info("cloud worker %s %s %s, store %s", self.worker_id,
                 "connected to" if self.connect else "listening on", self.endpoint,
                 self.out_dir)
        return self

    def _on_remote_keyframe(self, sample: zenoh.Sample) -> None:
        """Another worker's keyframe for the merger: taken if this worker merges."""
        try:
            if not self.merging.is_merger():
                return
            robot_id = keys.check_robot_id(keys.last_chunks(sample.key_expr, 1)[0])
            self.merging.take_remote(sample.payload.to_bytes(), robot_id)
        except ValueError as exc:
            self._count_unrouted()
            if self._throttle.due("remote keyframe"):
                log.warning("keyframe on %s rejected: %s", sample.key_expr, exc)

    # -- placement (which worker serves which robot) ----------------------------------------

    def _load(self) -> int:
        """Robots this worker is working for: unfinished sessions heard from lately (a
        session whose robot went quiet holds memory, not CPU)."""
        now = time.monotonic()
        active_s = self.config.placement.active_s
        return sum(1 for _, s in self.sessions.now()
                   if s.finished is None and now - s.last_heard < active_s)

    def _worth_serving(self, robot_id: str) -> bool:
        """A robot whose worker died is taken over when it has a checkpoint to restore (not
        by a worker that is stopping itself: workers stopped together would swap robots)."""
        return not self.stopped.is_set() and self.store.has_checkpoint(robot_id)

    def _claim_orphans(self) -> None:
        """Bid for every robot of the store that nobody serves: a restarted (or a new)
        worker takes over the sessions a dead worker left, finished ones too (the merge
        needs them). Once the liveliness history has arrived."""
        if self.stopped.wait(self.config.placement.settle_s):
            return
        for robot_id in self.store.robots_with_checkpoints():
            if self.placement is not None and self.placement.owner(robot_id) is None:
                self.placement.claim(robot_id)

    def _take(self, robot_id: str) -> None:
        """This worker won ``robot_id``: hear its frames and uploads, restore its session
        if the store has one, and answer what it said meanwhile."""
        z = self._zenoh
        if z is None or self.stopped.is_set():
            if self.placement is not None:
                self.placement.release(robot_id)  # stopping: another worker takes it
            return
        with self._lock:
            if self.connect and robot_id not in self._robot_subscribers:
                self._robot_subscribers[robot_id] = [
                    z.declare_subscriber(keys.frame(robot_id),
                                         lambda s: self._route(s, "frame")),
                    z.declare_subscriber(keys.keyframe(robot_id),
                                         lambda s: self._route(s, "keyframe")),
                ]
            pending = self._pending.pop(robot_id, None)
            existed = robot_id in self.sessions
        session = self.sessions.session(robot_id)
        restored = session is not None and not existed
        if restored and session.finished is None:
            # Taken over mid-stream: the robot's frames in flight went to the dead worker.
            # A welcome tells it to stop waiting for them (and to send intra frames).
            session.welcome(resumed=True, taken_over=True)
        if pending is not None and not (restored and _is_hello(pending[0])):
            # What the robot said while nobody served it (a hello kept from an election
            # lost long ago is answered by the welcome above).
            self._on_robot_control(robot_id, *pending)

    def _give_up(self, robot_id: str) -> None:
        """Another worker serves ``robot_id`` too (a partition healed): drop ours unsaved."""
        with self._lock:
            subs = self._robot_subscribers.pop(robot_id, [])
            session = self.sessions.remove(robot_id)
        for sub in subs:
            sub.undeclare()
        if session is not None:
            session.close()

    def close(self) -> None:
        """Stop; every session's state goes to the store first, then this worker's robots
        are given back (another worker restores them from there)."""
        self.stopped.set()
        self._reaper.join(30.0)
        for _, session in self.sessions.now():
            session.close(final_checkpoint=True)
        if self.placement is not None:
            self.placement.close()
        for subs in self._robot_subscribers.values():
            for sub in subs:
                sub.undeclare()
        self.merger.close()
        if self.local_mapping is not None:
            self.local_mapping.close()
        self.view.close()
        for sub in self._subscribers:
            sub.undeclare()
        if self._zenoh is not None:
            self._zenoh.close()
            self._zenoh = None

    def publish(self, key: str, data: bytes) -> None:
        if self._zenoh is not None:
            put(self._zenoh, key, data)

    # -- routing ------------------------------------------------------------------------

    def _route(self, sample: zenoh.Sample, kind: str) -> None:
        arrival = time.monotonic()
        key = str(sample.key_expr)
        try:
            data = sample.payload.to_bytes()
            if key == keys.CLOUD_CONTROL:
                return self._on_cloud_control(data)
            robot_id = keys.check_robot_id(keys.robot_of(key))
            if kind == "control":
                return self._on_control_of(robot_id, data, arrival)
            placement = self.placement
            if placement is not None and not placement.serves(robot_id):
                if placement.owner(robot_id) is not None:
                    return  # another worker's robot (a router-worker hears every robot)
                if self._worth_serving(robot_id):
                    return placement.claim(robot_id)  # a restart: restore, then serve
            session = self.sessions.session(robot_id)
            if session is None:
                self._error(keys.reply(robot_id), protocol.Code.NO_SESSION,
                            f"{kind} rejected: no session: send a hello first")
                return
            if kind == "frame":
                session.submit_frame(data, arrival)
            else:
                session.submit_keyframe(data, arrival)
        except ValueError as exc:
            self._count_unrouted()
            if self._throttle.due("unrouted"):
                log.warning("message on %s rejected: %s", sample.key_expr, exc)
        except Exception:
            self._count_unrouted()
            log.exception("message on %s failed", sample.key_expr)

    def _count_unrouted(self) -> None:
        with self._lock:  # Zenoh calls back on several threads
            self._count_unrouted_locked()

    def _count_unrouted_locked(self) -> None:
        self.unrouted += 1

    def _error(self, key: str, code: protocol.Code, reason: str, **extra: Any) -> None:
        """Tell the sender on ``key`` why, and log it. A flood of the same bad message must
        not become a flood of replies and log lines: the same reason at most once per
        interval per key; replies to a request id always go (a client waits for those)."""
        if "id" not in extra and not self._throttle.due(f"{key} {reason}"):
            return
        log.warning("%s: %s", key, reason)
        self.publish(key, protocol.encode(protocol.error(code, reason, **extra)))

    def _on_control_of(self, robot_id: str, data: bytes, arrival: float) -> None:
        """A robot's control message: handled if this worker serves the robot, ignored if
        another one does, else kept while the workers bid for the robot."""
        placement = self.placement
        if placement is None or placement.serves(robot_id):
            return self._on_robot_control(robot_id, data, arrival)
        if placement.owner(robot_id) is not None:
            with self._lock:  # another worker's robot: nothing of it to keep here
                self._pending.pop(robot_id, None)
            return
        with self._lock:
            if robot_id not in self._pending and len(self._pending) >= PENDING_ROBOTS:
                self._count_unrouted_locked()
                return
            self._pending[robot_id] = (data, arrival)
            full = self.sessions.full()
        if not full:  # a full worker does not bid; a robot nobody can take hears it below
            placement.claim(robot_id)
        elif len(placement.live_workers()) == 1:
            self._on_robot_control(robot_id, *self._pending.pop(robot_id))

    def _on_robot_control(self, robot_id: str, data: bytes, arrival: float) -> None:
        reply = keys.reply(robot_id)
        try:
            message = protocol.parse_control(data)
            hello = Hello.parse(message) if message["type"] == "hello" else None
        except ValueError as exc:
            return self._error(reply, protocol.Code.BAD_MESSAGE,
                               f"control message rejected: {exc}")
        session = self.sessions.session(robot_id)
        if hello is not None and session is not None \
                and session.state.hello.offload_at != hello.offload_at:
            return self._error(reply, protocol.Code.REFUSED,
                               f"session offloads at {session.state.hello.offload_at}; a robot "
                               f"cannot change its offloading point within a session")
        if session is None:
            if hello is None:
                return self._error(reply, protocol.Code.NO_SESSION,
                                   "no session: send a hello first")
            session = self.sessions.open(robot_id, hello)
            if session is None:
                reason = (f"the cloud serves at most {self.config.transport.max_sessions} "
                          f"robots at once (transport.max_sessions)")
                return self._error(reply, protocol.Code.REFUSED, reason)
            log.info("robot %s: new session, offloading at %d, source %s", robot_id,
                     hello.offload_at, hello.source)
            session.welcome(resumed=False)
            return
        if message["type"] == "end":
            # Heard at once; the answer (need / ended) comes when its frames are done.
            self.publish(reply, protocol.encode(protocol.ending()))
        session.submit_control(message, arrival)

    def _on_cloud_control(self, data: bytes) -> None:
        try:
            message = protocol.parse_control(data)
        except ValueError as exc:
            return self._error(keys.CLOUD_REPLY, protocol.Code.BAD_MESSAGE,
                               f"control message rejected: {exc}")
        rid = protocol.request_id(message)
        if message["type"] == "merge":
            if not self.merging.is_merger():
                return  # one worker merges: the live one whose id sorts first
            self.merge_requests.request(rid)
        elif message["type"] == "status":
            robots = {r: {"frames": s.counts()["frames"], "finished": s.finished is not None,
                          "worker": self.worker_id}
                      for r, s in self.sessions.now()}
            placement = self.placement
            self.publish(keys.CLOUD_REPLY, protocol.encode(protocol.status(
                rid, robots, self.merger.status(), worker=self.worker_id,
                workers=placement.live_workers() if placement else [self.worker_id],
                placement=placement.table() if placement else {},
                elections=dict(placement.elections) if placement else {})))
        else:
            self._error(keys.CLOUD_REPLY, protocol.Code.UNKNOWN_TYPE,
                        f"unknown request {message['type']!r}", id=rid)

    # -- merge and outputs ----------------------------------------------------------------

    def merge(self, timeout_s: float = 300.0) -> dict[str, Any]:
        """Write the global outputs of the finished robots (global trajectories, map, OctoMap)
        and summary.json; return the summary."""
        return self.fleet_merge.merge(timeout_s)
