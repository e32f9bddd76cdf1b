"""Does a weak robot stay real-time? (issue 47, item 3) The robot's own CPU per frame at
offloading point 3 (it runs the front end: ORB extraction, description, depth; the cloud
tracks), with the robot process pinned to one core of this machine and held to a quarter
of that core (a CPU cgroup's quota: a stand-in for a Raspberry-Pi-class CPU).

    PYTHONPATH=src .venv/bin/python bench/robot_cpu.py [--frames 300] [--rates 10]
        [--settings one-core,quarter-core] [--cameras files,bag] [--repeat 3] [--core 1]
        [--cloud-core 0] [--json bench/results/robot_cpu.json]

One cloud process (pinned to ``--cloud-core``) serves every run; each run is one robot
process (a new id) playing 7-Scenes redkitchen ``0..frames-1`` as a live camera at
``--rates`` fps (``robot --live --rate N``: frames come on the camera's clock and the robot
takes the newest, counting those it had no time for: ``camera_skipped``). The camera's
frames come from (``--cameras``) ``files``: the recording's own JPEG and PNG files, decoded
by the robot's camera thread as it plays them; ``bag``: the same frames written once, before
the runs, as a ROS 2 bag of raw images (rgb8, 16UC1 millimetres: what a RealSense's or a
Kinect's ROS 2 driver publishes, and near what pyrealsense2 hands over), so the robot pays
what a real camera's frames cost it, not a file format's decoding. Settings and cameras
alternate within each of ``--repeat`` rounds, so they see the same machine. Per run:
- CPU ms per frame, median and p95: the robot report's ``frame_cpu_ms`` (the main thread's
  CPU time for the stages and the message's encoding, per frame sent);
- the process's CPU ms per frame sent while streaming (``streaming_cpu_s``: image decoding
  by the camera thread, the link and keyframe uploads too), and its total CPU seconds from
  the start of the process to its end (``wait4`` resource usage: imports and the end too);
- frames sent; skipped by the robot while it streamed (camera_skipped less
  camera_skipped_at_start, the frames the camera delivered while the robot connected and
  said hello); dropped by the camera thread (decoded too late); the rate achieved (frames
  sent / streaming seconds); the seconds the cgroup held the robot back (throttled);
- the budget: a frame every 1/rate s on ``share`` of a core is 1000 / rate * share ms CPU.
A quarter core that cannot be set up (no writable cgroup v1 cpu controller) is said, and
that setting is not run (never measured as something else). Benches are not tests.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import bag_writer
import numpy as np
from shared_data import SEVEN_SCENES

from fleetslam.datasets.recording import open_source
from fleetslam.launch import CloudClient, free_endpoint, start_cloud, start_robot, stop
from fleetslam.tables import format_table

CGROUP_ROOT = Path("/sys/fs/cgroup/cpu")
PERIOD_US = 100_000
SHARES = {"one-core": 1.0, "quarter-core": 0.25}
CAMERAS = ("files", "bag")
ROBOT_TIMEOUT_S = 900.0


class CpuGroup:
    """A cgroup v1 CPU group holding its processes to ``share`` of one core."""

    def __init__(self, share: float) -> None:
        self.path = CGROUP_ROOT / f"fleetslam-robot-cpu-{os.getpid()}"
        self.path.mkdir()
        try:
            (self.path / "cpu.cfs_period_us").write_text(str(PERIOD_US))
            (self.path / "cpu.cfs_quota_us").write_text(str(int(PERIOD_US * share)))
        except OSError:
            self.path.rmdir()
            raise

    def join(self) -> None:
        """In the child, before the robot starts: this process (and its threads) in the group."""
        (self.path / "cgroup.procs").write_text(str(os.getpid()))

    def throttled(self) -> dict[str, int]:
        """The quota's counters (cumulative): periods, throttled periods, throttled ns."""
        stat = dict(line.split() for line in (self.path / "cpu.stat").read_text().splitlines())
        return {k: int(v) for k, v in stat.items()}

    def remove(self) -> None:
        # A group can be removed once its processes are gone (the robot was reaped).
        for _ in range(50):
            try:
                self.path.rmdir()
                return
            except OSError:
                time.sleep(0.1)
        print(f"could not remove {self.path}: remove it by hand (rmdir)", file=sys.stderr)


def make_group(share: float) -> tuple[CpuGroup | None, str | None]:
    """The group, or why it cannot be made here."""
    if not (CGROUP_ROOT / "cpu.cfs_quota_us").exists():
        return None, f"{CGROUP_ROOT} is not a cgroup v1 cpu controller"
    try:
        return CpuGroup(share), None
    except OSError as exc:
        return None, f"cannot make a cpu cgroup under {CGROUP_ROOT}: {exc}"


