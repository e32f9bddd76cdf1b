"""The whole system on recorded data: track every robot, build its dense map, merge the
maps with FS-HICP, write the run folder (trajectories, maps, global map, summary.json).

In this version all robots run in one process, one after the other; the robot/cloud split
is the pipeline's ``split(k)`` (see pipeline/split.py).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.config import Config, config_to_dict
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.evaluation.ate import absolute_trajectory_error
from fleetslam.io.ply import write_ply
from fleetslam.io.trajectory import write_tum_trajectory
from fleetslam.mapping.dense_map import build_dense_map, voxel_downsample
from fleetslam.pipeline.split import TrackingPipeline
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.progress import Progress
from fleetslam.registration.fshicp import chain_transforms, register_chain
from fleetslam.registration.metrics import transform_error
from fleetslam.report import format_table
from fleetslam.registration.initial_guess import perturbed_guess
from fleetslam.transforms import invert, transform_points

SUMMARY_VERSION = 1


@dataclass
class RobotRun:
    """One robot's tracking result, in its own map frame (its first camera pose)."""

    name: str
    source: str
    sequence: RgbdSequence
    timestamps: np.ndarray
    poses: np.ndarray  # N x 4 x 4 T_map_camera
    tracked: np.ndarray  # N bool
    keyframe_indices: list[int]
    keyframe_poses: np.ndarray
    stage_ms: dict[str, float]
    lost_frames: int
    loss_events: int
    repeated_frames: int
    resets: int
    wall_s: float
    ate: dict[str, float] | None = None
    # The poses as tracking reported them frame by frame (``poses`` follow every later
    # correction of their reference keyframes).
    online_poses: np.ndarray | None = None
    loop_closing: dict[str, Any] | None = None
    map_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    map_colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))


def track_robot(name: str, source: str, sequence: RgbdSequence, config: Config,
                show_progress: bool = True) -> RobotRun:
    pipeline = TrackingPipeline(config, sequence.camera)
    progress = Progress(f"robot {name} tracking", len(sequence), enabled=show_progress)
    poses, tracked, refs, T_refs = [], [], [], []
    session = pipeline.session.cloud
    start = time.perf_counter()
    for i, frame in enumerate(sequence):
        out = pipeline.track(CapturedFrame(frame.index, frame.timestamp, frame.rgb, frame.depth_m))
        poses.append(out.T_world_camera)
        tracked.append(out.tracked)
        refs.append(out.reference_keyframe)
        T_refs.append(out.T_reference_camera)
        progress.update(i + 1, f"kf {len(session.map.keyframes)} "
                               f"loops {len(session.loops.edges)}")
    wall = time.perf_counter() - start
    kfs = session.map.keyframes
    run = RobotRun(
        name, source, sequence, sequence.timestamps.copy(),
        session.final_poses(refs, T_refs, poses),
        np.array(tracked),
        [kf.frame_index for kf in kfs], np.array([kf.T_world_camera for kf in kfs]).reshape(-1, 4, 4),
        pipeline.timer.mean_ms(), session.lost_total, session.loss_events,
        session.repeated_frames, session.resets, wall, online_poses=np.array(poses),
        loop_closing=session.loop_summary())
    if sequence.has_ground_truth:
        ate = absolute_trajectory_error(run.poses, sequence.gt_poses)
        run.ate = {"rmse_m": ate.rmse_m, "mean_m": ate.mean_m, "median_m": ate.median_m,
                   "max_m": ate.max_m, "n_poses": ate.n_poses, "alignment": "SE(3) Umeyama"}
    return run


def build_robot_map(run: RobotRun, config: Config, show_progress: bool = True) -> None:
    progress = Progress(f"robot {run.name} dense map", len(run.keyframe_indices), "keyframes",
                        enabled=show_progress)

    def keyframes():
        for k, (index, T) in enumerate(zip(run.keyframe_indices, run.keyframe_poses)):
            frame = run.sequence[index]
            progress.update(k + 1)
            yield frame.rgb, frame.depth_m, T

    run.map_points, run.map_colors = build_dense_map(run.sequence.camera, keyframes(), config.map)


@dataclass
class MergeOutcome:
    T_global_map: list[np.ndarray]  # per robot, robot 0 defines the global frame
    pairs: list[dict[str, Any]]
    initial_guess: str


