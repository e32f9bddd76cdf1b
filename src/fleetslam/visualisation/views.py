"""Which live views the cloud runs (``--view`` / ``--save``: rerun's, live_view.py;
``--foxglove``: the Foxglove app's, ``--ros2-out``: a ROS 2 graph's, both topic_view.py), as
one view its sessions and merger call."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.visualisation.live_view import LiveView, NullView
from fleetslam.visualisation.topic_view import TopicView


class Views(NullView):
    """Several views as one (rerun's and Foxglove's): each call goes to every one."""

    def __init__(self, views: list[NullView]) -> None:
        self.views = views
        self.enabled = any(v.enabled for v in views)

    @property
    def dropped(self) -> int:  # type: ignore[override]
        return sum(v.dropped for v in self.views)

    def robot(self, robot: str, camera: Camera) -> None:
        for v in self.views:
            v.robot(robot, camera)

    def received(self, robot: str, nbytes: int) -> None:
        for v in self.views:
            v.received(robot, nbytes)

    def frame(self, robot: str, index: int, T_map_camera: np.ndarray, tracked: bool,
              is_keyframe: bool, split_point: int, cloud_ms: float,
              timestamp: float | None = None) -> None:
        for v in self.views:
            v.frame(robot, index, T_map_camera, tracked, is_keyframe, split_point, cloud_ms,
                    timestamp)

    def keyframe_poses(self, robot: str, frames: Sequence[int], poses: np.ndarray) -> None:
        for v in self.views:
            v.keyframe_poses(robot, frames, poses)

    def keyframe_points(self, robot: str, index: int, T_map_keyframe: np.ndarray,
                        rgb: np.ndarray, depth_raw: np.ndarray, decimated_by: int) -> None:
        for v in self.views:
            v.keyframe_points(robot, index, T_map_keyframe, rgb, depth_raw, decimated_by)

    def merged(self, T_global_map: dict[str, np.ndarray],
               constraints: list[tuple[np.ndarray, np.ndarray, bool | None]],
               fleet: list[str] | None = None) -> None:
        for v in self.views:
            v.merged(T_global_map, constraints, fleet)

    def fleet_map(self, run_dir: Path, summary: dict[str, Any]) -> None:
        for v in self.views:
            v.fleet_map(run_dir, summary)

    def close(self) -> None:
        for v in self.views:
            v.close()


def open_view(config: Config, save: str | Path | None, live: bool,
              foxglove_port: int | None = None) -> NullView:
    """The cloud's view for these options: rerun's with ``save`` or ``live``, Foxglove's
    with ``foxglove_port``, the ROS 2 graph's at ``[ros2_out] endpoint`` (``--ros2-out``),
    as many as asked, or off (a NullView)."""
    views: list[NullView] = []
    if save is not None or live:
        views.append(LiveView.open(config, Path(save) if save is not None else None, live))
    distro = config.ros2_out.distro
    if foxglove_port is not None:
        from fleetslam.visualisation.foxglove_view import FoxgloveSink

        views.append(TopicView(FoxgloveSink(config.view, foxglove_port, distro), distro))
    if config.ros2_out.endpoint:
        from fleetslam.visualisation.ros2_sink import Ros2Sink

        # One node per cloud process: ROS 2 wants node names unique on a graph.
        views.append(TopicView(Ros2Sink(config.ros2_out, f"fleetslam_cloud_{os.getpid()}"),
                               distro))
    if not views:
        return NullView()
    return views[0] if len(views) == 1 else Views(views)
