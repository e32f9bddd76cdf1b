"""The ``fleetslam`` command: demo, run, cloud, robot, merge, status, plan, certs, report,
export, view, generate, vocabulary."""

from __future__ import annotations

import argparse
import faulthandler
import functools
import os
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fleetslam import __version__
from fleetslam.camera import Camera
from fleetslam.config import Config, load_config
from fleetslam.datasets.live_sources import live_specs
from fleetslam.planner.model import OBJECTIVES, SWEEP_MBPS
from fleetslam.transport.keys import check_robot_id as keys_check
from fleetslam.transport.link import parse_link_trace
from fleetslam.validation.endpoints import check_endpoint, check_listenable

if TYPE_CHECKING:
    from fleetslam.merging.saved_map import LoadedMap

DEFAULT_ENDPOINT = Config().transport.endpoint


def _default_out(kind: str) -> Path:
    return Path("runs") / f"{kind}-{time.strftime('%Y%m%d-%H%M%S')}"


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "fleetslam"


def _scene_dir(config: Config) -> Path:
    s = config.synthetic
    return _cache_dir() / f"synthetic-seed{s.seed}-r{s.n_robots}-f{s.frames_per_robot}"


def _finish(summary: dict, out: Path, quiet: bool = False) -> None:
    from fleetslam.reporting import write_report
    from fleetslam.outputs import summary_table

    page = write_report(out, show_progress=not quiet)
    print(summary_table(summary))
    interrupted = summary.get("interrupted")
    if interrupted:
        tracked = interrupted["frames_tracked"]
        print("\ninterrupted (Ctrl-C): kept the frames tracked ("
              + ", ".join(f"{r} {n}/{interrupted['frames_given'][r]}" for r, n in tracked.items())
              + "); not built: " + (", ".join(interrupted["not_built"]) or "nothing"))
    print(f"\noutputs in {out}/ ({_output_files(summary)})")
    if summary.get("mcap"):
        print(f"mcap: {out / summary['mcap']}")
    print(f"report: {page}")