def first_ground_truth_pose(run: RobotRun) -> np.ndarray | None:
    gt = run.sequence.gt_poses
    if gt is None or not np.isfinite(gt[0]).all():
        return None
    return gt[0]


def merge_robot_maps(runs: list[RobotRun], config: Config, show_progress: bool = True
                     ) -> MergeOutcome | None:
    return merge_maps([r.name for r in runs], [r.map_points for r in runs],
                      [first_ground_truth_pose(r) for r in runs], config, show_progress)


def merge_maps(names: list[str], maps: list[np.ndarray], T_world_first: list[np.ndarray | None],
               config: Config, show_progress: bool = True) -> MergeOutcome | None:
    """Register every map into map 0's frame with FS-HICP, chained as the paper does:
    map i onto map i-1 (already in the global frame). Each map frame is its robot's first
    camera pose; the initial guess is the ground truth of those first poses plus a
    perturbation of the configured size (a later version finds it itself). None when a
    robot has no such prior."""
    if any(T is None for T in T_world_first):
        return None
    truth = [invert(T_world_first[0]) @ T for T in T_world_first]  # T_map0_mapi
    rng = np.random.default_rng(config.merge.seed)
    # Truth of T_{i-1}_i (map i into map i-1), the pair FS-HICP registers.
    truths = [invert(truth[i - 1]) @ truth[i] for i in range(1, len(maps))]
    guesses = [perturbed_guess(T_true, points, rng, config.merge.perturb_rotation_deg,
                               config.merge.perturb_translation_m)
               for T_true, points in zip(truths, maps[1:])]
    progress = Progress("merge (FS-HICP)", len(maps) - 1, "pairs", enabled=show_progress)
    results = register_chain(maps, guesses, config.fshicp)
    progress.update(len(maps) - 1)
    T_global = chain_transforms([r.T_target_source for r in results])
    pairs = []
    for i, (result, T_guess, T_true) in enumerate(zip(results, guesses, truths), start=1):
        err = transform_error(result.T_target_source, T_true)
        err_guess = transform_error(T_guess, T_true)
        global_err = transform_error(T_global[i], truth[i])
        pairs.append({
            "source": names[i], "target": names[i - 1],
            "initial_rotation_error_deg": err_guess.rotation_deg,
            "initial_translation_error_m": err_guess.translation_m,
            "rotation_error_deg": err.rotation_deg, "translation_error_m": err.translation_m,
            "paper_error_eq6": err.eq6,
            "global_rotation_error_deg": global_err.rotation_deg,
            "global_translation_error_m": global_err.translation_m,
            "initial_fitness_m2": result.initial_fitness, "final_fitness_m2": result.final_fitness,
            "rmse_m": result.rmse, "seconds": result.seconds,
            "coarse_steps": result.coarse_steps, "fine_steps": result.fine_steps,
            "T_target_source": result.T_target_source.tolist(),
        })
    return MergeOutcome(T_global, pairs,
                        f"ground truth perturbed by {config.merge.perturb_rotation_deg:g} deg "
                        f"(about the map centroid) and {config.merge.perturb_translation_m:g} m "
                        f"(seed {config.merge.seed})")


def write_global_map(path: Path, merge: MergeOutcome, maps: list[np.ndarray],
                     colors: list[np.ndarray], config: Config) -> int:
    """All maps in the global frame, voxel filtered again where they overlap, as PLY."""
    clouds = [transform_points(T, p) for T, p in zip(merge.T_global_map, maps)]
    points, merged_colors = voxel_downsample(np.vstack(clouds), np.vstack(colors),
                                             config.map.voxel_m)
    write_ply(path, points, merged_colors)
    return len(points)


