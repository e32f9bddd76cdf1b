"""What the live view costs the cloud: tracking fps and cloud ms per frame with the view on
(recording to an .rrd file) and off, same runs, same machine; the demo recording's size and
a check that rerun's own readers load it back.

    .venv/bin/python bench/live_view.py [--repeats 2] [--frames 120] [--real-frames 0-299]

Runs, alternating off / on ``--repeats`` times each:
- ``fleetslam demo`` (the synthetic scene, 2 robots, a cloud process and a process per
  robot over TLS), with and without ``--save <rrd>``;
- a real sequence through a cloud process: ``fleetslam cloud`` + ``fleetslam robot --source
  7-Scenes redkitchen:0-299 --offload-at paper`` (skipped when the data is absent).
Reads tracking fps and cloud ms / frame from each run's summary. Prints a table and writes
bench/results/live_view.json.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from shared_data import SEVEN_SCENES  # noqa: E402

from fleetslam.launch import CloudClient, free_endpoint, start_cloud, start_robot, stop  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "live_view.json"


def _robots(summary: dict[str, Any]) -> dict[str, float]:
    robots = summary["robots"]
    return {"fps": float(np.mean([r["tracking_fps"] for r in robots])),
            "cloud_ms": float(np.mean([r["cloud_ms_mean"] for r in robots])),
            "frames": int(sum(r["frames"] for r in robots))}


def run_demo(work: Path, frames: int, rrd: Path | None) -> dict[str, float]:
    out = work / f"demo-{time.monotonic_ns()}"
    cmd = [sys.executable, "-m", "fleetslam.cli", "--quiet", "demo", "--frames", str(frames),
           "--out", str(out)] + (["--save", str(rrd)] if rrd else [])
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return _robots(json.loads((out / "summary.json").read_text()))


def run_real(work: Path, source: str, rrd: Path | None) -> dict[str, float]:
    out = work / f"cloud-{time.monotonic_ns()}"
    endpoint = free_endpoint()
    cloud = start_cloud(endpoint, out, out.parent / f"{out.name}.log",
                        extra=["--save", str(rrd)] if rrd else [])
    client = None
    try:
        robot = start_robot(endpoint, "r1", source, "paper", out.parent / f"{out.name}-r1.log")
        if robot.wait(1800) != 0:
            raise RuntimeError(f"robot failed: see {out.parent / f'{out.name}-r1.log'}")
        client = CloudClient(endpoint, reach_deadline_s=60.0)
        summary = client.merge()
    finally:
        if client is not None:
            client.close()
        stop(cloud)
    return _robots(summary)


def load_back(rrd: Path) -> dict[str, Any]:
    """rerun's Python reader (chunk store, schema) and its CLI (rrd verify)."""
    from rerun.chunk import RrdReader

    store = RrdReader(str(rrd)).store()
    paths = store.schema().entity_paths()
    rows = sum(int(line.split(" rows=")[1].split()[0])
               for line in store.summary().splitlines() if " rows=" in line)
    cli = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    verify = subprocess.run([cli, "rrd", "verify", str(rrd)], capture_output=True, text=True,
                            stdin=subprocess.DEVNULL, timeout=300)
    return {"entity_paths": len(paths), "rows": rows,
            "has": {p: p in paths for p in ("/world/r0/camera", "/world/r0/trajectory/00000",
                                            "/world/r0/keyframes/000000/points",
                                            "/robots/r0/split_point",
                                            "/robots/r0/link_kB_per_s", "/world/constraints")},
            "rrd_verify_ok": verify.returncode == 0,
            "rrd_verify": (verify.stdout + verify.stderr).strip().splitlines()[-1:]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--frames", type=int, default=120, help="demo frames per robot")
    parser.add_argument("--real-frames", default="0-299")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="fleetslam-live-view-"))
    cases: dict[str, Any] = {"demo": lambda rrd: run_demo(work, args.frames, rrd)}
    if SEVEN_SCENES.exists():
        source = f"{SEVEN_SCENES}:{args.real_frames}"
        cases["7-Scenes " + args.real_frames] = lambda rrd: run_real(work, source, rrd)
    else:
        print(f"skip the real sequence: {SEVEN_SCENES} missing")
    results: dict[str, Any] = {"machine_cores": __import__("os").cpu_count(), "runs": {}}
    demo_rrd = None
    for name, run in cases.items():
        runs: dict[str, list] = {"off": [], "on": []}
        for i in range(args.repeats):
            for view in ("off", "on"):
                rrd = work / f"{name.split()[0]}-{i}.rrd" if view == "on" else None
                t = time.perf_counter()
                r = run(rrd)
                r["wall_s"] = time.perf_counter() - t
                if rrd is not None:
                    r["rrd_bytes"] = rrd.stat().st_size
                    if name == "demo":
                        demo_rrd = rrd
                runs[view].append(r)
                print(f"{name} view {view} #{i + 1}: {r['fps']:.2f} fps, "
                      f"{r['cloud_ms']:.1f} cloud ms/frame", flush=True)
        results["runs"][name] = runs
    rows = []
    for name, runs in results["runs"].items():
        for view in ("off", "on"):
            rs = runs[view]
            rows.append([name, view, len(rs), np.mean([r["fps"] for r in rs]),
                         np.mean([r["cloud_ms"] for r in rs]),
                         np.mean([r["rrd_bytes"] for r in rs]) / 1e6 if view == "on" else None])
        off = np.mean([r["fps"] for r in runs["off"]])
        on = np.mean([r["fps"] for r in runs["on"]])
        results.setdefault("fps_change_percent", {})[name] = 100.0 * (on - off) / off
    print(format_table(["run", "view", "runs", "tracking fps", "cloud ms/frame", "rrd MB"],
                       rows))
    for name, change in results["fps_change_percent"].items():
        print(f"{name}: fps with the view {change:+.1f} %")
    if demo_rrd is not None:
        results["demo_rrd"] = {"bytes": demo_rrd.stat().st_size, **load_back(demo_rrd)}
        d = results["demo_rrd"]
        print(f"demo recording: {d['bytes'] / 1e6:.2f} MB, {d['entity_paths']} entity paths, "
              f"{d['rows']} rows read back by rerun.chunk.RrdReader; rerun rrd verify: "
              f"{'ok' if d['rrd_verify_ok'] else 'FAILED'} {d['rrd_verify']}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2))
    print(f"wrote {RESULTS}")
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
