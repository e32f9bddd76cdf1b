"""How far one robot's accuracy moves when a setting moves a little: the tracker in-process
(deterministic: local BA in-line) on each sequence of ../shared/data, with the defaults and
with each of a few tracking settings nudged down and up by ``--step`` (a fraction of the
value; integers by 1). Nothing else changes between the runs, so their spread is how much
a run's ATE depends on where its keyframes happened to fall: the floor under any
comparison of one run's ATE with another's (issue 47 item 1 holds a fleet's robots, whose
local BA lands frames later, to one in-process run).

    .venv/bin/python bench/tracking_sensitivity.py [--step 0.02] [--settings a,b]
                                                   [--out bench/results/tracking_sensitivity.json]

Prints a row per run and a summary per sequence (the defaults' online and final ATE, the
nudged runs' min / median / max, and the largest as a ratio of the defaults'); writes JSON.
Online ATE scores each frame's pose as tracking answered it (what a robot got back);
final, the trajectory after every later map correction.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.config import Config, TrackingConfig, check_config, load_config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.evaluation.fleet import ate_summary
from fleetslam.system import track_robot
from fleetslam.tables import format_table
from shared_data import present_sequences

# Settings that decide which frames become keyframes and which matches count: a nudge of
# 2 % of any of them is within what their measurements (docs/decisions.md) could tell apart.
SETTINGS = ("keyframe_inlier_ratio", "keyframe_reference_ratio", "match_ratio",
            "prediction_min_inlier_ratio", "local_ba_relative_tolerance", "min_guided_matches")


def nudged(config: Config, setting: str, step: float) -> list[tuple[Any, Config]]:
    """(value, config) with ``tracking.<setting>`` moved down and up by ``step`` (a fraction;
    integers by 1); a value the setting's bounds refuse is left out."""
    known = {f.name for f in fields(TrackingConfig)}
    if setting not in known:
        raise SystemExit(f"--settings: tracking.{setting} is no setting")
    value = getattr(config.tracking, setting)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SystemExit(f"--settings: tracking.{setting} is {value!r}, not a number")
    if isinstance(value, int):
        values: list[Any] = [value - 1, value + 1]
    else:
        values = [round(value * (1 - step), 6), round(value * (1 + step), 6)]
    out = []
    for v in values:
        tracking = replace(config.tracking, **{setting: v})
        try:
            check_config(tracking, "tracking")
        except ValueError:
            continue
        out.append((v, replace(config, tracking=tracking)))
    return out


def score(name: str, folder: Path, config: Config) -> dict[str, Any]:
    seq = RgbdSequence(folder)
    run = track_robot(name, str(folder), seq, config, show_progress=False)
    online = ate_summary(run.online_poses, seq.gt_poses)
    final = ate_summary(run.poses, seq.gt_poses)
    return {"online_cm": online["rmse_m"] * 100 if online else None,
            "final_cm": final["rmse_m"] * 100 if final else None,
            "keyframes": len(run.keyframe_indices)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--step", type=float, default=0.02,
                        help="the nudge, a fraction of each setting's value")
    parser.add_argument("--settings", default=",".join(SETTINGS),
                        help="comma list of tracking settings to nudge")
    parser.add_argument("--config", help="a TOML file over the defaults: the runs' centre")
    parser.add_argument("--out", default="bench/results/tracking_sensitivity.json")
    args = parser.parse_args()
    if not 0 < args.step < 1:
        raise SystemExit(f"--step {args.step}: between 0 and 1")
    base = load_config(args.config)
    settings = [s for s in args.settings.split(",") if s]
    variants = [(s, v, c) for s in settings for v, c in nudged(base, s, args.step)]
    runs: list[dict[str, Any]] = []
    summary: list[dict[str, Any]] = []
    for name, folder in present_sequences():
        centre = {"sequence": name, "setting": "defaults", "value": None,
                  **score(name, folder, base)}
        runs.append(centre)
        print(f"{name}: defaults online {centre['online_cm']:.3f} cm", flush=True)
        mine = []
        for setting, value, config in variants:
            row = {"sequence": name, "setting": setting, "value": value,
                   **score(name, folder, config)}
            print(f"{name}: {setting} = {value}: online {row['online_cm']:.3f} cm", flush=True)
            runs.append(row)
            mine.append(row)
        online = np.array([r["online_cm"] for r in mine if r["online_cm"] is not None])
        if len(online) and centre["online_cm"]:
            summary.append({"sequence": name, "defaults_online_cm": centre["online_cm"],
                            "defaults_final_cm": centre["final_cm"], "nudged_runs": len(online),
                            "online_min_cm": float(online.min()),
                            "online_median_cm": float(np.median(online)),
                            "online_max_cm": float(online.max()),
                            "max_over_defaults": float(online.max() / centre["online_cm"])})
    print(format_table(["sequence", "setting", "value", "online ATE cm", "final ATE cm",
                        "keyframes"],
                       [[r["sequence"], r["setting"], r["value"], r["online_cm"],
                         r["final_cm"], r["keyframes"]] for r in runs]))
    print(f"\nEach setting nudged by {args.step:g} of its value (integers by 1):")
    print(format_table(["sequence", "defaults online / final cm", "nudged runs",
                        "online min / median / max cm", "max / defaults"],
                       [[s["sequence"],
                         f"{s['defaults_online_cm']:.3f} / {s['defaults_final_cm']:.3f}",
                         s["nudged_runs"], f"{s['online_min_cm']:.3f} / "
                         f"{s['online_median_cm']:.3f} / {s['online_max_cm']:.3f}",
                         f"{s['max_over_defaults']:.2f}"] for s in summary]))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(),
                               "step": args.step, "runs": runs, "summary": summary}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
