"""Robot trajectories and frame times.

Robots walk smooth, bounded paths in the middle of the room; they start looking at a
common region (the middle of the +y wall) and then turn apart, each sweeping its own side,
so their maps overlap and can be merged. Furniture keeps clear of the zone the paths stay
in (robot_zone). Poses are ``T_world_camera`` with OpenCV camera axes (x right, y down,
z forward).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from fleetslam.config import SyntheticConfig

# Robot paths (see robot_trajectories). Lateral spacing of the start positions (m), extra
# sideways drift while turning away (m), forward/back amplitude (m).
_ROBOT_SPACING_M = 0.5
_ROBOT_DRIFT_M = 0.45
_ROBOT_SWAY_M = 0.3
_MAX_ROBOTS_IN_ZONE = 4
# Heading offset between neighbouring robots at the start (negative: each looks a little
# towards the others, so all views cross in the middle of the +y wall), and how far each
# turns away. (Chosen so each of two robots' 120-frame maps shares ~45% of its 10 cm voxels
# with the other's: with less, sliding one map along the wall gains more overlap than the
# furniture costs.)
_START_SPREAD_DEG = -10.0
_TURN_DEG = 45.0
_TURN_RATE = 0.8  # rad/s of the turning cosine: peak yaw rate = _TURN_DEG/2 * 0.8 = 24 deg/s


def robot_zone(size_m: tuple[float, float, float]) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) that every robot path of up to 4 robots stays in."""
    half_x = _ROBOT_SPACING_M * (_MAX_ROBOTS_IN_ZONE - 1) / 2 + _ROBOT_DRIFT_M
    y0 = robot_base_y(size_m)
    return (-half_x, half_x, y0 - _ROBOT_SWAY_M, y0 + _ROBOT_SWAY_M)


def robot_base_y(size_m: tuple[float, float, float]) -> float:
    # Slightly in the -y half so the +y wall, which every robot looks at first, is not too far.
    return -0.1 * size_m[1]


def robot_timestamps(config: SyntheticConfig, robot: int) -> np.ndarray:
    """Frame times (s) of one robot, rounded to the 6 decimals of the file names."""
    return np.round(1000.0 + 100.0 * robot + np.arange(config.frames_per_robot) / config.fps, 6)


def _robot_pose(t: np.ndarray, robot: int, n_robots: int, size_m: tuple[float, float, float]
                ) -> np.ndarray:
    """Poses (N, 4, 4) at times ``t`` (s from the robot's start).

    Robot k (offset ``k`` from the middle of the group) starts looking at the middle of the
    +y wall (turned a little towards the group's middle, so the views cross there), then
    turns towards its own side by up to _TURN_DEG and
    back (periodic, so any length stays bounded), drifting sideways the same way. Every
    motion is a sinusoid, so velocity is smooth and starts at zero."""
    k = robot - (n_robots - 1) / 2
    away = float(np.sign(k))  # -1: the -x side, turning left (yaw up); +1: the +x side
    x0, y0 = k * _ROBOT_SPACING_M, robot_base_y(size_m)
    if away != 0:
        x = x0 + away * _ROBOT_DRIFT_M * (1 - np.cos(0.7 * t)) / 2
        yaw = (90.0 - _START_SPREAD_DEG * k) - away * _TURN_DEG * (1 - np.cos(_TURN_RATE * t)) / 2
    else:  # the middle robot of an odd group looks both ways
        x = x0 + 0.25 * np.sin(0.5 * t)
        yaw = 90.0 + _TURN_DEG / 2 * np.sin(_TURN_RATE * t)
    y = y0 + _ROBOT_SWAY_M * np.sin(0.7 * t + 1.3 * robot)
    z = 1.15 + 0.12 * robot + 0.05 * np.sin(0.9 * t + robot)
    tilt_down = 8.0 + 3.0 * np.sin(0.7 * t + 0.9 * robot)
    roll = 2.0 * np.sin(0.9 * t + 2.1 * robot)
    # Body frame: x forward, y left, z up; intrinsic z-y-x = yaw, then pitch (+ = nose down),
    # then roll. The OpenCV camera looks along body x with image x = -body y, image y = -body z.
    R_world_body = Rotation.from_euler("ZYX", np.stack([yaw, tilt_down, roll], axis=1),
                                       degrees=True).as_matrix()
    R_body_camera = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    poses = np.tile(np.eye(4), (len(t), 1, 1))
    poses[:, :3, :3] = R_world_body @ R_body_camera
    poses[:, :3, 3] = np.stack([x, y, z], axis=1)
    return poses


def robot_trajectories(config: SyntheticConfig) -> list[np.ndarray]:
    """Ground-truth T_world_camera (frames_per_robot, 4, 4) of every robot."""
    if not 1 <= config.n_robots <= _MAX_ROBOTS_IN_ZONE:
        raise ValueError(f"n_robots must be 1..{_MAX_ROBOTS_IN_ZONE}, got {config.n_robots}")
    t = np.arange(config.frames_per_robot) / config.fps
    return [_robot_pose(t, r, config.n_robots, tuple(config.room_size_m))
            for r in range(config.n_robots)]
