"""A long run through real processes: does the cloud's cost per frame stay flat as the map
grows? One robot plays 7-Scenes redkitchen forwards and back (0-599, 598-1, 0-599, ...)
for ``--frames`` frames at offloading point 3 (``--offload-at``) to one cloud process over
Zenoh on loopback.

    .venv/bin/python bench/long_run.py [--frames 5000] [--block 1000] [--rate max]
        [--offload-at 3] [--configs a.toml,b.toml] [--runs N] [--baseline REV]

Sampled every ``--every`` seconds from outside (``status`` and /proc): per block of
``--block`` frames the cloud tracked, the wall time per frame, the cloud's CPU time per
frame (its process and its local-mapping processes), its resident memory at the block's
end, its keyframes, the size of its checkpoint file, and the checkpoints it wrote in the
block with their bytes per checkpoint (new chunks included: the map's log patches and
bases). The last block against the first is the number that matters: the issue's target
is "the last 1000 frames no slower than the first 1000". After the run, the robot's ATE
against ground truth (read only then). ``--configs``: settings files (the
robot and the cloud read them), alternated within each of ``--runs`` rounds, so an A/B sees
the same machine. ``--baseline REV``: the cloud and the robot also run from the code at git
revision REV (its src/ extracted to a temporary folder), alternated with this code within
each round, so a before/after sees the same machine too. Per run also the loop closer's
queries to the worker (summary.json's loop_queries: bytes sent per query, where the code
counts them, and the time from a query's submission to its answer landing), and what the
robot sent: frame and keyframe-upload bytes, and at point 6 its keyframe pose tables (whole
or as deltas: poses sent against those whole tables would carry). Writes
bench/results/long_run.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator
from typing import Any

from shared_data import SEVEN_SCENES

from fleetslam.cloud.coordination.worker_load import tree_cpu_seconds as tree_cpu_s
from fleetslam.datasets.recording import open_source
from fleetslam.evaluation.fleet import score_fleet
from fleetslam.launch import CloudClient, free_endpoint, start_cloud, start_robot, stop_all
from fleetslam.tables import format_table

SEQUENCE_FRAMES = 600


def forth_and_back(frames: int, length: int = SEQUENCE_FRAMES) -> str:
    """Ranges of a ``length``-frame recording played forwards and back until ``frames``:
    0-599, 598-1, 0-599, ... (no frame twice in a row at a turn), the last one cut."""
    ranges, left, forward = [], frames, True
    while left > 0:
        a, b = (0, length - 1) if forward else (length - 2, 1)
        n = min(left, abs(b - a) + 1)
        b = a + n - 1 if forward else a - n + 1
        ranges.append(f"{a}-{b}")
        left -= n
        forward = not forward
    return ",".join(ranges)


def tree_rss_mb(pid: int) -> float:
    """Resident memory of ``pid`` and its children (MB, Linux /proc)."""
    total = 0.0
    pids = [pid]
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    pids.append(int(entry.name))
            except OSError:
                continue
    for p in pids:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024
        except OSError:
            continue
    return total


def checkpoint_writes(robot_status: dict[str, Any] | None) -> dict[str, int]:
    """The checkpoints the cloud wrote for the robot so far and their bytes, new chunks
    included (the status has them since the map's arrays became logs; 0 before)."""
    robot_status = robot_status or {}
    return {"checkpoints": robot_status.get("checkpoints", 0),
            "checkpoint_bytes": robot_status.get("checkpoint_bytes", 0)}


def checkpoint_kb(out: Path) -> float:
    """The size of the robot's checkpoint as last written (kB; its chunks, written once
    each, not counted): what every checkpoint write costs at that point of the run."""
    path = out / "r0" / "session.ckpt"
    try:
        return path.stat().st_size / 1000
    except OSError:
        return 0.0


@contextmanager
def code_from(src: Path | None) -> Iterator[None]:
    """The processes started meanwhile import fleetslam from ``src`` (None: this code)."""
    before = os.environ.get("PYTHONPATH")
    if src is not None:
        os.environ["PYTHONPATH"] = str(src)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = before


def extract_src(revision: str, into: Path) -> Path:
    """The src/ folder of git revision ``revision`` of this repository, under ``into``."""
    root = Path(__file__).resolve().parents[1]
    archive = subprocess.run(["git", "-C", str(root), "archive", revision, "src"],
                             check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into / "src"


def run(frames: int, block: int, rate: str, every_s: float, work: Path,
        config_path: Path | None = None, src: Path | None = None, point: int = 3
        ) -> dict[str, Any]:
    spec = f"{SEVEN_SCENES}:{forth_and_back(frames)}"
    load_start = os.getloadavg()[0]
    endpoint = free_endpoint()
    out = work / "cloud"
    config = None if config_path is None else str(config_path)
    with code_from(src):
        cloud = start_cloud(endpoint, out, work / "cloud.log", config)
    client = CloudClient(endpoint, reach_deadline_s=60.0)
    robot = None
    samples: list[dict[str, float]] = []
    try:
        client.status(timeout=60.0, gather_s=0.2)
        with code_from(src):
            robot = start_robot(endpoint, "r0", spec, point, work / "r0.log",
                                work / "r0_report.json", config_path=config,
                                extra=["--rate", rate])
        start = time.monotonic()
        next_block = block
        samples.append({"frames": 0, "t": 0.0, "cpu_s": tree_cpu_s(cloud.pid),
                        "rss_mb": tree_rss_mb(cloud.pid), "keyframes": 0,
                        "checkpoint_kb": checkpoint_kb(out), **checkpoint_writes(None)})
        while robot.poll() is None:
            time.sleep(every_s)
            if time.monotonic() - start > 3 * 3600:
                raise RuntimeError("the robot is still running after 3 h")
            try:
                status = client.status(timeout=10.0, gather_s=0.2)
            except TimeoutError:
                continue
            robot_status = status["robots"].get("r0")
            if robot_status is None:
                continue
            done = robot_status["frames"]
            merger = (status.get("merge") or {}).get("robots", {}).get("r0", {})
            if done >= next_block or robot.poll() is not None:
                samples.append({"frames": done, "t": time.monotonic() - start,
                                "cpu_s": tree_cpu_s(cloud.pid), "rss_mb": tree_rss_mb(cloud.pid),
                                "keyframes": merger.get("keyframes", 0),
                                "checkpoint_kb": checkpoint_kb(out),
                                **checkpoint_writes(robot_status)})
                print(f"  {done} frames at {samples[-1]['t']:.0f} s, cloud RSS "
                      f"{samples[-1]['rss_mb']:.0f} MB", flush=True)
                while next_block <= done:
                    next_block += block
        if robot.returncode != 0:
            raise RuntimeError(f"the robot failed (exit {robot.returncode}): see {work}/r0.log")
        summary = client.merge(timeout=600.0)
    finally:
        client.close()
        stop_all([p for p in (robot, cloud) if p is not None])
    score_fleet(summary, out, {"r0": open_source(spec)})  # ground truth, read only now
    blocks = []
    for a, b in zip(samples, samples[1:]):
        n = b["frames"] - a["frames"]
        if n <= 0:
            continue
        blocks.append({"frames": f"{a['frames']}-{b['frames']}",
                       "wall_ms_per_frame": 1000 * (b["t"] - a["t"]) / n,
                       "cloud_cpu_ms_per_frame": 1000 * (b["cpu_s"] - a["cpu_s"]) / n,
                       "rss_mb": b["rss_mb"], "keyframes": b["keyframes"],
                       "checkpoint_kb": b["checkpoint_kb"],
                       # What the block's checkpoints wrote, per checkpoint written.
                       "checkpoints": b["checkpoints"] - a["checkpoints"],
                       "written_kb_per_checkpoint": (b["checkpoint_bytes"] - a["checkpoint_bytes"])
                       / 1000 / max(b["checkpoints"] - a["checkpoints"], 1)})
    robot_summary = summary["robots"][0]
    report = json.loads((work / "r0_report.json").read_text())
    queries = ((robot_summary.get("loop_closing") or {}).get("local_mapping") or {}
               ).get("loop_queries", {})
    return {"frames": frames, "rate": rate, "offload_at": point, "blocks": blocks,
            "settings": None if config_path is None else str(config_path),
            "code": "this" if src is None else "baseline",
            "loop_queries": queries,
            # 1-minute load average as the run started and as it ended (other jobs count).
            "load_average": [load_start, os.getloadavg()[0]],
            "ate_cm": 100 * robot_summary["ate"]["rmse_m"] if robot_summary.get("ate") else None,
            "cloud_ms_median": robot_summary.get("cloud_ms_median"),
            "cloud_ms_p95": robot_summary.get("cloud_ms_p95"),
            "round_trip_ms_p95": report.get("round_trip_ms_p95"),
            "keyframes": robot_summary.get("keyframes"),
            "robot_frame_bytes": report.get("frame_bytes"),
            "robot_keyframe_bytes": report.get("keyframe_bytes"),
            "robot_pose_tables": {k: v for k, v in (report.get("inter_coding") or {}).items()
                                  if "pose" in k}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=5000)
    parser.add_argument("--block", type=int, default=1000)
    parser.add_argument("--rate", default="max", help="the robot's --rate")
    parser.add_argument("--offload-at", type=int, default=3, help="the robot's offloading point")
    parser.add_argument("--every", type=float, default=1.0, help="seconds between samples")
    parser.add_argument("--out", default="bench/results/long_run.json")
    parser.add_argument("--configs", default="",
                        help="settings files (comma-separated), alternated within each run")
    parser.add_argument("--runs", type=int, default=1, help="rounds over the settings")
    parser.add_argument("--baseline", default="",
                        help="a git revision whose code runs beside this code in each round")
    args = parser.parse_args()
    if not SEVEN_SCENES.exists():
        sys.exit(f"{SEVEN_SCENES} missing: this benchmark needs ../shared/data")
    settings: list[Path | None] = [Path(c) for c in args.configs.split(",") if c] or [None]
    for path in settings:
        if path is not None and not path.is_file():
            sys.exit(f"--configs: {path} is not a file")
    stamp = time.strftime("%Y%m%d-%H%M%S")
    baseline_dir = tempfile.TemporaryDirectory(prefix="long-run-baseline-")
    codes: list[Path | None] = [None]
    if args.baseline:
        codes = [extract_src(args.baseline, Path(baseline_dir.name)), None]
    results = []
    for round_ in range(args.runs):
        for src in codes:
            for path in settings:
                name = ("defaults" if path is None else path.stem) + (
                    f"-{args.baseline}" if src is not None else "")
                print(f"{name}, run {round_ + 1}: {args.frames} frames ...", flush=True)
                work = Path(args.out).parent / "long-runs" / stamp / f"run{round_ + 1}-{name}"
                results.append(run(args.frames, args.block, args.rate, args.every, work, path,
                                   src, args.offload_at))
                report(results[-1])
    baseline_dir.cleanup()
    if len(results) > 1:
        for key in dict.fromkeys((r["code"], r["settings"]) for r in results):
            mine = [r for r in results if (r["code"], r["settings"]) == key]
            print(f"{key[1] or 'defaults'} ({key[0]} code), {len(mine)} runs: "
                  f"{over_runs(mine)}")
    Path(args.out).write_text(json.dumps(results[0] if len(results) == 1 else results,
                                         indent=1))
    print(f"wrote {args.out}")


def over_runs(results: list[dict[str, Any]]) -> str:
    """Min-max over runs of one code and settings: last / first block, each block's cloud
    CPU per frame, RSS at the end, ATE, and the load average at the runs' starts and ends."""
    ratios = [last_over_first(r) for r in results]
    first = [r["blocks"][0]["cloud_cpu_ms_per_frame"] for r in results]
    last = [r["blocks"][-1]["cloud_cpu_ms_per_frame"] for r in results]
    return (f"last / first block cloud CPU {span([c for c, _ in ratios], 'x')}, wall "
            f"{span([w for _, w in ratios], 'x')}; cloud CPU first block "
            f"{span(first, ' ms')}, last {span(last, ' ms')} a frame; end RSS "
            f"{span([r['blocks'][-1]['rss_mb'] for r in results], ' MB')}; ATE "
            f"{span([r['ate_cm'] for r in results], ' cm')}; load average "
            f"{span([x for r in results for x in r['load_average']], '')}")


def span(values: list[float], unit: str) -> str:
    """min-max of ``values``, two decimals."""
    return f"{min(values):.2f}-{max(values):.2f}{unit}"


def last_over_first(result: dict[str, Any]) -> tuple[float, float]:
    """(cloud CPU, wall) per frame of the last block over the first."""
    first, last = result["blocks"][0], result["blocks"][-1]
    return (last["cloud_cpu_ms_per_frame"] / first["cloud_cpu_ms_per_frame"],
            last["wall_ms_per_frame"] / first["wall_ms_per_frame"])


def report(result: dict[str, Any]) -> None:
    blocks = result["blocks"]
    rows = [[b["frames"], b["wall_ms_per_frame"], b["cloud_cpu_ms_per_frame"], b["rss_mb"],
             b["keyframes"], b.get("checkpoint_kb"), b.get("checkpoints"),
             b.get("written_kb_per_checkpoint")] for b in blocks]
    print(format_table(["frames", "wall ms/frame", "cloud CPU ms/frame", "cloud RSS MB",
                        "keyframes (merger)", "checkpoint file kB", "checkpoints written",
                        "kB written / checkpoint"], rows))
    grown = blocks[-1]["keyframes"] - blocks[0]["keyframes"]
    if grown > 0:
        rss = (blocks[-1]["rss_mb"] - blocks[0]["rss_mb"]) / grown
        ckpt = (blocks[-1]["checkpoint_kb"] - blocks[0]["checkpoint_kb"]) / grown
        print(f"after the first block: {rss:.2f} MB of cloud RSS and {ckpt:.1f} kB of "
              f"checkpoint per keyframe ({grown} keyframes)")
    cpu, wall = last_over_first(result)
    print(f"last block / first block: cloud CPU {cpu:.2f}x, wall {wall:.2f}x; ATE "
          f"{result['ate_cm']:.2f} cm; cloud ms median {result['cloud_ms_median']}, p95 "
          f"{result['cloud_ms_p95']}; round trip p95 {result['round_trip_ms_p95']} ms; "
          f"load average {result['load_average'][0]:.2f} at the start, "
          f"{result['load_average'][1]:.2f} at the end", flush=True)
    sent_kb = (result["robot_frame_bytes"] or 0) / 1000
    tables = result["robot_pose_tables"]
    print(f"the robot sent {sent_kb:.0f} kB of frames "
          f"({sent_kb / max(result['frames'], 1):.2f} kB a frame) and "
          f"{(result['robot_keyframe_bytes'] or 0) / 1000:.0f} kB of keyframe uploads"
          + (f"; keyframe pose tables: {tables.get('pose_tables_whole', 0)} whole, "
             f"{tables.get('pose_tables_delta', 0)} as deltas, "
             f"{tables.get('keyframe_poses_sent', 0)} poses sent of "
             f"{tables.get('keyframe_poses_in_tables', 0)} in the tables" if tables else ""),
          flush=True)
    queries = result["loop_queries"]
    if queries:
        lag = queries.get("request_to_answered") or {}
        sent = queries.get("bytes_sent") or {}
        search = queries.get("database_query") or {}
        print(f"loop queries to the worker: {queries.get('answered')} answered, submission "
              f"to answer median {lag.get('median_ms')} ms, p95 {lag.get('p95_ms')} ms; in "
              f"the worker median {search.get('median_ms', 'not counted')} ms; "
              f"bytes sent per query median {sent.get('median', 'not counted')}, max "
              f"{sent.get('max', 'not counted')}, last {sent.get('last', 'not counted')}, "
              f"{sent.get('full', 'not counted')} whole; the database's arrays at the end "
              f"{queries.get('database_bytes', 'not counted')} B", flush=True)


if __name__ == "__main__":
    main()
