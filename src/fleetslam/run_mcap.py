"""A run's ``run.mcap``: its results as ROS 2 messages, made from the files of its folder
(named by summary.json), so a run (``run``, ``demo``, the cloud's ``merge``) and ``fleetslam
export`` on its folder write the same file.

    topic                 type                            frame        from
    /<robot>/path         nav_msgs/Path                   <robot>/map  <robot>/trajectory.tum
    /<robot>/global_path  nav_msgs/Path                   map          global/<robot>.tum
    /tf                   tf2_msgs/TFMessage, per frame   map (merged) or <robot>/map
                                                          -> <robot>/camera
    /tf_static            tf2_msgs/TFMessage              map -> <robot>/map (merged)
    /<robot>/map          sensor_msgs/PointCloud2         <robot>/map  <robot>/map.ply
    /map/global           sensor_msgs/PointCloud2         map          global_map.ply
    /map/octomap          octomap_msgs/Octomap            map          global_map.bt
    /map/constraints      visualization_msgs/MarkerArray  map          merge.constraints
    /map/grid             nav_msgs/OccupancyGrid          map          global_map.yaml / .pgm

``map`` is the global frame (the first camera of the group's anchor robot); ``<robot>/map``
is a robot's own map frame (its first camera), placed in ``map`` by the merge's
``T_global_map``. A merged robot's camera follows its global trajectory, which the merge's
pose graph bends; an unmerged robot's stays in its own frame. The results known at the end
(paths, maps, OctoMap, constraints, static transforms) are logged at the run's first time,
latched, so a player shows them from the start.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.io.mcap_out import McapOut, RosMessages, seconds_to_ns
from fleetslam.io.ply import read_ply
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.mapping.occupancy_grid import read_nav2_map
from fleetslam.mapping.octomap_export import octomap_binary_data

MCAP_FILE = "run.mcap"
GLOBAL_FRAME = "map"
# Inter-robot constraints as lines: kept (green) and rejected by GNC (red), as in the view.
KEPT_RGBA = (0.1, 0.9, 0.2, 1.0)
REJECTED_RGBA = (0.9, 0.1, 0.1, 1.0)
LINE_WIDTH_M = 0.01


def map_frame(robot: str) -> str:
    return f"{robot}/map"


def camera_frame(robot: str) -> str:
    return f"{robot}/camera"


def read_run_summary(run_dir: Path) -> dict[str, Any]:
    path = Path(run_dir) / "summary.json"
    try:
        return json.loads(path.read_text())
    except OSError:
        raise ValueError(f"{path}: no summary.json: not a finished run folder") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON: {exc}") from None


def _cloud(out: RosMessages, topic: str, frame: str, stamp: int, path: Path) -> None:
    points, colors = read_ply(path)
    if colors is None:
        raise ValueError(f"{path}: the PLY has no red, green, blue: no colours to publish")
    out.cloud(topic, frame, stamp, points, colors)


def _constraint_lines(merge: dict[str, Any]) -> list[tuple[np.ndarray, tuple[float, ...]]]:
    """(segments K x 2 x 3, colour) of the kept and the rejected constraints whose both
    keyframes are in the global map."""
    placed = [c for c in merge.get("constraints", [])
              if c.get("query_position") is not None and c.get("place_position") is not None]
    groups = []
    for kept, rgba in ((True, KEPT_RGBA), (False, REJECTED_RGBA)):
        segments = [[c["query_position"], c["place_position"]] for c in placed
                    if bool(c["kept"]) is kept]
        groups.append((np.array(segments, np.float64).reshape(-1, 2, 3), rgba))
    return groups


def write_run_mcap(run_dir: Path, summary: dict[str, Any] | None = None,
                   path: Path | None = None) -> Path:
    """Write the run's MCAP (``run_dir/run.mcap`` unless ``path``) from its files;
    ``summary``: the run's summary as it is being written (else summary.json is read).
    Returns the file's path; a summary that lacks an entry is a ValueError naming it, and
    no file is written."""
    run_dir = Path(run_dir)
    summary = read_run_summary(run_dir) if summary is None else summary
    path = run_dir / MCAP_FILE if path is None else Path(path)
    try:
        with McapOut(path) as out:
            _add_run(out, run_dir, summary)
    except KeyError as exc:
        raise ValueError(f"{run_dir / 'summary.json'}: not a fleetslam run summary (no "
                         f"{exc} entry)") from None
    return path


def _add_run(out: RosMessages, run_dir: Path, summary: dict[str, Any]) -> None:
    merge = summary.get("merge") or {}
    # The robots in the global frame (a run of robots that never joined still has one: the
    # largest group, a single robot).
    merged = merge.get("members") or []
    trajectories = {r["name"]: read_tum_trajectory(run_dir / r["trajectory"])
                    for r in summary["robots"]}
    if not trajectories:
        raise ValueError(f"{run_dir / 'summary.json'}: no robots in the run")
    start = int(min(seconds_to_ns(times[:1])[0] for times, _ in trajectories.values()))
    for robot in summary["robots"]:
        name = robot["name"]
        times, poses = trajectories[name]
        out.path(f"/{name}/path", map_frame(name), start, seconds_to_ns(times), poses)
        _cloud(out, f"/{name}/map", map_frame(name), start, run_dir / robot["map"])
        parent = map_frame(name)
        if name in merged:  # its camera as the global trajectory has it
            parent = GLOBAL_FRAME
            times, poses = read_tum_trajectory(run_dir / merge["global_trajectories"][name])
        out.transforms("/tf", parent, camera_frame(name), seconds_to_ns(times), poses)
    if merged:
        out.static_transforms("/tf_static", start, [
            (GLOBAL_FRAME, map_frame(name), np.array(merge["T_global_map"][name]))
            for name in merged])
        add_fleet_map(out, run_dir, summary, start)


def add_fleet_map(out: RosMessages, run_dir: Path, summary: dict[str, Any],
                  stamp_ns: int) -> None:
    """The merge's results in the global frame, each one latched message at ``stamp_ns``:
    every member's global path, the global cloud, OctoMap, constraints and grid (what
    the cloud publishes live after a merge, visualisation/topic_view.py)."""
    merge = summary["merge"]
    for name in merge["members"]:
        times, poses = read_tum_trajectory(run_dir / merge["global_trajectories"][name])
        out.path(f"/{name}/global_path", GLOBAL_FRAME, stamp_ns, seconds_to_ns(times), poses)
    _cloud(out, "/map/global", GLOBAL_FRAME, stamp_ns, run_dir / merge["global_map"])
    tree_id, resolution, data = octomap_binary_data(run_dir / merge["octomap"]["file"])
    out.octomap("/map/octomap", GLOBAL_FRAME, stamp_ns, resolution, tree_id, data)
    out.lines("/map/constraints", GLOBAL_FRAME, stamp_ns, "constraints",
              _constraint_lines(merge), LINE_WIDTH_M)
    grid_entry = merge.get("grid")
    if grid_entry is not None:  # runs from before the nav2 map have none
        grid = read_nav2_map((run_dir / grid_entry["image"]).with_suffix(".yaml"),
                             np.array(grid_entry["T_map_grid"]))
        out.grid("/map/grid", GLOBAL_FRAME, stamp_ns, grid.ros_cells(), grid.resolution,
                 grid.T_map_origin)
