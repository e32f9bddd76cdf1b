"""Robots on 1, 2 and 4 cloud workers behind one Zenoh router: the aggregate frame rate the
workers sustain, per-frame latency and the CPU each worker used; then the same with each
worker pinned to its own core, to show throughput grows with the cores given.

    .venv/bin/python bench/worker_scaling.py [--robots 8] [--frames 150] [--workers 1,2,4]
        [--pinned 1,2] [--load 0.8] [--ten-fps-from N]

Robots alternate between real sequences (7-Scenes redkitchen, 150-frame pieces, and TUM
fr1_rpy 0-149; with --frames above 150, fr1_rpy's length, every robot plays 7-Scenes from
frame 0); their messages at offloading point 3 are made before the clock starts
(bench/fleet.py), then published over Zenoh to the router as robots do. Per setting, fresh
router and workers sharing one store folder:
  1. saturation: every robot sends all its frames at once; rate = frames / span;
  2. paced: fresh sessions at (load x sustained / robots) fps each; latency median, p95;
  3. 10 fps: as many robots as the saturated rate allows at 10 fps each (at most --robots;
     --ten-fps-from N: N robots), then one robot fewer at a time until the latency p95 is
     under 300 ms: the fleet that setting really sustains at 10 fps per robot.
Online ATE: each robot's poses as the cloud answered them, against its ground truth (after
the run); median / max over the phase's robots. After each phase its robots end their
sessions as robots do (without keyframe images), outside the phase's clock: a worker holds
at most transport.max_sessions sessions, and idle ones stay for transport.idle_session_s.
CPU per worker: user + system seconds of the worker and its local-mapping and place-search
processes over the phase, divided by the phase's wall time (1.0 = one core busy). The wall
time, not the frames' span: when frames are dropped, the phase ends only after idle_s
without feedback, and the niced work that goes on meanwhile was divided by the span alone
(up to 7.6 "cores" on a 2-core machine).
Local BA per phase (each robot's robot.json, medians over the robots): keyframes, BAs applied
and superseded, and a BA's request-to-applied split into its wait in its worker's queue and
its solve there (wall and CPU seconds of the solving process).
Writes bench/results/worker_scaling.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from cpu_account import CpuAccount, speed_probe_ms
from fleet import Fleet, robot_messages, robot_messages_for
from shared_data import SEVEN_SCENES, TUM_RPY

from fleetslam.cloud.coordination.coordination_service import EtcdService
from fleetslam.launch import CloudClient, free_endpoint, start_router, start_worker, stop_all
from fleetslam.tables import format_table
from fleetslam.transport.zenoh_session import open_connecting

# A fleet at 10 fps per robot counts as sustained when its latency p95 stays under this.
SUSTAINED_P95_MS = 300.0


# The kinds of phase a setting runs, in this order (see the docstring).
PHASES = ("saturation", "paced", "10fps")

# Frames of the shared TUM fr1_rpy piece: a robot asked for more plays 7-Scenes instead.
TUM_FRAMES = 150


def prepare(n: int, frames: int) -> list[tuple[list[bytes], dict, Path]]:
    """Each robot's messages, camera and sequence: 7-Scenes pieces and TUM fr1_rpy
    alternating, or 7-Scenes only when a robot is to send more frames than fr1_rpy has.
    Robots that send the same piece share its messages (made once: the front end takes
    about 12 ms a frame, so 20 robots x 600 frames would take minutes each)."""
    out, made = [], {}
    for i in range(n):
        if i % 2 == 0 or frames > TUM_FRAMES:
            nth = i if frames > TUM_FRAMES else i // 2  # which 7-Scenes robot this is
            piece = (SEVEN_SCENES, nth * frames % max(600 - frames + 1, 1), frames)
        else:
            piece = (TUM_RPY, 0, frames)
        if piece not in made:
            made[piece] = robot_messages(f"r{i}", piece[1], piece[2], piece[0])
        out.append((*made[piece], piece[0]))
    return out


def run_setting(n_workers: int, pinned: bool, prepared: list, load: float, work: Path,
                placement: str = "etcd", config: str | None = None,
                ten_fps_from: int | None = None,
                kinds: tuple[str, ...] = PHASES) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    endpoint = free_endpoint()
    # With etcd (as `demo --workers` runs them), every worker is placed and fenced by it.
    etcd = EtcdService(work / "etcd").start() if placement == "etcd" else None
    extra = ["--coordination", etcd.endpoint] if etcd else []
    router = start_router(endpoint, work / "router.log")
    cores = os.cpu_count() or 1
    workers = {f"w{i}": start_worker(endpoint, f"w{i}", work / "store", work / f"w{i}.log",
                                     config_path=config, cpus=[i % cores] if pinned else None,
                                     extra=extra)
               for i in range(n_workers)}
    client = CloudClient(endpoint)
    z = open_connecting(endpoint)
    account = CpuAccount({w: p.pid for w, p in workers.items()}, router.pid,
                         etcd.pid if etcd is not None else None)
    results: dict[str, dict] = {}
    try:
        deadline = time.monotonic() + 60
        while len(client.status(timeout=30).get("answered", [])) < n_workers:
            if time.monotonic() > deadline:
                raise RuntimeError("the workers did not all answer within 60 s")
            time.sleep(0.5)
        phases = [p for p in ("saturation", "paced") if p in kinds]
        if "saturation" not in kinds:  # the 10 fps phases alone, from ten_fps_from robots
            phases.append(f"10fps x{min(len(prepared), ten_fps_from or len(prepared))}")
        while phases:
            phase = phases.pop(0)
            if phase == "saturation":
                fps, chosen = None, prepared
            elif phase == "paced":
                fps, chosen = load * results["saturation"]["cloud_fps"] / len(prepared), prepared
            else:
                n = int(phase.split("x")[1])
                fps, chosen = 10.0, prepared[:n]
            tag = {"saturation": "s", "paced": "p"}.get(phase, f"t{len(chosen)}-")
            robots = {f"{tag}{i}": (robot_messages_for(f"{tag}{i}", msgs), cam)
                      for i, (msgs, cam, _) in enumerate(chosen)}
            sequences = {f"{tag}{i}": sequence for i, (_, _, sequence) in enumerate(chosen)}
            fleet = Fleet(z, robots)
            fleet.hello()
            per_worker = placement_of(client, robots, workers)
            probe_ms = speed_probe_ms()
            before = account.snapshot()
            print(f"{n_workers} worker(s){' pinned' if pinned else ''}, {phase}: "
                  f"{len(robots)} robots {'all at once' if fps is None else f'at {fps:.1f} fps'}"
                  f"; placement {per_worker}", flush=True)
            fleet.send(fps)
            result = fleet.result(idle_s=20.0)
            after = account.snapshot()
            wall = after.wall - before.wall
            cpu = CpuAccount.worker_cores(before, after)
            shares = CpuAccount.shares(before, after)
            by_worker = {w: [1000 * (fleet.got[k] - fleet.sent[k]) for k in fleet.got
                             if k[0] in mine and k in fleet.sent]
                         for w, mine in per_worker.items()}
            result["latency_ms_p95_per_worker"] = {
                w: float(np.percentile(v, 95)) if v else None for w, v in by_worker.items()}
            result["merger_worker"] = merger_worker(work, workers)
            ate = fleet.online_ate_cm(sequences)
            result.update(offered_fps_per_robot=fps, wall_s=wall, robots=len(robots),
                          placement=per_worker, cpu_cores_per_worker=cpu, online_ate_cm=ate,
                          machine_cores=shares, speed_probe_ms=probe_ms)
            results[phase] = result
            if phase == "saturation" and "10fps" in kinds:
                n = int(min(len(prepared), ten_fps_from if ten_fps_from is not None
                            else result["cloud_fps"] // 10))
                phases.append(f"10fps x{max(n, 1)}")
            ended = fleet.end(timeout_s=120.0)
            if ended < len(robots):
                print(f"  {len(robots) - ended} of {len(robots)} robots' sessions did not end "
                      "within 120 s", flush=True)
            result["local_mapping"] = local_mapping_of(work / "store", robots)
            fleet.close()
            # 10 fps per robot: fewer robots until that fleet is really sustained.
            if phase.startswith("10fps") and result["latency_ms_p95"] > SUSTAINED_P95_MS \
                    and len(chosen) > 1:
                phases.append(f"10fps x{len(chosen) - 1}")
    finally:
        z.close()
        client.close()
        stop_all([*workers.values(), router])
        if etcd is not None:
            etcd.stop()
    return results


def placement_of(client: CloudClient, robots: dict, workers: dict) -> dict[str, list[str]]:
    """Which worker serves each of ``robots``, from the cloud's status. A worker answers
    status from a view at most 0.2 s old (cloud/operator_requests.py), so a status asked
    right after the hellos may not list them yet: asked again, up to 10 s."""
    deadline = time.monotonic() + 10.0
    while True:
        listed = client.status(timeout=30)["robots"]
        if set(robots) <= set(listed) or time.monotonic() > deadline:
            return {w: sorted(r for r, v in listed.items()
                              if v.get("worker") == w and r in robots) for w in workers}
        time.sleep(0.25)


def local_mapping_of(store: Path, robots: dict) -> dict[str, float]:
    """Medians over a phase's robots (from each robot.json, written at its session's end):
    keyframes, local BAs applied and superseded, and a BA's way from request to applied
    (median ms per robot): its wait in the worker's queue, its solve there (wall, CPU)."""
    rows = []
    for rid in robots:
        path = store / rid / "robot.json"
        if not path.is_file():
            continue
        loops = json.loads(path.read_text())["loop_closing"]
        mapping = loops.get("local_mapping", {})
        if "request_to_applied" not in mapping:
            continue  # in-line
        rows.append({"keyframes": sum(loops["keyframe_reasons"].values()),
                     "applied": mapping["applied"], "superseded": mapping["superseded"],
                     "lag_ms": mapping["request_to_applied"]["median_ms"],
                     "queued_ms": mapping["queued"]["median_ms"],
                     "solve_ms": loops["local_ba"]["median_ms"],
                     "solve_cpu_ms": mapping["solve_cpu"]["median_ms"]})
    return {k: float(np.median([r[k] for r in rows if r[k] is not None]))
            for k in rows[0]} if rows else {}


