"""The paper's "Performance of the whole system" for two robots: fleetslam's choice of
offloading point against total offloading, side by side, with the paper's numbers.

    .venv/bin/python bench/whole_system.py [--bandwidth-mbps 10] [--out bench/results/whole_system.json]

Two robots on 7-Scenes redkitchen (0-299 and 400-599) as real processes (one cloud, one
process per robot, Zenoh over loopback), each behind an emulated link. "fleetslam" runs at
the point `fleetslam plan` chooses for this link from a profile measured on the first frames;
"total offloading" sends the RGB-D frames (point 0); when the choice is not the paper's point
3, point 3 runs too (robots at point 6 send their keyframes' features, so the cloud merges
them as at point 3). Energies from the run's measured times
(planner/energy_report.py); the planner's parameters are the paper's.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from shared_data import SEVEN_SCENES  # noqa: E402

from fleetslam.config import Config  # noqa: E402
from fleetslam.datasets.recording import open_source  # noqa: E402
from fleetslam.demo import run_demo  # noqa: E402
from fleetslam.planner.energy_report import whole_system, whole_system_table  # noqa: E402
from fleetslam.planner.model import Link, candidates, choose  # noqa: E402
from fleetslam.planner.profiling import measure_profile  # noqa: E402
from fleetslam.transport.protocol import SUPPORTED_POINTS  # noqa: E402

SOURCES = [f"{SEVEN_SCENES}:0-299", f"{SEVEN_SCENES}:400-599"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bandwidth-mbps", type=float, default=10.0)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "whole_system.json"))
    parser.add_argument("--runs", default="/tmp/fleetslam-whole-system")
    args = parser.parse_args()
    config = Config()
    profile = measure_profile(open_source(SOURCES[0]), SOURCES[0], config, 60)
    chosen = choose(candidates(profile, Link(args.bandwidth_mbps), config.planner,
                               SUPPORTED_POINTS), config.planner)
    runs = Path(args.runs) / time.strftime("%Y%m%d-%H%M%S")
    link = ["--bandwidth-mbps", f"{args.bandwidth_mbps:g}"]
    results = {}
    plan = [(f"fleetslam's choice (k = {chosen.k}, eta {chosen.eta:.3f})", chosen.k)]
    if chosen.k != 3:  # the paper's point too, side by side
        plan.append(("the paper's point (k = 3)", 3))
    plan.append(("total offloading (k = 0)", 0))
    for label, k in plan:
        summary = run_demo(SOURCES, runs / f"k{k}", str(k), None, link_args=link,
                           show_progress=False)
        results[label] = whole_system(summary, config.planner)
        results[label]["ate_cm"] = {r["name"]: r["ate"]["rmse_m"] * 100 if r["ate"] else None
                                    for r in summary["robots"]}
    print(f"two robots, {args.bandwidth_mbps:g} Mbit/s each; planner parameters: the paper's")
    print(whole_system_table(results))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"bandwidth_mbps": args.bandwidth_mbps, "sources": SOURCES,
                               "chosen_k": chosen.k, "runs": results}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
