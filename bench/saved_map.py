"""How a saved map grows (issue 44 item 6): its bytes per keyframe, the time to read and load
it, and the memory a loaded map holds, from about 100 keyframes to about 1000.

Day after day a robot maps the same place again with the map loaded, so the map grows by a
session's keyframes each day (7-Scenes redkitchen, frames --first..--last, no ground truth
in the run): after each day the map is read (every file hashed and checked) and loaded into a
fresh fleet map, each timed, with the Python memory a loaded map holds (tracemalloc).

    .venv/bin/python bench/saved_map.py --until 1000          # minutes: a day is ~15 s
    .venv/bin/python bench/saved_map.py --until 150 --json bench/results/saved_map.json

Prints a table (one row per day) and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "src"))

from fleetslam.config import Config  # noqa: E402
from fleetslam.datasets.tum import RgbdSequence  # noqa: E402
from fleetslam.merging.fleet_map import FleetMap  # noqa: E402
from fleetslam.merging.saved_map import LoadedMap, read_map  # noqa: E402
from fleetslam.system import run_fleet  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402

SEQUENCE = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_seq01_f0000-0599"


def measure(folder: Path, config: Config) -> dict[str, float]:
    """Read and load the map in ``folder``: seconds each, and the memory it then holds."""
    tracemalloc.start()
    start = time.perf_counter()
    saved = read_map(folder)
    read_s = time.perf_counter() - start
    start = time.perf_counter()
    fleet = FleetMap(config)
    fleet.load(LoadedMap(saved))
    load_s = time.perf_counter() - start
    held, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    files = [p for p in folder.rglob("*") if p.is_file()]
    size = sum(p.stat().st_size for p in files)
    return {"keyframes": saved.keyframes, "robots": len(saved.robots),
            "constraints": len(saved.constraints), "bytes": size,
            "bytes_per_keyframe": size / max(saved.keyframes, 1), "read_s": read_s,
            "load_s": load_s, "held_mb": held / 2**20}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--until", type=int, default=1000, help="keyframes to grow the map to")
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--last", type=int, default=299)
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args()
    if not SEQUENCE.is_dir():
        raise SystemExit(f"{SEQUENCE}: the shared data is not there")
    config = Config()
    rows: list[dict[str, float]] = []
    with tempfile.TemporaryDirectory(prefix="saved-map-") as tmp:
        saved = None
        day = 0
        while not rows or rows[-1]["keyframes"] < args.until:
            day += 1
            out = Path(tmp) / f"day{day}"
            robot = [("r0", str(SEQUENCE), RgbdSequence(SEQUENCE, first=args.first,
                                                         last=args.last))]
            start = time.perf_counter()
            run_fleet(robot, config, out, show_progress=False,
                      loaded=LoadedMap(saved) if saved is not None else None)
            row = {"day": day, "run_s": time.perf_counter() - start,
                   **measure(out / "map", config)}
            rows.append(row)
            print(f"day {day}: {row['keyframes']} keyframes", file=sys.stderr, flush=True)
            saved = read_map(out / "map")
    headers = ["day", "keyframes", "robots", "constraints", "MB", "kB / keyframe", "read s",
               "load s", "held MB", "run s"]
    print(format_table(headers, [[r["day"], r["keyframes"], r["robots"], r["constraints"],
                                  r["bytes"] / 2**20,
                                  r["bytes_per_keyframe"] / 1024, r["read_s"], r["load_s"],
                                  r["held_mb"], r["run_s"]] for r in rows]))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"bench": "saved_map", "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
