"""The whole system on recorded data in one process, on its two facades: each robot's
``RobotSlam`` (backend/robot_slam.py) and the fleet's ``FleetMap`` (merging/fleet_map.py).

    fleet = FleetMap(config)
    for every frame i, robots taking turns:
        out = slam[robot].track(frame i)               # the robot's pose
        if out.is_keyframe:
            fleet.add_keyframe(newest keyframe, poses)  # robots join where they meet
    slam[robot].finish(); build each robot's dense map
    fleet.build_outputs(tracks, out_dir)               # global trajectories, PLY, octree
    score against ground truth, afterwards

The robot/cloud split is an index into the pipeline's stages (pipeline/split.py); the same
work as separate processes is cloud/ and edge/, making the same calls.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.config import Config
from fleetslam.datasets.source import RecordedSource
from fleetslam.evaluation.fleet import score_fleet, with_ground_truth
from fleetslam.mapping.dense_map import build_dense_map
from fleetslam.mapping.map_frame import mounting_up
from fleetslam.mapping.occupancy_grid import OccupancyGrid, occupancy_grid
from fleetslam.merging.fleet_map import FleetMap
from fleetslam.merging.global_map import GlobalMap, RobotTrack
from fleetslam.merging.saved_map import LoadedMap, MapError
from fleetslam.merging.inter_robot import keyframe_summary
from fleetslam.wire.merger_keyframes import KeyframeSummary
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.backend.state import BackEndState
from fleetslam.backend.workers import LocalMappingPool
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.progress import Progress
from fleetslam.outputs import write_robot_files, write_summary
from fleetslam.run_summary import RobotSummary, RunSummary
from fleetslam.run_mcap import write_run_mcap

@dataclass
class RobotRun:
    """One robot's tracking result, in its own map frame (its first camera pose)."""

    name: str
    source: str
    sequence: RecordedSource
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
    grid: OccupancyGrid | None = None  # its nav2 map, once its dense map is built

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

    def __init__(self, name: str, source: str, sequence: RecordedSource, config: Config,
                 workers: LocalMappingPool | None = None) -> None:
        self.name, self.source, self.sequence = name, source, sequence
        self.slam = RobotSlam.new(config, sequence.camera, workers)
        self.poses: list[np.ndarray] = []
        self.tracked: list[bool] = []
        self.refs: list[int] = []
        self.T_refs: list[np.ndarray | None] = []
        self.seconds = 0.0

    @property
    def state(self) -> BackEndState:
        return self.slam.state

    def step(self, i: int) -> KeyframeSummary | None:
        """Track frame ``i``; the new keyframe's summary if it became one."""
        frame = self.sequence[i]
        start = time.perf_counter()
        out = self.slam.track(CapturedFrame(frame.index, frame.timestamp, frame.rgb,
                                            frame.depth_m))
        self.seconds += time.perf_counter() - start
        self.poses.append(out.T_world_camera)
        self.tracked.append(out.tracked)
        self.refs.append(out.reference_keyframe)
        self.T_refs.append(out.T_reference_camera)
        if not out.is_keyframe:
            return None
        return keyframe_summary(self.name, self.state.map.keyframes[-1])

    def finish(self) -> RobotRun:
        self.slam.finish()
        state, sequence = self.state, self.sequence
        kfs = state.map.keyframes
        return RobotRun(
            # Only the frames tracked (fewer than the sequence's after a Ctrl-C).
            self.name, self.source, sequence, sequence.timestamps[:len(self.poses)].copy(),
            state.final_poses(self.refs, self.T_refs, self.poses), np.array(self.tracked),
            [kf.frame_index for kf in kfs], state.map.keyframe_poses(),
            self.slam.timer.mean_ms(), state.lost_total, state.loss_events,
            state.repeated_frames, state.resets, self.seconds,
            references=np.array(self.refs, np.int64), T_reference_camera=list(self.T_refs),
            online_poses=np.array(self.poses), loop_closing=self.slam.summary())


class Interrupt:
    """Ctrl-C during a run as a request to stop: the first sets ``requested`` and the run
    ends at its next check (between frames, between maps), keeping what it has; the second
    aborts (KeyboardInterrupt). Only the main thread receives signals: elsewhere (a run in a
    thread) it is never requested."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: Any = None

    def __enter__(self) -> Interrupt:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *_: Any) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)

    def _handle(self, _signum: int, _frame: Any) -> None:
        self.requested = True
        print("\ninterrupted: stopping at the next frame (or map) and writing what was tracked "
              "(Ctrl-C again to abort)", file=sys.stderr, flush=True)
        signal.signal(signal.SIGINT, signal.default_int_handler)


def track_robot(name: str, source: str, sequence: RecordedSource, config: Config,
                show_progress: bool = True) -> RobotRun:
    """One robot alone, start to end."""
    tracker = RobotTracker(name, source, sequence, config)
    progress = Progress(f"robot {name} tracking", len(sequence), enabled=show_progress)
    for i in range(len(sequence)):
        tracker.step(i)
        progress.update(i + 1, f"kf {len(tracker.state.map.keyframes)} "
                               f"loops {len(tracker.state.loops.edges)}")
    return tracker.finish()


def track_fleet(robots: list[tuple[str, str, RecordedSource]], config: Config,
                show_progress: bool = True, interrupt: Interrupt | None = None,
                fleet: FleetMap | None = None) -> tuple[list[RobotRun], FleetMap]:
    """Every robot tracked, taking turns frame by frame; each new keyframe goes to the
    fleet's map at once, so robots join as soon as they share a place (as in the cloud). An
    ``interrupt`` requested ends it early: each robot's run holds the frames it tracked."""
    interrupt = interrupt or Interrupt()
    trackers = [RobotTracker(name, source, seq, config) for name, source, seq in robots]
    fleet = fleet or FleetMap(config)
    for t in trackers:
        fleet.add_robot(t.name, t.sequence.camera.mounted(config.camera.base_link))
    total = sum(len(t.sequence) for t in trackers)
    progress = Progress("tracking", total, enabled=show_progress)
    done = 0
    for i in range(max(len(t.sequence) for t in trackers)):
        for t in trackers:
            if i >= len(t.sequence) or interrupt.requested:
                continue
            summary = t.step(i)
            if summary is not None:
                fleet.add_keyframe(summary, t.state.map.keyframe_poses())
            done += 1
        progress.update(done, f"groups {len(fleet.groups())}")
        if interrupt.requested:
            break
    return [t.finish() for t in trackers], fleet


