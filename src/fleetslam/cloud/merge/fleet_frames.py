"""Telling each robot where its map lies in the fleet: once the merger joins a robot to a
group, the robot gets a ``placed`` reply (protocol.py: the group and T_global_map), again
whenever the group's graph moves its map by more than a little, and once more with the
merge's final transform (summary.json's T_global_map). The robot publishes it to its ROS 2
graph as ``map -> <robot>/map`` (edge/ros2_out.py).

Sent from the merger's thread; the latest placement of every robot is sent again every
``merge.placement_resend_s``, so a robot that missed one (a restart, a lost message) has it
soon without asking.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from fleetslam.cloud.session.robot_session import Publish
from fleetslam.config import MergeConfig
from fleetslam.transforms import invert, rotation_angle_deg
from fleetslam.transport import keys, protocol

class FleetFrames:
    def __init__(self, cfg: MergeConfig, publish: Publish) -> None:
        self.cfg = cfg
        self.publish = publish
        self._lock = threading.Lock()
        # robot -> (group, T_global_map, final) as last sent
        self._sent: dict[str, tuple[str, np.ndarray, bool]] = {}
        # robot -> the live graph's T_global_map when last sent or last weighed against a
        # final one (a live update after a merge is measured against the graph, not the
        # merge's refined transform, which differs from it by the FS-HICP refinement)
        self._live: dict[str, np.ndarray] = {}
        self._resent_at = time.monotonic()

    def _worth_sending(self, robot: str, group: str, T: np.ndarray, final: bool) -> bool:
        """New, in another group, a merge's (final), or moved beyond placement_move_*: after
        a final one, the live graph itself moved since (new keyframes or joins)."""
        known = self._sent.get(robot)
        if known is None or known[0] != group or final:
            return True
        reference = self._live.setdefault(robot, T) if known[2] else known[1]
        delta = invert(reference) @ T
        return bool(np.linalg.norm(delta[:3, 3]) > self.cfg.placement_move_m
                    or rotation_angle_deg(delta[:3, :3]) > self.cfg.placement_move_deg)

    def update(self, placements: dict[str, tuple[str, np.ndarray]], final: bool = False
               ) -> int:
        """Each robot's (group, T_global_map) now; sends those new or moved (all of them
        when ``final``); how many were sent. A live update after a final one replaces it
        only when it moves the map (the merge's transform is the better one till then)."""
        sent = 0
        for robot, (group, T) in sorted(placements.items()):
            with self._lock:
                if not self._worth_sending(robot, group, T, final):
                    continue
                self._sent[robot] = (group, np.array(T, np.float64), final)
                if not final:
                    self._live[robot] = self._sent[robot][1]
            self._send(robot, group, T, final)
            sent += 1
        return sent

    def resend_due(self) -> None:
        """Every placement again, at most every ``placement_resend_s``."""
        now = time.monotonic()
        if now - self._resent_at < self.cfg.placement_resend_s:
            return
        self._resent_at = now
        with self._lock:
            known = dict(self._sent)
        for robot, (group, T, final) in known.items():
            self._send(robot, group, T, final)

    def _send(self, robot: str, group: str, T: np.ndarray, final: bool) -> None:
        self.publish(keys.reply(robot), protocol.encode(protocol.Placed(group, T, final)))
