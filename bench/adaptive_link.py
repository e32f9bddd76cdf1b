"""A robot that re-plans as its link changes, against a fixed point 3, over the same trace.

    .venv/bin/python bench/adaptive_link.py [--trace 0:10,300:1,700:10] [--out bench/results/adaptive_link.json]

1000 real frames (7-Scenes redkitchen 0-599 and back to 199), sent as fast as stages and
link allow, over an emulated link whose bandwidth follows the trace (default: 10 Mbit/s,
1 Mbit/s from frame 300, 10 again from frame 700). Each run is a real cloud process and a
real robot process over Zenoh. The adaptive robot (--offload-at auto) measures its link and
re-plans its split point, ORB features and frame step; the fixed robot stays at point 3.
Reported per run: total time (first frame sent -> the cloud's map built), frames sent and
skipped, tracking losses (frames the cloud could not track), ATE of the cloud's trajectory
(scored afterwards), bytes; and a PNG of what the adaptive robot measured and chose.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

from shared_data import SEVEN_SCENES  # noqa: E402

from fleetslam.datasets.recording import open_source  # noqa: E402
from fleetslam.evaluation.fleet import trajectory_ate  # noqa: E402
from fleetslam.launch import free_endpoint, start_cloud, start_robot, stop  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402

SOURCE = f"{SEVEN_SCENES}:0-599,598-199"


def run(label: str, offload_at: str, trace: str, out: Path, timeout_s: float) -> dict[str, Any]:
    folder = out / label
    endpoint = free_endpoint()
    cloud = start_cloud(endpoint, folder / "cloud", folder / "cloud.log")
    try:
        time.sleep(1.0)
        report_path = folder / "robot.json"
        robot = start_robot(endpoint, "r0", SOURCE, offload_at, folder / "robot.log",
                            report_path, extra=["--link-trace", trace])
        try:
            code = robot.wait(timeout_s)
        except Exception:
            stop(robot, 2.0)
            raise
        if code != 0:
            raise RuntimeError(f"{label}: robot exit {code}; see {folder / 'robot.log'}")
    finally:
        stop(cloud)
    report = json.loads(report_path.read_text())
    cloud_robot = json.loads((folder / "cloud" / "r0" / "robot.json").read_text())
    ate = trajectory_ate(folder / "cloud" / "r0" / "trajectory.tum", open_source(SOURCE))
    return {
        "label": label, "offload_at": offload_at, "total_s": report["total_s"],
        "streaming_s": report["streaming_s"], "frames_sent": report["frames"],
        "frames_skipped": report["frames_skipped"], "frames_lost_on_link":
        report["frames_lost_on_link"], "tracking_losses": cloud_robot["lost_frames"],
        "loss_events": cloud_robot["loss_events"], "keyframes": report["keyframes"],
        "frame_kb": report["frame_bytes"] / max(report["frames"], 1) / 1000,
        "keyframe_mb": report["keyframe_bytes"] / 1e6,
        "frames_per_point": report["frames_per_point"], "ate": ate,
        "plan_history": report["plan_history"],
    }


def plot(adaptive: dict[str, Any], trace: list[tuple[int, float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = adaptive["plan_history"]
    frames = [r["frame"] for r in h]
    fig, axes = plt.subplots(4, 1, figsize=(7, 7.5), sharex=True)
    steps = [f for f, _ in trace] + [1000]
    axes[0].step(steps, [b for _, b in trace] + [trace[-1][1]], where="post",
                 label="emulated link", color="grey")
    axes[0].plot(frames, [r["measured_mbps"] for r in h], "o-", label="measured by the robot")
    axes[0].set_ylabel("Mbit/s")
    axes[0].set_yscale("log")
    axes[0].legend(fontsize=7)
    for ax, key, label in ((axes[1], "k", "split point k"), (axes[2], "features", "ORB features"),
                           (axes[3], "frame_step", "frame step")):
        ax.step(frames, [r[key] for r in h], where="post", marker="o")
        ax.set_ylabel(label)
    axes[3].set_xlabel("frame")
    axes[0].set_title("adaptive robot: measured link and its choices (re-planned every "
                      f"{frames[1] - frames[0] if len(frames) > 1 else '?'} frames)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    from fleetslam.transport.link import parse_link_trace

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trace", default="0:10,300:1,700:10")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "adaptive_link.json"))
    parser.add_argument("--runs", default=str(Path("/tmp") / "fleetslam-adaptive-link"))
    parser.add_argument("--timeout", type=float, default=1800.0)
    args = parser.parse_args()
    trace = parse_link_trace(args.trace)
    runs = Path(args.runs) / time.strftime("%Y%m%d-%H%M%S")
    results = [run("fixed-3", "3", args.trace, runs, args.timeout),
               run("adaptive", "auto", args.trace, runs, args.timeout)]
    rows = [[r["label"], r["total_s"], r["frames_sent"], r["frames_skipped"],
             r["tracking_losses"], r["loss_events"], r["frames_lost_on_link"],
             r["ate"]["rmse_m"] * 100 if r["ate"] else None, r["frame_kb"], r["keyframe_mb"],
             " ".join(f"k{k}:{n}" for k, n in sorted(r["frames_per_point"].items()))]
            for r in results]
    print(f"trace {args.trace} (frame:Mbit/s), source {SOURCE}")
    print(format_table(["run", "total s", "sent", "skipped", "lost (tracking)", "loss events",
                        "lost on link", "ATE cm", "kB/frame", "keyframes MB", "frames per point"],
                       rows))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    png = out.with_suffix(".png")
    plot(results[1], trace, png)
    out.write_text(json.dumps({"trace": args.trace, "source": SOURCE, "runs": results},
                              indent=2))
    print(f"wrote {out} and {png}")


if __name__ == "__main__":
    main()
