"""Why did a robot join a loaded map late (or never)? For each keyframe of the robot, the
geometric check (merging/inter_robot.py, as the merger runs it) against every keyframe of
the loaded map's robots, not only the candidates place recognition gave: the best pair's
refined inliers (merge.min_refined_inliers passes) and descriptor matches.

    .venv/bin/python scripts/map_entry.py runs/tuesday/map --robot r0

Reads a map a run wrote after it loaded one (its robots there: the loaded map's, and this
run's). No ground truth is read. Prints one row per keyframe of ``--robot``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "src"))

from fleetslam.config import Config  # noqa: E402
from fleetslam.merging.inter_robot import verify_counting  # noqa: E402
from fleetslam.merging.saved_map import read_map  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("map", type=Path, help="a map/ folder written by a run that loaded one")
    parser.add_argument("--robot", required=True, help="the robot of that run (its name in "
                        "the map: r0, or r0-2 where the loaded map had an r0)")
    parser.add_argument("--against", action="append", help="the loaded map's robots to check "
                        "against (default: every other robot of the map)")
    args = parser.parse_args()
    config = Config()
    saved = read_map(args.map)
    if args.robot not in saved.robots:
        raise SystemExit(f"{args.map}: no robot {args.robot!r} (it has "
                         f"{', '.join(sorted(saved.robots))})")
    query = saved.robots[args.robot]
    others = [saved.robots[n] for n in (args.against or sorted(saved.robots))
              if n != args.robot]
    rows = []
    for q in query.keyframes:
        best = (0, 0, "-", -1)  # refined inliers, descriptor matches, robot, frame
        for other in others:
            for p in other.keyframes:
                match, matched = verify_counting(q, query.camera, p, other.camera, 0.0, config)
                found = (match.inliers if match is not None else 0, matched, other.name,
                         p.frame_index)
                best = max(best, found)
        rows.append([q.frame_index, best[0], best[1], f"{best[2]}:{best[3]}",
                     "yes" if best[0] else "no"])
    print(format_table(["frame", "refined inliers", "descriptor matches", "best pair",
                        "passes"], rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
