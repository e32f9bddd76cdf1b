"""The cloud's live topics (topic_view.py) on the lab's ROS 2 graph (``fleetslam cloud
--ros2-out ENDPOINT``), as a node ``fleetslam_<worker>`` made of plain Zenoh the way
rmw_zenoh makes one (ros2_out/node.py): latched topics transient local, so a subscriber that
starts later still gets the latest map. An unreachable router is said once and tried again
every ``[ros2_out] retry_s``; what could not be published meanwhile is counted, and no
caller ever waits for it.
"""

from __future__ import annotations

import logging
import threading

import zenoh

from fleetslam.config import Ros2OutConfig
from fleetslam.datasets.ros2_session import open_ros_session
from fleetslam.datasets.ros2_topics import resolve_domain_id
from fleetslam.io.mcap_out import RosMessages
from fleetslam.ros2_out.node import RosNode, RosPublisher
from fleetslam.visualisation.topic_view import STORES

log = logging.getLogger("fleetslam.ros2_out")

# Keep-last depths: a stream's (rmw's default), a latched topic's (its latest).
STREAM_DEPTH = 10
LATCHED_DEPTH = 1


class Ros2Sink:
    def __init__(self, cfg: Ros2OutConfig, node_name: str) -> None:
        self.cfg = cfg
        self.node_name = node_name
        self._definitions = RosMessages(STORES[cfg.distro])  # the type hashes
        self._lock = threading.Lock()
        self._node: RosNode | None = None
        self._session: zenoh.Session | None = None
        self._pubs: dict[str, RosPublisher] = {}
        self._stop = threading.Event()
        self._connected = threading.Event()
        self.published = 0
        self.unpublished = 0
        self._thread = threading.Thread(target=self._connect, daemon=True,
                                        name="ros2-out-cloud-connect")
        self._thread.start()

    def _connect(self) -> None:
        said = False
        while not self._stop.is_set():
            try:
                session = open_ros_session(
                    self.cfg.endpoint, self.cfg.connect_timeout_s, self.cfg.zenoh_config,
                    hint="Set it with fleetslam cloud --ros2-out or [ros2_out] endpoint")
            except TimeoutError as exc:
                if not said:
                    log.warning("ROS 2 out: %s; the cloud goes on without it, trying again "
                                "every %.0f s", exc, self.cfg.retry_s)
                    said = True
                self._stop.wait(self.cfg.retry_s)
                continue
            except ValueError as exc:  # a bad Zenoh config file: it will not mend itself
                log.error("ROS 2 out is off: %s", exc)
                return
            node = RosNode(session, self.node_name,
                           domain_id=resolve_domain_id(self.cfg.domain_id),
                           humble=self.cfg.distro == "humble")
            with self._lock:
                if self._stop.is_set():
                    node.close()
                    session.close()
                    return
                self._session, self._node = session, node
            self._connected.set()
            log.info("ROS 2 out: the cloud's topics go to the ROS 2 graph at %s (node %s)",
                     self.cfg.endpoint, self.node_name)
            return

    def wait_connected(self, timeout: float) -> bool:
        return self._connected.wait(timeout)

    def publish(self, topic: str, typename: str, data: bytes, latched: bool) -> None:
        with self._lock:
            node = self._node
            pub = self._pubs.get(topic)
            if node is not None and pub is None:
                pub = self._pubs[topic] = node.publisher(
                    topic, typename, LATCHED_DEPTH if latched else STREAM_DEPTH,
                    transient_local=latched, type_hash=self._definitions.type_hash(typename))
        if pub is None or not pub.publish(data):
            self.unpublished += 1
            return
        self.published += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(self.cfg.connect_timeout_s + 1.0)
        with self._lock:
            if self._node is not None:
                self._node.close()  # its publishers too, each under its own lock
            if self._session is not None:
                self._session.close()
            self._node = self._session = None
            self._pubs = {}
