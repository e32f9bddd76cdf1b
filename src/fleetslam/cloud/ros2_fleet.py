"""The fleet's map, live in ROS 2 (``fleetslam cloud --ros2-out ENDPOINT``): after each merge
the merging worker publishes what the merge wrote, as a node ``fleetslam_fleet`` on the
lab's ROS 2 graph, every topic transient local (a subscriber that starts later still gets
the latest):

    /map/global          sensor_msgs/PointCloud2         the global map (xyz, rgb)
    /map/grid            nav_msgs/OccupancyGrid          the nav2 map (global_map.pgm)
    /map/octomap         octomap_msgs/Octomap            the global OctoMap
    /map/constraints     visualization_msgs/MarkerArray  the inter-robot constraints
    /<robot>/global_path nav_msgs/Path                   each member robot in ``map``

The messages are run_mcap.py's (the same as run.mcap holds), serialised with the graph's
ROS 2 definitions (``[ros2_out] distro``). An unreachable router is said once; the merge is
never held up by ROS 2, and what could not be published is counted.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from fleetslam.config import Ros2OutConfig
from fleetslam.datasets.ros2_session import open_ros_session
from fleetslam.datasets.ros2_topics import resolve_domain_id
from fleetslam.io.mcap_out import RosMessages
from fleetslam.ros2_out.node import RosNode, RosPublisher
from fleetslam.run_mcap import add_fleet_map

log = logging.getLogger("fleetslam.ros2_out")

_STORES = {"jazzy": "ROS2_JAZZY", "humble": "ROS2_HUMBLE"}


class FleetRosOut:
    def __init__(self, cfg: Ros2OutConfig) -> None:
        self.cfg = cfg
        self._lock = threading.Lock()
        self._session: zenoh.Session | None = None
        self._node: RosNode | None = None
        self._pubs: dict[str, RosPublisher] = {}
        self._said = False
        self.published = 0
        self.unpublished = 0

    def _connected(self) -> RosNode | None:
        """The node, opened on first use (then again after a failure, said once)."""
        if self._node is not None:
            return self._node
        try:
            self._session = open_ros_session(
                self.cfg.endpoint, self.cfg.connect_timeout_s, self.cfg.zenoh_config,
                hint="Set it with fleetslam cloud --ros2-out or [ros2_out] endpoint")
        except (TimeoutError, ValueError) as exc:
            if not self._said:
                log.warning("ROS 2 out: %s; the merge's maps are not published (tried again "
                            "at the next merge)", exc)
                self._said = True
            return None
        self._node = RosNode(self._session, "fleetslam_fleet",
                             domain_id=resolve_domain_id(self.cfg.domain_id),
                             humble=self.cfg.distro == "humble")
        log.info("ROS 2 out: the merge's maps go to the ROS 2 graph at %s", self.cfg.endpoint)
        return self._node

    def merged(self, run_dir: Path, summary: dict[str, Any]) -> int:
        """Publish what the merge just wrote in ``run_dir``; how many messages went out."""
        if not (summary.get("merge") or {}).get("members"):
            return 0
        messages = RosMessages(_STORES[self.cfg.distro])
        add_fleet_map(messages, Path(run_dir), summary, time.time_ns())
        with self._lock:
            node = self._connected()
            if node is None:
                self.unpublished += len(messages.messages)
                return 0
            for _, _, topic, data in messages.messages:
                pub = self._pubs.get(topic)
                if pub is None:
                    typename = messages.topics[topic][0]
                    pub = self._pubs[topic] = node.publisher(
                        topic, typename, 1, transient_local=True,
                        type_hash=messages.type_hash(typename))
                pub.publish(data)
                self.published += 1
        return len(messages.messages)

    def close(self) -> None:
        with self._lock:
            if self._node is not None:
                self._node.close()
            if self._session is not None:
                self._session.close()
            self._node = self._session = None
