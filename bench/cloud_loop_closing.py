"""Loop closing in the cloud, through real processes: accuracy and the back-end's time per
frame, keyframe and loop query, with the loop closer's database query in the local
mapping worker (the default) against in-line on the tracking thread, run side by side.

    .venv/bin/python bench/cloud_loop_closing.py [--runs 3] [--rate recorded]
                                                 [--out bench/results/cloud_loop_closing.json]

Per sequence of ../shared/data and setting, ``--runs`` times: ``fleetslam cloud`` (local BA
asynchronous, the default) and one ``fleetslam robot --offload-at paper`` at the camera's
rate, on this machine's cores together. From the cloud's summary: ATE of its
trajectory.tum (evo-style SE(3) alignment), frame latency (robot send to feedback),
cloud ms per frame, loop query (database query + verification) and local BA per keyframe,
loop corrections, loops accepted / rejected, each kept loop edge against ground truth.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from shared_data import present_sequences

from fleetslam.datasets.tum import RgbdSequence
from fleetslam.evaluation.fleet import trajectory_ate
from fleetslam.launch import free_endpoint, start_cloud, start_robot, stop
from fleetslam.registration.metrics import transform_error
from fleetslam.tables import format_table
from fleetslam.transforms import invert

SETTINGS = {"query in worker": "", "query in-line": "[loop_closing]\nquery_in_worker = false\n"}
FALSE_LOOP_DEG, FALSE_LOOP_M = 5.0, 0.20


def kept_edges(summary: dict[str, Any], gt: np.ndarray | None) -> list[dict[str, Any]]:
    edges = []
    for event in summary["loop_closing"].get("events", []):
        if not event.get("accepted"):
            continue
        for (query, candidate), T, kept in zip(event["detection_frames"],
                                               event["T_candidate_query"],
                                               event["edges_kept"]):
            record: dict[str, Any] = {"query_frame": query, "candidate_frame": candidate,
                                      "kept": kept,
                                      "label": "no GT" if kept else "switched off by GNC"}
            if kept and gt is not None and np.isfinite(gt[[query, candidate]]).all():
                err = transform_error(np.array(T), invert(gt[candidate]) @ gt[query])
                record.update(rotation_error_deg=err.rotation_deg,
                              translation_error_m=err.translation_m,
                              label="false" if err.rotation_deg > FALSE_LOOP_DEG
                              or err.translation_m > FALSE_LOOP_M else "true")
            edges.append(record)
    return edges


def one_run(folder: Path, setting: str, work: Path, rate: str) -> dict[str, Any]:
    work.mkdir(parents=True, exist_ok=True)
    config = None
    if SETTINGS[setting]:
        config = work / "config.toml"
        config.write_text(SETTINGS[setting])
    endpoint = free_endpoint()
    cloud = start_cloud(endpoint, work / "store", work / "cloud.log",
                        config_path=None if config is None else str(config))
    try:
        robot = start_robot(endpoint, "r0", str(folder), "paper", work / "robot.log",
                            work / "robot.json",
                            config_path=None if config is None else str(config),
                            extra=["--rate", rate])
        if robot.wait() != 0:
            raise RuntimeError(f"the robot failed; see {work / 'robot.log'}")
    finally:
        stop(cloud)
    summary = json.loads((work / "store" / "r0" / "robot.json").read_text())
    sequence = RgbdSequence(folder)
    ate = trajectory_ate(work / "store" / "r0" / "trajectory.tum", sequence)
    lc = summary["loop_closing"]
    return {
        "ate_cm": None if ate is None else 100 * ate["rmse_m"],
        "keyframes": summary["keyframes"], "lost_frames": summary["lost_frames"],
        "latency_ms": [summary["latency_ms_median"], summary["latency_ms_p95"]],
        "cloud_ms": [summary["cloud_ms_median"], summary["cloud_ms_p95"]],
        "loop_query_ms": [lc["loop_query"]["median_ms"], lc["loop_query"]["p95_ms"]],
        "local_ba_ms": [lc["local_ba"]["median_ms"], lc["local_ba"]["p95_ms"]],
        "loop_correction": lc["loop_correction"],
        "loops_accepted": lc["loops_accepted"], "loops_rejected": lc["loops_rejected_by_graph"],
        "worker_loop_queries": lc["local_mapping"].get("loop_queries"),
        "kept_loop_edges": kept_edges(summary, sequence.gt_poses),
    }


def span(values: list[float | None]) -> str:
    v = [x for x in values if x is not None]
    if not v:
        return "-"
    return f"{min(v):.0f}-{max(v):.0f}" if max(v) >= 10 else f"{min(v):.2f}-{max(v):.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--rate", default="recorded",
                        help="the robot's frame rate: 'recorded', 'max' or frames per second")
    parser.add_argument("--out", default="bench/results/cloud_loop_closing.json")
    args = parser.parse_args()
    out = Path(args.out)
    work = out.parent / "cloud-loop-closing-runs" / time.strftime("%Y%m%d-%H%M%S")
    results: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for name, folder in present_sequences():
        results[name] = {}
        for run in range(args.runs):
            # Settings alternate within a run, so both see the same machine state.
            for setting in SETTINGS:
                print(f"{name}, {setting}, run {run + 1} ...", flush=True)
                results[name].setdefault(setting, []).append(
                    one_run(folder, setting, work / name / setting.replace(" ", "_") /
                            str(run), args.rate))
    rows = []
    for name, settings in results.items():
        for setting, runs in settings.items():
            edges = [e for r in runs for e in r["kept_loop_edges"]]
            rows.append([name, setting, span([r["ate_cm"] for r in runs]),
                         span([r["latency_ms"][0] for r in runs]),
                         span([r["latency_ms"][1] for r in runs]),
                         span([r["cloud_ms"][0] for r in runs]),
                         span([r["cloud_ms"][1] for r in runs]),
                         span([r["loop_query_ms"][0] for r in runs]),
                         span([r["loop_query_ms"][1] for r in runs]),
                         span([r["local_ba_ms"][0] for r in runs]),
                         span([r["local_ba_ms"][1] for r in runs]),
                         sum(r["loop_correction"]["n"] for r in runs),
                         sum(r["loops_accepted"] for r in runs),
                         sum(e["label"] == "false" for e in edges)])
    print(f"\nmin-max over {args.runs} run(s), rate {args.rate}, cores {os.cpu_count()} "
          "(robot, cloud and worker share them); ms: median / p95 per run")
    print(format_table(["sequence", "setting", "ATE cm", "latency med", "p95", "cloud ms med",
                        "p95", "loop query med", "p95", "local BA med", "p95",
                        "corrections", "loops acc", "false kept"], rows))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rate": args.rate, "runs": args.runs, "results": results},
                              indent=1, default=float))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
