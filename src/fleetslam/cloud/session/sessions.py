"""The robot sessions one cloud worker serves, by robot id: opened on a robot's hello,
restored from its checkpoint in the store (a restart, a takeover, a session closed while
idle), or read from the store without serving it (another worker's robot, for the merge).
Read it as a mapping; every change goes through its methods, under its lock. It tells the
merge hand-off (the merge role) of every session opened or restored and of each new keyframe.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator, Mapping
from typing import Protocol

import numpy as np

from fleetslam.backend.workers import LocalMappingPool
from fleetslam.cloud.session.memory_budget import sessions_allowed
from fleetslam.cloud.session.replies import Publish
from fleetslam.cloud.session.robot_session import RobotSession
from fleetslam.cloud.session.session_state import SessionState
from fleetslam.cloud.session.store import CHECKPOINT, CloudStore
from fleetslam.config import Config
from fleetslam.transport.protocol import Hello
from fleetslam.visualisation.live_view import NullView
from fleetslam.wire.data_tree import CheckpointError
from fleetslam.wire.merger_keyframes import KeyframeSummary

log = logging.getLogger("fleetslam.cloud")


class MergeHandoff(Protocol):
    """Who the table hands each robot and keyframe to for the fleet's merge (merge_role.py)."""

    def joined(self, robot_id: str, hello: Hello, restored: RobotSession | None) -> None:
        """A session opened (``restored`` None) or restored here, with the keyframes it has."""

    def keyframe_sink(self, summary: KeyframeSummary, poses: np.ndarray) -> None:
        """A session's new keyframe, once a checkpoint covers it."""


class NoMerge:
    """The hand-off of a table nobody merges from: robots and keyframes go nowhere."""

    def joined(self, robot_id: str, hello: Hello, restored: RobotSession | None) -> None:
        pass

    def keyframe_sink(self, summary: KeyframeSummary, poses: np.ndarray) -> None:
        pass