def build_robot_map(run: RobotRun, config: Config, show_progress: bool = True) -> None:
    progress = Progress(f"robot {run.name} dense map", len(run.keyframe_indices), "keyframes",
                        enabled=show_progress)

    def keyframes():
        for k, (index, T) in enumerate(zip(run.keyframe_indices, run.keyframe_poses)):
            frame = run.sequence[index]
            progress.update(k + 1)
            yield frame.rgb, frame.depth_m, T

    scans: list = []
    run.map_points, run.map_colors = build_dense_map(run.sequence.camera, keyframes(), config.map,
                                                     scans)
    # Up in the robot's map (its first camera) from the camera's mounting, where given.
    up = mounting_up(np.eye(4), run.sequence.camera.mounted(config.camera.base_link))
    run.grid = occupancy_grid(scans, np.asarray(run.keyframe_poses).reshape(-1, 4, 4),
                              config.grid, up)


def run_fleet(robots: list[tuple[str, str, RecordedSource]], config: Config, out_dir: Path,
              show_progress: bool = True, loaded: LoadedMap | None = None,
              ground_truth: dict[str, Path] | None = None) -> dict[str, Any]:
    """Track, map and merge; write everything under ``out_dir``; score against ground truth
    where a sequence has it or ``ground_truth`` gives a file for its robot (read after the
    run); return the summary. A Ctrl-C ends it early: the trajectories tracked so far are
    written, and ``summary["interrupted"]`` says so."""
    start = time.perf_counter()
    for _, _, sequence in robots:  # a bad mounting is said before anything is written
        sequence.camera.mounted(config.camera.base_link)
    fleet = FleetMap(config)
    # A loaded map is the fleet's first group: the robots search it as they search each other
    # (one it cannot take, or a robot it does not know the camera of, is said before
    # anything is written).
    saved_tracks = []
    if loaded is not None:
        for name, _, sequence in robots:
            problem = loaded.camera_problem(name, sequence.camera)
            if problem:
                raise MapError(loaded.saved.folder or Path("map"), problem)
        saved_tracks = fleet.load(loaded)
    out_dir.mkdir(parents=True, exist_ok=False)
    skipped: list[str] = []  # what a Ctrl-C left unbuilt
    with Interrupt() as interrupt:
        runs, fleet = track_fleet(robots, config, show_progress, interrupt, fleet)
        for run in runs:
            # After a Ctrl-C the trajectories are written, the maps are not built.
            if interrupt.requested:
                skipped.append(f"{run.name}'s dense map")
            else:
                build_robot_map(run, config, show_progress)
            write_robot_files(out_dir / run.name, run.name, run.source, run.timestamps,
                              run.poses, run.timestamps[run.keyframe_indices],
                              run.keyframe_poses, run.map_points, run.map_colors,
                              run.online_poses, run.tracked, run.grid)
        # A lone robot gets the fleet's outputs too: its map made level (map_frame.py).
        merged = not interrupt.requested
        if not merged:
            skipped.append("the merge and the global map")
        global_map = fleet.build_outputs([r.track() for r in runs] + saved_tracks, out_dir) \
            if merged else None
        # Localisation only: the map is not extended, so no new one is written.
        saved = fleet.save(out_dir / "map", global_map) if global_map is not None else None
        interrupted = interrupt.requested
    summary = make_summary(runs, fleet if merged else None, global_map, config,
                           time.perf_counter() - start)
    if saved is not None:
        summary["map"] = saved
    if interrupted:
        summary["interrupted"] = {
            "by": "Ctrl-C", "frames_tracked": {r.name: len(r.timestamps) for r in runs},
            "frames_given": {r.name: len(r.sequence) for r in runs}, "not_built": skipped}
    # Evaluation: ground truth is read only now, after every output is written.
    given = ground_truth or {}
    score_fleet(summary, out_dir, {r.name: with_ground_truth(r.sequence, given.get(r.name))
                                   for r in runs})
    if config.outputs.mcap and not interrupted:
        summary["mcap"] = write_run_mcap(out_dir, summary).name
    write_summary(out_dir, summary)
    return summary


def make_summary(runs: list[RobotRun], fleet: FleetMap | None,
                 global_map: GlobalMap | None, config: Config, wall_s: float
                 ) -> dict[str, Any]:
    """The run's summary; ``fleet`` None: no merge (an interrupted run)."""
    robots: list[RobotSummary | dict[str, Any]] = [RobotSummary(
        r.name, r.source, len(r.timestamps), len(r.keyframe_indices), r.lost_frames,
        r.loss_events, r.repeated_frames, r.resets, len(r.map_points), r.loop_closing,
        r.stage_ms, len(r.timestamps) / r.wall_s if r.wall_s > 0 else None,
        camera=r.sequence.camera_source) for r in runs]
    merge = fleet.summary(global_map) if fleet is not None else None
    return RunSummary(robots, merge, config, wall_s).to_dict()
