"""Loop closing on the real sequences of ../shared/data: accuracy with it off and on, every
loop edge against ground truth, place recognition alone, and the back-end's timing.

    .venv/bin/python bench/loop_closure.py [--runs 3] [--out bench/results/loop_closure.json]

Four tables, all written to one JSON:

1. Accuracy, loop closing off vs on (relocalisation on in both), each repeated ``--runs``
   times: mean and largest relative deviation from the mean of ATE RMSE (evo, SE(3)
   alignment, as ``evo_ape tum GT EST -a``) and RPE RMSE (evo, translation part, a fixed
   frame delta, as ``evo_rpe tum GT EST --delta 10 --delta_unit f``) of the final
   trajectory; lost frames, keyframes, loops accepted / rejected by the graph,
   relocalisations. ORB-SLAM3 RGB-D on the same frames beside them.
2. Every loop edge the closer tried (accepted or rejected by the pose graph) against ground
   truth: the edge's T_candidate_query vs inv(G[candidate]) @ G[query]; "false" beyond
   5 deg or 20 cm.
3. Place recognition alone, on the final keyframes of one run per sequence: precision and
   recall of the top candidate among keyframes >= 100 frames older, before and after
   geometric verification, and the time of a query and of a verification.
4. Timing of loop query, loop correction and local BA (median, p95) from the runs.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from evo.core import metrics
from evo.core.trajectory import PoseTrajectory3D
from evo.core.units import Unit

from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.evaluation.fleet import run_ate
from fleetslam.backend.loop_closing import verify
from fleetslam.backend.places import make_database
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.backend.state import BackEndState
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.registration.metrics import transform_error
from fleetslam.tables import format_table
from fleetslam.system import RobotRun, track_robot
from fleetslam.transforms import invert
from shared_data import present_sequences

# ORB-SLAM3 RGB-D, ATE RMSE on the same frames (cm).
ORB_SLAM3_ATE_CM = {"7scenes_redkitchen_0-599": 3.4, "tum_fr1_rpy_0-149": 2.8}
RPE_DELTA_FRAMES = 10
# A loop edge is false beyond these errors against ground truth.
FALSE_LOOP_DEG = 5.0
FALSE_LOOP_M = 0.20
# Ground-truth revisit: keyframe poses this close, frames at least this far apart.
REVISIT_M = 0.30
REVISIT_DEG = 20.0
REVISIT_MIN_FRAME_GAP = 100
# Run-to-run deviation of ATE and RPE allowed around their mean.
STABILITY_TOLERANCE = 0.10
ACCURACY_KEYS = ["ate_rmse_cm", "rpe_rmse_cm", "lost_frames", "keyframes", "loops_accepted",
                 "loops_rejected_by_graph", "relocalisations"]


def config_for(loop_closing: bool) -> Config:
    return Config().with_values({"loop_closing.enabled": loop_closing,
                                 "relocalisation.enabled": True})


def evo_errors(poses: np.ndarray, gt: np.ndarray, timestamps: np.ndarray) -> dict[str, float]:
    """ATE RMSE after SE(3) alignment and RPE RMSE (translation, fixed frame delta), by evo,
    over the frames with finite ground truth and estimate."""
    ok = np.isfinite(gt).all(axis=(1, 2)) & np.isfinite(poses).all(axis=(1, 2))
    ref = PoseTrajectory3D(poses_se3=list(gt[ok]), timestamps=timestamps[ok])
    est = PoseTrajectory3D(poses_se3=list(poses[ok]), timestamps=timestamps[ok])
    aligned = copy.deepcopy(est)
    aligned.align(ref, correct_scale=False)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, aligned))
    rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=RPE_DELTA_FRAMES,
                      delta_unit=Unit.frames, all_pairs=False)
    rpe.process_data((ref, est))
    return {"ate_rmse_m": float(ape.get_statistic(metrics.StatisticsType.rmse)),
            "rpe_rmse_m": float(rpe.get_statistic(metrics.StatisticsType.rmse)),
            "n_poses": int(ok.sum())}


def label_loop_edges(run: RobotRun) -> list[dict[str, Any]]:
    """One record per loop edge of every event: its error against ground truth and label."""
    gt = run.sequence.gt_poses
    events = (run.loop_closing or {}).get("events", [])
    edges = []
    for number, event in enumerate(events):
        kept = event.get("edges_kept") or [False] * len(event["detection_frames"])
        for k, ((query, candidate), T) in enumerate(zip(event["detection_frames"],
                                                         event["T_candidate_query"])):
            record: dict[str, Any] = {
                "event": number, "edge": k, "accepted": bool(event["accepted"]),
                "kept": bool(event["accepted"] and kept[k]),
                "query_frame": int(query), "candidate_frame": int(candidate),
                "rotation_error_deg": None, "translation_error_m": None, "label": "no GT"}
            if gt is not None and np.isfinite(gt[query]).all() and np.isfinite(gt[candidate]).all():
                err = transform_error(np.array(T), invert(gt[candidate]) @ gt[query])
                rot, trans = err.rotation_deg, err.translation_m
                record.update(rotation_error_deg=rot, translation_error_m=trans,
                              label="false" if rot > FALSE_LOOP_DEG or trans > FALSE_LOOP_M
                              else "true")
            edges.append(record)
    return edges


def accuracy_run(name: str, folder: Path, loop_closing: bool) -> dict[str, Any]:
    seq = RgbdSequence(folder)
    run = track_robot(name, str(folder), seq, config_for(loop_closing), show_progress=False)
    errors = evo_errors(run.poses, seq.gt_poses, run.timestamps)
    online = evo_errors(run.online_poses, seq.gt_poses, run.timestamps)
    lc = run.loop_closing or {}
    ate = run_ate(run)
    return {
        "ate_rmse_cm": errors["ate_rmse_m"] * 100, "rpe_rmse_cm": errors["rpe_rmse_m"] * 100,
        "online_ate_rmse_cm": online["ate_rmse_m"] * 100,
        "fleetslam_ate_rmse_cm": ate["rmse_m"] * 100 if ate else None,
        "n_poses": errors["n_poses"], "lost_frames": run.lost_frames,
        "keyframes": len(run.keyframe_indices),
        "loops_accepted": lc.get("loops_accepted", 0),
        "loops_rejected_by_graph": lc.get("loops_rejected_by_graph", 0),
        "relocalisations": lc.get("relocalisations", 0),
        "loop_queries": lc.get("loop_queries"), "candidates_verified": lc.get("candidates_verified"),
        "verified_detections": lc.get("verified_detections"),
        "timing": {k: lc.get(k) for k in ("loop_query", "loop_correction", "local_ba")},
        "wall_s": run.wall_s, "fps": len(run.timestamps) / run.wall_s,
        "loop_edges": label_loop_edges(run),
    }


def mean_and_deviation(values: list[float]) -> tuple[float, float]:
    """Mean and the largest |x - mean| / mean (0 when the mean is 0 and all agree)."""
    x = np.asarray(values, np.float64)
    mean = float(x.mean())
    spread = float(np.abs(x - mean).max())
    if mean == 0:
        return mean, 0.0 if spread == 0 else float("inf")
    return mean, spread / abs(mean)


def summarise_runs(runs: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in ACCURACY_KEYS:
        mean, dev = mean_and_deviation([r[key] for r in runs])
        out[key] = {"mean": mean, "max_relative_deviation": dev}
    out["stable"] = all(out[k]["max_relative_deviation"] <= STABILITY_TOLERANCE
                        for k in ("ate_rmse_cm", "rpe_rmse_cm"))
    return out


def track_session(folder: Path, config: Config) -> tuple[RgbdSequence, BackEndState]:
    """Run the pipeline over a sequence; return the sequence and the final cloud session."""
    seq = RgbdSequence(folder)
    pipeline = RobotSlam.new(config, seq.camera)
    for frame in seq:
        pipeline.track(CapturedFrame(frame.index, frame.timestamp, frame.rgb, frame.depth_m))
    return seq, pipeline.state


def gt_revisits(gt: np.ndarray) -> np.ndarray:
    """K x K bool: keyframe poses (camera-to-world) within REVISIT_M and REVISIT_DEG."""
    t = gt[:, :3, 3]
    dist = np.linalg.norm(t[:, None] - t[None], axis=2)
    R = gt[:, :3, :3]
    cos = (np.einsum("aji,bji->ab", R, R) - 1.0) / 2.0  # trace(R_a^T R_b)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    valid = np.isfinite(gt).all(axis=(1, 2))
    return (dist <= REVISIT_M) & (angle <= REVISIT_DEG) & valid[:, None] & valid[None]


def place_recognition(name: str, folder: Path,
                      tracked: tuple[RgbdSequence, BackEndState] | None = None,
                      database: Any = None) -> dict[str, Any]:
    """Top-1 place recognition over the final keyframes of a loop-closing run (``tracked``,
    else tracked here), with ``database`` (empty; default: the configured method's)."""
    config = config_for(True)
    seq, session = tracked or track_session(folder, config)
    kfs = session.map.keyframes
    frames = np.array([kf.frame_index for kf in kfs])
    gt_kf = seq.gt_poses[frames] if seq.gt_poses is not None else np.full((len(kfs), 4, 4), np.nan)
    has_gt = np.isfinite(gt_kf).all(axis=(1, 2))
    revisit = gt_revisits(gt_kf) & (np.abs(frames[:, None] - frames[None]) >= REVISIT_MIN_FRAME_GAP)
    # One database of every keyframe; a query allowed only the keyframes >= 100 frames older
    # is the same as a database of just those (the index and the idf see only allowed rows).
    db = database if database is not None else make_database(config.place_recognition)
    for kf in kfs:
        db.add(kf.id, kf.features.descriptors if kf.features is not None
               else np.zeros((0, 32), np.uint8))
    queries: list[dict[str, Any]] = []
    query_ms: list[float] = []
    verify_ms: list[float] = []
    for q, kf in enumerate(kfs):
        allowed = frames <= frames[q] - REVISIT_MIN_FRAME_GAP
        if not allowed.any() or not has_gt[q] or kf.features is None:
            continue
        start = time.perf_counter()
        found = db.query(kf.features.descriptors, allowed, top_k=1)
        query_ms.append(1000 * (time.perf_counter() - start))
        record: dict[str, Any] = {"query_keyframe": kf.id, "query_frame": int(frames[q]),
                                  "positive": bool(revisit[q, allowed].any()),
                                  "top_keyframe": None, "top_frame": None, "score": None,
                                  "top_is_revisit": False, "verified": False,
                                  "verified_rotation_error_deg": None,
                                  "verified_translation_error_m": None}
        if found:
            top = found[0]
            record.update(top_keyframe=int(top.key), top_frame=int(frames[top.entry]),
                          score=top.score, votes=top.votes,
                          top_is_revisit=bool(revisit[q, top.entry]))
            start = time.perf_counter()
            detection = verify(session, kf, int(top.key), top.score)
            verify_ms.append(1000 * (time.perf_counter() - start))
            if detection is not None:
                # The verified pose against ground truth, relative to the candidate keyframe.
                T_est = invert(kfs[top.entry].T_world_camera) @ detection.T_world_query
                err = transform_error(T_est, invert(gt_kf[top.entry]) @ gt_kf[q])
                rot, trans = err.rotation_deg, err.translation_m
                record.update(verified=True, inliers=detection.inliers,
                              verified_rotation_error_deg=rot, verified_translation_error_m=trans)
        queries.append(record)
    positives = sum(r["positive"] for r in queries)
    returned = sum(r["top_keyframe"] is not None for r in queries)
    tp_before = sum(r["top_is_revisit"] for r in queries)
    verified = sum(r["verified"] for r in queries)
    tp_after = sum(r["verified"] and r["top_is_revisit"] for r in queries)
    wrong_pose = sum(r["verified"] and (r["verified_rotation_error_deg"] > FALSE_LOOP_DEG or
                                        r["verified_translation_error_m"] > FALSE_LOOP_M)
                     for r in queries)

    def ratio(a: int, b: int) -> float | None:
        return a / b if b else None

    def stats(ms: list[float]) -> dict[str, float | None]:
        return {"n": len(ms), "median_ms": float(np.median(ms)) if ms else None,
                "p95_ms": float(np.percentile(ms, 95)) if ms else None}

    return {
        "sequence": name, "keyframes": len(kfs),
        "gt_revisit_pairs": int(np.triu(revisit, 1).sum()),
        "queries": len(queries), "positives": positives, "returned": returned,
        "true_positives_before": tp_before, "precision_before": ratio(tp_before, returned),
        "recall_before": ratio(tp_before, positives),
        "verified": verified, "true_positives_after": tp_after,
        "precision_after": ratio(tp_after, verified), "recall_after": ratio(tp_after, positives),
        "verified_with_wrong_pose": wrong_pose,
        "query_time": stats(query_ms), "verify_time": stats(verify_ms),
        "loops_accepted_in_run": sum(1 for e in session.loops.events if e["accepted"]),
        "per_query": queries,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3,
                        help="repeat every loop-closing off/on run this many times")
    parser.add_argument("--out", default="bench/results/loop_closure.json")
    args = parser.parse_args()
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    sequences = list(present_sequences())
    load_before = os.getloadavg()

    accuracy: list[dict[str, Any]] = []
    for name, folder in sequences:
        for loop_closing in (False, True):
            runs = [accuracy_run(name, folder, loop_closing) for _ in range(args.runs)]
            accuracy.append({"sequence": name, "loop_closing": loop_closing, "runs": runs,
                             "summary": summarise_runs(runs),
                             "orb_slam3_ate_cm": ORB_SLAM3_ATE_CM.get(name)})

    rows = []
    for a in accuracy:
        s = a["summary"]
        rows.append([a["sequence"], "on" if a["loop_closing"] else "off",
                     s["ate_rmse_cm"]["mean"], 100 * s["ate_rmse_cm"]["max_relative_deviation"],
                     s["rpe_rmse_cm"]["mean"], 100 * s["rpe_rmse_cm"]["max_relative_deviation"],
                     s["lost_frames"]["mean"], s["keyframes"]["mean"], s["loops_accepted"]["mean"],
                     s["loops_rejected_by_graph"]["mean"], s["relocalisations"]["mean"],
                     "yes" if s["stable"] else "NO", a["orb_slam3_ate_cm"]])
    print(f"1. accuracy, mean of {args.runs} run(s); ± = largest deviation from the mean, "
          f"stable = ATE and RPE within ±{100 * STABILITY_TOLERANCE:.0f} %")
    print(format_table(["sequence", "loops", "ATE cm", "±%", f"RPE(d={RPE_DELTA_FRAMES}f) cm",
                        "±%", "lost", "kf", "loops acc", "rej by graph", "reloc", "stable",
                        "ORB-SLAM3 ATE cm"], rows))

    edge_rows, false_accepted = [], 0
    for a in accuracy:
        if not a["loop_closing"]:
            continue
        for r, run in enumerate(a["runs"]):
            for e in run["loop_edges"]:
                false_accepted += e["kept"] and e["label"] == "false"
                rot, trans = e["rotation_error_deg"], e["translation_error_m"]
                edge_rows.append([a["sequence"], r, e["event"], e["edge"],
                                  "yes" if e["accepted"] else "no", "yes" if e["kept"] else "no",
                                  e["query_frame"], e["candidate_frame"],
                                  e["query_frame"] - e["candidate_frame"], rot,
                                  None if trans is None else trans * 100, e["label"]])
    print(f"\n2. loop edges vs ground truth (false beyond {FALSE_LOOP_DEG:g} deg or "
          f"{100 * FALSE_LOOP_M:g} cm)")
    if edge_rows:
        print(format_table(["sequence", "run", "event", "edge", "accepted", "kept", "query frame",
                            "cand frame", "gap", "rot err deg", "trans err cm", "label"],
                           edge_rows))
    else:
        print("no loop edges")
    print(f"false loop edges kept in accepted loops: {false_accepted}")

    places = [place_recognition(name, folder) for name, folder in sequences]
    print(f"\n3. place recognition, top-1 among keyframes >= {REVISIT_MIN_FRAME_GAP} frames older "
          f"(GT revisit: {100 * REVISIT_M:g} cm, {REVISIT_DEG:g} deg); P/R before and after "
          "verification\n   (verified on the final map of a loop-closing run; bad pose = verified "
          f"pose off GT by > {FALSE_LOOP_DEG:g} deg or {100 * FALSE_LOOP_M:g} cm)")
    print(format_table(
        ["sequence", "kf", "revisit pairs", "queries", "positives", "returned", "TP", "P", "R",
         "verified", "TP ver", "P ver", "R ver", "bad pose", "query ms", "p95",
         "verify ms", "p95"],
        [[p["sequence"], p["keyframes"], p["gt_revisit_pairs"], p["queries"], p["positives"],
          p["returned"], p["true_positives_before"], p["precision_before"], p["recall_before"],
          p["verified"], p["true_positives_after"], p["precision_after"], p["recall_after"],
          p["verified_with_wrong_pose"], p["query_time"]["median_ms"],
          p["query_time"]["p95_ms"], p["verify_time"]["median_ms"], p["verify_time"]["p95_ms"]]
         for p in places]))

    timing_rows = []
    for a in accuracy:
        t = [r["timing"] for r in a["runs"]]

        def mean_of(part: str, stat: str) -> float | None:
            values = [x[part][stat] for x in t if x[part] and x[part][stat] is not None]
            return float(np.mean(values)) if values else None

        timing_rows.append([a["sequence"], "on" if a["loop_closing"] else "off"] + [
            v for part in ("loop_query", "loop_correction", "local_ba")
            for v in (mean_of(part, "n"), mean_of(part, "median_ms"), mean_of(part, "p95_ms"))])
    print(f"\n4. timing (ms), mean over {args.runs} run(s) of each run's median and p95")
    print(format_table(["sequence", "loops", "query n", "median", "p95", "correction n", "median",
                        "p95", "local BA n", "median", "p95"], timing_rows))
    # Times depend on what else runs: faiss's OpenMP search slows down many times over when
    # another process holds a core.
    load_after = os.getloadavg()
    print(f"cores: {os.cpu_count()}, load average (1 min) {load_before[0]:.2f} at start, "
          f"{load_after[0]:.2f} at end")

    out.write_text(json.dumps({
        "date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(), "runs": args.runs,
        "load_average_1min": {"start": load_before[0], "end": load_after[0]},
        "rpe_delta_frames": RPE_DELTA_FRAMES,
        "false_loop_bounds": {"rotation_deg": FALSE_LOOP_DEG, "translation_m": FALSE_LOOP_M},
        "revisit_bounds": {"translation_m": REVISIT_M, "rotation_deg": REVISIT_DEG,
                           "min_frame_gap": REVISIT_MIN_FRAME_GAP},
        "accuracy": accuracy, "false_loop_edges_kept": false_accepted,
        "place_recognition": places,
    }, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
