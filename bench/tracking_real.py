"""Tracking on the real sequences of ../shared/data: frames, losses, ATE, time per stage.

    .venv/bin/python bench/tracking_real.py [--out bench/results/tracking_real.json] [--config F]

Prints one table row per sequence and writes JSON. ATE is RMSE after an SE(3) alignment,
as `evo_ape tum GT EST -a`; the trajectory of each run is written beside the JSON so evo
can check it.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from fleetslam.config import load_config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.evaluation.fleet import run_ate
from fleetslam.io.trajectory import write_tum_trajectory
from fleetslam.tables import format_table
from fleetslam.system import track_robot
from shared_data import present_sequences

STAGES = ["extract", "describe", "associate_depth", "match", "estimate_pose", "decide_keyframe"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/tracking_real.json")
    parser.add_argument("--config", help="a TOML file over the defaults (an A/B of a setting)")
    args = parser.parse_args()
    config = load_config(args.config)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    results = []
    for name, folder in present_sequences():
        seq = RgbdSequence(folder)
        run = track_robot(name, str(folder), seq, config, show_progress=False)
        write_tum_trajectory(out.parent / f"{name}.tum", run.timestamps, run.poses)
        ate = run_ate(run)
        results.append({
            "sequence": name, "frames": len(run.timestamps),
            "tracked": int(run.tracked.sum()), "lost_frames": run.lost_frames,
            "keyframes": len(run.keyframe_indices), "repeated_frames": run.repeated_frames,
            "ate_rmse_m": ate["rmse_m"] if ate else None,
            "ate_max_m": ate["max_m"] if ate else None,
            "fps": len(run.timestamps) / run.wall_s, "stage_ms": run.stage_ms,
        })
    headers = ["sequence", "frames", "tracked", "lost", "kf", "ATE cm", "fps"] + \
        [f"{s} ms" for s in STAGES]
    rows = [[r["sequence"], r["frames"], r["tracked"], r["lost_frames"], r["keyframes"],
             r["ate_rmse_m"] * 100, r["fps"]] + [r["stage_ms"].get(s) for s in STAGES]
            for r in results]
    print(format_table(headers, rows))
    print(f"cores: {os.cpu_count()}")
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(),
                               "results": results}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
