"""A node on a ROS 2 graph, connected in the background so that nobody waits for ROS 2: the
first attempt waits ``connect_timeout_s``; a router that does not answer is said once, in
one line, and tried again every ``retry_s``; a Zenoh config file that is not one ends it
(said). Once connected, the node is handed to its user (``GraphUser.declare``: its
publishers and subscribers); ``close`` undoes it all."""

from __future__ import annotations

import logging
import threading
from typing import Protocol

import zenoh

from fleetslam.config import Ros2OutConfig
from fleetslam.datasets.ros2_session import open_ros_session
from fleetslam.datasets.ros2_topics import resolve_domain_id
from fleetslam.ros2_out.node import RosNode

log = logging.getLogger("fleetslam.ros2_out")


class GraphUser(Protocol):
    """What a node is for: its publishers and subscribers, declared once it is there."""

    def declare(self, node: RosNode) -> None: ...


class GraphLink:
    def __init__(self, cfg: Ros2OutConfig, node_name: str, user: GraphUser, who: str,
                 hint: str) -> None:
        """``who``: whose output it is, for the log ("robot r1", "the cloud"); ``hint``:
        which flag or setting names the endpoint."""
        self.cfg = cfg
        self.node_name = node_name
        self.user = user
        self.who = who
        self.hint = hint
        self.node: RosNode | None = None
        self._session: zenoh.Session | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.connected = threading.Event()
        self._thread = threading.Thread(target=self._connect, daemon=True,
                                        name=f"ros2-out-{node_name}")

    def start(self) -> GraphLink:
        self._thread.start()
        return self

    def _connect(self) -> None:
        said = False
        while not self._stop.is_set():
            try:
                session = open_ros_session(self.cfg.endpoint, self.cfg.connect_timeout_s,
                                           self.cfg.zenoh_config, hint=self.hint)
            except TimeoutError as exc:
                if not said:
                    log.warning("%s: ROS 2 out: %s; %s goes on without it, trying again "
                                "every %.0f s", self.who, exc, self.who, self.cfg.retry_s)
                    said = True
                self._stop.wait(self.cfg.retry_s)
                continue
            except ValueError as exc:  # a bad Zenoh config file: it will not mend itself
                log.error("%s: ROS 2 out is off: %s", self.who, exc)
                return
            node = RosNode(session, self.node_name,
                           domain_id=resolve_domain_id(self.cfg.domain_id),
                           humble=self.cfg.distro == "humble")
            with self._lock:
                if self._stop.is_set():
                    node.close()
                    session.close()
                    return
                self._session = session
            self.user.declare(node)
            self.node = node
            self.connected.set()
            log.info("%s: ROS 2 out at %s (domain %d) as node %s", self.who,
                     self.cfg.endpoint, node.domain_id, self.node_name)
            return

    def close(self) -> None:
        """The node's publishers, tokens and session (its user's subscribers first)."""
        self._stop.set()
        self._thread.join(self.cfg.connect_timeout_s + 1.0)
        with self._lock:
            if self.node is not None:
                self.node.close()
            if self._session is not None:
                self._session.close()
            self.node = self._session = None