def run_fleet(robots: list[tuple[str, str, RgbdSequence]], config: Config, out_dir: Path,
              show_progress: bool = True) -> dict[str, Any]:
    """Track, map and merge; write everything under ``out_dir``; return the summary."""
    start = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=False)
    runs: list[RobotRun] = []
    for name, source, sequence in robots:
        run = track_robot(name, source, sequence, config, show_progress)
        build_robot_map(run, config, show_progress)
        robot_dir = out_dir / name
        write_tum_trajectory(robot_dir / "trajectory.tum", run.timestamps, run.poses,
                             comment=f"fleetslam robot {name} from {source}\n"
                                     "T_map_camera; map frame = first camera pose")
        write_tum_trajectory(robot_dir / "keyframes.tum", run.timestamps[run.keyframe_indices],
                             run.keyframe_poses, comment=f"fleetslam robot {name} keyframes")
        write_ply(robot_dir / "map.ply", run.map_points, run.map_colors)
        runs.append(run)

    merge = merge_robot_maps(runs, config, show_progress) if len(runs) > 1 else None
    if merge is not None:
        write_global_map(out_dir / "global_map.ply", merge, [r.map_points for r in runs],
                         [r.map_colors for r in runs], config)
    summary = make_summary(runs, merge, config, time.perf_counter() - start)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def make_summary(runs: list[RobotRun], merge: MergeOutcome | None, config: Config,
                 wall_s: float) -> dict[str, Any]:
    return {
        "version": SUMMARY_VERSION,
        "wall_time_s": wall_s,
        "robots": [{
            "name": r.name, "source": r.source, "camera": r.sequence.camera_source,
            "frames": len(r.timestamps), "keyframes": len(r.keyframe_indices),
            "lost_frames": r.lost_frames, "loss_events": r.loss_events,
            "repeated_frames": r.repeated_frames, "map_resets": r.resets,
            "ate": r.ate, "tracking_fps": len(r.timestamps) / r.wall_s,
            "stage_ms": r.stage_ms, "map_points": len(r.map_points),
            "loop_closing": r.loop_closing,
            "trajectory": f"{r.name}/trajectory.tum", "map": f"{r.name}/map.ply",
        } for r in runs],
        "merge": None if merge is None else {
            "method": "FS-HICP", "initial_guess": merge.initial_guess, "pairs": merge.pairs,
            "global_map": "global_map.ply",
            "T_global_map": {r.name: T.tolist() for r, T in zip(runs, merge.T_global_map)},
        },
        "merge_skipped_reason": None if merge is not None or len(runs) < 2 else
        "a robot has no ground truth for its first frame, which this version's initial guess needs",
        "config": config_to_dict(config),
    }


def summary_table(summary: dict[str, Any]) -> str:
    rows = []
    for r in summary["robots"]:
        ate = r["ate"]["rmse_m"] * 100 if r["ate"] else None
        loops = r.get("loop_closing") or {}
        rows.append([r["name"], r["frames"], r["keyframes"], r["lost_frames"],
                     loops.get("relocalisations"), loops.get("loops_accepted"), ate,
                     r["tracking_fps"], r["map_points"]])
    text = format_table(["robot", "frames", "keyframes", "lost", "relocalised", "loops",
                         "ATE RMSE cm", "fps", "map points"], rows)
    deployed = [r for r in summary["robots"] if "transport" in r]
    if deployed:
        trows = []
        for r in deployed:
            robot = r.get("robot") or {}
            counts = r["transport"]
            trows.append([
                r["name"], r["offload_at"],
                robot["frame_bytes"] / max(robot["frames"], 1) / 1000 if robot else None,
                robot.get("frames_lost_on_link"),
                sum(v for k, v in counts.items() if k.startswith("rejected")),
                robot.get("keyframe_uploads"), robot.get("upload_retries"),
                r["cloud_ms_mean"], r["latency_ms_median"], robot.get("round_trip_ms_median"),
                robot.get("round_trip_ms_p95")])
        text += "\n\nrobot -> cloud (separate processes over Zenoh)\n" + format_table(
            ["robot", "offload at", "kB/frame", "lost on link", "rejected", "KF uploads",
             "retries", "cloud ms/frame", "cloud latency ms", "round trip ms", "p95"], trows)
    merge = summary.get("merge")
    if merge:
        mrows = [[f"{p['source']} -> {p['target']}", p["initial_rotation_error_deg"],
                  p["initial_translation_error_m"] * 100, p["rotation_error_deg"],
                  p["translation_error_m"] * 100, p["final_fitness_m2"], p["seconds"]]
                 for p in merge["pairs"]]
        text += "\n\nmerge: FS-HICP, initial guess = " + merge["initial_guess"] + "\n"
        text += format_table(["pair", "start rot deg", "start trans cm", "rot err deg",
                              "trans err cm", "fitness m2", "s"], mrows)
    elif summary.get("merge_skipped_reason"):
        text += "\n\nmerge skipped: " + summary["merge_skipped_reason"]
    text += f"\n\nwall time {summary['wall_time_s']:.1f} s"
    return text
