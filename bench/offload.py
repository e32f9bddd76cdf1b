"""Offloading over an emulated 10 Mbps link, measured end to end with real processes.

    .venv/bin/python bench/offload.py [--points 0,3,6] [--frames 1000] [--mbps 10]
        [--coding inter,intra]
        [--rate max|recorded|FPS] [--configs a.toml,b.toml] [--runs N]

For each offloading point: a fresh cloud process, one robot process streaming the 7-Scenes
frames as fast as its stages and its link allow (1000 frames = 0-599 then back 598-199),
and the paper's columns (Table "Running time comparison"):
  robot  seconds of robot computation (its stages and message encoding)
  trans  seconds the link was busy (frames, keyframe uploads, control)
  cloud  seconds of cloud computation (its stages)
  sum    robot + trans + cloud
  total  wall time, first frame sent -> the cloud's 'ended' (all frames tracked, the
         keyframes stored and the dense map built); less than sum where they overlap.
Point 0 is total offloading (eta = 0), 3 the paper's point, 6 everything on the robot.
``--coding``: each point with inter-frame coding of the frame message (the default,
wire.inter_frame = true) and/or without it (intra: every frame coded alone); only points
2-5 carry descriptors, so only there does it change anything.
``--configs``: each point under each settings file (robot and cloud both read it), the
files alternating within each of ``--runs`` rounds, so an A/B sees the same machine.
Writes bench/results/offload.json.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from fleetslam.datasets.recording import open_source
from fleetslam.evaluation.fleet import trajectory_ate
from fleetslam.launch import free_endpoint, start_cloud, start_robot, stop
from fleetslam.tables import format_table
from shared_data import SEVEN_SCENES

SEQ = SEVEN_SCENES
PAPER = {  # robot / trans / cloud / sum / total seconds, 1000 frames at 10 Mbps
    "paper total offloading": (0, 498, 80, 578, 578),
    "paper partial (eta 0.484)": (50, 232, 45, 327, 282),
}


def source_spec(frames: int) -> str:
    """``frames`` frames of the 600-frame sequence: forward, then back along the same path."""
    if frames <= 600:
        return f"{SEQ}:0-{frames - 1}"
    if frames > 1199:
        raise ValueError("at most 1199 frames (600 forward, 599 back)")
    return f"{SEQ}:0-599,598-{598 - (frames - 601)}"


def run_point(k: int, spec: str, mbps: float, work: Path, coding: str = "inter",
              rate: str = "max", settings: Path | None = None, tag: str = "") -> dict:
    name = f"point{k}-{coding}{tag}"
    endpoint, out = free_endpoint(), work / name
    config_path = settings
    if coding == "intra":
        config_path = work / f"intra{tag}.toml"
        config_path.write_text((settings.read_text() if settings else "")
                               + "\n[wire]\ninter_frame = false\n")
    cloud = start_cloud(endpoint, out, work / f"{name}-cloud.log",
                        None if settings is None else str(settings))
    report_path = work / f"{name}-robot.json"
    try:
        robot = start_robot(endpoint, "r0", spec, k, work / f"{name}-robot.log", report_path,
                            config_path=None if config_path is None else str(config_path),
                            extra=["--bandwidth-mbps", str(mbps), "--rate", rate])
        code = robot.wait()
        if code != 0:
            raise RuntimeError(f"robot at point {k} failed ({code}); see "
                               f"{work / f'{name}-robot.log'}")
    finally:
        stop(cloud)
    r = json.loads(report_path.read_text())
    cloud_summary = r["cloud_summary"]
    ate = trajectory_ate(out / "r0" / "trajectory.tum", open_source(spec))
    robot_s, trans_s, cloud_s = r["robot_compute_s"], r["link_busy_s"], cloud_summary["cloud_s_total"]
    return {
        "point": k, "coding": coding, "rate": rate,
        "settings": None if settings is None else str(settings), "frames": r["frames"], "robot_s": robot_s, "trans_s": trans_s,
        "cloud_s": cloud_s, "sum_s": robot_s + trans_s + cloud_s, "total_s": r["total_s"],
        "last_feedback_s": r["last_feedback_s"], "streaming_s": r["streaming_s"],
        "frame_kB": r["frame_bytes"] / r["frames"] / 1000,
        "keyframes": cloud_summary["keyframes"], "keyframe_MB": r["keyframe_bytes"] / 1e6,
        "upload_retries": r["upload_retries"],
        "lost_frames": cloud_summary["lost_frames"],
        "ate_m": ate["rmse_m"] if ate else None,
        "cloud_ms_median": cloud_summary.get("cloud_ms_median"),
        "cloud_ms_p95": cloud_summary.get("cloud_ms_p95"),
        "round_trip_ms_median": r["round_trip_ms_median"],
        "round_trip_ms_p95": r["round_trip_ms_p95"],
        "robot_stage_ms": r["robot_stage_ms"], "cloud_stage_ms": cloud_summary["stage_ms"],
        "encode_ms_mean": r.get("encode_ms_mean"), "encode_ms_p95": r.get("encode_ms_p95"),
        "inter_coding": r.get("inter_coding"),
        "flow_wait_s": r.get("flow_wait_s"), "flow_timeouts": r.get("flow_timeouts"),
        "frames_dropped_by_cloud": cloud_summary["transport"].get(
            "frames dropped (session busy)", 0),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", default="0,3,6", help="offloading points to measure")
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--mbps", type=float, default=10.0)
    parser.add_argument("--coding", default="inter",
                        help="inter and/or intra (comma-separated): frame message coding")
    parser.add_argument("--rate", default="max",
                        help="the robot's frame rate: 'max' (as fast as it can), 'recorded' "
                             "(the camera's timestamps) or frames per second")
    parser.add_argument("--configs", default="",
                        help="settings files (comma-separated), alternated within each run")
    parser.add_argument("--runs", type=int, default=1, help="rounds over the settings")
    parser.add_argument("--out", default="bench/results/offload.json")
    args = parser.parse_args()
    settings: list[Path | None] = [Path(c) for c in args.configs.split(",") if c] or [None]
    for path in settings:
        if path is not None and not path.is_file():
            sys.exit(f"--configs: {path} is not a file")
    if "[wire]" in "".join(p.read_text() for p in settings if p) and "intra" in args.coding:
        sys.exit("--coding intra adds its own [wire] table: give the settings' wire keys "
                 "without it, or use --coding inter")
    if not SEQ.exists():
        sys.exit(f"{SEQ} missing: this benchmark needs ../shared/data")
    out = Path(args.out)
    work = out.parent / "offload-runs" / time.strftime("%Y%m%d-%H%M%S")
    work.mkdir(parents=True, exist_ok=True)
    spec = source_spec(args.frames)
    results = []
    for run in range(args.runs):
        for k in (int(p) for p in args.points.split(",")):
            for coding in args.coding.split(","):
                for path in settings:
                    label = "" if path is None else f" {path.stem}"
                    print(f"point {k} ({coding}{label}, run {run + 1}): {args.frames} frames "
                          f"over {args.mbps:g} Mbit/s ...", flush=True)
                    tag = f"-run{run + 1}" + ("" if path is None else f"-{path.stem}")
                    results.append(run_point(k, spec, args.mbps, work, coding, args.rate,
                                             path, tag))
                    r = results[-1]
                    print(f"  total {r['total_s']:.1f} s, {r['frame_kB']:.1f} kB/frame",
                          flush=True)

    def label(r: dict) -> str:
        settings_name = "" if r["settings"] is None else f" {Path(r['settings']).stem}"
        return f"point {r['point']} {r['coding']}{settings_name}"

    rows = [[label(r), r["robot_s"], r["trans_s"], r["cloud_s"], r["sum_s"],
             r["total_s"], r["frame_kB"], r["keyframes"], r["keyframe_MB"],
             None if r["ate_m"] is None else r["ate_m"] * 100,
             r["cloud_ms_median"], r["cloud_ms_p95"],
             r["round_trip_ms_median"], r["round_trip_ms_p95"],
             (r["inter_coding"] or {}).get("intra_share")] for r in results]
    rows += [[name, *cols, None, None, None, None, None, None, None, None, None]
             for name, cols in PAPER.items()]
    print(format_table(["run", "robot s", "trans s", "cloud s", "sum s", "total s",
                        "kB/frame", "KF", "KF MB", "ATE cm", "cloud ms med", "cloud ms p95",
                        "RT ms med", "RT ms p95",
                        "intra share"], rows))
    if args.runs > 1:
        for name in dict.fromkeys(label(r) for r in results):
            mine = [r for r in results if label(r) == name]
            spans = {c: (min(r[c] for r in mine), max(r[c] for r in mine))
                     for c in ("total_s", "robot_s", "trans_s", "frame_kB")}
            print(f"{name}, {len(mine)} runs: " + ", ".join(
                f"{c} {lo:.2f}-{hi:.2f}" for c, (lo, hi) in spans.items()))
    print(f"{args.frames} frames of {SEQ.name} ({spec.split(':')[-1]}), link "
          f"{args.mbps:g} Mbit/s, rate {args.rate}, cores: {os.cpu_count()} (robot and cloud share them)")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"frames": args.frames, "mbps": args.mbps, "rate": args.rate,
                               "source": spec,
                               "cores": os.cpu_count(), "results": results,
                               "paper": PAPER}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
