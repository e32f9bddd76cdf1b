"""Robots that start anywhere, merged with no ground truth in the run; scored afterwards.

    .venv/bin/python bench/merge_fleet.py [--out bench/results/merge_fleet.json] [--keep DIR]
                                          [--only CASE ...] [--config FILE.toml]
                                          [--processes POINT] [--case NAME=SOURCE,SOURCE...]

Cases (real data from ../shared/data, plus the built-in synthetic scene):
  rk-2       redkitchen 0-299 and 400-599 (frames 500-560 revisit 272-339's places)
  rpy-2      fr1_rpy 0-59 and 90-149
  rk-3       redkitchen 0-199, 250-349 and 480-599
  apart-*    robots in different places, which must never join: redkitchen 0-299 with
             fr1_rpy 0-149, and each of them with synthetic robot 0
``--case`` adds a case of any sources (a recording folder with ground truth, ``:FIRST-LAST`` for a
range of its frames), e.g. a pair held back from every choice of settings:
``--case rk-held=../data/redkitchen:0-299,../data/redkitchen:600-999 --only rk-held``.
Per case: which robots joined and at which frames, every inter-robot constraint against
ground truth (false = above 5 deg or 20 cm; the feature estimate, and the edge the graph kept,
dense where its refinement was accepted; "proximity": edges registered on depth where the graph
put two joined robots' keyframes near each other, merge.proximity_constraints), each robot's map frame in the global frame
against ground truth before and after FS-HICP, the joint ATE of the concatenated global
trajectories (one SE(3) alignment); each robot's global trajectory aligned apart (and the
bound a perfect merge approaches: their errors together, each aligned apart) and the
map-to-map error (how far each robot's alignment is from the first's: rotation, and
translation at the global frame's origin); each robot alone (its own frame); and the global
outputs (PLY, OctoMap).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from shared_data import SEVEN_SCENES, TUM_RPY  # noqa: E402

from fleetslam.config import Config, load_config  # noqa: E402
from fleetslam.datasets.synthetic import ensure_scene  # noqa: E402
from fleetslam.datasets.recording import open_source  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402
from fleetslam.demo import run_demo  # noqa: E402
from fleetslam.system import run_fleet  # noqa: E402

FALSE_ROTATION_DEG = 5.0
FALSE_TRANSLATION_M = 0.20


def joined_cases() -> dict[str, list[str]]:
    """The shared cases whose robots share places and must join (bench/merge_bounds.py too)."""
    rk, rpy = str(SEVEN_SCENES), str(TUM_RPY)
    return {
        "rk-2": [f"{rk}:0-299", f"{rk}:400-599"],
        "rpy-2": [f"{rpy}:0-59", f"{rpy}:90-149"],
        "rk-3": [f"{rk}:0-199", f"{rk}:250-349", f"{rk}:480-599"],
    }


def cases(synthetic: Path) -> dict[str, list[str]]:
    rk, rpy = str(SEVEN_SCENES), str(TUM_RPY)
    return {
        **joined_cases(),
        "apart-rk-rpy": [f"{rk}:0-299", f"{rpy}:0-149"],
        "apart-rk-syn": [f"{rk}:0-299", str(synthetic)],
        "apart-rpy-syn": [f"{rpy}:0-149", str(synthetic)],
    }


def parse_case(text: str) -> tuple[str, list[str]]:
    """``NAME=SOURCE,SOURCE...`` of ``--case``; SystemExit naming what is wrong."""
    name, _, sources = text.partition("=")
    specs = [s.strip() for s in sources.split(",") if s.strip()]
    if not name.strip() or len(specs) < 2:
        raise SystemExit(f"--case {text!r}: expected NAME=SOURCE,SOURCE[,...] (two robots or more)")
    return name.strip(), specs


def run_case(name: str, specs: list[str], out: Path, config: Config, config_path: str | None,
             processes_at: str | None) -> dict[str, Any]:
    start = time.perf_counter()
    if processes_at is None:
        robots = [(f"r{i}", spec, open_source(spec)) for i, spec in enumerate(specs)]
        summary = run_fleet(robots, config, out / name, show_progress=False)
    else:  # a cloud and one robot per source as processes, on loopback over TLS
        summary = run_demo(specs, out / name, processes_at, config_path, show_progress=False)
    merge = summary["merge"]
    ev = merge.get("evaluation") or {}
    scored = [c for c in ev.get("constraints", []) if "rotation_error_deg" in c]
    false = [c for c in scored if c["rotation_error_deg"] > FALSE_ROTATION_DEG
             or c["translation_error_m"] > FALSE_TRANSLATION_M]
    unscored_kept = [c for c in ev.get("constraints", []) if "rotation_error_deg" not in c]
    return {
        "case": name, "sources": specs, "seconds": time.perf_counter() - start,
        "components": merge["components"], "joins": merge["joins"],
        "robot_ate_cm": {r["name"]: r["ate"]["rmse_m"] * 100 if r["ate"] else None
                         for r in summary["robots"]},
        "constraints": len(merge["constraints"]),
        "constraints_rejected_by_gnc": sum(c["kept"] is False for c in merge["constraints"]),
        "constraint_errors": scored,
        "dense_used": sum(c.get("used") == "dense" for c in merge["constraints"]),
        "proximity": sum(c.get("found") == "proximity" for c in merge["constraints"]),
        "dense_ms_median": merge.get("dense_ms_median"), "dense_ms_p95": merge.get("dense_ms_p95"),
        "global_map_seconds": merge.get("global_map_seconds"),
        "offload_at": processes_at,
        # What each robot sent (processes only): frames, control, keyframe uploads.
        "bytes_per_frame": {r["name"]: sum(r["robot"].get(k, 0) for k in
                                           ("frame_bytes", "control_bytes", "keyframe_bytes"))
                            / max(r["frames"], 1) for r in summary["robots"] if "robot" in r},
        "keyframes": sum(r["keyframes"] for r in merge["robots"].values()),
        "false_constraints": len(false) + len(unscored_kept),
        "relative_poses": ev.get("relative_poses", []),
        "joint_ate_cm": ev["joint_ate"]["rmse_m"] * 100 if ev.get("joint_ate") else None,
        # Each robot's global trajectory aligned apart, the bound a perfect merge approaches,
        # and how far apart the alignments are (evaluation/fleet.py map_to_map).
        "separately_aligned_cm": {m: v * 100 for m, v in
                                  ev.get("separately_aligned_m", {}).items()},
        "separately_aligned_bound_cm": ev["separately_aligned_bound_m"] * 100
        if ev.get("separately_aligned_bound_m") is not None else None,
        "map_to_map": ev.get("map_to_map", []),
        "fshicp": merge.get("fshicp"), "octomap": merge.get("octomap"),
        "global_map_points": merge.get("global_map_points"),
        "query_ms_median": merge.get("query_ms_median"),
        "query_ms_p95": merge.get("query_ms_p95"),
        "graph_ms_median": merge.get("graph_ms_median"),
    }


def worse_ratio(result: dict[str, Any]) -> float | None:
    """The joint ATE against the worse robot's alone (above 1: the merged map is worse than
    each of its robots on its own)."""
    alone = [v for v in result["robot_ate_cm"].values() if v is not None]
    if result["joint_ate_cm"] is None or not alone:
        return None
    return result["joint_ate_cm"] / max(alone)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "merge_fleet.json"))
    parser.add_argument("--keep", help="write the runs here (default: a temporary folder)")
    parser.add_argument("--only", nargs="*", help="case names to run")
    parser.add_argument("--config", help="a fleetslam TOML config (default: the defaults)")
    parser.add_argument("--case", action="append", default=[], metavar="NAME=SOURCE,SOURCE...",
                        help="a case of these sources besides the built-in ones (repeatable)")
    parser.add_argument("--processes", metavar="POINT",
                        help="run each case as real cloud and robot processes (fleetslam demo) "
                             "with the robots at this offloading point, instead of in one "
                             "process")
    args = parser.parse_args()
    config = load_config(args.config)
    extra = dict(parse_case(text) for text in args.case)
    if not SEVEN_SCENES.exists() or not TUM_RPY.exists():
        raise SystemExit(f"needs {SEVEN_SCENES} and {TUM_RPY}")
    with tempfile.TemporaryDirectory() as tmp:
        runs = Path(args.keep) if args.keep else Path(tmp)
        synthetic = ensure_scene(Path(tmp) / "synthetic", Config().synthetic)[0]
        results = [run_case(name, specs, runs, config, args.config, args.processes)
                   for name, specs in {**cases(synthetic), **extra}.items()
                   if not args.only or name in args.only]
    rows = []
    for r in results:
        rel = r["relative_poses"]
        errs = r["constraint_errors"]
        rows.append([
            r["case"], " | ".join("+".join(m) for m in r["components"].values()),
            "; ".join(f"{j['query_robot']}:{j['query_frame']}~{j['place_robot']}:{j['place_frame']}"
                      for j in r["joins"]) or "-",
            r["constraints"], r["dense_used"], r.get("proximity", 0), r["false_constraints"],
            max((c["feature_rotation_error_deg"] for c in errs
                 if "feature_rotation_error_deg" in c), default=None),
            max((c["feature_translation_error_m"] * 100 for c in errs
                 if "feature_translation_error_m" in c), default=None),
            max((c["rotation_error_deg"] for c in errs if c["kept"]), default=None),
            max((c["translation_error_m"] * 100 for c in errs if c["kept"]), default=None),
            " ".join(f"{p['graph_rotation_error_deg']:.2f}/{p['graph_translation_error_m'] * 100:.1f}"
                     for p in rel if "graph_rotation_error_deg" in p) or "-",
            " ".join(f"{p['final_rotation_error_deg']:.2f}/{p['final_translation_error_m'] * 100:.1f}"
                     for p in rel if "final_rotation_error_deg" in p) or "-",
            r["joint_ate_cm"], worse_ratio(r),
            " ".join(f"{p['rotation_deg']:.1f}/{p['translation_m'] * 100:.1f}"
                     for p in r["map_to_map"]) or "-",
            " ".join(f"{v:.2f}" for v in r["separately_aligned_cm"].values()) +
            (f" ({r['separately_aligned_bound_cm']:.2f})"
             if r["separately_aligned_bound_cm"] is not None else "") or "-",
            " ".join(f"{v:.2f}" for v in r["robot_ate_cm"].values() if v is not None),
            r["query_ms_median"], r["dense_ms_median"],
            " ".join(f"{v / 1000:.1f}" for v in r["bytes_per_frame"].values()) or "-"])
    print(format_table(["case", "groups", "joined at", "constraints", "dense", "proximity",
                        "false",
                        "features: max deg", "max cm", "kept edges: max deg", "max cm",
                        "rel. pose graph deg/cm", "after FS-HICP deg/cm", "joint ATE cm",
                        "joint / worse alone", "map-to-map deg/cm", "apart cm (bound)", "robot ATE cm", "query ms", "dense ms", "kB/frame sent"], rows))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"false_constraint": {"rotation_deg": FALSE_ROTATION_DEG,
                                                    "translation_m": FALSE_TRANSLATION_M},
                               "cases": results}, indent=2))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
