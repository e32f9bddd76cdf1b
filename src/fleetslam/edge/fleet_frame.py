"""Where the cloud placed this robot's map in its group's frame: ``placed`` replies
(cloud/merge/fleet_frames.py) checked, kept in the report and handed to ROS 2 out as
``map -> <robot>/map``; and the hold after the session (``ros2_out.hold_s``) that keeps the
node up until a merge's final placement arrives."""

from __future__ import annotations

import logging
import threading

from fleetslam.edge.report import RobotReport
from fleetslam.edge.ros2_out import RobotRosOut
from fleetslam.transport import protocol

log = logging.getLogger("fleetslam.robot")


class FleetFrame:
    def __init__(self, robot_id: str, report: RobotReport, ros_out: RobotRosOut | None,
                 hold_s: float) -> None:
        self.robot_id = robot_id
        self.report = report
        self.ros_out = ros_out
        self.hold_s = hold_s
        # Ends the hold: a merge's (final) placement, or the robot told to stop.
        self._over = threading.Event()

    def rejected(self, reason: str) -> None:
        """A ``placed`` reply that did not parse: said and dropped."""
        self.report.placed_messages += 1
        self.report.placed_rejected += 1
        log.warning("robot %s: placement from the cloud rejected: %s", self.robot_id, reason)

    def take(self, placed: protocol.Placed) -> None:
        """A ``placed`` reply (a Zenoh callback), checked."""
        self.report.placed_messages += 1
        self.report.placed = {"group": placed.group, "final": placed.final,
                              "T_global_map": placed.T_global_map.tolist()}
        if self.ros_out is not None:
            self.ros_out.placed(placed)
        if placed.final:
            self._over.set()

    def hold(self) -> None:
        """With ROS 2 out, keep the node up after the session ended, ``hold_s`` at most: its
        TF stays, and a merge's final placement of its map reaches ROS 2."""
        if self.ros_out is None or self.hold_s <= 0 or self._over.is_set():
            return
        log.info("robot %s: holding its ROS 2 node up to %.0f s for a merge's placement "
                 "(Ctrl-C ends it)", self.robot_id, self.hold_s)
        if not self._over.wait(self.hold_s):
            log.info("robot %s: no merge placed its map within %.0f s", self.robot_id,
                     self.hold_s)

    def release(self) -> None:
        """End the hold now (or before it starts)."""
        self._over.set()
