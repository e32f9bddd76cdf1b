"""Inter-frame coding of the frame message (wire/inter.py) against intra coding, at point 3,
on the real sequences of ../shared/data.

    .venv/bin/python bench/inter_coding.py [--out bench/results/inter_coding.json] [--frames N]

Each sequence's states at point 3 (1000 ORB features asked) are computed once; then every
frame is encoded as the robot would, and decoded by a cloud with its ring of references
(every decoded state is checked bit for bit). Runs: intra only; inter with the cloud's
feedback reaching the robot 1 frame after it sent a frame (the next frame can use it) or 3
frames after (a robot whose link and cloud lag); each with no loss and with 10 % of frames
lost on the link (a lost frame is never acknowledged, so never a reference). Per run: kB
per frame (mean, p95, over all frames and over the frames with all 1000 features), the
intra share, the share of descriptors coded against a reference, and the robot's encode
ms per frame (matching included; the machine is shared, so timings are noisy).

Also: the residual block's zstd size against its entropy bound under a per-bit-position
Bernoulli model (what an ideal adaptive binary arithmetic / rANS coder would reach), to
weigh a dedicated entropy coder.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import zstandard

from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.pipeline.split import run_stages
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.progress import Progress
from fleetslam.tables import format_table
from fleetslam.wire import inter as wire_inter
from fleetslam.wire.frames import decode_frame_message, encode_frame_message
from fleetslam.wire.inter import (
    INTER_MAX_HAMMING,
    InterEncoder,
    InterStats,
    ReferenceRing,
    nearest,
    reference_of,
)
from shared_data import present_sequences

ROBOT = "bench"
K = 3
OPENCV_RUN = "inter, ack lag 1, OpenCV matcher (no faiss)"
RUNS = [  # (name, inter, ack lag in frames, loss)
    ("intra", False, 1, 0.0),
    ("inter, ack lag 1", True, 1, 0.0),
    # A robot's base install has no faiss: OpenCV's brute-force matcher finds the same rows
    # (the bytes are compared with the run above), in more of the robot's time.
    (OPENCV_RUN, True, 1, 0.0),
    ("inter, ack lag 3", True, 3, 0.0),
    ("intra, 10 % lost", False, 1, 0.1),
    ("inter, ack lag 1, 10 % lost", True, 1, 0.1),
    ("inter, ack lag 3, 10 % lost", True, 3, 0.1),
]


def stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=float)
    if not len(a):
        return {"mean": float("nan"), "p95": float("nan")}
    return {"mean": float(a.mean()), "p95": float(np.percentile(a, 95))}


def same(a, b) -> bool:
    return all(x.tobytes() == y.tobytes() for x, y in (
        (a.descriptors, b.descriptors), (a.keypoints[:, [0, 1, 2, 5, 6]],
                                         b.keypoints[:, [0, 1, 2, 5, 6]]),
        (a.depth, b.depth), (a.uv, b.uv)))


def run(states: list, camera, config: Config, inter: bool, lag: int, loss: float,
        messages: list[bytes] | None = None) -> dict:
    """One run; ``messages`` collects every message's bytes."""
    wire = config.with_values({"wire.inter_frame": inter}).wire
    encoder = InterEncoder(wire, wire.reference_frames)
    ring = ReferenceRing(wire.reference_frames)
    rng = np.random.default_rng(0)
    sizes, full, enc_ms, dec_ms, in_flight = [], [], [], [], []
    for seq, state in enumerate(states):
        while in_flight and in_flight[0] <= seq - lag:
            encoder.acked(in_flight.pop(0))
        start = time.perf_counter()
        refs = encoder.choose(seq)
        info = InterStats()
        data = encode_frame_message(state, K, ROBOT, seq, camera, wire, refs, info)
        encoder.sent(seq, reference_of(state), len(refs))
        encoder.record(info)
        enc_ms.append(1000 * (time.perf_counter() - start))
        sizes.append(len(data))
        if messages is not None:
            messages.append(data)
        if len(state.keypoints) == config.orb.n_features:
            full.append(len(data))
        if seq and rng.random() < loss:
            continue
        start = time.perf_counter()
        _, decoded = decode_frame_message(data, camera, ring)
        dec_ms.append(1000 * (time.perf_counter() - start))
        if not same(state, decoded):
            raise AssertionError(f"frame seq {seq}: decoded state differs")
        ring.put(seq, reference_of(decoded))
        in_flight.append(seq)
    return {"bytes": stats(sizes), "bytes_full_features": stats(full),
            "frames_full_features": len(full), **encoder.counts.summary(),
            "encode_ms": stats(enc_ms), "decode_ms": stats(dec_ms)}


