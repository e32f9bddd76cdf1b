"""Reading a recording as ROS bags beside the sequence folder it was made from.

    .venv/bin/python bench/bag_read.py [--source FOLDER] [--frames N] [--work DIR]
                                       [--out bench/results/bag_read.json]

Writes the folder (default: the shared TUM fr1_rpy frames 0-149) as bags with rosbags'
writers (bench/bag_writer.py): ROS 1, ROS 2 MCAP and ROS 2 sqlite3 with rgb8 colour and
32FC1 depth, and ROS 2 MCAP with JPEG colour. Opens each (the index pass, timed), then plays
them all side by side in this process, frame by frame in turn (so a busy machine slows every
reader alike), and times every frame read. Prints median and p95 ms per frame, their ratio to
the folder reader's, and the process RSS after reading; writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import bag_writer  # noqa: E402
from shared_data import TUM_RPY  # noqa: E402

from fleetslam.camera import TUM_CAMERAS  # noqa: E402
from fleetslam.datasets.recording import open_source  # noqa: E402
from fleetslam.datasets.tum import detect_camera  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402

# (name, bag flavour, colour as written)
BAGS = (("ros1", "ros1", "rgb8"), ("ros2 mcap", "mcap", "rgb8"),
        ("ros2 sqlite3", "sqlite3", "rgb8"), ("ros2 mcap jpeg", "mcap", "jpeg"))


def rss_mb() -> float:
    """This process's resident set now (Linux /proc), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def write_bags(folder: Path, work: Path) -> dict[str, Path]:
    camera = detect_camera(folder)[0]
    if camera.depth_scale != TUM_CAMERAS["freiburg1"].depth_scale:
        print(f"note: {folder} depth scale {camera.depth_scale}; bags carry 32FC1 metres")
    paths = {}
    for name, flavour, colour in BAGS:
        target = work / (name.replace(" ", "_") + (".bag" if flavour == "ros1" else ""))
        if target.exists():  # a --work folder of an earlier run: reused as it is
            paths[name] = target
            continue
        start = time.perf_counter()
        paths[name] = bag_writer.write_tum_bag(folder, target, flavour, camera, colour)
        print(f"wrote {target} in {time.perf_counter() - start:.1f} s")
    return paths


def disk_mb(path: Path) -> float:
    files = [path] if path.is_file() else [f for f in path.rglob("*") if f.is_file()]
    return sum(f.stat().st_size for f in files) / 1e6


def measure(folder: Path, bags: dict[str, Path], frames: int | None) -> dict:
    spec = f"{folder}:0-{frames - 1}" if frames else str(folder)
    rss_before = rss_mb()
    sources, open_s = {}, {}
    for name, path in [("folder", folder), *bags.items()]:
        start = time.perf_counter()
        sources[name] = open_source(spec.replace(str(folder), str(path), 1))
        open_s[name] = time.perf_counter() - start
    rss_open = rss_mb()
    n = min(len(s) for s in sources.values())
    times: dict[str, list[float]] = {name: [] for name in sources}
    for i in range(n):
        for name, source in sources.items():
            start = time.perf_counter()
            source[i]
            times[name].append(time.perf_counter() - start)
    rss_read = rss_mb()
    folder_median = float(np.median(times["folder"]))
    rows = {}
    for name, t in times.items():
        ms = np.asarray(t) * 1000
        rows[name] = {"open_s": open_s[name], "median_ms": float(np.median(ms)),
                      "p95_ms": float(np.percentile(ms, 95)),
                      "ratio_median": float(np.median(t)) / folder_median,
                      "disk_mb": disk_mb(folder if name == "folder" else bags[name])}
    return {"frames": n, "readers": rows, "rss_mb_before_open": rss_before,
            "rss_mb_after_open": rss_open, "rss_mb_after_reading": rss_read,
            "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", type=Path, default=TUM_RPY)
    parser.add_argument("--frames", type=int, help="play frames 0..N-1 (default all)")
    parser.add_argument("--work", type=Path, help="folder for the bags, kept and reused by "
                        "the next run (default a temp dir, removed after)")
    parser.add_argument("--out", default="bench/results/bag_read.json")
    args = parser.parse_args()
    if not args.source.is_dir():
        sys.exit(f"bag_read: {args.source}: no such folder")
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        result = measure(args.source, write_bags(args.source, work), args.frames)
    print(f"\n{result['frames']} frames of {args.source}, played side by side\n")
    print(format_table(
        ["reader", "open s", "median ms", "p95 ms", "x folder", "disk MB"],
        [[name, f"{r['open_s']:.2f}", f"{r['median_ms']:.2f}", f"{r['p95_ms']:.2f}",
          f"{r['ratio_median']:.2f}", f"{r['disk_mb']:.0f}"]
         for name, r in result["readers"].items()]))
    print(f"\nprocess RSS MB: {result['rss_mb_before_open']:.0f} before opening, "
          f"{result['rss_mb_after_open']:.0f} after opening all, "
          f"{result['rss_mb_after_reading']:.0f} after reading (peak {result['max_rss_mb']:.0f})")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(),
                               "load": os.getloadavg(), "source": str(args.source),
                               **result}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