def cmd_config(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.config_reference import config_toml, reference_markdown

    print(reference_markdown() if args.markdown else config_toml(config), end="")
    return 0


def _output_files(summary: dict) -> str:
    """The files a run's folder holds, by the summary."""
    merged = (summary.get("merge") or {}).get("members")
    return ("summary.json, <robot>/trajectory.tum, <robot>/online.tum, <robot>/map.ply, "
            "<robot>/map.pgm + .yaml (nav2)"
            + (", global/<robot>.tum, global_map.ply, global_map.bt, global_map.pgm + .yaml "
               "(nav2)" if merged else "")
            + (", map/ (the saved map)" if summary.get("map") else ""))


def cmd_report(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.reporting import write_report

    print(write_report(Path(args.run_dir), show_progress=not args.quiet,
                       groundtruth=args.groundtruth or []))
    return 0


def cmd_export(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.run_mcap import write_run_mcap

    print(write_run_mcap(Path(args.run_dir), path=Path(args.mcap)))
    return 0


def _synthetic_scene(folder: Path, config: Config, quiet: bool) -> list[Path]:
    """The built-in scene's robot folders, made once in ``folder`` (then reused; making it
    takes a minute or more, so it shows progress)."""
    from fleetslam.datasets.synthetic import ensure_scene
    from fleetslam.progress import Progress

    synthetic = config.synthetic
    progress = Progress(f"synthetic scene {folder}",
                        synthetic.n_robots * synthetic.frames_per_robot, enabled=not quiet)
    return ensure_scene(folder, synthetic, progress=lambda done, _: progress.update(done))


def cmd_generate(args: argparse.Namespace, config: Config) -> int:
    out = Path(args.out) if args.out else _scene_dir(config)
    for folder in _synthetic_scene(out, config, args.quiet):
        print(folder)
    return 0


def cmd_demo(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.demo import run_demo

    if args.robots is not None:
        config = config.with_values({"synthetic.n_robots": args.robots}, flag="--robots")
    if args.frames is not None:
        config = config.with_values({"synthetic.frames_per_robot": args.frames},
                                    flag="--frames")
    config = _apply_link(args, config)  # checked here: the demo's robot processes get them
    if config.synthetic.n_robots < 2:
        raise ValueError("the demo needs at least 2 robots (--robots)")
    _check_offload_at(args.offload_at)  # before the scene, the cloud and the run folder
    out = Path(args.out) if args.out else _default_out("demo")
    scene = Path(args.scene) if args.scene else _scene_dir(config)
    # Absolute, so `fleetslam report` finds the scene's ground truth from any directory.
    folders = [f.resolve() for f in _synthetic_scene(scene, config, args.quiet)]
    view_args = _view_args(args, config)
    if view_args and args.in_process:
        raise ValueError("--view / --save show the cloud process: not with --in-process")
    if args.workers < 1 or (args.in_process and args.workers > 1):
        raise ValueError("--workers N: at least 1, and cloud workers are processes (not with "
                         "--in-process)")
    loaded = _loaded_map(args)
    map_args = ["--map", str(Path(args.map).resolve())] + \
        ["--localise-only"] * args.localise_only + ["--new-camera"] * args.new_camera \
        if args.map else []
    _free_out(out, args.overwrite)  # after every check: an earlier run is replaced only to run
    if args.in_process:
        from fleetslam.datasets.tum import RgbdSequence
        from fleetslam.system import run_fleet

        robots = [(f"r{i}", str(f), RgbdSequence(f)) for i, f in enumerate(folders)]
        summary = run_fleet(robots, config, out, show_progress=not args.quiet, loaded=loaded)
    else:
        summary = run_demo([str(f) for f in folders], out, args.offload_at, args.config,
                           link_args=_link_args(args), show_progress=not args.quiet,
                           zenoh_config=config.transport.zenoh_config or None,
                           secure=not args.insecure, cloud_args=view_args + map_args,
                           workers=args.workers)
    _finish(summary, out, args.quiet)
    return 130 if summary.get("interrupted") else 0  # 130: the shell's code for Ctrl-C


def _check_offload_at(text: str) -> int | None:
    """The split point ``--offload-at`` names (None: 'auto'), ValueError saying what is
    allowed: checked before anything starts."""
    from fleetslam.pipeline.split import parse_offload_point

    try:
        return None if text == "auto" else parse_offload_point(text)
    except ValueError as exc:
        raise ValueError(f"--offload-at {text}: {exc}") from None


def _link_args(args: argparse.Namespace) -> list[str]:
    out = []
    for name in ("bandwidth_mbps", "latency_ms", "loss"):
        value = getattr(args, name, None)
        if value is not None:
            out += [f"--{name.replace('_', '-')}", str(value)]
    return out


def _with_flags(config: Config, section: str, given: dict[str, Any]) -> Config:
    """``config`` with ``section``'s settings NAME that a flag ``--NAME`` gave (None: not
    given), each checked and named by its flag."""
    for name, value in given.items():
        if value is not None:
            config = config.with_values({f"{section}.{name}": value},
                                        flag=f"--{name.replace('_', '-')}")
    return config


def _apply_link(args: argparse.Namespace, config: Config) -> Config:
    """``config`` with --bandwidth-mbps, --latency-ms, --loss in its link, checked."""
    return _with_flags(config, "link", {name: getattr(args, name, None) for name in
                                        ("bandwidth_mbps", "latency_ms", "loss")})


def _add_link_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bandwidth-mbps", type=float, help="emulated link bandwidth "
                        "(Mbit/s; default from config: not limited)")
    parser.add_argument("--latency-ms", type=float, help="emulated one-way latency")
    parser.add_argument("--loss", type=float, help="probability a message is lost on the link "
                        "(keyframe uploads are resent until acknowledged)")


def _add_topic_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rgb-topic", help="a bag's colour image topic (default: its only "
                        "colour Image or CompressedImage topic)")
    parser.add_argument("--depth-topic", help="a bag's depth image topic (default: its only "
                        "16UC1 / 32FC1 / compressedDepth topic)")
    parser.add_argument("--camera-info-topic", help="a bag's CameraInfo for the colour camera "
                        "(default: camera_info beside the colour topic, else the only one)")


def _apply_topics(args: argparse.Namespace, config: Config) -> Config:
    """``config`` with --rgb-topic, --depth-topic, --camera-info-topic in its source."""
    return _with_flags(config, "source", {name: getattr(args, name, None) or None for name in
                                          ("rgb_topic", "depth_topic", "camera_info_topic")})


def _add_view_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--view", action="store_true", help="live view in rerun: spawn a "
                        "viewer if this machine has a display, else serve it over gRPC and "
                        "print the URL (needs pip install 'fleetslam[view]')")
    parser.add_argument("--save", metavar="FILE.rrd", help="record the live view to this "
                        "file (replay: rerun FILE.rrd); with or without --view")


def _view_args(args: argparse.Namespace, config: Config) -> list[str]:
    """The demo's --view / --save, passed on to its cloud process (rerun checked here)."""
    if not (args.view or args.save):
        return []
    from fleetslam.visualisation.recording import import_rerun, live_plan

    import_rerun()
    save = Path(args.save).resolve() if args.save else None
    for line in live_plan(config.view, save, args.view):
        print(f"{line} (the cloud process)", file=sys.stderr)
    return (["--view"] if args.view else []) + (["--save", str(save)] if save else [])


def cmd_view(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.visualisation.run_view import view_run

    print(view_run(Path(args.run_dir), config, Path(args.save) if args.save else None))
    return 0


def _setup_logging(quiet: bool) -> None:
    import logging

    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    # faiss's loader says at INFO which CPU build it tried (7 lines in every robot's and
    # cloud's log); its warnings still show.
    logging.getLogger("faiss").setLevel(logging.WARNING)


def cmd_cloud(args: argparse.Namespace, config: Config) -> int:
    import signal
    import threading

    from fleetslam.cloud.server import CloudServer
    from fleetslam.visualisation.views import open_view
    from fleetslam.visualisation.recording import live_plan

    _setup_logging(args.quiet)
    config = _with_flags(config, "placement", {name: getattr(args, name) or None for name in
                                               ("worker_id", "coordination",
                                                "coordination_certs")})
    if args.ros2_out:  # before the views: the ROS 2 graph's is one of them
        config = config.with_values({"ros2_out.endpoint": args.ros2_out}, flag="--ros2-out")
    loaded = _loaded_map(args)  # checked before anything starts
    view = open_view(config, args.save, args.view, args.foxglove)
    for line in live_plan(config.view, Path(args.save) if args.save else None, args.view):
        print(f"fleetslam cloud: {line}", file=sys.stderr, flush=True)
    out = Path(args.out)
    made = not out.exists()
    try:
        server = CloudServer(config, out, args.listen, view=view, connect=args.connect,
                             loaded=loaded).start()
    except BaseException:
        if made and out.is_dir() and not any(out.iterdir()):
            out.rmdir()  # a cloud that did not start leaves no store behind
        raise
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"fleetslam cloud: worker {server.worker_id} "
          f"{'connected to' if args.connect else 'listening on'} {server.endpoint}, "
          f"store {args.out}", file=sys.stderr, flush=True)
    stop.wait()
    server.close()
    print("fleetslam cloud: stopped", file=sys.stderr)
    return 0


def cmd_router(args: argparse.Namespace, config: Config) -> int:
    import signal
    import threading

    from fleetslam.transport.zenoh_session import open_router

    _setup_logging(args.quiet)
    endpoint = args.listen or config.transport.endpoint
    session = open_router(endpoint, args.connect, config.transport.zenoh_config or None,
                          config.transport.router_block_s)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"fleetslam router: listening on {endpoint}"
          + (f", joined {', '.join(args.connect)}" if args.connect else ""),
          file=sys.stderr, flush=True)
    stop.wait()
    session.close()
    print("fleetslam router: stopped", file=sys.stderr)
    return 0


def _online_planner(args: argparse.Namespace, config: Config, sequence: Any) -> Any:
    """The adaptive robot's planner, from a saved profile or one measured on its own first
    frames (this machine's stage times, the bytes of every point)."""
    from fleetslam.planner.online import OnlinePlanner, Setting
    from fleetslam.planner.profile import Profile

    n = config.orb.n_features
    options = (n, *[f for f in config.planner.feature_options if f < n])
    cfg = config.with_values({"planner.feature_options": options}).planner
    if args.plan_profile:
        profile = Profile.load(Path(args.plan_profile))
    else:
        from fleetslam.progress import Progress

        try:  # measuring the whole pipeline runs the back-end: the cloud extra
            from fleetslam.planner.profiling import measure_profile
        except ImportError as exc:
            raise ValueError(
                f"--offload-at auto without --plan-profile measures the whole pipeline, "
                f"which needs the cloud extra: pip install 'fleetslam[cloud]' ({exc}). "
                f"Without it give --plan-profile: a profile measured where the cloud runs, "
                f"with this robot's side in it (fleetslam plan --robot-side here, then "
                f"fleetslam plan --profile CLOUD.json --robot-profile ROBOT.json "
                f"--save-profile FILE)") from None

        frames = min(cfg.profile_frames, len(sequence))
        progress = Progress(f"profile {args.source} (for --offload-at auto)", frames,
                            enabled=not args.quiet)
        profile = measure_profile(sequence, args.source, config, frames, progress.update)
    return OnlinePlanner(profile, cfg, Setting(3, n, 1))


