"""Scoring a finished run against ground truth: each robot's ATE in its own frame, and the
merge (every inter-robot constraint, each robot's place in the global frame, and the joint
ATE of all global trajectories under one alignment, as collaborative-SLAM papers score).

Evaluation only: it reads the run's written outputs and the sequences' ground truth after the
run; nothing here feeds back into the system.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.camera import Camera
from fleetslam.datasets.source import Frame, RecordedSource
from fleetslam.datasets.tum import ground_truth_at_stamps
from fleetslam.evaluation.ate import absolute_trajectory_error, relative_pose_error
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.registration.metrics import transform_error
from fleetslam.transforms import invert


GROUND_TRUTH_FLAG = "--groundtruth"


class GivenGroundTruth:
    """A recording scored against a TUM-format ground-truth file given for it
    (``--groundtruth``: a bag, which carries none, or a folder without groundtruth.txt);
    the file is read on first use, for evaluation only."""

    def __init__(self, sequence: RecordedSource, path: Path) -> None:
        self.sequence, self.path = sequence, path
        self.folder: Path = sequence.folder
        self.timestamps: np.ndarray = sequence.timestamps
        self.first: int = sequence.first

    @property
    def camera(self) -> Camera:
        return self.sequence.camera

    @property
    def camera_source(self) -> str:
        return self.sequence.camera_source

    def __len__(self) -> int:
        return len(self.sequence)

    def __getitem__(self, i: int) -> Frame:
        return self.sequence[i]

    @functools.cached_property
    def gt_poses(self) -> np.ndarray | None:
        # At each played frame's recorded time (a retimed range plays at other times).
        return ground_truth_at_stamps(self.path, getattr(
            self.sequence, "recorded_timestamps", self.sequence.timestamps))

    @property
    def has_ground_truth(self) -> bool:
        return self.gt_poses is not None and bool(np.isfinite(self.gt_poses[:, 0, 0]).any())


def with_ground_truth(sequence: RecordedSource, path: Path | None) -> RecordedSource:
    """``sequence`` scored against ``path`` where one is given, else its own ground truth."""
    return sequence if path is None else GivenGroundTruth(sequence, path)


def match_ground_truth(values: Sequence[str], names: Sequence[str]) -> dict[str, Path]:
    """Robot name -> ground-truth file from ``--groundtruth`` values: ``NAME=FILE`` names
    its robot, a bare ``FILE`` goes to the robots in order (not both kinds at once); each
    file is checked to be a TUM trajectory now, not after a long run. ValueError naming the
    flag and what is wrong."""
    named, bare = {}, []
    for value in values:
        name, sep, rest = value.partition("=")
        if sep and name in names:
            if name in named:
                raise ValueError(f"{GROUND_TRUTH_FLAG} {value}: robot {name} has one already")
            named[name] = Path(rest)
        elif sep and not Path(value).exists():
            raise ValueError(f"{GROUND_TRUTH_FLAG} {value}: no robot {name} (robots: "
                             f"{', '.join(names)}) and no such file")
        else:
            bare.append(Path(value))
    if named and bare:
        raise ValueError(f"{GROUND_TRUTH_FLAG}: give every one as NAME=FILE (robots: "
                         f"{', '.join(names)}) or every one as FILE, in the robots' order")
    if len(bare) > len(names):
        raise ValueError(f"{len(bare)} {GROUND_TRUTH_FLAG} for {len(names)} robots "
                         f"({', '.join(names)})")
    files = named or dict(zip(names, bare))
    for path in files.values():
        try:
            read_tum_trajectory(path)
        except ValueError as exc:
            raise ValueError(f"{GROUND_TRUTH_FLAG}: {exc}") from None
    return {name: path.resolve() for name, path in files.items()}


def ground_truth_at(times: np.ndarray, sequence: RecordedSource) -> tuple[np.ndarray, np.ndarray]:
    """(mask of ``times`` that are frames of ``sequence``, their ground-truth poses)."""
    if not sequence.has_ground_truth or not len(times):
        return np.zeros(len(times), bool), np.zeros((0, 4, 4))
    stamps = sequence.timestamps
    idx = np.zeros(len(times), np.int64)
    if len(stamps) > 1:  # the nearer of the two frames around each time
        idx = np.searchsorted(stamps, times).clip(1, len(stamps) - 1)
        idx = np.where(np.abs(stamps[idx - 1] - times) < np.abs(stamps[idx] - times),
                       idx - 1, idx)
    ok = np.abs(stamps[idx] - times) < 1e-3
    gt = sequence.gt_poses[idx[ok]]
    finite = np.isfinite(gt).all(axis=(1, 2))
    ok[np.flatnonzero(ok)[~finite]] = False
    return ok, gt[finite]


def ate_summary(poses: np.ndarray, gt: np.ndarray) -> dict[str, Any] | None:
    """ATE (SE(3) alignment) over the poses whose ground truth is known; None if < 3."""
    if np.sum(np.isfinite(gt).all(axis=(1, 2)) & np.isfinite(poses).all(axis=(1, 2))) < 3:
        return None
    ate = absolute_trajectory_error(poses, gt)
    return {"rmse_m": ate.rmse_m, "mean_m": ate.mean_m, "median_m": ate.median_m,
            "max_m": ate.max_m, "rotation_rmse_deg": ate.rotation_rmse_deg,
            "rotation_mean_deg": ate.rotation_mean_deg, "rotation_max_deg": ate.rotation_max_deg,
            "n_poses": ate.n_poses, "alignment": "SE(3) Umeyama"}


def rpe_summary(poses: np.ndarray, gt: np.ndarray) -> dict[str, Any] | None:
    """RPE between consecutive poses with ground truth (evo_rpe's default, delta 1 frame);
    None with fewer than 2 such poses."""
    if np.sum(np.isfinite(gt).all(axis=(1, 2)) & np.isfinite(poses).all(axis=(1, 2))) < 2:
        return None
    rpe = relative_pose_error(poses, gt)
    return {"translation_rmse_m": rpe.translation_rmse_m,
            "translation_mean_m": rpe.translation_mean_m,
            "translation_max_m": rpe.translation_max_m,
            "rotation_rmse_deg": rpe.rotation_rmse_deg,
            "rotation_mean_deg": rpe.rotation_mean_deg,
            "rotation_max_deg": rpe.rotation_max_deg, "n_pairs": rpe.n_pairs,
            "delta": "1 frame"}


def run_ate(run: Any) -> dict[str, Any] | None:
    """ATE of an in-process run (``system.RobotRun``: its poses and its sequence)."""
    gt = run.sequence.gt_poses
    return None if gt is None else ate_summary(run.poses, gt)


def _with_ground_truth(trajectory: Path, sequence: RecordedSource
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(poses of a written TUM trajectory that are frames of ``sequence`` with ground truth,
    that ground truth), paired by timestamp (a cloud's trajectory misses frames the link
    lost)."""
    times, poses = read_tum_trajectory(trajectory)
    ok, gt = ground_truth_at(times, sequence)
    return poses[ok], gt


def trajectory_ate(trajectory: Path, sequence: RecordedSource) -> dict[str, Any] | None:
    """ATE of a written TUM trajectory against the sequence's ground truth."""
    return ate_summary(*_with_ground_truth(trajectory, sequence))


def trajectory_rpe(trajectory: Path, sequence: RecordedSource) -> dict[str, Any] | None:
    """RPE of a written TUM trajectory against the sequence's ground truth."""
    return rpe_summary(*_with_ground_truth(trajectory, sequence))


def same_world(a: RecordedSource, b: RecordedSource) -> bool:
    """Two robots' ground truths share a frame when they play the same recording, or
    recordings of one generated scene (its ``scene.json`` declares one world frame)."""
    fa, fb = a.folder.resolve(), b.folder.resolve()
    shared = fa == fb or (fa.parent == fb.parent and (fa.parent / "scene.json").is_file())
    return shared and a.has_ground_truth and b.has_ground_truth


def score_merge(merge: dict[str, Any], out_dir: Path, sequences: dict[str, RecordedSource]
                ) -> dict[str, Any]:
    """Errors of the merge against ground truth (see the module docstring)."""
    result: dict[str, Any] = {"constraints": [], "relative_poses": [], "joint_ate": None}
    for c in merge.get("constraints", []):
        q, p = sequences.get(c["query_robot"]), sequences.get(c["place_robot"])
        row = {k: c[k] for k in ("query_robot", "query_frame", "place_robot", "place_frame",
                                 "trusted", "kept")}
        if q is None or p is None:
            row["note"] = "a loaded map's robot: its ground truth is not this run's"
        elif same_world(q, p):
            true = invert(p.gt_poses[c["place_frame"]]) @ q.gt_poses[c["query_frame"]]
            err = transform_error(np.array(c["T_place_query"]), true)
            row.update(rotation_error_deg=err.rotation_deg, translation_error_m=err.translation_m,
                       used=c.get("used", "features"), found=c.get("found", "features"))
            if "T_place_query_features" in c:
                feat = transform_error(np.array(c["T_place_query_features"]), true)
                row.update(feature_rotation_error_deg=feat.rotation_deg,
                           feature_translation_error_m=feat.translation_m)
        else:
            row["note"] = "different recordings: no common ground-truth frame"
        result["constraints"].append(row)
    # A loaded map's robots are not scored (their sources are not this run's): this run's
    # robots are, in the map's frame, with one alignment.
    members = [m for m in merge.get("members") or [] if m in sequences]
    anchor = merge.get("anchor")
    if len(members) < 2 or anchor is None:
        return result
    if anchor not in members:  # the group's frame is a robot that had not finished
        anchor = members[0]
    a = sequences[anchor]
    # A map frame is its robot's first camera, so ground truth gives the true relative pose
    # of two maps at their first frames; a robot's drift before the shared place counts.
    for m in members:
        if m == anchor:
            continue
        b = sequences[m]
        if not same_world(a, b):
            result["relative_poses"].append({"robot": m, "note": "different recordings"})
            continue
        true = invert(a.gt_poses[0]) @ b.gt_poses[0]
        row: dict[str, Any] = {"robot": m, "to": anchor}
        for label, key in (("graph", "T_global_map_graph"), ("final", "T_global_map")):
            est = invert(np.array(merge[key][anchor])) @ np.array(merge[key][m])
            err = transform_error(est, true)
            row[f"{label}_rotation_error_deg"] = err.rotation_deg
            row[f"{label}_translation_error_m"] = err.translation_m
        result["relative_poses"].append(row)
    if all(same_world(a, sequences[m]) for m in members):
        est, gt = [], []
        for m in members:
            times, poses = read_tum_trajectory(out_dir / merge["global_trajectories"][m])
            ok, g = ground_truth_at(times, sequences[m])
            est.append(poses[ok])
            gt.append(g)
        result["joint_ate"] = ate_summary(np.concatenate(est), np.concatenate(gt))
        result.update(map_to_map(members, est, gt))
    return result


def pose_alignment(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """T_gt_est fitted to whole poses: the rotation that best turns the estimate's
    orientations into ground truth's (chordal mean), then the translation of the positions.
    A position-only fit leaves the rotation free where a trajectory barely moves (fr1_rpy
    turns in place: 39 degrees apart on a 60-frame piece whose merge was right)."""
    ok = np.isfinite(gt).all(axis=(1, 2)) & np.isfinite(est).all(axis=(1, 2))
    M = np.einsum("nij,nkj->ik", gt[ok, :3, :3], est[ok, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    t = (gt[ok, :3, 3] - est[ok, :3, 3] @ R.T).mean(axis=0)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def map_to_map(members: list[str], est: list[np.ndarray], gt: list[np.ndarray]
               ) -> dict[str, Any]:
    """Each member's global trajectory aligned to ground truth on its own: its ATE, the
    bound a perfect merge approaches (their errors together, each aligned apart), and how
    far each one's alignment (fitted to whole poses: ``pose_alignment``) is from the first
    member's (the map-to-map error: zero when the merge put the maps exactly where ground
    truth has them relative to each other; translation at the global frame's origin)."""
    alone = {m: absolute_trajectory_error(e, g) for m, e, g in zip(members, est, gt)
             if np.sum(np.isfinite(g).all(axis=(1, 2))) >= 3}
    if len(alone) < 2:
        return {}
    first, *others = alone
    pose_fit = {m: pose_alignment(e, g) for m, e, g in zip(members, est, gt) if m in alone}
    rows = []
    for m in others:
        err = transform_error(pose_fit[m], pose_fit[first])
        rows.append({"robot": m, "to": first, "rotation_deg": err.rotation_deg,
                     "translation_m": err.translation_m})
    n = sum(r.n_poses for r in alone.values())
    bound = float(np.sqrt(sum(r.n_poses * r.rmse_m ** 2 for r in alone.values()) / n))
    return {"separately_aligned_m": {m: r.rmse_m for m, r in alone.items()},
            "separately_aligned_bound_m": bound, "map_to_map": rows}


def score_fleet(summary: dict[str, Any], out_dir: Path, sequences: dict[str, RecordedSource]
                ) -> None:
    """Add ground-truth scores to ``summary`` in place (robots' ATE and RPE, merge
    evaluation), and the ground-truth file given for a robot (``GivenGroundTruth``), so
    that a report made later scores with it too."""
    for robot in summary["robots"]:
        sequence = sequences.get(robot["name"])
        if sequence is None:  # its scores, if any, stay as they are
            continue
        trajectory = out_dir / robot["trajectory"]
        if isinstance(sequence, GivenGroundTruth):
            robot["groundtruth"] = str(sequence.path)
        robot["ate"] = trajectory_ate(trajectory, sequence)
        robot["rpe"] = trajectory_rpe(trajectory, sequence)
    merge = summary.get("merge")
    loaded = set(merge.get("loaded_map", [])) if merge is not None else set()
    if merge is not None and all(n in sequences for n in merge.get("robots", {})
                                 if n not in loaded):
        merge["evaluation"] = score_merge(merge, out_dir, sequences)
