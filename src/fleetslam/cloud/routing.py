"""Where each message a cloud worker hears goes. A robot's frames and keyframe uploads go
to its session; its control messages too, or are kept while the workers bid for the robot
(placement.py); a hello opens a session; the operator's requests go to the status and the
merge (operator_requests.py). Zenoh calls back on several threads: nothing here works on a
message, it checks the key and enqueues, and says why when it cannot (at most once a second
per reason and key). The placement hands this worker its robots through the router
(``take``, ``give_up``, ``worth_serving``: placement_protocol.Served).

Alone, the cloud is the Zenoh router and hears every robot; as a worker it hears a robot's
frames and uploads only while it serves that robot (``take``).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zenoh

from fleetslam.cloud.coordination.placement_protocol import Placement
from fleetslam.cloud.merge.merge_role import MergeRole
from fleetslam.cloud.operator_requests import OperatorRequests
from fleetslam.cloud.session.inbox import REJECTION_REPLY_INTERVAL_S, Throttle
from fleetslam.cloud.session.replies import Publish
from fleetslam.cloud.session.sessions import SessionTable
from fleetslam.transport import keys, protocol
from fleetslam.transport.protocol import Hello

log = logging.getLogger("fleetslam.cloud")

# Control messages of robots nobody serves yet, kept for the election's winner (per robot:
# the newest), and at most this many robots' at once.
PENDING_ROBOTS = 256


def _is_hello(data: bytes) -> bool:
    try:
        return protocol.parse_control(data)["type"] == "hello"
    except ValueError:
        return False


class Router:
    def __init__(self, sessions: SessionTable, placement: Placement, merging: MergeRole,
                 operator: OperatorRequests, publish: Publish,
                 stopped: threading.Event) -> None:
        """``operator``: answers the operator's requests; ``stopped``: the worker is
        stopping (it takes no robot)."""
        self.sessions = sessions
        self.placement = placement
        self.merging = merging
        self.operator = operator
        self.publish = publish
        self.stopped = stopped
        self.unrouted = 0  # messages on keys that name no valid robot
        self._throttle = Throttle(REJECTION_REPLY_INTERVAL_S)
        self._zenoh: zenoh.Session | None = None
        self._every_robot = False
        self._subscribers: list[Any] = []
        # Zenoh calls back on several threads. Under it: the subscribers of each robot this
        # worker serves, the control message of each robot nobody serves yet, ``unrouted``.
        self._lock = threading.Lock()
        self._robot_subscribers: dict[str, list[Any]] = {}
        self._pending: dict[str, tuple[bytes, float]] = {}

    # -- what this worker hears ---------------------------------------------------------

    def listen(self, z: zenoh.Session, every_robot: bool) -> None:
        """Every robot's control messages, the client's requests and the other workers'
        keyframes for the merger; with ``every_robot``, every robot's frames and uploads."""
        self._zenoh = z
        self._every_robot = every_robot
        self._subscribers = [
            z.declare_subscriber(keys.ALL_CONTROL, self._route_control),
            z.declare_subscriber(f"{keys.MERGE_KEYFRAMES}/*", self.remote_keyframe),
        ]
        if every_robot:
            # The router itself hears every robot's frames at no cost to the network (they
            # pass through it): it serves its own and tells a robot nobody serves to say
            # hello. A worker behind a router hears only the robots it serves (take).
            self._subscribers += [
                z.declare_subscriber(keys.ALL_FRAMES, self._route_frame),
                z.declare_subscriber(keys.ALL_KEYFRAMES, self._route_keyframe),
            ]

    def worth_serving(self, robot_id: str) -> bool:
        """A robot whose worker died is taken over when it has a checkpoint to restore (not
        by a worker that is stopping itself: workers stopped together would swap robots)."""
        return not self.stopped.is_set() and self.sessions.store.has_checkpoint(robot_id)

    def take(self, robot_id: str) -> None:
        """This worker won ``robot_id``: hear its frames and uploads, restore its session
        if the store has one, and answer what it said meanwhile."""
        z = self._zenoh
        if z is None or self.stopped.is_set():
            self.placement.release(robot_id)  # stopping: another worker takes it
            return
        with self._lock:
            if not self._every_robot and robot_id not in self._robot_subscribers:
                self._robot_subscribers[robot_id] = [
                    z.declare_subscriber(keys.frame(robot_id), self._route_frame),
                    z.declare_subscriber(keys.keyframe(robot_id), self._route_keyframe),
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

    def give_up(self, robot_id: str) -> None:
        """Another worker serves ``robot_id`` (a partition healed, or this worker was
        fenced): drop ours unsaved, silent at once."""
        with self._lock:  # against a take of the robot meanwhile (the table's lock inside)
            subs = self._robot_subscribers.pop(robot_id, [])
            session = self.sessions.remove(robot_id)
        for sub in subs:
            sub.undeclare()
        if session is not None:
            session.drop()

    def close_robots(self) -> None:
        """Stop hearing the robots this worker serves."""
        for subs in self._robot_subscribers.values():
            for sub in subs:
                sub.undeclare()

    def close(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        self._zenoh = None

    # -- routing ------------------------------------------------------------------------

    def _route_control(self, sample: zenoh.Sample) -> None:
        self.route(sample, "control")

    def _route_frame(self, sample: zenoh.Sample) -> None:
        self.route(sample, "frame")

    def _route_keyframe(self, sample: zenoh.Sample) -> None:
        self.route(sample, "keyframe")

    def route(self, sample: zenoh.Sample, kind: str) -> None:
        arrival = time.monotonic()
        key = str(sample.key_expr)
        try:
            data = sample.payload.to_bytes()
            if key == keys.CLOUD_CONTROL:
                return self._on_cloud_control(data)
            robot_id = keys.check_robot_id(keys.robot_of(key))
            if kind == "control":
                return self._on_control_of(robot_id, data, arrival)
            if not self.placement.serves(robot_id):
                if self.placement.owner(robot_id) is not None:
                    return  # another worker's robot (a router-worker hears every robot)
                if self.worth_serving(robot_id):
                    return self.placement.claim(robot_id)  # a restart: restore, then serve
            session = self.sessions.session(robot_id)
            if session is None:
                self.error(keys.reply(robot_id), protocol.Code.NO_SESSION,
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

    def remote_keyframe(self, sample: zenoh.Sample) -> None:
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

    def _count_unrouted(self) -> None:
        with self._lock:
            self.unrouted += 1

    def error(self, key: str, code: protocol.Code, reason: str, **extra: Any) -> None:
        """Tell the sender on ``key`` why, and log it. A flood of the same bad message must
        not become a flood of replies and log lines: the same reason at most once per
        interval per key; replies to a request id always go (a client waits for those)."""
        if "id" not in extra and not self._throttle.due(f"{key} {reason}"):
            return
        # Logged once per reason and interval whatever the key: made-up robot ids each
        # get their answer, not a log line each.
        if self._throttle.due(f"log {reason}"):
            log.warning("%s: %s", key, reason)
        self.publish(key, protocol.encode(protocol.Error.of(code, reason, **extra)))

    # -- control messages -----------------------------------------------------------------

    def _on_control_of(self, robot_id: str, data: bytes, arrival: float) -> None:
        """A robot's control message: handled if this worker serves the robot, ignored if
        another one does, else kept while the workers bid for the robot."""
        placement = self.placement
        if placement.serves(robot_id):
            return self._on_robot_control(robot_id, data, arrival)
        waiting = placement.unavailable()
        if waiting is not None and _is_hello(data):
            # Nobody can be granted the robot now: said, so that it waits for the right thing.
            return self.error(keys.reply(robot_id), protocol.Code.REFUSED, waiting,
                              answer_to="hello", wait=True)
        if placement.owner(robot_id) is not None:
            with self._lock:  # another worker's robot: nothing of it to keep here
                self._pending.pop(robot_id, None)
            return
        with self._lock:
            if robot_id not in self._pending and len(self._pending) >= PENDING_ROBOTS:
                self.unrouted += 1
                return
            self._pending[robot_id] = (data, arrival)
        # A worker that would refuse the robot does not bid (one full of finished sessions
        # would not: it closes one); a robot nobody can take hears it below.
        if self.sessions.has_room():
            placement.claim(robot_id)
            return
        live = placement.live_workers()
        if len(live) == 1:
            self._on_robot_control(robot_id, *self._pending.pop(robot_id))
        elif _is_hello(data) and placement.says_full():
            # Every worker full: one of them says so, or the robot would hear silence and
            # blame the network. A worker that frees a slot reports it within
            # placement.load_report_s; the robot's next hello is placed then.
            with self._lock:
                self._pending.pop(robot_id, None)
            self.error(keys.reply(robot_id), protocol.Code.REFUSED,
                       f"the cloud is full: each of its {len(live)} workers ({', '.join(live)}) "
                       f"holds as many robots as it may, all at work (here "
                       f"{self.sessions.allowed()}: transport.max_sessions and "
                       f"transport.cloud_budget_mb)",
                       answer_to="hello", full=True, max_sessions=self.sessions.allowed())

    def _on_robot_control(self, robot_id: str, data: bytes, arrival: float) -> None:
        """A robot's control message. Refusals of a hello or an end say which they answer
        (``answer_to``), so the robot tells a refusal from silence."""
        reply = keys.reply(robot_id)
        try:
            message = protocol.parse_control(data)
            hello = Hello.parse(message) if message["type"] == "hello" else None
        except ValueError as exc:
            live = self.sessions.live(robot_id)
            if live is not None:  # counted against the robot: a flood of them pauses it
                return live.reject_control(f"control message rejected: {exc}")
            return self.error(reply, protocol.Code.BAD_MESSAGE,
                              f"control message rejected: {exc}", answer_to="hello")
        session = self.sessions.session(robot_id)
        if hello is not None and session is not None \
                and session.state.hello.offload_at != hello.offload_at:
            return self.error(reply, protocol.Code.REFUSED,
                              f"session offloads at {session.state.hello.offload_at}; a robot "
                              f"cannot change its offloading point within a session",
                              answer_to="hello")
        if session is None:
            if hello is None:
                return self.error(reply, protocol.Code.NO_SESSION,
                                  "no session: send a hello first")
            problem = self.merging.hello_problem(robot_id, hello)
            if problem is not None:
                return self.error(reply, protocol.Code.REFUSED, problem, answer_to="hello")
            session = self.sessions.open(robot_id, hello)
            if session is None:
                return self.error(reply, protocol.Code.REFUSED, self.sessions.refusal(),
                                  answer_to="hello", full=True,
                                  max_sessions=self.sessions.allowed())
            log.info("robot %s: new session, offloading at %d, source %s", robot_id,
                     hello.offload_at, hello.source)
            session.welcome(resumed=False)
            return
        if session.submit_control(message, arrival) and message["type"] == "end":
            # Heard at once; the answer (need / ended) comes when its frames are done.
            self.publish(reply, protocol.encode(protocol.Ending()))

    def _on_cloud_control(self, data: bytes) -> None:
        """The operator's request: ``merge`` or ``status``."""
        try:
            message = protocol.parse_control(data)
        except ValueError as exc:
            return self.error(keys.CLOUD_REPLY, protocol.Code.BAD_MESSAGE,
                              f"control message rejected: {exc}")
        try:
            request = protocol.Request.parse(message)
        except ValueError as exc:
            return self.error(keys.CLOUD_REPLY, protocol.Code.UNKNOWN_TYPE, str(exc),
                              id=protocol.request_id(message))
        if request.kind == "merge":
            self.operator.merge(request.id)
        else:
            self.publish(keys.CLOUD_REPLY, protocol.encode(self.operator.status(request.id)))
