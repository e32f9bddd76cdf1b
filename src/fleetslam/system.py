"""The whole system on recorded data in one process: track every robot (taking turns frame
by frame, each new keyframe handed to the map merger at once), build each dense map, write
the global outputs, then score against ground truth where a sequence has it.

The robot/cloud split is the pipeline's ``split(k)`` (see pipeline/split.py); the same work
as separate processes is cloud/ and edge/.
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
from fleetslam.evaluation.fleet import score_fleet
from fleetslam.io.ply import write_ply
from fleetslam.io.trajectory import write_tum_trajectory
from fleetslam.mapping.dense_map import build_dense_map
from fleetslam.merging.global_map import (
    GlobalMap,
    RobotTrack,
    build_global_map,
    merge_summary,
)
from fleetslam.merging.inter_robot import KeyframeSummary, keyframe_summary
from fleetslam.merging.merger import MapMerger
from fleetslam.pipeline.session import CloudSession
from fleetslam.pipeline.split import TrackingPipeline
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.progress import Progress
from fleetslam.report import format_table

SUMMARY_VERSION = 3


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
    # Each frame's reference keyframe (-1: none) and its pose relative to it.
    references: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    T_reference_camera: list[np.ndarray | None] = field(default_factory=list)
    # The poses as tracking reported them frame by frame (``poses`` follow every later
    # correction of their reference keyframes).
    online_poses: np.ndarray | None = None
    loop_closing: dict[str, Any] | None = None
    map_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    map_colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.uint8))

    def track(self) -> RobotTrack:
        """What the global map needs of this robot."""
        sequence = self.sequence

        def keyframe_image(index: int) -> tuple[np.ndarray, np.ndarray, int]:
            frame = sequence[index]
            return frame.rgb, frame.depth_m, 1

        return RobotTrack(self.name, sequence.camera, self.timestamps, self.poses,
                          self.references, self.T_reference_camera, keyframe_image)


class RobotTracker:
    """One robot's tracking frame by frame (robots of a fleet take turns, so the merger
    sees their keyframes in the order they would arrive)."""

    def __init__(self, name: str, source: str, sequence: RgbdSequence, config: Config) -> None:
        self.name, self.source, self.sequence = name, source, sequence
        self.pipeline = TrackingPipeline(config, sequence.camera)
        self.poses: list[np.ndarray] = []
        self.tracked: list[bool] = []
        self.refs: list[int] = []
        self.T_refs: list[np.ndarray | None] = []
        self.seconds = 0.0

    @property
    def session(self) -> CloudSession:
        return self.pipeline.session.cloud

    def step(self, i: int) -> KeyframeSummary | None:
        """Track frame ``i``; the new keyframe's summary if it became one."""
        frame = self.sequence[i]
        start = time.perf_counter()
        out = self.pipeline.track(CapturedFrame(frame.index, frame.timestamp, frame.rgb,
                                                frame.depth_m))
        self.seconds += time.perf_counter() - start
        self.poses.append(out.T_world_camera)
        self.tracked.append(out.tracked)
        self.refs.append(out.reference_keyframe)
        self.T_refs.append(out.T_reference_camera)
        if not out.is_keyframe:
            return None
        return keyframe_summary(self.name, self.session.map.keyframes[-1])

    def finish(self) -> RobotRun:
        session, sequence = self.session, self.sequence
        kfs = session.map.keyframes
        return RobotRun(
            self.name, self.source, sequence, sequence.timestamps.copy(),
            session.final_poses(self.refs, self.T_refs, self.poses), np.array(self.tracked),
            [kf.frame_index for kf in kfs], session.map.keyframe_poses(),
            self.pipeline.timer.mean_ms(), session.lost_total, session.loss_events,
            session.repeated_frames, session.resets, self.seconds,
            references=np.array(self.refs, np.int64), T_reference_camera=list(self.T_refs),
            online_poses=np.array(self.poses), loop_closing=session.loop_summary())