class SessionTable(Mapping[str, RobotSession]):
    def __init__(self, config: Config, store: CloudStore, publish: Publish,
                 view: NullView) -> None:
        self.config = config
        self.store = store
        self.publish = publish
        self.view = view
        # The merge role reads this table, so it comes after it: ``hand_to``.
        self._merge: MergeHandoff = NoMerge()
        # The local-mapping workers sessions opened from now on use (None: in-line).
        self.local_mapping: LocalMappingPool | None = None
        self._live: dict[str, RobotSession] = {}
        # Why a robot's stored session could not be restored (its checkpoint set aside):
        # the fresh session opened for its next hello tells the robot (welcome history_lost).
        self._lost: dict[str, str] = {}
        # Every change of the table; a caller whose change must go with others (the routing's
        # subscribers and pending messages, the idle reaper's final checkpoint) holds it
        # around them all (re-entrant: the table's methods take it again).
        self.lock = threading.RLock()

    def hand_to(self, merge: MergeHandoff) -> None:
        """Every session opened or restored from now on, and its keyframes, go to ``merge``."""
        self._merge = merge

    # -- reading (a Zenoh callback, the merge or status may read while another changes it) --

    def __getitem__(self, robot_id: str) -> RobotSession:
        return self._live[robot_id]

    def __iter__(self) -> Iterator[str]:
        return iter(self._live)

    def __len__(self) -> int:
        return len(self._live)

    def now(self) -> list[tuple[str, RobotSession]]:
        """The table as it is now (Zenoh callbacks and the idle reaper change it)."""
        with self.lock:
            return list(self._live.items())

    def live(self, robot_id: str) -> RobotSession | None:
        with self.lock:
            return self._live.get(robot_id)

    def at_work(self) -> int:
        """Robots this worker is working for: unfinished sessions heard from lately (the
        load placement weighs: worker_load.CpuMeter)."""
        now = time.monotonic()
        active_s = self.config.placement.active_s
        return sum(1 for _, s in self.now()
                   if s.finished is None and now - s.last_heard < active_s)

    def allowed(self) -> int:
        """Sessions this worker holds at most (transport.max_sessions, or fewer: each
        reserves transport.session_budget_mb of transport.cloud_budget_mb)."""
        return sessions_allowed(self.config.transport)

    def full(self) -> bool:
        """Whether a new session would pass ``allowed``."""
        return len(self._live) >= self.allowed()

    def refusal(self) -> str:
        """Why a hello is refused when the table is full."""
        t = self.config.transport
        return (f"the cloud is full: it serves at most {sessions_allowed(t)} robots at once "
                f"(transport.max_sessions {t.max_sessions}; transport.cloud_budget_mb "
                f"{t.cloud_budget_mb:.0f} holds {t.cloud_budget_mb // t.session_budget_mb:.0f} "
                f"sessions of transport.session_budget_mb {t.session_budget_mb:.0f})")

    def held_bytes(self) -> int:
        """Bytes every live session holds now (their budgets' use)."""
        return sum(s.budget.used for _, s in self.now())

    # -- changing ---------------------------------------------------------------------------

    def open(self, robot_id: str, hello: Hello) -> RobotSession | None:
        """A new session for the robot's hello (the live one if a hello just opened it); None
        if the table is full (``full``)."""
        with self.lock:
            if robot_id not in self._live and self.full() and not self._make_room(robot_id):
                return None
            session = self._live.get(robot_id)
            if session is None:
                session = RobotSession.open(robot_id, hello, self.config, self.store,
                                            self.publish, self._merge.keyframe_sink, self.view,
                                            self.local_mapping)
                session.history_lost = self._lost.pop(robot_id, None)
            self._live[robot_id] = session
            self.view.robot(robot_id, hello.camera)
            self._merge.joined(robot_id, hello, None)
            return session

    def _make_room(self, robot_id: str) -> bool:
        """Close a session for ``robot_id``'s hello; whether there was one to close. First
        the finished session heard from longest ago: its end is on disk (its outputs, its
        final checkpoint), a merge reads it from the store, and a hello under its id is
        refused from that checkpoint as from the session (session_ended); without this, a
        worker that had served max_sessions runs was full for good. Else the oldest that
        only said hello (no frame arrived, nothing tracked or stored): on plain TCP anyone
        may say hello under any id, and hellos alone must never keep a robot out; its robot,
        if real, is told no_session at its first frame and says hello again. Called with
        the lock."""
        found = self._room()
        if found is None:
            return False
        victim, finished = found
        session = self._live.pop(victim)
        session.close()
        if finished:
            log.info("robot %s: its finished session closed for robot %s's hello (the cloud "
                     "holds transport.max_sessions)", victim, robot_id)
        else:
            log.warning("robot %s: its session (a hello %.1f s ago, no frame since) closed "
                        "for robot %s's hello: the cloud is full", victim,
                        time.monotonic() - session.opened, robot_id)
        return True

    def _room(self) -> tuple[str, bool] | None:
        """(the session ``_make_room`` would close, whether it is a finished one); None if
        none may be. Called with the lock."""
        finished = [(s.last_heard, r) for r, s in self._live.items() if s.finished is not None]
        if finished:
            return min(finished)[1], True
        empty = [(s.opened, r) for r, s in self._live.items()
                 if not s.heard_frame and not s.state.rows and s.finished is None
                 and not self.store.has_checkpoint(r)]
        return (min(empty)[1], False) if empty else None

    def has_room(self) -> bool:
        """Whether a new robot's hello would get a session here (``full``, or a session
        ``_make_room`` may close): a worker that would refuse it does not bid for it."""
        with self.lock:
            return not self.full() or self._room() is not None

    def session(self, robot_id: str) -> RobotSession | None:
        """The live session, or the one restored from its checkpoint after a restart; None
        without one, or if it cannot be restored (the checkpoint is then set aside, and the
        robot's next hello opens a fresh session that tells it why)."""
        with self.lock:
            session = self._live.get(robot_id)
            if session is None:
                state = self.stored_state(robot_id, serving=True)
                if state is None:
                    return None
                try:
                    session = RobotSession(state, self.config, self.store, self.publish,
                                           self._merge.keyframe_sink, self.view,
                                           self.local_mapping).start()
                except Exception as exc:  # a state that passed the checks and still fails
                    log.exception("robot %s: restoring its session failed", robot_id)
                    self._lose(robot_id, CheckpointError(
                        str(self.store.robot_dir(robot_id) / CHECKPOINT),
                        f"cannot be restored ({exc!r})"))
                    return None
                self._live[robot_id] = session
                self.view.robot(robot_id, state.hello.camera)
                # The merger is rebuilt from the keyframes the session already has (none for
                # a robot that tracks itself).
                self._merge.joined(robot_id, state.hello, session)
                log.info("robot %s: session restored from its checkpoint (frame %d)",
                         robot_id, state.last_index)
            return session

    def remove(self, robot_id: str) -> RobotSession | None:
        """Out of the table (the caller closes it)."""
        with self.lock:
            return self._live.pop(robot_id, None)

    # -- the store ------------------------------------------------------------------------

    def stored_state(self, robot_id: str, serving: bool = False) -> SessionState | None:
        """The robot's session as its last checkpoint has it; None without one, or if it
        cannot be restored (logged with the file and why). ``serving``: this worker serves
        the robot, so a checkpoint that cannot be restored is set aside for a fresh start."""
        try:
            return self.store.load_checkpoint(robot_id)
        except CheckpointError as exc:
            if serving:
                self._lose(robot_id, exc)
            else:
                log.error("%s", exc)
            return None

    def _lose(self, robot_id: str, exc: CheckpointError) -> None:
        """The robot's stored session is lost: its checkpoint goes aside (kept, never
        deleted) and its next session is told why."""
        moved = self.store.set_aside(robot_id)
        kept = f"; kept as {', '.join(map(str, moved))}" if moved else ""
        reason = f"{exc}{kept}"
        log.error("robot %s: its session history is lost, starting afresh: %s", robot_id,
                  reason)
        with self.lock:
            self._lost[robot_id] = reason

    def stored(self, robot_id: str) -> RobotSession | None:
        """The robot's session from the store, read only: not started (no threads, nothing
        written), not served here."""
        state = self.stored_state(robot_id)
        return None if state is None else RobotSession(state, self.config, self.store,
                                                      self.publish)
