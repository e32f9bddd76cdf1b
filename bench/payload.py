"""Bytes on the wire at every split point, on the real sequences of ../shared/data.

    .venv/bin/python bench/payload.py [--out bench/results/payload.json] [--frames N]

Each sequence is tracked once; every frame's state at every split point k = 0..6 is encoded
as a frame message, with zstd and without, and decoded again (timed). For comparison: k = 0
with JPEG colour (lossy; depth stays PNG), the paper's YAML message (same features as k = 3),
the RGB-D frame in memory (RGB uint8 + depth uint16) and its files on disk (7-Scenes stores
colour as JPEG, TUM as PNG). Prints one table per sequence and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.progress import Progress
from fleetslam.tables import format_table
from fleetslam.wire.frames import STATE_TYPES, decode_frame_message, encode_frame_message
from fleetslam.wire.paper_yaml import paper_yaml_bytes
from shared_data import present_sequences

ROBOT = "bench"


def stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    return {"mean": float(a.mean()), "p95": float(np.percentile(a, 95)), "max": float(a.max())}


def measure(name: str, folder: Path, last: int | None) -> dict:
    seq = RgbdSequence(folder, last=last)
    config = Config()
    wire = config.wire
    jpeg = replace(wire, frame_image_codec="jpeg")
    uncompressed = replace(wire, compress=False)
    pipeline = RobotSlam.new(config, seq.camera)
    n_points = len(pipeline.stages) + 1
    zstd: list[list[int]] = [[] for _ in range(n_points)]
    raw: list[list[int]] = [[] for _ in range(n_points)]
    enc_ms: list[list[float]] = [[] for _ in range(n_points)]
    dec_ms: list[list[float]] = [[] for _ in range(n_points)]
    extra: dict[str, list[float]] = {"jpeg_k0": [], "yaml": [], "memory": [], "files": [],
                                     "keypoints": [], "k3_at_1000": []}
    progress = Progress(f"payload {name}", len(seq))
    for i, frame in enumerate(seq):
        state = CapturedFrame(frame.index, frame.timestamp, frame.rgb, frame.depth_m)
        states = [state]
        for stage in pipeline.stages:
            state = stage(state, pipeline.sides.part(stage.side))
            states.append(state)
        for k, s in enumerate(states):
            start = time.perf_counter()
            packed = encode_frame_message(s, k, ROBOT, i, seq.camera, wire)
            mid = time.perf_counter()
            decode_frame_message(packed, seq.camera)
            end = time.perf_counter()
            plain = encode_frame_message(s, k, ROBOT, i, seq.camera, uncompressed)
            zstd[k].append(len(packed))
            raw[k].append(len(plain))
            enc_ms[k].append(1000 * (mid - start))
            dec_ms[k].append(1000 * (end - mid))
        extra["jpeg_k0"].append(len(encode_frame_message(states[0], 0, ROBOT, i, seq.camera, jpeg)))
        n_kp = len(states[3].keypoints)
        extra["keypoints"].append(n_kp)
        if n_kp == config.orb.n_features:
            extra["k3_at_1000"].append(zstd[3][-1])
        extra["yaml"].append(len(paper_yaml_bytes(states[3])))
        extra["memory"].append(frame.rgb.nbytes + frame.depth_raw.nbytes)
        extra["files"].append(seq.rgb_paths[i].stat().st_size + seq.depth_paths[i].stat().st_size)
        progress.update(i + 1)
    names = ["nothing"] + pipeline.stage_names
    return {
        "sequence": name, "frames": len(seq),
        "mean_keypoints": float(np.mean(extra["keypoints"])),
        "split_points": [{
            "k": k, "state": STATE_TYPES[k].__name__, "robot_runs_up_to": names[k],
            "zstd_bytes": stats(zstd[k]), "raw_bytes": stats(raw[k]),
            "encode_ms": float(np.mean(enc_ms[k])), "decode_ms": float(np.mean(dec_ms[k])),
        } for k in range(n_points)],
        "k0_jpeg_colour_bytes": stats(extra["jpeg_k0"]),
        "paper_yaml_bytes": stats(extra["yaml"]),
        "rgbd_memory_bytes": stats(extra["memory"]),
        "rgbd_files_bytes": stats(extra["files"]),
        "k3_frames_with_full_features": len(extra["k3_at_1000"]),
        "k3_zstd_bytes_with_full_features": stats(extra["k3_at_1000"] or [np.nan]),
    }


def table(result: dict) -> str:
    headers = ["split point", "robot runs up to", "zstd kB", "p95", "no zstd kB", "p95",
               "encode ms", "decode ms"]
    kb = 1e-3
    rows = [[f"k={p['k']} {p['state']}", p["robot_runs_up_to"], p["zstd_bytes"]["mean"] * kb,
             p["zstd_bytes"]["p95"] * kb, p["raw_bytes"]["mean"] * kb, p["raw_bytes"]["p95"] * kb,
             p["encode_ms"], p["decode_ms"]] for p in result["split_points"]]
    s = result["k0_jpeg_colour_bytes"]
    rows.append(["k=0, JPEG colour (lossy)", "nothing", s["mean"] * kb, s["p95"] * kb, None,
                 None, None, None])
    for label, key in (("paper YAML (k=3 features)", "paper_yaml_bytes"),
                       ("RGB-D in memory", "rgbd_memory_bytes"),
                       ("RGB-D files on disk", "rgbd_files_bytes")):
        s = result[key]
        rows.append([label, "", None, None, s["mean"] * kb, s["p95"] * kb, None, None])
    return format_table(headers, rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/payload.json")
    parser.add_argument("--frames", type=int, default=None, help="first N frames of each")
    args = parser.parse_args()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    results = []
    for name, folder in present_sequences():
        last = None if args.frames is None else args.frames - 1
        result = measure(name, folder, last)
        results.append(result)
        full = result["k3_zstd_bytes_with_full_features"]
        print(f"\n{name}: {result['frames']} frames, {result['mean_keypoints']:.0f} keypoints "
              f"per frame; k=3 with all {Config().orb.n_features} features "
              f"({result['k3_frames_with_full_features']} frames): mean {full['mean'] / 1e3:.2f} "
              f"kB, p95 {full['p95'] / 1e3:.2f} kB (kB = 1000 bytes)")
        print(table(result))
    print(f"cores: {os.cpu_count()}")
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(),
                               "kB": 1000, "results": results}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
