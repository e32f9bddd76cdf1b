"""The cloud's live topics (topic_view.py) on the lab's ROS 2 graph (``fleetslam cloud
--ros2-out ENDPOINT``), as a node ``fleetslam_<worker>`` made of plain Zenoh the way
rmw_zenoh makes one (ros2_out/node.py): latched topics transient local, so a subscriber that
starts later still gets the latest map. An unreachable router is said once and tried again
every ``[ros2_out] retry_s``; what comes meanwhile is dropped, and no caller ever waits for
it.
"""

from __future__ import annotations

import threading

from fleetslam.config import Ros2OutConfig
from fleetslam.io.mcap_out import RosMessages
from fleetslam.ros2_out.graph import GraphLink
from fleetslam.ros2_out.node import RosNode, RosPublisher
from fleetslam.visualisation.topic_view import STORES

# Keep-last depths: a stream's (rmw's default), a latched topic's (its latest).
STREAM_DEPTH = 10
LATCHED_DEPTH = 1


class Ros2Sink:
    def __init__(self, cfg: Ros2OutConfig, node_name: str) -> None:
        self.cfg = cfg
        self._definitions = RosMessages(STORES[cfg.distro])  # the type hashes
        self._lock = threading.Lock()
        self._pubs: dict[str, RosPublisher] = {}
        self.graph = GraphLink(cfg, node_name, self, "the cloud",
                               hint="Set it with fleetslam cloud --ros2-out or [ros2_out] "
                                    "endpoint").start()

    def declare(self, node: RosNode) -> None:
        """Publishers are declared as their topics first come (``publish``)."""

    def wait_connected(self, timeout: float) -> bool:
        return self.graph.connected.wait(timeout)

    def publish(self, topic: str, typename: str, data: bytes, latched: bool) -> None:
        with self._lock:
            node = self.graph.node
            pub = self._pubs.get(topic)
            if node is not None and pub is None:
                pub = self._pubs[topic] = node.publisher(
                    topic, typename, LATCHED_DEPTH if latched else STREAM_DEPTH,
                    transient_local=latched, type_hash=self._definitions.type_hash(typename))
        if pub is not None:
            pub.publish(data)  # False once closed: the cloud is stopping

    def close(self) -> None:
        with self._lock:
            self._pubs = {}
        self.graph.close()  # the node closes its publishers, each under its own lock
