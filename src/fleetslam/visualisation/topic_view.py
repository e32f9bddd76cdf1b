"""The cloud's live topics as ROS 2 messages (CDR), to a sink: a ROS 2 graph (``fleetslam
cloud --ros2-out ENDPOINT``, ``ros2_sink.py``) or the Foxglove app (``--foxglove PORT``,
``foxglove_view.py``). The same messages as run.mcap and a robot's ``--ros2-out``:

    /<robot>/pose        geometry_msgs/PoseStamped  each frame this worker tracked, in
                                                    <robot>/map, at its capture time
    /tf                  tf2_msgs/TFMessage         <robot>/map -> <robot>/camera
    /tf_static           tf2_msgs/TFMessage         map -> <robot>/map for the robots of the
                                                    fleet's group (a loaded map's, else the
                                                    largest joined one: the merge's), as
                                                    the merger places them (at most every
                                                    view.global_every_s)
    /map/global, /map/grid, /map/octomap, /map/constraints, /<robot>/global_path
                                                    each merge's (run_mcap.add_fleet_map)

Latched topics (the static transforms and a merge's maps) go out as such: transient local
on a ROS 2 graph, sent again to a late Foxglove client. With many workers each publishes its
own robots' poses and the merging one the fleet's. Every call only hands a message to the
sink, which never waits for a subscriber: a robot's session is never held up.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from fleetslam.io.mcap_out import RosMessages
from fleetslam.ros2_out import cdr
from fleetslam.run_mcap import GLOBAL_FRAME, add_fleet_map, camera_frame, map_frame
from fleetslam.visualisation.live_view import NullView

# The definitions the messages follow: Jazzy's (and Humble's for these types but Marker).
STORES = {"jazzy": "ROS2_JAZZY", "humble": "ROS2_HUMBLE"}


class TopicSink(Protocol):
    """Where the messages go: ``publish`` a topic's message (CDR of ``typename``)."""

    def publish(self, topic: str, typename: str, data: bytes, latched: bool) -> None: ...

    def close(self) -> None: ...


class TopicView(NullView):
    enabled = True

    def __init__(self, sink: TopicSink, distro: str = "jazzy") -> None:
        self.sink = sink
        self.store = STORES[distro]

    def frame(self, robot: str, index: int, T_map_camera: np.ndarray, tracked: bool,
              is_keyframe: bool, split_point: int, cloud_ms: float,
              timestamp: float | None = None) -> None:
        if not tracked:
            return
        stamp = time.time_ns() if timestamp is None else cdr.stamp_ns(timestamp)
        self.sink.publish(f"/{robot}/pose", cdr.POSE_STAMPED,
                          cdr.pose_stamped(stamp, map_frame(robot), T_map_camera), False)
        self.sink.publish("/tf", cdr.TF_MESSAGE, cdr.tf_message(
            [(stamp, map_frame(robot), camera_frame(robot), T_map_camera)]), False)

    def merged(self, T_global_map: dict[str, np.ndarray],
               constraints: list[tuple[np.ndarray, np.ndarray, bool | None]],
               fleet: list[str] | None = None) -> None:
        # `map` is the fleet group's frame; a robot not joined yet is in no fleet frame.
        members = fleet or []
        if not members:
            return
        now = time.time_ns()
        self.sink.publish("/tf_static", cdr.TF_MESSAGE, cdr.tf_message(
            [(now, GLOBAL_FRAME, map_frame(robot), T_global_map[robot])
             for robot in sorted(members) if robot in T_global_map]), True)

    def fleet_map(self, run_dir: Path, summary: dict[str, Any]) -> None:
        if not (summary.get("merge") or {}).get("members"):
            return
        now = time.time_ns()
        messages = RosMessages(self.store)
        add_fleet_map(messages, Path(run_dir), summary, now)
        for _, _, topic, data in messages.messages:
            self.sink.publish(topic, messages.topics[topic][0], data, True)
        # The merge's own transforms (FS-HICP's, summary.json's), after the graph's.
        merge = summary["merge"]
        self.sink.publish("/tf_static", cdr.TF_MESSAGE, cdr.tf_message(
            [(now, GLOBAL_FRAME, map_frame(robot), np.array(merge["T_global_map"][robot]))
             for robot in sorted(merge["members"])]), True)

    def close(self) -> None:
        self.sink.close()