def pre_exec(core: int, group: CpuGroup | None) -> Callable[[], None]:
    """What the robot's child process does before it starts: its core, its group."""
    def setup() -> None:
        os.sched_setaffinity(0, {core})
        if group is not None:
            group.join()
    return setup


def wait_reaped(proc: subprocess.Popen, timeout_s: float) -> tuple[int, float]:
    """(exit code, CPU seconds user + system of the whole process) once it ends."""
    deadline = time.monotonic() + timeout_s
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            return proc.returncode, usage.ru_utime + usage.ru_stime
        if time.monotonic() > deadline:
            proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + 30.0
        time.sleep(0.2)


def camera_bag(frames: int, folder: Path) -> Path:
    """redkitchen's frames 0..frames-1 as a bag of raw camera topics in ``folder``."""
    path = folder / "redkitchen-raw"
    start = time.perf_counter()
    bag_writer.write_bag(path, "mcap", bag_writer.recording_messages(
        open_source(str(SEVEN_SCENES)), "mcap", frames, depth="16UC1"))
    print(f"wrote {path} ({frames} frames of raw images) in "
          f"{time.perf_counter() - start:.1f} s", flush=True)
    return path


def run_robot(endpoint: str, robot_id: str, source: str, rate: float, core: int,
              group: CpuGroup | None, work: Path) -> dict[str, Any]:
    """One robot run; its measurements."""
    report_path = work / f"{robot_id}.json"
    before = group.throttled() if group is not None else None
    proc = start_robot(endpoint, robot_id, source, 3,
                       work / f"{robot_id}.log", report_path,
                       extra=["--live", "--rate", f"{rate:g}"], pre_exec=pre_exec(core, group))
    code, cpu_total_s = wait_reaped(proc, ROBOT_TIMEOUT_S)
    if code != 0 or not report_path.exists():
        tail = (work / f"{robot_id}.log").read_text()[-2000:]
        raise RuntimeError(f"robot {robot_id} exited {code}:\n{tail}")
    after = group.throttled() if group is not None else None
    return measure(json.loads(report_path.read_text()), cpu_total_s, before, after)


def measure(r: dict[str, Any], cpu_total_s: float, before: dict[str, int] | None,
            after: dict[str, int] | None) -> dict[str, Any]:
    """What one robot report says about its CPU and its pace."""
    cpu = np.asarray(r["frame_cpu_ms"], float)
    sent = r["frames"]
    stages = dict(r["robot_stage_ms"])
    return {
        "frames_sent": sent, "camera_skipped": r["camera_skipped"],
        # Skipped while it streamed: those before its first frame were its start's.
        "skipped_streaming": r["camera_skipped"] - r["camera_skipped_at_start"],
        "skipped_at_start": r["camera_skipped_at_start"],
        "camera_late": r["camera_undelivered"], "frames_skipped": r["frames_skipped"],
        "camera_delivered": r["camera_delivered"],
        "achieved_fps": sent / r["streaming_s"] if r["streaming_s"] else None,
        "cpu_ms_median": float(np.median(cpu)), "cpu_ms_p95": float(np.percentile(cpu, 95)),
        "cpu_ms_mean": float(cpu.mean()),
        "wall_ms_mean": 1000.0 * r["robot_compute_s"] / sent,
        "process_cpu_ms_per_frame": 1000.0 * r["streaming_cpu_s"] / sent,
        "process_cpu_s_total": cpu_total_s, "streaming_s": r["streaming_s"],
        "encode_ms_mean": r["encode_ms_mean"], "encode_ms_p95": r["encode_ms_p95"],
        "robot_stage_ms": stages, "flow_wait_s": r["flow_wait_s"],
        "keyframes": r["keyframes"],
        "throttled_periods": None if before is None
        else after["nr_throttled"] - before["nr_throttled"],
        "throttled_s": None if before is None
        else (after["throttled_time"] - before["throttled_time"]) / 1e9,
    }


