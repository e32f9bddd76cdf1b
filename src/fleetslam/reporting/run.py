"""A finished run folder as plain arrays for the report: trajectories (own map frame and
global frame), ground truth at the same instants, the global map, stage times, and what each
robot put on its link.

Ground truth is evaluation only: it is read here, after the run, from the ``groundtruth.txt``
of the folder each robot played (its ``source`` in summary.json; a ROS bag carries none), or
from a file given for the robot (``--groundtruth`` to ``run``, kept in summary.json as its
``groundtruth``, or to ``report``). The summary's scores are made again from it, so tables
and plots show the same errors. A run without it, or a report made without it (the cloud's
own report), still loads everything else.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.config import SourceConfig
from fleetslam.datasets.recording import open_source, spec_is_bag, spec_path
from fleetslam.datasets.source import RecordedSource
from fleetslam.evaluation.ate import umeyama
from fleetslam.evaluation.fleet import (ground_truth_at, match_ground_truth, same_world,
                                        score_fleet, with_ground_truth)
from fleetslam.io.ply import read_ply
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.outputs import ROBOT_REPORT


@dataclass
class Trajectory:
    times: np.ndarray  # (N,) seconds
    poses: np.ndarray  # (N, 4, 4) T_frame_camera
    gt: np.ndarray | None = None  # (N, 4, 4) ground truth at the same times, NaN where none

    @property
    def has_gt(self) -> bool:
        return self.gt is not None and bool(np.isfinite(self.gt[:, 0, 0]).any())


@dataclass
class Sends:
    """Messages a robot put on its link (RobotReport.sends), one array entry each."""

    start_s: np.ndarray
    end_s: np.ndarray
    nbytes: np.ndarray
    keyframe: np.ndarray  # bool: a keyframe upload (else a frame)
    delivered: np.ndarray  # bool: False if the emulated link lost it


@dataclass
class RobotData:
    name: str
    source: str
    own: Trajectory | None  # in its own map frame (its first camera)
    glob: Trajectory | None  # in the global frame (merged robots only)
    frames: int
    stage_ms: dict[str, float]  # stages of the cloud (or of the one process), ms per frame
    robot_stage_ms: dict[str, float]  # stages run on the robot (deployed runs), ms per frame
    sends: Sends | None
    ate_rmse_m: float | None
    offload_at: int | None = None  # a deployed robot's split point (None: one process)
    gt_note: str = ""  # why this robot has no ground truth, if it has none


@dataclass
class RunData:
    folder: Path
    summary: dict[str, Any]
    robots: list[RobotData]
    map_points: np.ndarray | None = None  # global_map.ply, (N, 3) in the global frame
    map_colors: np.ndarray | None = None  # (N, 3) uint8
    ground_truth_read: bool = True  # False: made without ground truth (the cloud's report)
    joint_gt: bool = False  # the merged robots share one ground-truth world
    bandwidth_mbps: float | None = None  # the emulated link, if limited
    notes: list[str] = field(default_factory=list)

    @property
    def merged(self) -> list[RobotData]:
        return [r for r in self.robots if r.glob is not None]

    def color(self, name: str) -> str:
        """One colour per robot, the same in every plot."""
        index = [r.name for r in self.robots].index(name)
        return f"C{index % 10}"


def load_run(folder: Path, ground_truth: bool = True, groundtruth: Sequence[str] = ()
             ) -> RunData:
    """Everything the report shows, from a finished run folder (ValueError if it has no
    summary.json). ``groundtruth``: ``--groundtruth`` values, ground-truth files for the
    robots (over the ones the run was given and its recordings' own). The robots are scored
    here, once, with the ground truth the plots use: the tables show these scores."""
    folder = Path(folder)
    path = folder / "summary.json"
    if not path.is_file():
        raise ValueError(f"{folder}: no summary.json (not a finished run folder)")
    try:
        summary = json.loads(path.read_text())
    except ValueError as exc:
        raise ValueError(f"{path}: not JSON: {exc}") from exc
    run = RunData(folder, summary, [], ground_truth_read=ground_truth)
    if summary.get("interrupted"):
        run.notes.append(_interrupted_note(summary["interrupted"]))
    given = match_ground_truth(groundtruth, [r["name"] for r in summary.get("robots", [])])
    sequences: dict[str, RecordedSource] = {}
    merge = summary.get("merge") or {}
    global_files = merge.get("global_trajectories") or {}
    for r in summary.get("robots", []):
        name = r["name"]
        own = _read_trajectory(folder / r.get("trajectory", f"{name}/trajectory.tum"), run.notes)
        glob = _read_trajectory(folder / global_files[name], run.notes) \
            if name in global_files else None
        note = ""
        if ground_truth:
            file = given.get(name) or (Path(r["groundtruth"]) if r.get("groundtruth") else None)
            sequence, note = _open_source(r.get("source"), file, _source_config(summary))
            if sequence is not None:
                sequences[name] = sequence
                for traj in (own, glob):
                    if traj is not None:
                        traj.gt = _gt_at(traj.times, sequence)
        robot = r.get("robot") or {}
        run.robots.append(RobotData(
            name, str(r.get("source")), own, glob, int(r.get("frames", 0)),
            dict(r.get("stage_ms") or {}), dict(robot.get("robot_stage_ms") or {}),
            _read_sends(folder / name / ROBOT_REPORT), None, r.get("offload_at"), note))
    # Scored where its trajectory is there to score (score_fleet reads it).
    scored = {r.name: sequences[r.name] for r in run.robots
              if r.name in sequences and r.own is not None}
    if scored:
        _score(run, scored)
    for robot, entry in zip(run.robots, summary.get("robots", [])):
        robot.ate_rmse_m = (entry.get("ate") or {}).get("rmse_m")
    if ground_truth:
        missing = [f"{r.name}: {r.gt_note}" for r in run.robots if r.gt_note]
        if missing:
            run.notes.append("no ground truth for " + "; ".join(missing))
    _read_merge(run, sequences, merge)
    return run


def _score(run: RunData, sequences: dict[str, RecordedSource]) -> None:
    """The summary's scores (robots' ATE and RPE, the merge's evaluation) from the ground
    truth read here: a cloud's summary has none, a run's are made again the same way. Kept
    in the report, not written back to summary.json."""
    try:
        score_fleet(run.summary, run.folder, sequences)
    except (ValueError, KeyError, IndexError) as exc:  # outputs that are not there any more
        run.notes.append(f"not scored against ground truth: {type(exc).__name__}: {exc}")


def _read_merge(run: RunData, sequences: dict[str, RecordedSource], merge: dict[str, Any]
                ) -> None:
    """Whether the merged robots share one ground-truth world, and the global map."""
    merged = [r.name for r in run.robots if r.glob is not None]
    run.joint_gt = len(merged) > 1 and all(m in sequences for m in merged) and all(
        same_world(sequences[merged[0]], sequences[m]) for m in merged[1:])
    if run.ground_truth_read and len(merged) > 1 and not run.joint_gt:
        run.notes.append("the merged robots' ground truths share no world frame (or some "
                         "are missing): the global frame is shown unaligned")
    map_path = run.folder / merge.get("global_map", "global_map.ply")
    if merge.get("global_map") and map_path.is_file():
        run.map_points, run.map_colors = read_ply(map_path)
    run.bandwidth_mbps = _bandwidth(run.summary)


def _source_config(summary: dict[str, Any]) -> SourceConfig:
    """The run's topic choices, so a bag opens here as it did in the run."""
    given = (summary.get("config") or {}).get("source") or {}
    keys = ("rgb_topic", "depth_topic", "camera_info_topic", "pair_tolerance_s")
    return SourceConfig(**{k: given[k] for k in keys if k in given})


def _interrupted_note(interrupted: dict[str, Any]) -> str:
    """What a run stopped by Ctrl-C kept and left out."""
    tracked = ", ".join(f"{r} {n}" for r, n in interrupted.get("frames_tracked", {}).items())
    not_built = ", ".join(interrupted.get("not_built") or []) or "nothing"
    return (f"interrupted ({interrupted.get('by', 'Ctrl-C')}): only the frames tracked before "
            f"it are shown (frames: {tracked}); not built: {not_built}")


def _read_trajectory(path: Path, notes: list[str]) -> Trajectory | None:
    try:
        times, poses = read_tum_trajectory(path)
    except ValueError as exc:  # a robot that never finished, a deleted file
        notes.append(str(exc))
        return None
    return Trajectory(times, poses)


def _open_source(source: str | None, file: Path | None, config: SourceConfig
                 ) -> tuple[RecordedSource | None, str]:
    """The robot's recording with its ground truth (``file``: a ground-truth file given for
    it); (None, why) if there is none."""
    if not source:
        return None, "the summary names no source"
    if spec_is_bag(source) and file is None:  # not indexed only to find no ground truth
        return None, (f"{spec_path(source)} is a ROS bag (a bag carries no ground truth; "
                      f"give one with --groundtruth)")
    try:
        sequence = with_ground_truth(open_source(source, source_config=config), file)
    except (ValueError, OSError) as exc:
        # Runs made before sources were stored absolute name them as given.
        hint = ("; the path is relative to the directory the run was started in: run "
                "`fleetslam report` from there" if not spec_path(source).is_absolute() else "")
        return None, f"source not readable here ({exc}{hint})"
    try:
        has = sequence.has_ground_truth  # a given file is read here
    except ValueError as exc:  # the run's file moved or changed since
        return None, f"ground truth not readable here ({exc}; give it with --groundtruth)"
    if not has:
        where = f"{file} covers none of its frames" if file else \
            f"{sequence.folder} has no groundtruth.txt (give one with --groundtruth)"
        return None, where
    return sequence, ""


def _gt_at(times: np.ndarray, sequence: RecordedSource) -> np.ndarray:
    """Ground truth at each of ``times`` (NaN where the sequence has none)."""
    ok, gt = ground_truth_at(times, sequence)
    out = np.full((len(times), 4, 4), np.nan)
    out[ok] = gt
    return out


def _read_sends(path: Path) -> Sends | None:
    """The robot's per-message record, if its report has one (a deployed run's robot)."""
    if not path.is_file():
        return None
    try:
        rows = json.loads(path.read_text()).get("sends") or []
    except ValueError:
        return None
    if not rows:
        return None
    start, end, nbytes, kind, delivered = zip(*rows)
    return Sends(np.array(start, float), np.array(end, float), np.array(nbytes, np.int64),
                 np.array(kind) == "keyframe", np.array(delivered, bool))


def _bandwidth(summary: dict[str, Any]) -> float | None:
    """The emulated link's bandwidth (Mbit/s) the demo gave its robots; None: not limited."""
    args = (summary.get("deployment") or {}).get("link") or []
    if "--bandwidth-mbps" in args:
        value = float(args[args.index("--bandwidth-mbps") + 1])
        return value if value > 0 else None
    value = ((summary.get("config") or {}).get("link") or {}).get("bandwidth_mbps")
    return float(value) if value else None


# -- alignment, as evo aligns (SE(3) Umeyama over the poses with ground truth) ------------


def alignment(trajectories: list[Trajectory]) -> np.ndarray | None:
    """One SE(3) alignment of the estimates onto ground truth over all the given
    trajectories together (one robot: its own map; merged robots: the global frame, so a
    wrong relative placement of two maps shows as error). None without >= 3 pairs."""
    est, gt = [], []
    for t in trajectories:
        if t.gt is None:
            return None
        ok = np.isfinite(t.gt).all(axis=(1, 2)) & np.isfinite(t.poses).all(axis=(1, 2))
        est.append(t.poses[ok, :3, 3])
        gt.append(t.gt[ok, :3, 3])
    if not est or sum(len(e) for e in est) < 3:
        return None
    T, _ = umeyama(np.concatenate(est), np.concatenate(gt))
    return T


def transform(T: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """T @ poses for a stack of poses."""
    return np.einsum("ij,njk->nik", T, poses)


def translation_errors(traj: Trajectory, T: np.ndarray) -> np.ndarray:
    """Per frame: |aligned estimate - ground truth| (m), NaN where no ground truth."""
    assert traj.gt is not None
    est = traj.poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    return np.linalg.norm(est - traj.gt[:, :3, 3], axis=1)
