"""A live camera the robot cannot keep up with: memory stays flat, frames are skipped and
counted, tracking goes on.

    .venv/bin/python bench/live_replay.py [--frames 1000] [--fps 30] [--point 0] [--mbps 30]

A cloud process and a robot process (``fleetslam robot --live --rate FPS``): the 7-Scenes
frames (1000 = 0-599 then back 598-199) replayed as a camera at FPS, whether or not the
robot takes them, through an emulated link of MBPS at offloading point POINT (point 0 sends
the whole RGB-D frame, so a 30 Mbit/s link carries about 6 a second: the robot is slower
than its camera). The robot process's RSS is sampled every 0.5 s. Prints: frames delivered
by the camera / taken by the robot / skipped (replaced by a newer one while the robot was
busy) / never delivered (the replay decoded too late), RSS at start, median, max, at a
third of the run and at its end; what the cloud tracked (frames, lost) and the ATE against
ground truth (read after the run, evaluation only). Writes bench/results/live_replay.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import psutil

from fleetslam.datasets.recording import open_source
from fleetslam.evaluation.fleet import trajectory_ate
from fleetslam.launch import free_endpoint, start_cloud, start_robot, stop
from fleetslam.tables import format_table
from shared_data import SEVEN_SCENES

SAMPLE_S = 0.5
ROBOT_TIMEOUT_S = 1200.0


def source_spec(frames: int) -> str:
    """``frames`` frames of the 600-frame sequence: forward, then back along the same path."""
    if frames <= 600:
        return f"{SEVEN_SCENES}:0-{frames - 1}"
    if frames > 1199:
        raise ValueError("at most 1199 frames (600 forward, 599 back)")
    return f"{SEVEN_SCENES}:0-599,598-{598 - (frames - 601)}"


def sample_rss(pid: int, robot, deadline: float) -> list[tuple[float, float]]:
    """(seconds since start, RSS MB) of process ``pid`` every SAMPLE_S until it exits."""
    process, start, samples = psutil.Process(pid), time.monotonic(), []
    while robot.poll() is None:
        if time.monotonic() > deadline:
            robot.kill()
            raise RuntimeError(f"the robot did not finish in {ROBOT_TIMEOUT_S:.0f} s")
        try:
            samples.append((time.monotonic() - start, process.memory_info().rss / 2 ** 20))
        except psutil.NoSuchProcess:
            break
        time.sleep(SAMPLE_S)
    return samples


def run(frames: int, fps: float, point: int, mbps: float, work: Path) -> dict:
    spec = source_spec(frames)
    endpoint, out = free_endpoint(), work / "cloud"
    cloud = start_cloud(endpoint, out, work / "cloud.log")
    report_path = work / "robot.json"
    try:
        robot = start_robot(endpoint, "r0", spec, point, work / "robot.log", report_path,
                            extra=["--live", "--rate", f"{fps:g}", "--bandwidth-mbps",
                                   f"{mbps:g}"])
        samples = sample_rss(robot.pid, robot, time.monotonic() + ROBOT_TIMEOUT_S)
        if robot.wait() != 0:
            raise RuntimeError(f"the robot failed; see {work / 'robot.log'}")
    finally:
        stop(cloud)
    r = json.loads(report_path.read_text())
    entry = json.loads((out / "r0" / "robot.json").read_text())
    ate = trajectory_ate(out / "r0" / "trajectory.tum", open_source(spec))
    # RSS while frames streamed, not while the process imported or waited for the map: the
    # report's times count from the first frame taken to the cloud's end.
    first = samples[-1][0] - r["total_s"] if samples else 0.0
    streaming = [mb for t, mb in samples if first <= t <= first + r["streaming_s"]] or [0.0]
    third = streaming[len(streaming) // 3]
    return {
        "frames": frames, "fps": fps, "point": point, "mbps": mbps,
        "camera_delivered": r["camera_delivered"], "camera_taken": r["camera_taken"],
        "camera_skipped": r["camera_skipped"], "never_delivered": frames - r["camera_delivered"],
        "robot_fps": r["camera_taken"] / r["streaming_s"] if r["streaming_s"] else None,
        "streaming_s": r["streaming_s"], "total_s": r["total_s"],
        "rss_mb_start": streaming[0], "rss_mb_third": third, "rss_mb_end": streaming[-1],
        "rss_mb_median": statistics.median(streaming), "rss_mb_max": max(streaming),
        "rss_samples": samples,
        "cloud_frames": entry["frames"], "cloud_lost": entry["lost_frames"],
        "cloud_tracked": entry["frames"] - entry["lost_frames"],
        "summary_live_camera": entry.get("live_camera"),
        "keyframes": entry["keyframes"], "keyframes_without_images":
            entry.get("keyframes_without_images"),
        "ate_rmse_cm": None if ate is None else ate["rmse_m"] * 100,
        "load_average_after": list(os.getloadavg()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--point", type=int, default=0)
    parser.add_argument("--mbps", type=float, default=30.0)
    args = parser.parse_args()
    results = Path(__file__).resolve().parent / "results"
    work = results / f"live_replay-{time.strftime('%Y%m%d-%H%M%S')}"
    work.mkdir(parents=True)
    load_before = list(os.getloadavg())
    row = run(args.frames, args.fps, args.point, args.mbps, work)
    row["load_average_before"] = load_before
    print(format_table(
        ["frames", "camera fps", "delivered", "taken", "skipped", "never delivered",
         "robot fps"],
        [[row["frames"], row["fps"], row["camera_delivered"], row["camera_taken"],
          row["camera_skipped"], row["never_delivered"], row["robot_fps"]]]))
    print(format_table(
        ["RSS MB start", "at 1/3", "end", "median", "max"],
        [[row["rss_mb_start"], row["rss_mb_third"], row["rss_mb_end"], row["rss_mb_median"],
          row["rss_mb_max"]]]))
    print(format_table(
        ["cloud frames", "tracked", "lost", "keyframes", "KF without images", "ATE cm"],
        [[row["cloud_frames"], row["cloud_tracked"], row["cloud_lost"], row["keyframes"],
          row["keyframes_without_images"], row["ate_rmse_cm"]]]))
    print(f"\nload average (1, 5, 15 min) before {load_before}, after "
          f"{row['load_average_after']} (a shared 2-core machine)")
    (results / "live_replay.json").write_text(json.dumps(row, indent=2))
    print(f"\nwrote {results / 'live_replay.json'} (logs in {work})")


if __name__ == "__main__":
    main()
