"""Closing the sessions whose robots went quiet: every unfinished session that has heard
nothing from its robot for ``transport.idle_session_s`` is checkpointed and closed, so its
threads and memory are freed; the robot's next message restores it from that checkpoint. A
session that tracked no frame goes ``transport.idle_empty_session_s`` after it opened, with no
checkpoint (it has nothing to keep; its robot's next hello opens a new one): hellos under
made-up ids must not hold the cloud full. A finished session goes after
``transport.idle_session_s`` too, without a checkpoint: its end is on disk, and a merge reads
it from the store as it reads another worker's robots.
"""

from __future__ import annotations

import logging
import threading
import time

from fleetslam.cloud.session.sessions import SessionTable
from fleetslam.config import TransportConfig

log = logging.getLogger("fleetslam.cloud")


class IdleReaper:
    def __init__(self, sessions: SessionTable, transport: TransportConfig,
                 stopped: threading.Event) -> None:
        """Looks every quarter of the idle time (at most every 5 s) until ``stopped``."""
        self.sessions = sessions
        self.transport = transport
        self.stopped = stopped
        self._thread = threading.Thread(target=self._run, name="cloud-idle", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def join(self, timeout: float) -> None:
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _run(self) -> None:
        idle_s = self.transport.idle_session_s
        empty_s = self.transport.idle_empty_session_s
        while not self.stopped.wait(min(idle_s / 4.0, empty_s / 4.0, 5.0)):
            self.close_idle(idle_s, empty_s)

    def close_idle(self, idle_s: float, empty_s: float | None = None) -> None:
        """``empty_s``: for sessions that never tracked a frame (None: ``idle_s``)."""
        now = time.monotonic()
        empty_s = idle_s if empty_s is None else empty_s
        # Under the table's lock: a message arriving meanwhile must find either the live
        # session or the checkpoint written here, never an older one.
        with self.sessions.lock:
            for robot_id, session in self.sessions.now():
                quiet = now - session.last_heard
                if session.finished is not None:
                    if quiet > idle_s:
                        # Its end is on disk; a merge reads it from the store, a hello under
                        # its id is refused as ended from its checkpoint.
                        self.sessions.remove(robot_id)
                        session.close()
                        log.info("robot %s: finished session closed after %.0f s without a "
                                 "message", robot_id, quiet)
                    continue
                # From its opening, not its last message: hellos resent under a made-up id
                # must not keep its slot.
                if not session.state.rows and now - session.opened > empty_s \
                        and not self.sessions.store.has_checkpoint(robot_id):
                    self.sessions.remove(robot_id)
                    session.close()
                    log.info("robot %s: session closed, no frame %.0f s after it opened",
                             robot_id, now - session.opened)
                elif quiet > idle_s:
                    self.sessions.remove(robot_id)
                    session.close(final_checkpoint=True)
                    log.info("robot %s: session closed after %.0f s without a message "
                             "(checkpointed; its next message restores it)", robot_id,
                             now - session.last_heard)
