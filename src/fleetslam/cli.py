"""The ``fleetslam`` command: demo, run, generate."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from fleetslam.camera import Camera
from fleetslam.config import Config, load_config


def _default_out(kind: str) -> Path:
    return Path("runs") / f"{kind}-{time.strftime('%Y%m%d-%H%M%S')}"


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "fleetslam"


def _scene_dir(config: Config) -> Path:
    s = config.synthetic
    return _cache_dir() / f"synthetic-seed{s.seed}-r{s.n_robots}-f{s.frames_per_robot}"


def _finish(summary: dict, out: Path) -> None:
    from fleetslam.system import summary_table

    print(summary_table(summary))
    print(f"\noutputs in {out}/ (summary.json, <robot>/trajectory.tum, <robot>/map.ply"
          + (", global_map.ply)" if summary.get("merge") else ")"))


def cmd_generate(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.datasets.synthetic import ensure_scene
    from fleetslam.progress import Progress

    out = Path(args.out) if args.out else _scene_dir(config)
    progress = Progress("synthetic scene", config.synthetic.n_robots * config.synthetic.frames_per_robot,
                        enabled=not args.quiet)
    folders = ensure_scene(out, config.synthetic, progress=lambda d, t: progress.update(d))
    for folder in folders:
        print(folder)
    return 0


def cmd_demo(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.datasets.synthetic import ensure_scene
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.progress import Progress
    from fleetslam.system import run_fleet

    if args.robots is not None:
        config.synthetic.n_robots = args.robots
    if args.frames is not None:
        config.synthetic.frames_per_robot = args.frames
    if config.synthetic.n_robots < 2:
        raise ValueError("the demo needs at least 2 robots (--robots)")
    scene = Path(args.scene) if args.scene else _scene_dir(config)
    total = config.synthetic.n_robots * config.synthetic.frames_per_robot
    progress = Progress(f"synthetic scene {scene}", total, enabled=not args.quiet)
    folders = ensure_scene(scene, config.synthetic, progress=lambda d, t: progress.update(d))
    robots = [(f"r{i}", str(f), RgbdSequence(f)) for i, f in enumerate(folders)]
    out = Path(args.out) if args.out else _default_out("demo")
    summary = run_fleet(robots, config, out, show_progress=not args.quiet)
    _finish(summary, out)
    return 0


def cmd_run(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.datasets.tum import open_robot
    from fleetslam.system import run_fleet

    camera = Camera.from_json(Path(args.camera)) if args.camera else None
    names = args.name or []
    if names and len(names) != len(args.robot):
        raise ValueError(f"{len(names)} --name for {len(args.robot)} --robot")
    robots = []
    for i, spec in enumerate(args.robot):
        name = names[i] if names else f"r{i}"
        robots.append((name, spec, open_robot(spec, camera)))
    out = Path(args.out) if args.out else _default_out("run")
    summary = run_fleet(robots, config, out, show_progress=not args.quiet)
    _finish(summary, out)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fleetslam", description="Multi-robot RGB-D SLAM with partial offloading and "
        "FS-HICP map merging.")
    parser.add_argument("--config", help="TOML file overriding the defaults of config.py")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run >= 2 robots on the built-in synthetic scene")
    demo.add_argument("--out", help="run folder to create (default runs/demo-<time>)")
    demo.add_argument("--scene", help="where the synthetic scene is generated or reused "
                      "(default: a cache folder)")
    demo.add_argument("--robots", type=int, help="number of robots (default from config: 2)")
    demo.add_argument("--frames", type=int, help="frames per robot (default from config)")
    demo.set_defaults(func=cmd_demo)

    run = sub.add_parser("run", help="run robots on TUM-layout folders")
    run.add_argument("--robot", action="append", required=True, metavar="DIR[:FIRST-LAST]",
                     help="a TUM-layout folder, optionally a frame range of it; repeat per robot")
    run.add_argument("--name", action="append", help="robot name, once per --robot")
    run.add_argument("--camera", help="camera.json overriding the detected camera")
    run.add_argument("--out", help="run folder to create (default runs/run-<time>)")
    run.set_defaults(func=cmd_run)

    gen = sub.add_parser("generate", help="write the synthetic scene in TUM layout")
    gen.add_argument("--out", help="scene folder (default: the demo's cache folder)")
    gen.set_defaults(func=cmd_generate)
    return parser


def main(argv: list[str] | None = None) -> int:
    # small_gicp's OpenMP threads busy-wait by default, which slows everything else on a
    # 2-core robot or a shared server; they must sleep instead.
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        config = load_config(args.config)
        return args.func(args, config)
    except (ValueError, FileExistsError) as exc:
        print(f"fleetslam: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fleetslam: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
