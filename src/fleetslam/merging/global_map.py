"""The global map: every merged robot's keyframes in one frame, refined by FS-HICP, and the
outputs other tools open (TUM trajectories, a voxel-fused PLY cloud, an OctoMap .bt).

The merger's pose graph places keyframes; the dense maps are rebuilt from those global
keyframe poses (so the cloud follows every correction), then FS-HICP (the paper's
registration) aligns each robot's dense map to the rest of its group, and the alignment is
kept only if it lowers the fitness score. Robots outside the largest group stay in their own
frame and are reported as not merged, with the reason.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.io.ply import write_ply
from fleetslam.io.trajectory import write_tum_trajectory
from fleetslam.mapping.dense_map import keyframe_local_cloud, voxel_downsample
from fleetslam.mapping.map_frame import base_link_frame, mounting_up
from fleetslam.mapping.occupancy_grid import OccupancyGrid, occupancy_grid, write_nav2_map
from fleetslam.mapping.octomap_export import write_octomap
from fleetslam.merging.merger import MapMerger
from fleetslam.transforms import invert, poses_from_references, transform_points
from fleetslam.registration.fshicp import fshicp
from fleetslam.registration.metrics import transform_error

log = logging.getLogger("fleetslam.merge")

# (rgb, depth_m, decimated_by) of the keyframe at a frame index; None for a keyframe whose
# images the robot could not upload (a live camera's, gone from its buffer).
KeyframeImage = Callable[[int], tuple[np.ndarray, np.ndarray, int] | None]


@dataclass
class RobotTrack:
    """One robot's result as the global map needs it (its own map frame)."""

    name: str
    camera: Camera
    timestamps: np.ndarray
    poses: np.ndarray  # N x 4 x 4 T_map_camera (final)
    references: np.ndarray  # N int: reference keyframe of each frame, -1 none
    T_reference_camera: list[np.ndarray | None]
    keyframe_image: KeyframeImage
    # A loaded map's robot: each keyframe's dense cloud as saved, by frame index (it has no
    # images).
    keyframe_clouds: dict[int, tuple[np.ndarray, np.ndarray]] | None = None


@dataclass
class GlobalMap:
    members: list[str]  # robots in the global frame (the largest joined group)
    anchor: str  # whose map frame is the global frame
    T_global_map: dict[str, np.ndarray]  # members only: the graph's, after FS-HICP
    T_global_map_graph: dict[str, np.ndarray]  # before FS-HICP
    trajectories: dict[str, np.ndarray]  # members: N x 4 x 4 T_global_camera
    keyframe_poses: dict[str, np.ndarray]  # members: K x 4 x 4
    fshicp: list[dict[str, Any]] = field(default_factory=list)
    not_merged: dict[str, str] = field(default_factory=dict)
    points: int = 0
    octomap: dict[str, Any] | None = None
    grid: dict[str, Any] | None = None  # the nav2 map (global_map.pgm / .yaml)
    # How the level map frame was found, and where it lies in the anchor's own map.
    map_frame: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0  # building it: dense refinement, graph, FS-HICP, outputs
    # Members: each keyframe's dense cloud in its camera frame (points, colours), for the
    # saved map (saved_map.py).
    keyframe_clouds: dict[str, list[tuple[np.ndarray, np.ndarray]]] = \
        field(default_factory=dict)


def largest_component(components: dict[str, list[str]]) -> str:
    """The anchor of the group with the most members; on a tie, the one whose anchor's id
    sorts first (the group a merge writes, and the live ``map`` frame follows)."""
    return min(components, key=lambda a: (-len(components[a]), a))


def largest_group(merger: MapMerger, among: Iterable[str]) -> tuple[str, list[str]]:
    """(anchor, members among ``among``) of the biggest component (largest_component), or
    a loaded map's group, whatever its size: the fleet's map is the loaded one. The group's
    frame is its anchor's, even if the anchor is not among them."""
    among = set(among)
    components = {a: [m for m in ms if m in among] for a, ms in merger.components().items()}
    components = {a: ms for a, ms in components.items() if ms}
    if not components:
        raise ValueError("no robot to merge")
    anchor = merger.fixed_anchor if merger.fixed_anchor in components \
        else largest_component(components)
    return anchor, components[anchor]


def global_trajectory(track: RobotTrack, keyframe_poses: np.ndarray,
                      T_global_map: np.ndarray) -> np.ndarray:
    """Every frame in the global frame: from its reference keyframe's global pose, so the
    graph's bending reaches it; frames without one are moved rigidly."""
    return poses_from_references(keyframe_poses, track.references, track.T_reference_camera,
                                 T_global_map @ track.poses)