def track_robot(name: str, source: str, sequence: RgbdSequence, config: Config,
                show_progress: bool = True) -> RobotRun:
    """One robot alone, start to end."""
    tracker = RobotTracker(name, source, sequence, config)
    progress = Progress(f"robot {name} tracking", len(sequence), enabled=show_progress)
    for i in range(len(sequence)):
        tracker.step(i)
        progress.update(i + 1, f"kf {len(tracker.session.map.keyframes)} "
                               f"loops {len(tracker.session.loops.edges)}")
    return tracker.finish()


def track_fleet(robots: list[tuple[str, str, RgbdSequence]], config: Config,
                show_progress: bool = True) -> tuple[list[RobotRun], MapMerger]:
    """Every robot tracked, taking turns frame by frame; each new keyframe goes to the
    merger at once, so robots join as soon as they share a place (as in the cloud)."""
    trackers = [RobotTracker(name, source, seq, config) for name, source, seq in robots]
    merger = MapMerger(config)
    for t in trackers:
        merger.add_robot(t.name, t.sequence.camera)
    total = sum(len(t.sequence) for t in trackers)
    progress = Progress("tracking", total, enabled=show_progress)
    done = 0
    for i in range(max(len(t.sequence) for t in trackers)):
        for t in trackers:
            if i >= len(t.sequence):
                continue
            summary = t.step(i)
            if summary is not None:
                merger.add_keyframe(summary, t.session.map.keyframe_poses())
            done += 1
        progress.update(done, f"groups {len(merger.components())}")
    return [t.finish() for t in trackers], merger


def build_robot_map(run: RobotRun, config: Config, show_progress: bool = True) -> None:
    progress = Progress(f"robot {run.name} dense map", len(run.keyframe_indices), "keyframes",
                        enabled=show_progress)

    def keyframes():
        for k, (index, T) in enumerate(zip(run.keyframe_indices, run.keyframe_poses)):
            frame = run.sequence[index]
            progress.update(k + 1)
            yield frame.rgb, frame.depth_m, T

    run.map_points, run.map_colors = build_dense_map(run.sequence.camera, keyframes(), config.map)


def run_fleet(robots: list[tuple[str, str, RgbdSequence]], config: Config, out_dir: Path,
              show_progress: bool = True) -> dict[str, Any]:
    """Track, map and merge; write everything under ``out_dir``; score against ground truth
    where a sequence has it (after the run); return the summary."""
    start = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=False)
    runs, merger = track_fleet(robots, config, show_progress)
    for run in runs:
        build_robot_map(run, config, show_progress)
        robot_dir = out_dir / run.name
        write_tum_trajectory(robot_dir / "trajectory.tum", run.timestamps, run.poses,
                             comment=f"fleetslam robot {run.name} from {run.source}\n"
                                     "T_map_camera; map frame = first camera pose")
        write_tum_trajectory(robot_dir / "keyframes.tum", run.timestamps[run.keyframe_indices],
                             run.keyframe_poses, comment=f"fleetslam robot {run.name} keyframes")
        write_ply(robot_dir / "map.ply", run.map_points, run.map_colors)
    global_map = build_global_map(merger, [r.track() for r in runs], config, out_dir) \
        if len(runs) > 1 else None
    summary = make_summary(runs, merger, global_map, config, time.perf_counter() - start)
    # Evaluation: ground truth is read only now, after every output is written.
    score_fleet(summary, out_dir, {r.name: r.sequence for r in runs})
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def make_summary(runs: list[RobotRun], merger: MapMerger, global_map: GlobalMap | None,
                 config: Config, wall_s: float) -> dict[str, Any]:
    return {
        "version": SUMMARY_VERSION,
        "wall_time_s": wall_s,
        "robots": [{
            "name": r.name, "source": r.source, "camera": r.sequence.camera_source,
            "frames": len(r.timestamps), "keyframes": len(r.keyframe_indices),
            "lost_frames": r.lost_frames, "loss_events": r.loss_events,
            "repeated_frames": r.repeated_frames, "map_resets": r.resets,
            "ate": None, "tracking_fps": len(r.timestamps) / r.wall_s,
            "stage_ms": r.stage_ms, "map_points": len(r.map_points),
            "loop_closing": r.loop_closing,
            "trajectory": f"{r.name}/trajectory.tum", "map": f"{r.name}/map.ply",
        } for r in runs],
        "merge": merge_summary(merger, global_map) if len(runs) > 1 else None,
        "config": config_to_dict(config),
    }