def _onboard_pipeline(config: Config, camera: Camera) -> Any:
    """The whole pipeline for a robot that tracks by itself (point 6): its back-end needs
    the cloud's libraries (``pip install 'fleetslam[cloud]'``)."""
    try:
        from fleetslam.backend.robot_slam import RobotSlam
    except ImportError as exc:
        raise ValueError(f"a robot that tracks by itself (--offload-at 6) runs the back-end, "
                         f"which needs the cloud extra: pip install 'fleetslam[cloud]' "
                         f"({exc})") from None
    return RobotSlam.new(config, camera)


def _robot_source(args: argparse.Namespace, config: Config) -> tuple[Any, Any]:
    """(what the robot streams: a recording or a live source; the recording behind it, if
    any). A live spec (``realsense...``) is a camera; a recording with ``--live`` is replayed
    as one, on its recorded clock or at ``--rate`` fps; otherwise it is paced by ``--rate``."""
    from fleetslam.datasets.live_sources import open_live
    from fleetslam.datasets.replay import ReplaySource
    from fleetslam.datasets.recording import open_source
    from fleetslam.edge.pacing import parse_rate

    live = open_live(args.source, config)
    if live is not None:
        if args.rate is not None:
            raise ValueError(f"--source {args.source}: a camera runs at its own rate; "
                             f"--rate is for recordings")
        if args.camera:
            raise ValueError(f"--source {args.source}: the camera model comes from the "
                             f"device; --camera is for recordings")
        return live, None
    camera = Camera.from_json(Path(args.camera)) if args.camera else None
    config = _apply_topics(args, config)
    recording = open_source(args.source, camera, config.source)
    if not args.live:
        return recording, recording
    rate = args.rate or "recorded"
    if rate == "max":
        raise ValueError("--live --rate max: a live replay runs on a camera's clock: "
                         "'recorded' or frames per second")
    return ReplaySource(recording, args.source, parse_rate(rate) or None), recording


def _run_until_stopped(robot: Any, robot_id: str) -> Any:
    """``robot.run()``; the first Ctrl-C (or SIGTERM) ends its stream and lets it finish
    with the cloud (a live camera has no last frame), the second aborts."""
    import signal

    def stop(signum: int, _frame: Any) -> None:
        print(f"fleetslam robot {robot_id}: stopping: finishing with the cloud "
              f"(Ctrl-C again to abort)", file=sys.stderr, flush=True)
        robot.stop()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)

    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return robot.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _warn_of_another_identity(robot_id: str, config: Config) -> None:
    """Said at once: a lab's cloud drops, without a word, a robot's messages sent under
    another identity's certificate (Zenoh reports no access control refusal)."""
    zenoh_config = config.transport.zenoh_config
    if not zenoh_config:
        return
    from fleetslam.transport.identity import certificate_name

    found = certificate_name(zenoh_config)
    if found is not None and found[1] != robot_id:
        print(f"fleetslam robot {robot_id}: warning: --zenoh-config {zenoh_config} connects "
              f"with the certificate of '{found[1]}' ({found[0]}), not of '{robot_id}': a "
              f"lab's cloud admits a robot's messages only under its own certificate "
              f"(robot-{robot_id}.json5 of the lab) and drops the others unseen",
              file=sys.stderr, flush=True)