def run_setting(name: str, rate: float, camera: str, source: str, args: argparse.Namespace,
                endpoint: str, n: int, work: Path) -> dict[str, Any] | str:
    """One run of one setting with one camera (``source``), or why it cannot run here."""
    group = None
    if SHARES[name] < 1.0:
        group, why = make_group(SHARES[name])
        if group is None:
            print(f"{name}: not measured: {why}", flush=True)
            return why
    try:
        result = run_robot(endpoint, f"r{n}", source, rate, args.core, group, work)
    finally:
        if group is not None:
            group.remove()
    result.update(setting=name, camera=camera, rate=rate, share=SHARES[name],
                  budget_cpu_ms=1000.0 / rate * SHARES[name])
    result["keeps_up"] = result["skipped_streaming"] == 0 and result["camera_late"] == 0
    print(f"  {name}, {camera}, at {rate:g} fps: {result['cpu_ms_median']:.1f} ms CPU/frame median, "
          f"{result['skipped_streaming']} skipped streaming ({result['skipped_at_start']} at "
          f"start), {result['achieved_fps']:.2f} fps", flush=True)
    return result


def spread(values: list[float], fmt: str = "{:.1f}") -> str:
    lo, hi = min(values), max(values)
    return fmt.format(lo) if fmt.format(lo) == fmt.format(hi) else \
        f"{fmt.format(lo)}-{fmt.format(hi)}"