def _local_clouds(track: RobotTrack, frame_indices: Iterable[int], config: Config
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    clouds = []
    for i in frame_indices:
        if track.keyframe_clouds is not None:
            clouds.append(track.keyframe_clouds[i])
            continue
        image = track.keyframe_image(i)
        if image is None:  # no images: an empty cloud keeps the list aligned with the poses
            clouds.append((np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)))
            continue
        rgb, depth_m, decimated_by = image
        clouds.append(keyframe_local_cloud(track.camera, rgb, depth_m, config.map, decimated_by))
    return clouds


def _place(clouds: Sequence[tuple[np.ndarray, np.ndarray]], poses: np.ndarray
           ) -> list[np.ndarray]:
    """Each keyframe's points in the frame its pose maps them to."""
    return [transform_points(T, p) for (p, _), T in zip(clouds, poses)]


def build_global_map(merger: MapMerger, tracks: list[RobotTrack], config: Config,
                     out_dir: Path) -> GlobalMap:
    """Write ``global/<robot>.tum``, ``global_map.ply`` and ``global_map.bt`` under
    ``out_dir`` for the largest joined group; returns what was built."""
    started = time.perf_counter()
    by_name = {t.name: t for t in tracks}
    anchor, members = largest_group(merger, by_name)
    clouds = {m: _local_clouds(by_name[m], [k.frame_index for k in merger.robots[m].keyframes],
                               config) for m in members}

    def cloud_of(robot: str, keyframe: int) -> np.ndarray | None:
        found = clouds.get(robot)
        return None if found is None or not len(found[keyframe][0]) else found[keyframe][0]

    # Every constraint of the group on the keyframes' depth, before the graph places them.
    merger.refine_constraints(cloud_of)
    graph_poses = merger.solve_keyframe_poses()
    result = GlobalMap(members, anchor, {}, {}, {}, {},
                       not_merged=_not_merged(merger, list(by_name), members),
                       keyframe_clouds={m: clouds[m] for m in members})
    kf_poses = {m: graph_poses[m].copy() for m in members}
    # Made level below.
    result.T_global_map_graph = {m: merger.solve_T_global_map(m) for m in members}
    correction = {m: np.eye(4) for m in members}
    if config.merge.fshicp_refine and len(members) > 1:
        result.fshicp = _refine_by_fshicp(members, clouds, kf_poses, correction, config,
                                          merger.saved)
    # Every keyframe placed once, for the point cloud, the grid and the octree's scans.
    placed_points = [p for m in members for p in _place(clouds[m], kf_poses[m])]
    origins = [T[:3, 3] for m in members for T in kf_poses[m]]
    colors_in = [c for m in members for _, c in clouds[m]]
    if not placed_points:  # a lone robot whose keyframes never reached the merger
        placed_points, colors_in = [np.zeros((0, 3))], [np.zeros((0, 3), np.uint8)]
    # The anchor's first keyframe first: the grid is level under it, facing its view.
    poses = np.vstack([kf_poses[m] for m in sorted(members, key=lambda m: m != anchor)])
    graph = dict(result.T_global_map_graph)
    T_graph_anchor = correction.get(anchor, np.eye(4)) @ (
        graph[anchor] if anchor in graph else merger.solve_T_global_map(anchor))
    grid, T_map_graph, result.map_frame = _fleet_frame(
        list(zip(placed_points, origins)), poses.reshape(-1, 4, 4),
        merger.robots[anchor].camera, T_graph_anchor, config,
        loaded=anchor == merger.fixed_anchor)
    # Everything from here on in the level map frame (map_frame.py).
    placed_points = [transform_points(T_map_graph, p) for p in placed_points]
    origins = [transform_points(T_map_graph, o[None])[0] for o in origins]
    for m in members:
        result.T_global_map_graph[m] = T_map_graph @ graph[m]
        result.T_global_map[m] = T_map_graph @ correction[m] @ graph[m]
        result.keyframe_poses[m] = T_map_graph @ kf_poses[m]
        _write_global_trajectory(out_dir, by_name[m], result)
    _write_maps(out_dir, placed_points, origins, colors_in, grid, config, result)
    result.seconds = time.perf_counter() - started
    log.info("global map: %s in the map frame (%s's, up from the %s), %d points, octomap "
             "%d occupied / %d free leaves", ", ".join(members), anchor,
             result.map_frame["source"], result.points, result.octomap["occupied"],
             result.octomap["free"])
    return result