def cmd_robot(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.datasets.recording import absolute_spec
    from fleetslam.edge.encoder import prepare as prepare_encoder
    from fleetslam.edge.robot import Robot
    from fleetslam.edge.report import EXIT_INCOMPLETE
    from fleetslam.pipeline.split import ROBOT_TRACKS

    _setup_logging(args.quiet)
    point = _check_offload_at(args.offload_at)  # before a camera starts
    _warn_of_another_identity(args.id, config)
    config = _apply_link(args, config)
    if args.link_seed is not None:
        config = config.with_values({"link.seed": args.link_seed}, flag="--link-seed")
    if args.ros2_out:
        config = config.with_values({"ros2_out.endpoint": args.ros2_out}, flag="--ros2-out")
    # One-time costs of the first frames, paid before a live camera's clock starts.
    prepare_encoder(config, point)
    sequence, recording = _robot_source(args, config)
    live = sequence is not recording
    if live:  # its camera model (the device's, or the recording's image size) builds stages
        sequence.start(config.source.live_frame_timeout_s)
    trace = parse_link_trace(args.link_trace) if args.link_trace else None
    if trace:
        if trace[0][0] != 0:
            raise ValueError("--link-trace must start at frame 0")
        config = config.with_values({"link.bandwidth_mbps": trace[0][1]}, flag="--link-trace")
    planner = None
    if point is None:
        k = 3
        if recording is None and not args.plan_profile:
            raise ValueError(f"--source {args.source} --offload-at auto: a camera cannot be "
                             f"profiled before it runs; give --plan-profile")
        planner = _online_planner(args, config, recording)
    else:
        k = point
    # The cloud's summary names this source: absolute, so its report finds the ground truth.
    source = args.source if recording is None else absolute_spec(args.source)
    robot = Robot(args.id, sequence, source, k, config, args.connect,
                  "max" if live else args.rate or "max", show_progress=not args.quiet,
                  paper_yaml_dir=Path(args.paper_yaml) if args.paper_yaml else None,
                  planner=planner, link_trace=trace,
                  onboard=_onboard_pipeline(config, sequence.camera) if k == ROBOT_TRACKS
                  else None, localise_only=args.localise_only)
    report = _run_until_stopped(robot, args.id)
    if args.report:
        Path(args.report).parent.mkdir(parents=True, exist_ok=True)
        Path(args.report).write_text(report.to_json())
    print(report.summary_line(), file=sys.stderr)
    if report.incomplete:
        print(f"robot {args.id}: the cloud did not keep everything sent: "
              + "; ".join(report.incomplete), file=sys.stderr)
        return EXIT_INCOMPLETE
    return 0


def _ask_cloud(args: argparse.Namespace, config: Config, request: str) -> dict[str, Any]:
    """One request (merge, status) to the running cloud at ``--connect``, as the operator:
    its first answer within --deadline (reaching the endpoint included), else an error
    saying what to check; a merge, once the cloud answered, within merge_timeout_s."""
    from fleetslam.launch import CloudClient

    if args.deadline is not None:
        config = config.with_values({"transport.ask_deadline_s": args.deadline},
                                    flag="--deadline")
    cfg = config.transport
    deadline = time.monotonic() + cfg.ask_deadline_s
    # Nothing listening is known at once; the deadline is for a cloud that may yet answer.
    client = CloudClient(args.connect or cfg.endpoint, cfg.ask_deadline_s,
                         cfg.zenoh_config or None, silence_hint_s=cfg.silence_hint_s,
                         deadline_setting="--deadline, transport.ask_deadline_s",
                         refused_ends=True)
    try:
        left = max(deadline - time.monotonic(), 1.0)
        if request == "status":
            return client.status(timeout=left)
        client.ping(left)  # the cloud is there and answers us: now it may take its time
        return client.merge(cfg.merge_timeout_s, answered=True)
    finally:
        client.close()


def cmd_merge(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.outputs import summary_table

    summary = _ask_cloud(args, config, "merge")
    print(summary_table(summary, drop_empty=True))
    outputs = summary.get("outputs") or {}
    # On the cloud's machine (a cloud too old to say: its --out folder).
    folder = outputs.get("folder")
    print(f"\noutputs in {f'{folder}/' if folder else 'its --out folder'} on the cloud's "
          f"machine ({_output_files(summary)}"
          + (f", {summary['mcap']}" if summary.get("mcap") else "") + ")")
    if outputs.get("report"):
        print(f"report: {folder}/{outputs['report']} (made without ground truth: "
              f"`fleetslam report {folder}` where the robots' sequences are adds the errors "
              f"against it)")
    elif outputs:
        print("report: none (the cloud could not write it: see its log)")
    return 0


def cmd_status(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.outputs import map_groups

    status = _ask_cloud(args, config, "status")
    merge = status.get("merge") or {}
    merged = merge.get("robots", {})
    print(f"{'robot':<12} {'frames':>7} {'finished':>9} {'keyframes':>10} {'joined to':>10}  "
          f"worker")
    for robot, s in sorted(status["robots"].items()):
        m = merged.get(robot, {})
        print(f"{robot:<12} {s['frames']:>7} {'yes' if s['finished'] else 'no':>9} "
              f"{m.get('keyframes', 0):>10} {m.get('anchor', '-'):>10}  {s.get('worker', '-')}")
    print(f"workers: {', '.join(status.get('workers') or [])} (answered: "
          f"{', '.join(status.get('answered') or [])})")
    print(f"map groups (merger of worker {status.get('worker')}): {map_groups(merge)}; "
          f"inter-robot constraints: {merge.get('constraints', 0)} "
          f"({merge.get('constraints_rejected', 0)} rejected){_still_merging(merge)}")
    return 0


def _still_merging(merge: dict[str, Any]) -> str:
    """What the merger has yet to do, as the groups printed may still change; empty if
    nothing."""
    queued, waiting = merge.get("queued", 0), merge.get("searches_waiting", 0)
    if not queued and not waiting:
        return ""
    return f"; still merging: {queued} keyframes queued, {waiting} place searches waiting"


def cmd_run(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.datasets.recording import absolute_spec, open_source
    from fleetslam.evaluation.fleet import match_ground_truth
    from fleetslam.system import run_fleet

    camera = Camera.from_json(Path(args.camera)) if args.camera else None
    config = _apply_topics(args, config)
    names = args.name or []
    if names and len(names) != len(args.robot):
        raise ValueError(f"{len(names)} --name for {len(args.robot)} --robot")
    for name in names:  # a robot's folder in the run: <out>/<name>/
        try:
            keys_check(name)
        except ValueError as exc:
            raise ValueError(f"--name {name!r}: {exc}") from None
    names = names or [f"r{i}" for i in range(len(args.robot))]
    # Checked now, read again only after the run (evaluation/fleet.py).
    ground_truth = match_ground_truth(args.groundtruth or [], names)
    robots = []
    for name, spec in zip(names, args.robot):
        # Absolute, so `fleetslam report` finds its ground truth from any directory.
        robots.append((name, absolute_spec(spec), open_source(spec, camera, config.source)))
    loaded = _loaded_map(args)  # checked before anything runs
    out = Path(args.out) if args.out else _default_out("run")
    _free_out(out, args.overwrite)
    summary = run_fleet(robots, config, out, show_progress=not args.quiet, loaded=loaded,
                        ground_truth=ground_truth)
    _finish(summary, out, args.quiet)
    return 130 if summary.get("interrupted") else 0  # 130: the shell's code for Ctrl-C


def _loaded_map(args: argparse.Namespace) -> LoadedMap | None:
    """The saved map of --map, read and checked whole, with how it is used."""
    from fleetslam.merging.saved_map import LoadedMap, read_map

    if not args.map:
        for flag in ("localise_only", "new_camera"):
            if getattr(args, flag):
                raise ValueError(f"--{flag.replace('_', '-')} is about a saved map: give it "
                                 f"with --map")
        return None
    return LoadedMap(read_map(Path(args.map)), args.localise_only, args.new_camera)


def _add_map_options(parser: argparse.ArgumentParser, where: str) -> None:
    parser.add_argument("--map", metavar="DIR", help="a saved map (a run's or a store's "
                        f"map/): the fleet's first group, in its own frame; {where}")
    parser.add_argument("--localise-only", action="store_true", help="with --map: place the "
                        "robots in the map without extending it (its keyframes keep their "
                        "poses; no new map/ is written)")
    parser.add_argument("--new-camera", action="store_true", help="with --map: let robots "
                        "whose camera is none of the map's search it (without it they are "
                        "refused: a wrong camera file or a wrong map)")


def _free_out(out: Path, overwrite: bool) -> None:
    """Make room for a run folder: an existing one is replaced only with --overwrite, and
    only if it is empty or a run folder (has summary.json): never someone's other files."""
    import shutil

    if not out.exists():
        return
    if not overwrite:
        raise ValueError(f"--out {out}: the folder exists; give another --out, or add "
                         f"--overwrite to replace it")
    if not out.is_dir() or (any(out.iterdir()) and not (out / "summary.json").is_file()):
        raise ValueError(f"--out {out}: not a run folder (no summary.json): --overwrite "
                         f"replaces only a run folder; give another --out")
    shutil.rmtree(out)


def cmd_vocabulary(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.backend.vocabulary import Vocabulary, image_descriptors, training_images
    from fleetslam.progress import Progress

    out = Path(args.out)
    if out.suffix != ".npz":
        raise ValueError(f"{out}: a vocabulary is written as .npz")
    paths = [p for folder in args.images for p in training_images(folder, args.every)]
    progress = Progress("vocabulary: ORB descriptors", len(paths), "images",
                        enabled=not args.quiet)
    descriptors = []
    for i, path in enumerate(paths):
        descriptors.append(image_descriptors(path, config))
        progress.update(i + 1)
    pr = config.place_recognition
    if not args.quiet:
        print(f"clustering {sum(len(d) for d in descriptors)} descriptors into "
              f"{pr.vocabulary_branching}^{pr.vocabulary_levels} words ...", file=sys.stderr)
    start = time.perf_counter()
    vocabulary = Vocabulary.train(descriptors, pr.vocabulary_branching, pr.vocabulary_levels,
                                  trained_on=", ".join(f"{f} (every {args.every})"
                                                       for f in args.images))
    out.parent.mkdir(parents=True, exist_ok=True)
    vocabulary.save(out)
    print(f"{out}: {vocabulary.n_words} words from {len(paths)} images "
          f"({time.perf_counter() - start:.0f} s); use it with [place_recognition] "
          f"method = \"bag_of_words\", vocabulary = \"{out}\"")
    return 0


def cmd_plan(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.planner.model import Link
    from fleetslam.planner.plan import plan, report, write_plan
    from fleetslam.planner.profile import Profile, RobotSideProfile, paper_profile
    from fleetslam.pipeline.split import SUPPORTED_POINTS

    config = _with_flags(config, "planner", {name: getattr(args, name) for name in
                                             ("bandwidth_mbps", "latency_ms")})
    if args.frames is not None:
        config = config.with_values({"planner.profile_frames": args.frames}, flag="--frames")
    if args.robot_side:
        return _plan_robot_side(args, config)
    offered: tuple[int, ...] | None = SUPPORTED_POINTS
    measured = ""  # a profile measured here on part of a sequence: which part
    if args.paper:
        if args.profile or args.source or args.robot_profile:
            raise ValueError("--paper plans with the paper's numbers: no --profile / --source "
                             "/ --robot-profile")
        profile = paper_profile()
        # The paper's Table "Parameter values".
        config = config.with_values({"planner.c_total_g": 1.0})
        offered = None  # the paper's seven candidates
    elif args.profile:
        profile = Profile.load(Path(args.profile))
    else:
        profile, measured = _measure_whole_profile(args, config)
    if args.robot_profile:
        profile = profile.with_robot_side(RobotSideProfile.load(Path(args.robot_profile)))
    if args.save_profile and not args.paper:  # what a robot's --plan-profile reads
        profile.save(Path(args.save_profile))
    cfg = config.planner
    bandwidths = SWEEP_MBPS if args.sweep else (cfg.bandwidth_mbps,)
    result = plan(profile, [Link(b, cfg.latency_ms) for b in bandwidths], cfg, offered,
                  args.objective)
    out = Path(args.out) if args.out else _default_out("plan")
    paths, not_drawn = write_plan(result, out)
    print(f"profile: {profile.source} ("
          + (measured or f"{profile.label}, {profile.frames} frames") + ")")
    print(report(result, cfg))
    print("\nwrote " + ", ".join(str(p) for p in paths))
    if not_drawn:
        print(not_drawn)
    return 0


def _measure_whole_profile(args: argparse.Namespace, config: Config) -> tuple[Any, str]:
    """(the whole pipeline's profile measured here, which part of the source it saw); it
    runs the back-end, so it needs the cloud extra: said, with what a robot does instead."""
    from fleetslam.datasets.recording import open_source
    from fleetslam.progress import Progress

    try:
        from fleetslam.planner.profiling import measure_profile
        source = args.source or str(_synthetic_scene(_scene_dir(config), config,
                                                     args.quiet)[0])
    except ImportError as exc:
        raise ValueError(
            f"measuring the whole pipeline runs the cloud's stages, which need the cloud "
            f"extra: pip install 'fleetslam[cloud]' ({exc}). Without it, measure the "
            f"robot's side here (fleetslam plan --robot-side --source SOURCE --save-profile "
            f"robot.json) and plan with a profile measured where the cloud runs "
            f"(--profile CLOUD.json --robot-profile robot.json)") from None
    config = _apply_topics(args, config)
    sequence = open_source(source, None, config.source)
    frames = min(config.planner.profile_frames, len(sequence))
    if not args.quiet:
        print(f"profile: measuring the first {frames} of the {len(sequence)} frames of "
              f"{source} (--frames N, or [planner] profile_frames)", file=sys.stderr)
    progress = Progress(f"profile {source}", frames, enabled=not args.quiet)
    profile = measure_profile(sequence, source, config, frames, progress.update)
    measured = ""
    if frames < len(sequence):
        measured = f"measured on the first {frames} of its {len(sequence)} frames: --frames"
    return profile, measured


def _plan_robot_side(args: argparse.Namespace, config: Config) -> int:
    """``fleetslam plan --robot-side``: the robot's own stage times and payloads, measured
    here with the base install, written for a plan made with the cloud's profile."""
    from fleetslam.datasets.recording import open_source
    from fleetslam.planner.robot_profiling import measure_robot_side
    from fleetslam.progress import Progress
    from fleetslam.tables import format_table

    if args.paper or args.profile or args.robot_profile:
        raise ValueError("--robot-side measures this machine as the robot: no --paper / "
                         "--profile / --robot-profile")
    if not args.source:
        # The built-in scene is generated with the cloud extra; a robot has its own frames.
        raise ValueError("--robot-side needs --source: a recording (or camera) of this robot")
    config = _apply_topics(args, config)
    sequence = open_source(args.source, None, config.source)
    frames = min(config.planner.profile_frames, len(sequence))
    progress = Progress(f"robot side {args.source}", frames, enabled=not args.quiet)
    robot = measure_robot_side(sequence, args.source, config, frames, progress.update)
    path = Path(args.save_profile) if args.save_profile else \
        (Path(args.out) if args.out else _default_out("plan")) / "robot_profile.json"
    robot.save(path)
    print(f"robot side of {args.source} ({robot.frames} frames, {robot.host}):")
    print(format_table(["stage", "median ms", "p95 ms"],
                       [[n, m, p] for n, m, p in zip(robot.stages, robot.stage_ms,
                                                     robot.stage_ms_p95)]))
    print(format_table(["point", "kB per frame"],
                       [[k, b / 1000] for k, b in enumerate(robot.frame_bytes)]))
    print(f"keyframe upload: {robot.keyframe_bytes / 1000:.1f} kB")
    print(f"wrote {path}; plan with it beside a profile measured where the cloud runs: "
          f"fleetslam plan --profile CLOUD.json --robot-profile {path}")
    return 0


def cmd_certs(args: argparse.Namespace, config: Config) -> int:
    from fleetslam.transport.certs import lab_robots, make_lab

    for robot in args.robot:
        keys_check(robot)
    files = make_lab(Path(args.out), args.host or ["localhost", "127.0.0.1"], args.robot)
    print(f"lab CA and certificates in {args.out}/ (keep ca.key off the robots); "
          f"robots admitted by the cloud's access control: "
          f"{', '.join(lab_robots(Path(args.out))) or 'none'}")
    tls = f"tls/HOST:{DEFAULT_ENDPOINT.rpartition(':')[2]}"
    print(f"cloud:   fleetslam --zenoh-config {files['cloud']} cloud --listen {tls} ...")
    print(f"clients: fleetslam --zenoh-config {files['client']} merge --connect {tls}")
    print(f"or several workers: fleetslam --zenoh-config {files['cloud']} router --listen "
          f"{tls}, then on each worker machine: fleetslam --zenoh-config "
          f"{files['worker']} cloud --connect {tls} --worker-id wN --out SHARED")
    for robot in args.robot:
        print(f"robot {robot}: fleetslam --zenoh-config {files[robot]} robot --id {robot} "
              f"--connect {tls} ...")
    return 0


def _add_global_options(parser: argparse.ArgumentParser, default: Any) -> None:
    """--config, --quiet, --zenoh-config; ``default``: None on the main parser,
    argparse.SUPPRESS on each command's (given there, they override)."""
    parser.add_argument("--config", default=default, metavar="FILE",
                        help="TOML file overriding the defaults of config.py (all of them: "
                        "fleetslam config)")
    parser.add_argument("--quiet", action="store_true",
                        default=False if default is None else default, help="no progress lines")
    parser.add_argument("--zenoh-config", metavar="FILE", default=default,
                        help="a Zenoh config file (JSON5) to start from: TLS, authentication, "
                        "access control, routers (also [transport] zenoh_config)")


def _add_cloud_request_options(parser: argparse.ArgumentParser) -> None:
    """--connect and --deadline of a command that asks a running cloud (merge, status)."""
    defaults = Config().transport
    parser.add_argument("--connect", default=None, metavar="ENDPOINT",
                        help="the cloud's Zenoh endpoint, as its --listen, or a router of "
                        "several workers (default from config [transport] endpoint: "
                        f"{defaults.endpoint}); tls/... needs --zenoh-config")
    parser.add_argument("--deadline", type=float, metavar="SECONDS",
                        help="wait this long for the cloud's first answer, then say what to "
                        "check (default from config: transport.ask_deadline_s, "
                        f"{defaults.ask_deadline_s:g} s)")


def _add_demo_command(sub: Any) -> None:
    demo = sub.add_parser("demo", help="run >= 2 robots on the built-in synthetic scene")
    demo.add_argument("--out", help="run folder to create (default runs/demo-<time>)")
    demo.add_argument("--overwrite", action="store_true", help="replace --out if it is an "
                      "earlier run folder")
    demo.add_argument("--scene", help="where the synthetic scene is generated or reused "
                      "(default: a cache folder)")
    demo.add_argument("--robots", type=int, help="number of robots (default from config: 2)")
    demo.add_argument("--frames", type=int, help="frames per robot (default from config)")
    demo.add_argument("--offload-at", default="paper",
                      help="split point of every robot: 0-3 or 6, 'paper' (3), or the first "
                      "cloud stage's name")
    demo.add_argument("--workers", type=int, default=1,
                      help="cloud workers: N > 1 runs a Zenoh router and N cloud worker "
                           "processes that share the robots (default 1: one cloud process)")
    _add_map_options(demo, "the robots search it and, where they find it, track in its "
                     "frame (the cloud's --map)")
    demo.add_argument("--in-process", action="store_true",
                      help="track, map and merge in this one process (no network)")
    demo.add_argument("--insecure", action="store_true",
                      help="plain TCP instead of TLS between the demo's processes")
    _add_link_options(demo)
    _add_view_options(demo)
    demo.set_defaults(func=cmd_demo)


def _add_run_command(sub: Any) -> None:
    run = sub.add_parser("run", help="run robots on TUM-layout folders or ROS bags")
    run.add_argument("--robot", action="append", required=True, metavar="SOURCE[:FIRST-LAST]",
                     help="a TUM-layout folder or a ROS bag (.bag, ROS 2 bag folder, .mcap), "
                     "optionally frame ranges of it (a-b,c-d); repeat per robot")
    run.add_argument("--name", action="append", help="robot name, once per --robot")
    run.add_argument("--camera", help="camera.json overriding the detected camera")
    _add_topic_options(run)
    _add_map_options(run, "the robots search it and, where they find it, track in its "
                     "frame; the run writes the extended map as its own map/ (DIR is never "
                     "changed)")
    _add_groundtruth_option(run)
    run.add_argument("--out", help="run folder to create (default runs/run-<time>)")
    run.add_argument("--overwrite", action="store_true", help="replace --out if it is an "
                     "earlier run folder (an interrupted one, say)")
    run.set_defaults(func=cmd_run)


def _add_cloud_command(sub: Any) -> None:
    cloud = sub.add_parser("cloud", help="serve robots over Zenoh: track, map, merge")
    where = cloud.add_mutually_exclusive_group()
    where.add_argument("--listen", default=None, metavar="ENDPOINT",
                       help="alone: be the Zenoh router robots connect to, listening here "
                            f"(default from config [transport] endpoint: {DEFAULT_ENDPOINT})")
    where.add_argument("--connect", default=None, metavar="ENDPOINT",
                       help="as one of several workers: connect to the Zenoh router there "
                            "(`fleetslam router`); robots are shared among the workers")
    cloud.add_argument("--worker-id", help="this worker's name in the placement (A-Z a-z 0-9 "
                       "_ -; default w-<host>-<pid>)")
    cloud.add_argument("--coordination", metavar="https://HOST:PORT",
                       help="with several workers: the etcd that decides which worker owns "
                            "which robot, fenced against partitions (config [placement] "
                            "coordination; every worker of a fleet is given the same)")
    cloud.add_argument("--coordination-certs", metavar="DIR",
                       help="the etcd's TLS folder `fleetslam certs` made (<lab>/etcd): its "
                            "CA and the workers' client certificate ([placement] "
                            "coordination_certs)")
    _add_map_options(cloud, "searched by every robot; a robot that finds it tracks in its "
                     "frame, and each merge writes the extended map to the store's map/ (DIR "
                     "is never changed); every worker gets the same")
    cloud.add_argument("--out", required=True, help="the store: maps, trajectories, "
                       "keyframes and checkpoints (reused after a restart; every worker of "
                       "a fleet is given the same folder, a shared volume across machines)")
    cloud.add_argument("--foxglove", metavar="PORT", type=int, help="serve the live topics "
                       "(poses, TF, each merge's maps) to the Foxglove app over its WebSocket "
                       "protocol on this port, no ROS 2 needed (pip install "
                       "'fleetslam[foxglove]'; host: [view] foxglove_host)")
    cloud.add_argument("--ros2-out", metavar="ENDPOINT", help="after each merge, publish the "
                       "global map, grid, OctoMap, constraints and global paths (transient "
                       "local) to the ROS 2 graph whose Zenoh router is there ([ros2_out])")
    _add_view_options(cloud)
    cloud.set_defaults(func=cmd_cloud)


def _add_router_command(sub: Any) -> None:
    router = sub.add_parser("router", help="a Zenoh router that cloud workers and robots "
                            "connect to")
    router.add_argument("--listen", default=None, metavar="ENDPOINT",
                        help="endpoint to listen on (default from config [transport] "
                        f"endpoint: {DEFAULT_ENDPOINT})")
    router.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help="another router to join (repeatable)")
    router.set_defaults(func=cmd_router)


def _add_robot_command(sub: Any) -> None:
    robot = sub.add_parser("robot", help="stream a recorded sequence or a camera to the cloud")
    robot.add_argument("--connect", default=None, metavar="ENDPOINT",
                       help="the cloud's Zenoh endpoint (default from config [transport] "
                       f"endpoint: {DEFAULT_ENDPOINT}); a robot may start first: it says so "
                       "and keeps trying for transport.reach_deadline_s "
                       f"({Config().transport.reach_deadline_s:g} s)")
    robot.add_argument("--id", required=True, help="robot id (A-Z a-z 0-9 _ -)")
    robot.add_argument("--localise-only", action="store_true", help="be placed in the "
                       "cloud's saved map (cloud --map) without moving or extending it; the "
                       "cloud refuses the robot if it has no map loaded")
    robot.add_argument("--source", required=True, metavar="SOURCE[:FIRST-LAST] | CAMERA",
                       help="TUM-layout folder (a synthetic scene's robot folder works too), "
                       "a ROS bag (.bag, ROS 2 bag folder, .mcap), optionally frame ranges, "
                       "or a live camera: " + live_specs())
    robot.add_argument("--live", action="store_true",
                       help="play the recording as a live camera: frames come on its clock "
                       "(--rate: 'recorded', the default, or frames per second) and the robot "
                       "takes the newest, skipping those it has no time for")
    robot.add_argument("--camera", help="camera.json overriding the detected camera")
    _add_topic_options(robot)
    robot.add_argument("--offload-at", default="paper",
                       help="split point: 0-3 (cloud tracks) or 6 (robot tracks), 'paper' "
                       "(3), the first cloud stage's name (e.g. match), or 'auto' (re-plan "
                       "point, ORB features and frame step from the measured link)")
    robot.add_argument("--plan-profile", help="with --offload-at auto: a saved profile "
                       "(fleetslam plan --save-profile); default: measured at start")
    robot.add_argument("--link-trace", metavar="FRAME:MBPS,...",
                       help="change the emulated bandwidth at these frames, e.g. "
                       "0:10,300:1,700:10")
    robot.add_argument("--rate", default=None,
                       help="a recording: 'max' (default: as fast as stages and link allow), "
                       "'recorded' (at the recording's timestamps) or frames per second, "
                       "each frame held back, none skipped; with --live, the camera's rate")
    _add_link_options(robot)
    robot.add_argument("--link-seed", type=int, help="seed of the link's loss pattern")
    robot.add_argument("--report", help="write the robot's measurements here (JSON)")
    robot.add_argument("--paper-yaml", metavar="DIR", help="also write every frame's message "
                       "as the paper's OpenCV YAML file (point 3 only)")
    robot.add_argument("--ros2-out", metavar="ENDPOINT", help="publish the robot's pose, /tf, "
                       "path and status live to the ROS 2 graph whose Zenoh router "
                       "(rmw_zenohd) is there, e.g. tcp/localhost:7447 ([ros2_out])")
    robot.set_defaults(func=cmd_robot)


def _add_merge_command(sub: Any) -> None:
    merge = sub.add_parser("merge", help="ask a running cloud to merge the finished maps")
    _add_cloud_request_options(merge)
    merge.set_defaults(func=cmd_merge)


def _add_status_command(sub: Any) -> None:
    status = sub.add_parser("status", help="ask a running cloud which robots it serves and "
                            "how their maps are joined")
    _add_cloud_request_options(status)
    status.set_defaults(func=cmd_status)


def _add_plan_command(sub: Any) -> None:
    planner = sub.add_parser("plan", help="choose the offloading point: the paper's energy "
                             "model and a time model on measured (or the paper's) costs")
    planner.add_argument("--paper", action="store_true",
                         help="the paper's own stage times, payloads and parameters")
    planner.add_argument("--profile", help="a saved profile (JSON) to plan with")
    planner.add_argument("--source", metavar="SOURCE[:FIRST-LAST]",
                         help="measure a profile on this sequence folder or ROS bag "
                         "(default: the built-in synthetic scene)")
    _add_topic_options(planner)
    planner.add_argument("--frames", type=int, help="frames to measure (default from config)")
    planner.add_argument("--save-profile", help="write the profile planned with here (JSON: "
                         "measured, or with --robot-profile's side in it)")
    planner.add_argument("--robot-side", action="store_true",
                         help="measure only the robot's side (its stages, the bytes it "
                         "sends) on --source, with the base install; writes --save-profile "
                         "(default OUT/robot_profile.json)")
    planner.add_argument("--robot-profile", help="the robot's side measured on the robot "
                         "(--robot-side): its stage times and payloads replace those of "
                         "the profile planned with")
    planner.add_argument("--bandwidth-mbps", type=float,
                         help="link bandwidth (default from config: 10)")
    planner.add_argument("--latency-ms", type=float, help="one-way link latency")
    planner.add_argument("--sweep", action="store_true",
                         help=f"every bandwidth of {', '.join(f'{b:g}' for b in SWEEP_MBPS)} "
                         "Mbit/s")
    planner.add_argument("--objective", choices=OBJECTIVES,
                         help="what to minimise / maximise (default from config: energy)")
    planner.add_argument("--out", help="folder for plan.json and the plots (default "
                         "runs/plan-<time>)")
    planner.set_defaults(func=cmd_plan)


def _add_certs_command(sub: Any) -> None:
    certs = sub.add_parser("certs", help="make a lab's TLS material: a CA, the cloud's and "
                           "each robot's certificate, and the Zenoh config files using them")
    certs.add_argument("--out", required=True, help="folder to create (keep ca.key safe)")
    certs.add_argument("--host", action="append",
                       help="a name or address the robots reach the cloud by (repeat; "
                       "default localhost and 127.0.0.1)")
    certs.add_argument("--robot", action="append", default=[],
                       help="a robot id (repeat); in an existing lab, adds the robot (then "
                       "restart the cloud: its access control admits the lab's robots)")
    certs.set_defaults(func=cmd_certs)


def _add_report_command(sub: Any) -> None:
    report = sub.add_parser("report", help="(re)build a finished run's report/ (PNG plots "
                            "and report.html); prints the page's path")
    report.add_argument("run_dir", metavar="RUN_DIR", help="a run folder with summary.json "
                        "(a `fleetslam run`'s, a demo's or a cloud's --out store)")
    _add_groundtruth_option(report)
    report.set_defaults(func=cmd_report)


def _add_groundtruth_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--groundtruth", action="append", metavar="[NAME=]FILE",
                        help="a TUM-format ground-truth file for a robot whose recording has "
                        "none (a bag): FILE goes to the robots in order, NAME=FILE to robot "
                        "NAME; repeat per robot. Read only after the run, to score it")


def _add_export_command(sub: Any) -> None:
    export = sub.add_parser("export", help="write a finished run's results as ROS 2 messages "
                            "in an MCAP file (Foxglove, ros2 bag play); a run writes "
                            "run.mcap itself unless [outputs] mcap = false")
    export.add_argument("run_dir", metavar="RUN_DIR", help="a run folder with summary.json")
    export.add_argument("--mcap", required=True, metavar="FILE", help="the MCAP file to write")
    export.set_defaults(func=cmd_export)


def _add_generate_command(sub: Any) -> None:
    gen = sub.add_parser("generate", help="write the synthetic scene in TUM layout")
    gen.add_argument("--out", help="scene folder (default: the demo's cache folder)")
    gen.set_defaults(func=cmd_generate)


def _add_vocabulary_command(sub: Any) -> None:
    vocab = sub.add_parser("vocabulary", help="train a bag-of-words vocabulary on ORB "
                           "descriptors of your own images (for [place_recognition] method = "
                           "\"bag_of_words\")")
    vocab.add_argument("--images", nargs="+", required=True, metavar="DIR",
                       help="folders of colour images (TUM layout, 7-Scenes, or plain)")
    vocab.add_argument("--every", type=int, default=5, help="use every n-th image "
                       "(neighbouring video frames repeat each other)")
    vocab.add_argument("--out", required=True, metavar="FILE.npz")
    vocab.set_defaults(func=cmd_vocabulary)


def _add_view_command(sub: Any) -> None:
    view = sub.add_parser("view", help="open a finished run's maps and trajectories in rerun "
                          "(needs pip install 'fleetslam[view]')")
    view.add_argument("run_dir", metavar="RUN_DIR", help="a run folder (runs/<command>-<time>)")
    view.add_argument("--save", metavar="FILE.rrd", help="write a recording (open it with "
                      "rerun FILE.rrd) instead of spawning a viewer")
    view.set_defaults(func=cmd_view)


def _add_config_command(sub: Any) -> None:
    settings = sub.add_parser("config", help="print every setting as a TOML file to start "
                              "from: its value (the defaults, or with --config those in "
                              "effect), what it means and what it may be")
    settings.add_argument("--markdown", action="store_true", help="the defaults as the "
                          "reference page docs/config.md instead")
    settings.set_defaults(func=cmd_config)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fleetslam", description="Multi-robot RGB-D SLAM with partial offloading and "
        "FS-HICP map merging.")
    _add_global_options(parser, None)
    parser.add_argument("--version", action="version", version=f"fleetslam {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    # The same options after the command too: `fleetslam run --config f.toml` as well as
    # `fleetslam --config f.toml run` (there, unset ones keep what was given before it).
    common = argparse.ArgumentParser(add_help=False)
    _add_global_options(common, argparse.SUPPRESS)
    sub.add_parser = functools.partial(sub.add_parser, parents=[common])  # type: ignore
    # In the order `fleetslam --help` lists them.
    for add in (_add_demo_command, _add_run_command, _add_cloud_command, _add_router_command,
                _add_robot_command, _add_merge_command, _add_status_command,
                _add_plan_command, _add_certs_command, _add_report_command,
                _add_export_command, _add_generate_command, _add_vocabulary_command,
                _add_view_command, _add_config_command):
        add(sub)
    return parser


# What the cloud extra brings (pyproject.toml), by the name a missing one is imported as.
CLOUD_EXTRA_MODULES = ("gtsam", "small_gicp", "faiss", "scipy", "octomap", "matplotlib",
                       "cryptography", "rosbags", "mcap")


def _check_endpoints(args: argparse.Namespace, config: Config) -> None:
    """Every --listen / --connect endpoint, before any work and before Zenoh sees it; a
    command taking one but given none (cloud, router, robot) uses [transport] endpoint."""
    zenoh_config = config.transport.zenoh_config or None
    flags = [f for f in ("listen", "connect") if hasattr(args, f)]
    for flag in flags:
        given = getattr(args, flag)
        for endpoint in given if isinstance(given, list) else [given]:
            if endpoint is not None:
                check_endpoint(endpoint, f"--{flag}", zenoh_config)
    where = f"{args.config}: transport.endpoint" if args.config else "transport.endpoint"
    if flags and not any(getattr(args, f) for f in flags):
        check_endpoint(config.transport.endpoint, where, zenoh_config)
    # A lone cloud and a router listen: a taken port is said before anything is made.
    if args.command == "router" or (args.command == "cloud" and not args.connect):
        check_listenable(args.listen or config.transport.endpoint,
                         "--listen" if args.listen else where)


def _stacks_on_request() -> None:
    """`kill -USR1 <pid>` writes every thread's stack to stderr and lets the process go on:
    where a robot or cloud that seems stuck is waiting (launch.dump_stacks asks for it).
    Not where stderr is no file (main called inside another program that captures it)."""
    if not hasattr(signal, "SIGUSR1"):
        return
    try:
        faulthandler.register(signal.SIGUSR1, file=sys.stderr, all_threads=True)
    except (AttributeError, ValueError, OSError):  # io.UnsupportedOperation is both
        pass


def main(argv: list[str] | None = None) -> int:
    # small_gicp's OpenMP threads busy-wait by default, which slows everything else on a
    # 2-core robot or a shared server; they must sleep instead.
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    _stacks_on_request()
    if os.environ.get("RUST_LOG"):  # Zenoh's own log (why a session did not open) on request
        import zenoh

        zenoh.try_init_log_from_env()
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        config = load_config(args.config)
        if args.zenoh_config:
            if not Path(args.zenoh_config).is_file():
                raise ValueError(f"{args.zenoh_config}: no such Zenoh config file")
            config = config.with_values({"transport.zenoh_config": args.zenoh_config},
                                        flag="--zenoh-config")
        _check_endpoints(args, config)
        return args.func(args, config)
    except (ValueError, FileExistsError, RuntimeError, TimeoutError) as exc:
        print(f"fleetslam: error: {exc}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:
        if exc.name is None or exc.name.split(".")[0] not in CLOUD_EXTRA_MODULES:
            raise
        # A robot's install (numpy, OpenCV, Zenoh, zstd) runs `fleetslam robot`; the rest
        # needs the cloud's libraries.
        print(f"fleetslam: error: `fleetslam {args.command}` needs the cloud extra: "
              f"pip install 'fleetslam[cloud]' (no module named {exc.name!r})",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fleetslam: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
