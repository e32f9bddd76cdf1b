"""The fleet's ``map`` frame as a ROS user expects it: REP 103, x forward, y left, z up.

The tracker's frames are optical: a robot's map (``<robot>/map``) is its first camera's frame
(x right, y down, z forward) and the merge's graph works in the anchor robot's map. The
fleet's ``map`` is that frame made level, by the best the run knows of up:

1. the anchor camera's mounting (``[camera] base_link``): ``map`` is the anchor's base_link
   at its first frame (x forward and z up as the robot stood, REP 105's usual map origin);
2. else, once a merge has the dense map, the grid's level frame (occupancy_grid.py): up from
   the floor plane (or ``[grid] up`` where no floor shows), x the first camera's view along
   the floor, the origin on the floor under it;
3. live, before a merge has looked for the floor: ``[grid] up``, the origin at the first
   camera (the final merge's frame replaces it).

The fleet's outputs are in ``map`` (global_map.ply / .bt / .pgm, global/<robot>.tum,
summary.json's T_global_map, ``map -> <robot>/map`` on /tf_static, run.mcap's /map/*); a
robot's own files and topics stay in ``<robot>/map``.
"""

from __future__ import annotations

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import GridConfig
from fleetslam.mapping.occupancy_grid import level_frame, unit
from fleetslam.transforms import invert, matrix_from_quaternion


def T_base_camera(camera: Camera) -> np.ndarray | None:
    """The camera's mounting (``Camera.base_link``) as a 4 x 4 transform, or None."""
    if not camera.base_link:
        return None
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion(np.asarray(camera.base_link[3:]))[0]
    T[:3, 3] = camera.base_link[:3]
    return T


def base_link_frame(T_graph_camera0: np.ndarray, camera: Camera) -> np.ndarray | None:
    """``map`` in the graph's frame from the anchor's mounting: its base_link when its first
    camera was at ``T_graph_camera0``; None without a mounting."""
    mounting = T_base_camera(camera)
    return None if mounting is None else T_graph_camera0 @ invert(mounting)


def mounting_up(T_graph_camera0: np.ndarray, camera: Camera) -> np.ndarray | None:
    """Up (base_link's z) in the graph's frame from the anchor's mounting, or None."""
    frame = base_link_frame(T_graph_camera0, camera)
    return None if frame is None else frame[:3, 2].copy()


def live_map_frame(T_graph_camera0: np.ndarray, camera: Camera, cfg: GridConfig
                   ) -> np.ndarray:
    """``map`` in the graph's frame while the robots run: from the mounting, else level by
    ``[grid] up`` (a direction in the first camera's frame) at the first camera."""
    frame = base_link_frame(T_graph_camera0, camera)
    if frame is not None:
        return frame
    up = unit(T_graph_camera0[:3, :3] @ np.asarray(cfg.up, np.float64))
    if up is None:
        raise ValueError(f"[grid] up = {list(cfg.up)} is not a direction (all zero)")
    centre = T_graph_camera0[:3, 3]
    return level_frame(up, float(centre @ up), T_graph_camera0[None])