def _write_global_trajectory(out_dir: Path, track: RobotTrack, result: GlobalMap) -> None:
    """A member's every frame in the global frame, from its keyframes' global poses."""
    m = track.name
    result.trajectories[m] = global_trajectory(track, result.keyframe_poses[m],
                                               result.T_global_map[m])
    write_tum_trajectory(out_dir / "global" / f"{m}.tum", track.timestamps,
                         result.trajectories[m],
                         comment=f"fleetslam robot {m} in the fleet's map frame (level, z up: "
                                 f"{result.map_frame['source']}; robot {result.anchor}'s)")


def _write_maps(out_dir: Path, placed_points: list[np.ndarray], origins: list[np.ndarray],
                colors: list[np.ndarray], grid: OccupancyGrid, config: Config,
                result: GlobalMap) -> None:
    """global_map.ply (voxel-fused), .bt (each keyframe a scan from its camera) and the
    nav2 grid, all in the map frame; their counts into ``result``."""
    points, fused_colors = voxel_downsample(np.vstack(placed_points), np.vstack(colors),
                                            config.map.voxel_m)
    assert fused_colors is not None
    write_ply(out_dir / "global_map.ply", points, fused_colors)
    result.points = len(points)
    start = time.perf_counter()
    stats = write_octomap(out_dir / "global_map.bt", zip(placed_points, origins),
                          config.merge.octomap_resolution_m, config.merge.octomap_max_range_m)
    stats["seconds"] = time.perf_counter() - start
    stats["scans"] = len(origins)
    result.octomap = stats
    write_nav2_map(out_dir / "global_map", grid, "the fleet's map frame")
    result.grid = grid.summary("global_map.pgm")


def _not_merged(merger: MapMerger, robots: list[str], members: list[str]) -> dict[str, str]:
    """Why each robot outside the global map is (a lone robot's run: none)."""
    out = {}
    loaded = [m for m in members if m in merger.saved]
    for name in robots:
        if name in members and (len(members) > 1 or len(robots) == 1 or name in loaded):
            continue
        if name not in merger.robots or not merger.robots[name].keyframes:
            out[name] = "no keyframe features reached the merger (it made no keyframe, or " \
                        "none of its keyframe messages arrived)"
        elif loaded:
            out[name] = "never found the loaded map (no verified place shared with " \
                        + ", ".join(members) + "): it stays in its own frame"
        elif len(members) > 1:
            out[name] = "shares no verified place with " + ", ".join(members)
        else:
            out[name] = "no robot shares a verified place with another"
    return out


def _refine_by_fshicp(members: list[str], clouds: dict[str, list[tuple[np.ndarray, np.ndarray]]],
                      kf_poses: dict[str, np.ndarray], correction: dict[str, np.ndarray],
                      config: Config, fixed: set[str]) -> list[dict[str, Any]]:
    """FS-HICP of each member's dense map to the rest of the group's, kept where it lowers
    the fitness: ``kf_poses`` and ``correction`` updated in place; one record per robot.
    The first member, and a loaded map's robots (``fixed``), stay."""
    records = []
    placed = {m: voxel_downsample(np.vstack(_place(clouds[m], kf_poses[m])), None,
                                  config.map.voxel_m)[0] for m in members}
    for m in [m for m in members[1:] if m not in fixed]:
        target = np.vstack([placed[o] for o in members if o != m])
        fit = fshicp(placed[m], target, np.eye(4), config.fshicp)
        improved = fit.final_fitness < fit.initial_fitness
        moved = transform_error(fit.T_target_source, np.eye(4))
        records.append({
            "robot": m, "initial_fitness_m2": fit.initial_fitness,
            "final_fitness_m2": fit.final_fitness, "kept": bool(improved),
            "rotation_deg": moved.rotation_deg, "translation_m": moved.translation_m,
            "seconds": fit.seconds, "coarse_steps": fit.coarse_steps,
            "fine_steps": fit.fine_steps})
        if improved:
            correction[m] = fit.T_target_source
            kf_poses[m] = fit.T_target_source @ kf_poses[m]
            placed[m] = transform_points(fit.T_target_source, placed[m])
    return records


