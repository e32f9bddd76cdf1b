"""How fast a robot's pose reaches its ROS 2 graph (``fleetslam robot --ros2-out``).

    .venv/bin/python bench/ros2_out.py [--frames 300] [--runs 2] [--links 0:0,10:20]

A cloud process and a robot process (``--rate recorded``: the 7-Scenes frames at their own
30 fps, as a camera gives them) over an emulated link per ``--links`` (MBPS:LATENCY_MS; 0:0
is loopback unlimited), the robot publishing to a Zenoh router in this process that stands
in for rmw_zenohd, where a plain Zenoh subscriber on ``/r0/pose``'s key notes when each pose
arrives. Per pose, all on this machine's clock (time.time_ns):

- feedback -> put: the cloud's feedback heard by the robot -> its PoseStamped put on Zenoh
  (the robot's report);
- feedback -> on ROS 2: -> the subscriber on the router has it (target p95 <= 5 ms);
- capture -> on ROS 2: the robot took the frame from its source -> the subscriber has its
  pose (target: within the link's round trip + 5 ms; the round trip is the robot's, sent ->
  feedback, so capture -> on ROS 2 also holds the frame's encoding and its wait for the link).

Prints median and p95 per link and run, min-max over runs; writes bench/results/ros2_out.json.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from pathlib import Path

import numpy as np

from fleetslam.launch import free_endpoint, start_cloud, start_robot, stop
from fleetslam.tables import format_table
from fleetslam.transport.zenoh_session import open_connecting, open_router
from shared_data import SEVEN_SCENES

ROBOT_TIMEOUT_S = 600.0


def percentiles(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    return float(np.median(values)), float(np.percentile(values, 95))


def run(frames: int, mbps: float, latency_ms: float, work: Path) -> dict:
    from fleetslam.datasets.rmw_zenoh import parse_attachment, topic_key
    from fleetslam.ros2_out.cdr import CdrReader

    ros_graph, cloud_endpoint = free_endpoint(), free_endpoint()
    router = open_router(ros_graph)
    listener = open_connecting(ros_graph, 10.0)
    arrivals: dict[int, int] = {}  # the pose's stamp (ns) -> when it arrived
    sources: dict[int, int] = {}  # the pose's stamp -> its attachment's source time
    lock = threading.Lock()

    def on_pose(sample) -> None:
        now = time.time_ns()
        r = CdrReader(sample.payload.to_bytes(), "/r0/pose")
        sec, nanosec = r.unpack("iI")
        with lock:
            arrivals[sec * 1_000_000_000 + nanosec] = now
            sources[sec * 1_000_000_000 + nanosec] = parse_attachment(
                sample.attachment.to_bytes()).source_timestamp_ns

    sub = listener.declare_subscriber(topic_key(0, "/r0/pose"), on_pose)
    cloud = start_cloud(cloud_endpoint, work / "cloud", work / "cloud.log")
    report_path = work / "robot.json"
    try:
        robot = start_robot(cloud_endpoint, "r0", f"{SEVEN_SCENES}:0-{frames - 1}", 3,
                            work / "robot.log", report_path,
                            extra=["--rate", "recorded", "--ros2-out", ros_graph,
                                   "--bandwidth-mbps", f"{mbps:g}", "--latency-ms",
                                   f"{latency_ms:g}"])
        if robot.wait(ROBOT_TIMEOUT_S) != 0:
            raise RuntimeError(f"the robot failed; see {work / 'robot.log'}")
    finally:
        stop(cloud)
        sub.undeclare()
        listener.close()
        router.close()
    report = json.loads(report_path.read_text())
    stamps = [float(line.split()[0]) for line in
              (work / "cloud" / "r0" / "online.tum").read_text().splitlines()
              if line and not line.startswith("#")]
    by_index = {t[0]: t for t in report["ros2_timings"]}
    # The robot's timings are by frame index, the subscriber's by stamp: frame i's stamp is
    # the sequence's i-th (the robot played 0..frames-1 in order).
    from fleetslam.datasets.recording import open_source
    from fleetslam.ros2_out.cdr import stamp_ns

    played = [stamp_ns(t) for t in open_source(f"{SEVEN_SCENES}:0-{frames - 1}").timestamps]
    put_ms, on_ros_ms, capture_ms, hop_ms, coding_ms, trip_ms = [], [], [], [], [], []
    for index, stamp in enumerate(played):
        timing, arrived = by_index.get(index), arrivals.get(stamp)
        if timing is None or arrived is None:
            continue
        _, taken, sent, heard, put = timing
        put_ms.append((put - heard) / 1e6)
        on_ros_ms.append((arrived - heard) / 1e6)
        hop_ms.append((arrived - sources[stamp]) / 1e6)
        if taken is not None and sent is not None:
            capture_ms.append((arrived - taken) / 1e6)
            coding_ms.append((sent - taken) / 1e6)
            trip_ms.append((heard - sent) / 1e6)
    return {
        "frames": frames, "mbps": mbps, "latency_ms": latency_ms,
        "tracked": len(stamps), "poses_on_ros": len(arrivals),
        "feedback_to_put_ms": percentiles(put_ms),
        "feedback_to_ros_ms": percentiles(on_ros_ms),
        "put_to_subscriber_ms": percentiles(hop_ms),
        "capture_to_ros_ms": percentiles(capture_ms),
        # capture -> on ROS 2 = taken -> sent (coding) + sent -> feedback + feedback -> ROS 2
        "taken_to_sent_ms": percentiles(coding_ms),
        "sent_to_feedback_ms": percentiles(trip_ms),
        "round_trip_ms": (report["round_trip_ms_median"], report["round_trip_ms_p95"]),
        "encode_ms": (report["encode_ms_mean"], report["encode_ms_p95"]),
        "load_average_after": list(os.getloadavg()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--links", default="0:0,10:20",
                        help="MBPS:LATENCY_MS,... (0:0 = loopback, unlimited)")
    args = parser.parse_args()
    links = [tuple(float(v) for v in link.split(":")) for link in args.links.split(",")]
    results = Path(__file__).resolve().parent / "results"
    work = results / f"ros2_out-{time.strftime('%Y%m%d-%H%M%S')}"
    load_before = list(os.getloadavg())
    rows = []
    for run_index in range(args.runs):
        for mbps, latency in links:  # alternating: both links see the same machine load
            folder = work / f"run{run_index}-{mbps:g}mbps-{latency:g}ms"
            folder.mkdir(parents=True)
            rows.append(run(args.frames, mbps, latency, folder))

    def ms(pair) -> str:
        return "-" if pair[0] is None else f"{pair[0]:.2f} / {pair[1]:.2f}"

    print(format_table(
        ["link", "tracked", "on ROS 2", "feedback->put", "feedback->ROS 2",
         "capture->ROS 2", "taken->sent", "sent->feedback", "round trip"],
        [[f"{r['mbps']:g} Mbit/s {r['latency_ms']:g} ms" if r["mbps"] else "loopback",
          r["tracked"], r["poses_on_ros"], ms(r["feedback_to_put_ms"]),
          ms(r["feedback_to_ros_ms"]), ms(r["capture_to_ros_ms"]),
          ms(r["taken_to_sent_ms"]), ms(r["sent_to_feedback_ms"]), ms(r["round_trip_ms"])]
         for r in rows]))
    print("(median / p95 ms; targets: feedback->ROS 2 p95 <= 5 ms, capture->ROS 2 within the "
          "round trip + 5 ms)")
    summary = {}
    for mbps, latency in links:
        mine = [r for r in rows if (r["mbps"], r["latency_ms"]) == (mbps, latency)]
        p95 = [r["feedback_to_ros_ms"][1] for r in mine if r["feedback_to_ros_ms"][1]]
        over = [r["capture_to_ros_ms"][1] - r["round_trip_ms"][1] for r in mine
                if r["capture_to_ros_ms"][1] and r["round_trip_ms"][1]]
        summary[f"{mbps:g}:{latency:g}"] = {
            "feedback_to_ros_p95_ms_min_max": [min(p95), max(p95)] if p95 else None,
            "capture_to_ros_p95_minus_round_trip_p95_ms_min_max":
                [min(over), max(over)] if over else None}
    print(json.dumps(summary, indent=1))
    print(f"load average (1, 5, 15 min) before {load_before}, after "
          f"{list(os.getloadavg())} (a shared 2-core machine)")
    out = {"runs": rows, "summary": summary, "load_average_before": load_before}
    (results / "ros2_out.json").write_text(json.dumps(out, indent=2))
    print(f"wrote {results / 'ros2_out.json'} (logs in {work})")


if __name__ == "__main__":
    main()