def merger_worker(work: Path, workers: dict) -> str | None:
    """The worker that merges (the last to say so in its log), or None."""
    said: list[tuple[str, str]] = []
    for w in workers:
        log_path = work / f"{w}.log"
        if log_path.exists():
            said += [(line[:23], w) for line in log_path.read_text(errors="replace").splitlines()
                     if f"worker {w} merges now" in line]
    return max(said)[1] if said else None


def _ate_range(ate: dict[str, float]) -> str:
    """The robots' online ATE (cm): median and max over the robots of a phase."""
    if not ate:
        return "-"
    values = sorted(ate.values())
    return f"{values[len(values) // 2]:.2f} / {values[-1]:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=8)
    parser.add_argument("--frames", type=int, default=150, help="frames per robot")
    parser.add_argument("--workers", default="1,2,4", help="worker counts, unpinned")
    parser.add_argument("--pinned", default="1,2", help="worker counts, one core each")
    parser.add_argument("--load", type=float, default=0.8,
                        help="paced run: offered rate as a fraction of the sustained rate")
    parser.add_argument("--placement", default="etcd",
                        help="comma list of liveliness, etcd: how workers agree on robots")
    parser.add_argument("--configs", default="",
                        help="comma list of cloud config files (TOML) to compare side by "
                        "side, each a setting of its own; empty: the defaults")
    parser.add_argument("--runs", type=int, default=1,
                        help="runs of every setting, alternating (min-max reported)")
    parser.add_argument("--ten-fps-from", type=int, default=None, metavar="N",
                        help="start the 10 fps phases at N robots (at most --robots) instead "
                        "of the saturated rate's estimate, which a noisy saturation phase "
                        "can put below what the workers sustain")
    parser.add_argument("--phases", default=",".join(PHASES),
                        help="comma list of the phases to run; without saturation, paced "
                        "cannot run and the 10 fps phases start at --ten-fps-from (default "
                        "--robots) on workers that served no robot before")
    parser.add_argument("--out", default="bench/results/worker_scaling.json")
    parser.add_argument("--keep", action="store_true",
                        help="keep each setting's store and logs (1.5-4 GB a setting of 20 "
                             "robots x 600 frames) under worker-scaling-runs/ next to --out; "
                             "default: deleted once the setting is measured")
    args = parser.parse_args()
    for folder in (SEVEN_SCENES, TUM_RPY):
        if not folder.exists():
            sys.exit(f"{folder} missing: this benchmark needs ../shared/data")
    print(f"preparing {args.robots} x {args.frames} messages (robot stages, point 3) ...",
          flush=True)
    prepared = prepare(args.robots, args.frames)
    out = Path(args.out)
    work = out.parent / "worker-scaling-runs" / time.strftime("%Y%m%d-%H%M%S")
    placements = [p for p in args.placement.split(",") if p]
    if not set(placements) <= {"liveliness", "etcd"}:
        sys.exit(f"--placement {args.placement}: give liveliness, etcd or both")
    settings = [(int(n), False) for n in args.workers.split(",") if n] + \
        [(int(n), True) for n in args.pinned.split(",") if n]
    kinds = tuple(p for p in args.phases.split(",") if p)
    if not set(kinds) <= set(PHASES) or ("paced" in kinds and "saturation" not in kinds):
        sys.exit(f"--phases {args.phases}: a comma list of {', '.join(PHASES)}; paced needs "
                 "saturation")
    configs = [c or None for c in args.configs.split(",")]
    for c in configs:
        if c is not None and not Path(c).is_file():
            sys.exit(f"--configs: {c} is not a file")
    results = {}
    for run in range(args.runs):
        for n, pinned in settings:
            for placement in placements:
                for config in configs:
                    name = (f"{n} worker{'s' if n > 1 else ''}"
                            f"{', 1 core each' if pinned else ''}"
                            + (f", {placement}" if len(placements) > 1 else "")
                            + (f", {Path(config).stem if config else 'defaults'}"
                               if len(configs) > 1 else "")
                            + (f", run {run + 1}" if args.runs > 1 else ""))
                    folder = work / name.replace(" ", "_").replace(",", "")
                    results[name] = run_setting(n, pinned, prepared, args.load, folder,
                                                placement, config, args.ten_fps_from, kinds)
                    if not args.keep:
                        shutil.rmtree(folder, ignore_errors=True)
    rows = []
    for name, phases in results.items():
        for phase, r in phases.items():
            cpu = r["cpu_cores_per_worker"]
            rows.append([name, phase, r["robots"], r["frames_tracked"], r["frames_dropped"],
                         "all at once" if r["offered_fps_per_robot"] is None
                         else f"{r['offered_fps_per_robot'] * r['robots']:.1f}",
                         r["cloud_fps"], r["latency_ms_median"], r["latency_ms_p95"],
                         " ".join(f"{v:.2f}" for v in cpu.values()),
                         " ".join("-" if v is None else f"{v:.0f}"
                                  for v in r.get("latency_ms_p95_per_worker", {}).values()),
                         r.get("merger_worker") or "-",
                         _ate_range(r["online_ate_cm"]),
                         " ".join(str(len(v)) for v in r["placement"].values())])
    print(format_table(["setting", "run", "robots", "frames", "dropped", "offered fps",
                        "sustained fps", "latency ms median", "latency ms p95",
                        "cores used per worker", "p95 ms per worker", "merger on",
                        "online ATE cm", "robots per worker"], rows))
    print("Where the machine's cores went in each phase (cores; bench/cpu_account.py), and the "
          "speed probe timed just before it (ms; higher = a slower machine):")
    parts = ["tracking", "background", "router", "etcd", "bench", "other", "steal", "idle"]
    print(format_table(["setting", "run", "speed probe ms", *parts,
                        "worker CPU ms a frame"],
                       [[name, phase, r["speed_probe_ms"],
                         *(r["machine_cores"][k] for k in parts),
                         1000 * (r["machine_cores"]["tracking"] + r["machine_cores"]["background"])
                         * r["wall_s"] / max(r["frames_tracked"], 1)]
                        for name, phases in results.items() for phase, r in phases.items()]))
    print("Local BA per robot (medians over the phase's robots; ms: a BA's request to "
          "applied, its wait in the worker's queue, its solve there, wall and CPU):")
    mapping_keys = ["keyframes", "applied", "superseded", "lag_ms", "queued_ms", "solve_ms",
                    "solve_cpu_ms"]
    print(format_table(["setting", "run", *mapping_keys],
                       [[name, phase, *(r.get("local_mapping", {}).get(k, "-")
                                        for k in mapping_keys)]
                        for name, phases in results.items() for phase, r in phases.items()]))
    summary: dict[str, list[tuple[float, int]]] = {}
    for name, phases in results.items():
        ok = [r["robots"] for p, r in phases.items() if p.startswith("10fps")
              and r["latency_ms_p95"] <= SUSTAINED_P95_MS]
        saturated = phases.get("saturation", {}).get("cloud_fps", float("nan"))
        print(f"{name}: saturated {saturated:.1f} fps; sustains "
              f"{max(ok) if ok else 'no'} robot(s) at 10 fps each with latency p95 <= "
              f"{SUSTAINED_P95_MS:.0f} ms")
        summary.setdefault(name.split(", run ")[0], []).append(
            (saturated, max(ok) if ok else 0))
    if args.runs > 1:
        for setting, runs in summary.items():
            fps, fleet = [r[0] for r in runs], [r[1] for r in runs]
            print(f"{setting}, {len(runs)} runs: saturated {min(fps):.1f}-{max(fps):.1f} fps; "
                  f"robots at 10 fps with p95 <= {SUSTAINED_P95_MS:.0f} ms: "
                  f"{min(fleet)}-{max(fleet)}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"robots": args.robots, "frames_per_robot": args.frames,
                               "cores": os.cpu_count(), "results": results}, indent=2))
    if args.keep:
        print(f"each setting's store and logs kept under {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