def _fleet_frame(scans: list[tuple[np.ndarray, np.ndarray]], poses: np.ndarray,
                 anchor_camera: Camera, T_graph_anchor: np.ndarray, config: Config,
                 loaded: bool = False) -> tuple[OccupancyGrid, np.ndarray, dict[str, Any]]:
    """(the grid, in the map frame; T_map_graph; how the map frame was found): the anchor's
    base_link at its first frame with a mounting, else the grid's level frame (map_frame.py);
    a loaded map's group keeps the map's frame (the graph's is it)."""
    grid = occupancy_grid(scans, poses, config.grid, mounting_up(T_graph_anchor, anchor_camera))
    mounted = base_link_frame(T_graph_anchor, anchor_camera)
    if loaded:
        T_graph_map, source = np.eye(4), "the loaded map's frame"
    elif mounted is None:
        T_graph_map, source = grid.T_map_grid, grid.up_source
        grid.T_map_grid = np.eye(4)
    else:
        T_graph_map, source = mounted, "camera mounting"
        grid.T_map_grid = invert(mounted) @ grid.T_map_grid
    return grid, invert(T_graph_map), {"source": source,
                                       "T_anchor_map": (invert(T_graph_anchor)
                                                        @ T_graph_map).tolist()}


def _constraint_entries(merger: MapMerger, placed: dict[str, np.ndarray]
                        ) -> list[dict[str, Any]]:
    """Each inter-robot constraint as summary.json has it; its keyframes' camera centres in
    the global frame where they are members of the global map (``placed``)."""

    def position(robot: str, keyframe: int) -> list[float] | None:
        poses = placed.get(robot)
        return poses[keyframe][:3, 3].tolist() if poses is not None and \
            keyframe < len(poses) else None

    return [{
        "query_robot": c.match.query.robot, "query_frame": c.match.query.frame_index,
        "place_robot": c.match.place.robot, "place_frame": c.match.place.frame_index,
        "inliers": c.match.inliers, "ransac_inliers": c.match.ransac_inliers,
        "score": c.match.score, "trusted": c.trusted, "kept": c.kept,
        # The edge's measurement (dense where accepted) and the feature estimate it began as.
        "used": "dense" if c.dense is not None and c.dense.accepted else "features",
        # How the pair was found: features matched, or the graph put the two near each other
        # (merge.proximity_constraints; no feature estimate then).
        "found": "proximity" if c.proximity else "features",
        "T_place_query": c.T_place_query.tolist(),
        **({} if c.proximity else {"T_place_query_features": c.match.T_place_query.tolist()}),
        "dense": None if c.dense is None else c.dense.to_json(),
        "query_position": position(c.match.query.robot, c.match.query.keyframe),
        "place_position": position(c.match.place.robot, c.match.place.keyframe),
    } for c in merger.constraints]


def merge_summary(merger: MapMerger, global_map: GlobalMap | None) -> dict[str, Any]:
    """The merge as summary.json records it (the same schema in and out of the cloud)."""
    status = merger.status()
    placed = global_map.keyframe_poses if global_map is not None else {}
    constraints = _constraint_entries(merger, placed)

    def ms(values: list[float], q: float = 50.0) -> float | None:
        return 1000.0 * float(np.percentile(values, q)) if values else None

    out: dict[str, Any] = {
        "method": "inter-robot place recognition, dense (depth GICP) refinement of each "
                  "constraint, depth registration of joined robots' keyframes the graph puts "
                  "near each other, global pose graph (GNC), FS-HICP refinement",
        "components": status["components"], "joins": status["events"],
        "robots": status["robots"], "constraints": constraints,
        # A loaded map: its robots (no source in this run), and each robot's way from its
        # first frame to its first pose in the map's frame.
        **({"loaded_map": sorted(merger.saved), "entered_map": merger.entered_map}
           if merger.fixed_anchor is not None else {}),
        "keyframes_not_searched": status["keyframes_not_searched"],
        "keyframes_searched_late": status["keyframes_searched_late"],
        "query_ms_median": ms(merger.query_seconds),
        "query_ms_p95": ms(merger.query_seconds, 95),
        "graph_ms_median": ms(merger.graph_seconds),
        "dense_ms_median": ms(merger.dense_seconds),
        "dense_ms_p95": ms(merger.dense_seconds, 95),
    }
    if global_map is not None:
        out.update({
            "members": global_map.members, "anchor": global_map.anchor,
            "not_merged": global_map.not_merged,
            "T_global_map": {m: T.tolist() for m, T in global_map.T_global_map.items()},
            "T_global_map_graph": {m: T.tolist()
                                   for m, T in global_map.T_global_map_graph.items()},
            "fshicp": global_map.fshicp,
            "global_trajectories": {m: f"global/{m}.tum" for m in global_map.members},
            "global_map": "global_map.ply", "global_map_points": global_map.points,
            "octomap": global_map.octomap, "global_map_seconds": global_map.seconds,
            "grid": global_map.grid, "map_frame": global_map.map_frame,
        })
    return out