def print_tables(runs: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per run, then min-max per setting and rate (returned for the JSON)."""
    cols = ["setting", "camera", "fps", "run", "sent", "skipped", "at start", "late", "achieved fps",
            "CPU ms/frame median", "p95", "budget ms", "process CPU ms/frame",
            "process CPU s", "throttled s"]
    rows, groups = [], {}
    for r in runs:
        key = f"{r['setting']}, {r['camera']} @ {r['rate']:g} fps"
        groups.setdefault(key, []).append(r)
        rows.append([r["setting"], r["camera"], f"{r['rate']:g}", r["round"], r["frames_sent"],
                     r["skipped_streaming"], r["skipped_at_start"], r["camera_late"],
                     round(r["achieved_fps"], 2),
                     round(r["cpu_ms_median"], 1), round(r["cpu_ms_p95"], 1),
                     round(r["budget_cpu_ms"], 1), round(r["process_cpu_ms_per_frame"], 1),
                     round(r["process_cpu_s_total"], 1),
                     "-" if r["throttled_s"] is None else round(r["throttled_s"], 1)])
    print(format_table(cols, rows))
    summary = {key: summarise(rs) for key, rs in groups.items()}
    rows = [[key, s["runs"], s["skipped"], s["late"], s["achieved_fps"], s["cpu_ms_median"],
             s["cpu_ms_p95"], s["budget_cpu_ms"], s["process_cpu_ms_per_frame"],
             s["keeps_up"], s["top_stages_ms"]] for key, s in summary.items()]
    print(format_table(["setting", "runs", "skipped", "late", "achieved fps",
                        "CPU ms/frame median", "p95", "budget ms", "process CPU ms/frame",
                        "kept up", "costliest stages ms (wall, mean)"], rows))
    return summary


def summarise(rs: list[dict[str, Any]]) -> dict[str, Any]:
    """Min-max over the runs of one setting and rate."""
    stages: dict[str, list[float]] = {}
    for r in rs:
        for name, ms in r["robot_stage_ms"].items():
            stages.setdefault(name, []).append(ms)
    top = sorted(stages, key=lambda s: -float(np.mean(stages[s])))[:3]
    return {"runs": len(rs),
            "skipped": spread([r["skipped_streaming"] for r in rs], "{:.0f}"),
            "late": spread([r["camera_late"] for r in rs], "{:.0f}"),
            "achieved_fps": spread([r["achieved_fps"] for r in rs], "{:.2f}"),
            "cpu_ms_median": spread([r["cpu_ms_median"] for r in rs]),
            "cpu_ms_p95": spread([r["cpu_ms_p95"] for r in rs]),
            "budget_cpu_ms": f"{rs[0]['budget_cpu_ms']:.0f}",
            "process_cpu_ms_per_frame": spread([r["process_cpu_ms_per_frame"] for r in rs]),
            "keeps_up": f"{sum(r['keeps_up'] for r in rs)}/{len(rs)}",
            "top_stages_ms": ", ".join(f"{s} {spread(stages[s])}" for s in top)}


def other_load() -> dict[str, Any]:
    """What else the machine ran: its load averages and the busiest other processes."""
    out = subprocess.run(["ps", "-eo", "pid,pcpu,etime,args", "--sort=-pcpu"],
                         capture_output=True, text=True).stdout.splitlines()
    return {"loadavg": Path("/proc/loadavg").read_text().split()[:3],
            "busiest": [line[:160] for line in out[1:8]]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300, help="redkitchen frames 0..N-1")
    parser.add_argument("--rates", default="10", help="camera rates, fps, comma-separated")
    parser.add_argument("--settings", default="one-core,quarter-core",
                        help=f"comma-separated, of {', '.join(SHARES)}")
    parser.add_argument("--cameras", default=",".join(CAMERAS),
                        help=f"comma-separated, of {', '.join(CAMERAS)} (module docstring)")
    parser.add_argument("--repeat", type=int, default=3, help="rounds of every setting")
    parser.add_argument("--core", type=int, default=1, help="the core the robot runs on")
    parser.add_argument("--cloud-core", type=int, default=0, help="the core of the cloud")
    parser.add_argument("--json", default=str(Path(__file__).parent / "results" /
                                              "robot_cpu.json"), help="write results here")
    args = parser.parse_args()
    settings = [s for s in args.settings.split(",") if s]
    if not settings or not set(settings) <= set(SHARES):
        sys.exit(f"--settings {args.settings}: give one or more of {', '.join(SHARES)}")
    cameras = [c for c in args.cameras.split(",") if c]
    if not cameras or not set(cameras) <= set(CAMERAS):
        sys.exit(f"--cameras {args.cameras}: give one or more of {', '.join(CAMERAS)}")
    try:
        rates = [float(x) for x in args.rates.split(",") if x]
    except ValueError:
        sys.exit(f"--rates {args.rates}: frames per second, comma-separated")
    if not rates or min(rates) <= 0:
        sys.exit(f"--rates {args.rates}: frames per second > 0")
    if not 1 <= args.frames <= 600:
        sys.exit(f"--frames {args.frames}: redkitchen has 600 frames")
    if args.core not in os.sched_getaffinity(0) or args.cloud_core not in os.sched_getaffinity(0):
        sys.exit(f"--core {args.core} / --cloud-core {args.cloud_core}: this machine's cores "
                 f"are {sorted(os.sched_getaffinity(0))}")
    if not SEVEN_SCENES.exists():
        sys.exit(f"{SEVEN_SCENES} missing: this benchmark needs ../shared/data")
    results = measure_all(args, settings, rates, cameras)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(f"wrote {out}")


def measure_all(args: argparse.Namespace, settings: list[str], rates: list[float],
                cameras: list[str]) -> dict[str, Any]:
    """Every round of every setting, rate and camera against one cloud; the JSON's content."""
    work = Path(__file__).parent / "results" / "robot-cpu-runs" / time.strftime("%Y%m%d-%H%M%S")
    bag_folder = Path(tempfile.mkdtemp(prefix="robot-cpu-bag-"))
    try:
        sources = {"files": f"{SEVEN_SCENES}:0-{args.frames - 1}"}
        if "bag" in cameras:
            sources["bag"] = str(camera_bag(args.frames, bag_folder))
        return measure_with(args, settings, rates, cameras, sources, work)
    finally:
        shutil.rmtree(bag_folder, ignore_errors=True)


def measure_with(args: argparse.Namespace, settings: list[str], rates: list[float],
                 cameras: list[str], sources: dict[str, str], work: Path) -> dict[str, Any]:
    endpoint = free_endpoint()
    cloud = start_cloud(endpoint, work / "cloud", work / "cloud.log")
    os.sched_setaffinity(cloud.pid, {args.cloud_core})  # its threads inherit it
    # Ready before the first robot: a cloud starting would count in that robot's start.
    client = CloudClient(endpoint, reach_deadline_s=120.0)
    client.status(timeout=120.0, gather_s=0.2)
    client.close()
    load_before = other_load()
    runs: list[dict[str, Any]] = []
    not_run: dict[str, str] = {}
    n = 0
    try:
        for round_ in range(1, args.repeat + 1):
            for rate in rates:
                for name in settings:
                    for camera in cameras:
                        result = run_setting(name, rate, camera, sources[camera], args,
                                             endpoint, n, work)
                        n += 1
                        if isinstance(result, str):
                            not_run[name] = result
                            continue
                        runs.append({**result, "round": round_})
    finally:
        stop(cloud)
    summary = print_tables(runs) if runs else {}
    for name, why in not_run.items():
        print(f"{name}: not measured: {why}")
    return {"frames": args.frames, "rates": rates, "cameras": cameras, "core": args.core,
            "cloud_core": args.cloud_core, "cores": os.cpu_count(),
            "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"],
                                     capture_output=True, text=True).stdout.strip(),
            "other_load_before": load_before, "other_load_after": other_load(),
            "not_run": not_run, "summary": summary, "runs": runs}


if __name__ == "__main__":
    main()
