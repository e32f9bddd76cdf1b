"""A finished run in rerun (``fleetslam view RUN_DIR``): each robot's trajectory, keyframes
and dense map, the merged robots' global trajectories and the global map.

Entities: ``world/<r>`` (the robot's map frame, placed in the global frame by its first
frame's global pose when the run merged it, else where it is), ``world/<r>/trajectory``,
``world/<r>/camera`` (its pose on the ``frame_<r>`` timeline), ``world/<r>/keyframe_centres``,
``world/<r>/map``; ``world/global/<r>`` (global/<r>.tum) and ``world/global/map``
(global_map.ply).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.config import Config
from fleetslam.io.ply import read_ply
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.transforms import invert
from fleetslam.visualisation.live_view import frame_timeline, robot_colour
from fleetslam.visualisation.recording import (
    ViewUnavailable,
    can_spawn_viewer,
    close_recording,
    import_rerun,
    open_recording,
)


def run_robots(run_dir: Path) -> list[str]:
    """The robots of a run folder (each has <robot>/trajectory.tum); a clear error naming
    the folder when it is not a run."""
    if not run_dir.is_dir():
        raise ValueError(f"{run_dir}: no such folder")
    robots = sorted(p.name for p in run_dir.iterdir()
                    if p.is_dir() and (p / "trajectory.tum").is_file())
    if not robots:
        raise ValueError(f"{run_dir}: not a fleetslam run folder (no <robot>/trajectory.tum "
                         f"in it)")
    return robots


def _points(path: Path, cap: int) -> tuple[np.ndarray, np.ndarray | None] | None:
    if not path.is_file():
        return None
    points, colours = read_ply(path)
    if len(points) > cap:  # every n-th point, so the whole map stays in view
        keep = np.linspace(0, len(points) - 1, cap).astype(np.int64)
        points, colours = points[keep], None if colours is None else colours[keep]
    return points.astype(np.float32), colours


def _T(rr: Any, T: np.ndarray) -> Any:
    return rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3])


def log_run(recording: Any, run_dir: Path, config: Config) -> dict[str, int]:
    """Log a run folder's outputs; returns how many points and poses were logged."""
    rr = import_rerun()
    robots = run_robots(run_dir)
    cap = config.view.max_map_points
    counts = {"robots": len(robots), "poses": 0, "map_points": 0}
    recording.log("world", rr.ViewCoordinates.RDF, static=True)
    for i, name in enumerate(robots):
        colour = robot_colour(i)
        times, poses = read_tum_trajectory(run_dir / name / "trajectory.tum")
        global_file = run_dir / "global" / f"{name}.tum"
        T_global_map = np.eye(4)
        if global_file.is_file():
            g_times, g_poses = read_tum_trajectory(global_file)
            first = int(np.argmin(np.abs(times - g_times[0])))
            T_global_map = g_poses[0] @ invert(poses[first])
            recording.log(f"world/global/{name}", rr.LineStrips3D(
                [g_poses[:, :3, 3]], colors=[colour], radii=[0.004]), static=True)
        recording.log(f"world/{name}", _T(rr, T_global_map), static=True)
        recording.log(f"world/{name}/trajectory", rr.LineStrips3D(
            [poses[:, :3, 3]], colors=[colour], radii=[0.004]), static=True)
        recording.log(f"world/{name}/camera", rr.TransformAxes3D(0.1), static=True)
        recording.send_columns(
            f"world/{name}/camera",
            indexes=[rr.TimeColumn(frame_timeline(name), sequence=np.arange(len(poses)))],
            columns=rr.Transform3D.columns(translation=poses[:, :3, 3],
                                           mat3x3=poses[:, :3, :3]))
        counts["poses"] += len(poses)
        keyframes = run_dir / name / "keyframes.tum"
        if keyframes.is_file():
            _, kf_poses = read_tum_trajectory(keyframes)
            recording.log(f"world/{name}/keyframe_centres", rr.Points3D(
                kf_poses[:, :3, 3], colors=[colour], radii=[0.015]), static=True)
        cloud = _points(run_dir / name / "map.ply", cap)
        if cloud is not None:
            recording.log(f"world/{name}/map", rr.Points3D(cloud[0], colors=cloud[1]),
                          static=True)
            counts["map_points"] += len(cloud[0])
    cloud = _points(run_dir / "global_map.ply", cap)
    if cloud is not None:
        recording.log("world/global/map", rr.Points3D(cloud[0], colors=cloud[1]), static=True)
        counts["map_points"] += len(cloud[0])
    return counts


def view_run(run_dir: Path, config: Config, save: Path | None) -> str:
    """Write the run to ``save`` (an .rrd), or show it in a spawned viewer; what was done."""
    run_robots(run_dir)  # a folder that is not a run: say so before anything else
    if save is None and not can_spawn_viewer():
        raise ViewUnavailable("no display to open a rerun viewer on here: write a recording "
                              "with --save FILE.rrd and open it with `rerun FILE.rrd` where "
                              "there is one")
    recording = open_recording(config.view, save, live=save is None)
    try:
        counts = log_run(recording, run_dir, config)
    finally:
        close_recording(recording)
    where = f"wrote {save}" if save is not None else "sent to the rerun viewer"
    return (f"{run_dir}: {counts['robots']} robots, {counts['poses']} poses, "
            f"{counts['map_points']} map points; {where}")
