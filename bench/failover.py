"""One of two cloud workers killed with SIGKILL mid-run: every robot finishes, no keyframe
the cloud acknowledged is lost, each affected robot's pause and ATE against runs without
the kill; and the global map of robots spread over 2 workers against 1 cloud process.

    .venv/bin/python bench/failover.py [--rate 10] [--kill-at 0.4] [--runs 1]

Four robot processes play overlapping pieces of 7-Scenes redkitchen at offloading point 3
(``--rate`` frames per second each), over mutual TLS on loopback, as ``fleetslam demo``
runs them (demo.py). Settings, side by side:
  1 cloud       one cloud process (the router itself);
  2 workers     a Zenoh router and two cloud workers sharing one store, placed by etcd
                or by liveliness alone (``--placement``);
  2 workers, kill   the same, and once the robots have sent ``--kill-at`` of their frames,
                the worker serving the most robots is killed with SIGKILL.
Each run ends with a merge; ground truth is read only afterwards (evaluation/fleet.py).
"Acknowledged keyframes lost": keyframes the robot heard an ack for (robot_report.json)
that are not keyframes of the session's final checkpoint in the store.
Writes bench/results/failover.json.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from pathlib import Path
from typing import Any

from shared_data import SEVEN_SCENES

from fleetslam.cloud.coordination.fenced_store import stored_run
from fleetslam.cloud.session.store import CloudStore
from fleetslam.demo import run_demo
from fleetslam.tables import format_table

PIECES = ["0-199", "130-329", "260-459", "400-599"]


class Killer:
    """Kills the worker serving the most robots once the fleet is ``at`` through its frames."""

    def __init__(self, at: float, total: int) -> None:
        self.at, self.total = at, total
        self.killed: dict[str, Any] | None = None

    def __call__(self, status: dict[str, Any], workers: list) -> None:
        frames = sum(r["frames"] for r in status["robots"].values())
        if self.killed is not None or frames < self.at * self.total or len(workers) < 2:
            return
        served: dict[str, list[str]] = {}
        for robot, info in status["robots"].items():
            if not info.get("finished"):
                served.setdefault(info["worker"], []).append(robot)
        if not served:
            return
        victim = max(sorted(served), key=lambda w: len(served[w]))
        workers[int(victim[1:])].send_signal(signal.SIGKILL)
        self.killed = {"worker": victim, "robots": sorted(served[victim]),
                       "at_frames": frames, "at_s": time.monotonic()}
        print(f"  killed {victim} (serving {', '.join(served[victim])}) at {frames} frames",
              flush=True)


def acknowledged_lost(store: CloudStore, robot: dict[str, Any]) -> int:
    state = store.load_checkpoint(robot["name"])
    kept = {kf.frame_index for kf in state.tracking.map.keyframes}
    return len(set(robot["robot"].get("acknowledged", [])) - kept)


def run(name: str, workers: int, kill_at: float | None, rate: str, work: Path,
        coordination: bool = True) -> dict[str, Any]:
    sources = [f"{SEVEN_SCENES}:{piece}" for piece in PIECES]
    total = sum(int(p.split("-")[1]) - int(p.split("-")[0]) + 1 for p in PIECES)
    killer = Killer(kill_at, total) if kill_at is not None else None
    out = work / name.replace(" ", "_").replace(",", "")
    print(f"{name}: {len(sources)} robots at {rate} fps ...", flush=True)
    summary = run_demo(sources, out, "3", None, link_args=["--rate", rate],
                       show_progress=False, workers=workers, watch=killer,
                       coordination=coordination)
    robots = {}
    with stored_run(out) as store:  # with etcd (2 workers): the checkpoints it names
        lost = {r["name"]: acknowledged_lost(store, r) for r in summary["robots"]}
    for r in summary["robots"]:
        report = r["robot"]
        robots[r["name"]] = {
            "frames_sent": report["frames"], "frames_tracked": r["frames"],
            "keyframes": r["keyframes"], "acknowledged": len(report.get("acknowledged", [])),
            "acknowledged_lost": lost[r["name"]],
            "takeovers": report.get("takeovers", 0),
            "pause_s": report.get("longest_feedback_gap_s"),
            "lost_frames": r["lost_frames"], "relocalised": r["loop_closing"].get(
                "relocalisations"),
            "ate_cm": 100 * r["ate"]["rmse_m"] if r.get("ate") else None}
    joint = ((summary.get("merge") or {}).get("evaluation") or {}).get("joint_ate")
    return {"workers": workers, "killed": killer.killed if killer else None,
            "robots": robots, "joint_ate_cm": 100 * joint["rmse_m"] if joint else None,
            "wall_time_s": summary["wall_time_s"], "out": str(out)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", default="10", help="each robot's frames per second")
    parser.add_argument("--kill-at", type=float, default=0.4,
                        help="kill when the robots have sent this share of their frames")
    parser.add_argument("--runs", type=int, default=1, help="repeat every setting")
    parser.add_argument("--placement", default="etcd",
                        help="comma list of etcd, liveliness: how the workers agree on robots "
                             "(each worker setting is run with each, alternating)")
    parser.add_argument("--out", default="bench/results/failover.json")
    args = parser.parse_args()
    if not SEVEN_SCENES.exists():
        sys.exit(f"{SEVEN_SCENES} missing: this benchmark needs ../shared/data")
    out = Path(args.out)
    work = out.parent / "failover-runs" / time.strftime("%Y%m%d-%H%M%S")
    results: list[tuple[str, dict]] = []
    placements = [p for p in args.placement.split(",") if p]
    if not placements or not set(placements) <= {"etcd", "liveliness"}:
        sys.exit(f"--placement {args.placement}: give etcd, liveliness or both")
    for i in range(args.runs):
        settings = [("1 cloud", 1, None, True)] + [
            (f"2 workers{', kill' if kill else ''}, {p}", 2, kill, p == "etcd")
            for kill in (None, args.kill_at) for p in placements]
        for name, workers, kill, fenced in settings:
            results.append((name, run(f"{name} {i}", workers, kill, args.rate, work, fenced)))
    rows = []
    for name, r in results:
        victims = set((r["killed"] or {}).get("robots", []))
        for robot, v in r["robots"].items():
            rows.append([name, robot, "yes" if robot in victims else "", v["frames_sent"],
                         v["frames_tracked"], v["keyframes"], v["acknowledged"],
                         v["acknowledged_lost"], v["takeovers"], v["pause_s"], v["ate_cm"],
                         r["joint_ate_cm"]])
    print(format_table(["setting", "robot", "its worker killed", "frames sent",
                        "frames tracked", "keyframes", "KF acked", "acked KF lost",
                        "takeovers", "longest pause s", "ATE cm", "joint ATE cm"], rows))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rate": args.rate, "pieces": PIECES,
                               "results": [{"setting": n, **r} for n, r in results]},
                              indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
