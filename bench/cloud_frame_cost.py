"""What one robot's cloud session costs per frame, in one process: a real RobotSession (its
receive, tracking, keyframe and checkpoint-writer threads, a store in a temporary folder,
the local-mapping worker process as the cloud starts it) fed a robot's messages at
offloading point 3 one at a time (each tracked before the next is sent), so every frame's
time is its own and not a queue's.

    .venv/bin/python bench/cloud_frame_cost.py [--frames 600] [--messages /tmp/m.pkl]
        [--runs 3] [--out bench/results/cloud_frame_cost.json]

The messages (the robot's side, 7-Scenes redkitchen from frame 0) are made once and kept
in ``--messages``, so runs of two versions of the cloud code (PYTHONPATH) read the same
bytes. Per run: the cloud's tracking time per frame (``cloud_ms``: the stages after the
offloading point; median, p95, max), and the wall time from submit to tracked (decode and
the keyframe's checkpoint snapshot too), each split into keyframes and other frames; and the
mean ms per stage; and the CPU time of the whole process (every thread of the session, not
the local-mapping worker) per frame, which a busy machine inflates far less than wall times.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import tempfile
import time
from pathlib import Path

import numpy as np
from fleet import robot_messages
from shared_data import SEVEN_SCENES

from fleetslam.backend.workers import LocalMappingPool
from fleetslam.camera import Camera
from fleetslam.cloud.session.robot_session import RobotSession
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.tables import format_table
from fleetslam.transport.protocol import Hello

POINT = 3


def messages(path: Path | None, frames: int) -> tuple[list[bytes], dict]:
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    made = robot_messages("r0", 0, frames, SEVEN_SCENES)
    if path is not None:
        path.write_bytes(pickle.dumps(made))
    return made


def stats(values: list[float]) -> dict:
    a = np.asarray(values) if values else np.zeros(1)
    return {"n": len(values), "median": float(np.median(a)),
            "p95": float(np.percentile(a, 95)), "max": float(a.max()), "mean": float(a.mean())}


def run(msgs: list[bytes], camera: Camera, pool: LocalMappingPool | None) -> dict:
    config = Config()
    with tempfile.TemporaryDirectory() as tmp:
        session = RobotSession.open("r0", Hello(POINT, camera, "bench"), config,
                                    CloudStore(Path(tmp)), lambda key, data: None,
                                    local_mapping=pool)
        wall = []
        cpu_start = time.process_time()
        start = time.perf_counter()
        for data in msgs:
            t0 = time.perf_counter()
            session.submit_frame(data, time.monotonic())
            session.drain()
            wall.append(1000.0 * (time.perf_counter() - t0))
        span = time.perf_counter() - start
        cpu = time.process_time() - cpu_start
        session.tracker.slam.finish()
        st = session.state
        session.close()
    cloud = list(st.cloud_ms)
    kf = np.array([r.is_keyframe for r in st.rows])
    wall_a, cloud_a = np.array(wall[:len(kf)]), np.array(cloud)
    return {
        "frames": len(cloud), "keyframes": int(kf.sum()), "span_s": span,
        "cpu_ms_per_frame": 1000.0 * cpu / len(cloud),
        "cloud_ms": stats(cloud), "cloud_ms_keyframes": stats(list(cloud_a[kf])),
        "cloud_ms_other": stats(list(cloud_a[~kf])),
        "wall_ms": stats(wall), "wall_ms_keyframes": stats(list(wall_a[kf])),
        "stage_ms": {k: 1000.0 * v / len(cloud) for k, v in st.stage_seconds.items()},
        "errors": st.counts.get("errors", 0),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--messages", type=Path, default=None)
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--out", default="bench/results/cloud_frame_cost.json")
    args = parser.parse_args()
    msgs, camera = messages(args.messages, args.frames)
    camera = Camera.from_dict(camera, "bench camera")
    config = Config()
    pool = (LocalMappingPool(config.tracking.local_mapping_workers)
            if config.tracking.local_mapping == "async" and config.tracking.local_ba else None)
    results = []
    try:
        for _ in range(args.runs):
            results.append(run(msgs[:args.frames], camera, pool))
    finally:
        if pool is not None:
            pool.close()
    headers = ["run", "frames", "kf", "cpu ms/frame", "cloud med", "cloud p95", "cloud max", "kf cloud med",
               "wall med", "wall p95", "kf wall med", "errors"]
    rows = [[i, r["frames"], r["keyframes"], r["cpu_ms_per_frame"], r["cloud_ms"]["median"], r["cloud_ms"]["p95"],
             r["cloud_ms"]["max"], r["cloud_ms_keyframes"]["median"], r["wall_ms"]["median"],
             r["wall_ms"]["p95"], r["wall_ms_keyframes"]["median"], r["errors"]]
            for i, r in enumerate(results)]
    print(format_table(headers, rows))
    for i, r in enumerate(results):
        print(f"run {i} stage ms/frame: "
              + ", ".join(f"{k} {v:.2f}" for k, v in r["stage_ms"].items()))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(),
                               "load": os.getloadavg(), "results": results}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