Table = tuple[list[str], list[list[Any]]]  # headers, rows (the text and the HTML report)


def robot_table(summary: dict[str, Any]) -> Table:
    """One row per robot: frames, losses, loops, ATE (if scored), speed, map size."""
    rows = []
    for r in summary["robots"]:
        ate = r["ate"]["rmse_m"] * 100 if r.get("ate") else None
        loops = r.get("loop_closing") or {}
        rows.append([r["name"], r["frames"], r["keyframes"], r["lost_frames"],
                     loops.get("relocalisations"), loops.get("loops_accepted"), ate,
                     r.get("tracking_fps"), r["map_points"]])
    return (["robot", "frames", "keyframes", "lost", "relocalised", "loops", "ATE RMSE cm",
             "fps", "map points"], rows)


def transport_table(summary: dict[str, Any]) -> Table | None:
    """Robot -> cloud traffic and timing of a deployed run (None in one process)."""
    deployed = [r for r in summary["robots"] if "transport" in r]
    if not deployed:
        return None
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
    return (["robot", "offload at", "kB/frame", "lost on link", "rejected", "KF uploads",
             "retries", "cloud ms/frame", "cloud latency ms", "round trip ms", "p95"], trows)


def summary_table(summary: dict[str, Any]) -> str:
    text = format_table(*robot_table(summary))
    transport = transport_table(summary)
    if transport:
        text += "\n\nrobot -> cloud (separate processes over Zenoh)\n" + format_table(*transport)
    merge = summary.get("merge")
    if merge:
        text += "\n\n" + merge_table(merge)
    text += f"\n\nwall time {summary['wall_time_s']:.1f} s"
    return text


def merge_robot_table(merge: dict[str, Any]) -> Table:
    """Per robot: its group, the frames it joined at, its errors if scored."""
    evaluation = merge.get("evaluation") or {}
    relative = {r["robot"]: r for r in evaluation.get("relative_poses", [])}
    rows = []
    for name, info in sorted(merge["robots"].items()):
        joined = info.get("joined")
        rel = relative.get(name, {})
        rows.append([name, info["anchor"],
                     " ".join(f"{r}:{f}" for r, f in joined["frames"].items()) if joined
                     else None,
                     rel.get("final_rotation_error_deg"),
                     None if rel.get("final_translation_error_m") is None
                     else rel["final_translation_error_m"] * 100,
                     (merge.get("not_merged") or {}).get(name, "")])
    return (["robot", "group", "joined at (robot:frame)", "rel. rot err deg",
             "rel. trans err cm", "not merged because"], rows)


def merge_notes(merge: dict[str, Any]) -> tuple[str, list[str]]:
    """(the groups line, the lines after the table: constraints, joint ATE)."""
    evaluation = merge.get("evaluation") or {}
    joint = evaluation.get("joint_ate")
    head = "merge (no ground truth in the run): " + ", ".join(
        "+".join(m) for m in merge["components"].values())
    scored = [c for c in evaluation.get("constraints", []) if "rotation_error_deg" in c]
    kept = [c for c in scored if c["kept"]]
    line = (f"inter-robot constraints: {len(merge['constraints'])} "
            f"({sum(c['kept'] is False for c in merge['constraints'])} rejected by GNC)")
    if kept:
        worst = max(kept, key=lambda c: c["rotation_error_deg"])
        line += (f"; kept ones against ground truth: worst {worst['rotation_error_deg']:.2f} deg"
                 f" / {max(c['translation_error_m'] for c in kept) * 100:.1f} cm")
    lines = [line]
    if joint:
        lines.append(f"joint ATE of the global trajectories: {joint['rmse_m'] * 100:.2f} cm")
    return head, lines


def merge_table(merge: dict[str, Any]) -> str:
    """Which robots joined, when, with how many constraints; the errors if scored."""
    head, lines = merge_notes(merge)
    return "\n".join([head, format_table(*merge_robot_table(merge)), *lines])