def entropy_bound(states: list, refs_per_frame: int) -> dict:
    """Residual block (descriptors coded against the newest ``refs_per_frame`` frames, ack
    lag 1): zstd (as sent) vs a per-bit-position Bernoulli model's entropy."""
    cctx = zstandard.ZstdCompressor(level=Config().wire.zstd_level)
    zstd_sizes, bound = [], []
    for i in range(refs_per_frame, len(states)):
        d = states[i].descriptors
        stacked = np.concatenate([states[i - r].descriptors for r in range(1, refs_per_frame + 1)])
        row, dist = nearest(d, stacked)
        coded = dist < INTER_MAX_HAMMING
        residual = d[coded] ^ stacked[row[coded]]
        zstd_sizes.append(len(cctx.compress(residual.tobytes())))
        p = np.unpackbits(residual, axis=1).mean(0).clip(1e-9, 1 - 1e-9)
        h = -(p * np.log2(p) + (1 - p) * np.log2(1 - p))
        bound.append(len(residual) * h.sum() / 8)
    return {"residual_zstd_bytes": float(np.mean(zstd_sizes)),
            "residual_entropy_bound_bytes": float(np.mean(bound))}


def measure(name: str, folder: Path, last: int | None) -> dict:
    # --frames beyond a sequence's end takes all of it.
    seq = RgbdSequence(folder, last=None if last is None or last >= len(RgbdSequence(folder))
                       else last)
    camera = seq.camera
    pipeline = RobotSlam.new(Config(), camera)
    robot, _ = pipeline.split(K)
    progress = Progress(f"point-3 states {name}", len(seq))
    states = []
    for i, f in enumerate(seq):
        states.append(run_stages(robot, CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m),
                                 pipeline.sides))
        progress.update(i + 1)
    runs = {}
    messages: dict[str, list[bytes]] = {}
    for run_name, inter, lag, loss in RUNS:
        messages[run_name] = []
        with_faiss = wire_inter._faiss
        if run_name == OPENCV_RUN:
            wire_inter._faiss = lambda: None  # as on a robot without faiss
        try:
            runs[run_name] = {"inter": inter, "ack_lag": lag, "loss": loss,
                              **run(states, camera, Config(), inter, lag, loss,
                                    messages[run_name])}
        finally:
            wire_inter._faiss = with_faiss
        r = runs[run_name]
        print(f"  {run_name}: {r['bytes']['mean'] / 1e3:.2f} kB/frame", flush=True)
    if messages[OPENCV_RUN] != messages["inter, ack lag 1"]:
        raise AssertionError("OpenCV's matcher and faiss coded a frame differently")
    return {"sequence": name, "frames": len(seq),
            "mean_keypoints": float(np.mean([len(s.keypoints) for s in states])),
            "runs": runs, "entropy": entropy_bound(states, Config().wire.inter_references)}


def table(result: dict) -> str:
    kb = 1e-3
    rows = [[name, r["bytes"]["mean"] * kb, r["bytes"]["p95"] * kb,
             r["bytes_full_features"]["mean"] * kb, r["bytes_full_features"]["p95"] * kb,
             100 * r["intra_share"], 100 * r["inter_descriptor_share"], r["encode_ms"]["mean"],
             r["encode_ms"]["p95"], r["decode_ms"]["mean"]] for name, r in result["runs"].items()]
    return format_table(["run", "kB", "p95", "kB (1000 f)", "p95", "intra %", "inter desc %",
                         "enc ms", "p95", "dec ms"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/inter_coding.json")
    parser.add_argument("--frames", type=int, default=None, help="first N frames of each")
    args = parser.parse_args()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    results = []
    for name, folder in present_sequences():
        result = measure(name, folder, None if args.frames is None else args.frames - 1)
        results.append(result)
        e = result["entropy"]
        print(f"\n{name}: {result['frames']} frames, {result['mean_keypoints']:.0f} keypoints "
              f"per frame (kB = 1000 bytes)")
        print(table(result))
        print(f"residual block (lag 1): zstd {e['residual_zstd_bytes'] / 1e3:.2f} kB, "
              f"per-bit entropy bound {e['residual_entropy_bound_bytes'] / 1e3:.2f} kB")
    print(f"cores: {os.cpu_count()} (shared with other work: timings are noisy)")
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(),
                               "kB": 1000, "split_point": K,
                               "config": vars(Config().wire), "results": results}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
