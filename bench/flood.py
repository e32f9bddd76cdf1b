"""Flood: hostile and garbage messages on every fleet key while an authenticated robot runs a
real sequence; the cloud must survive with bounded memory and the robot's ATE unchanged.

    .venv/bin/python bench/flood.py [--rate 2000] [--seconds 30] [--source SEQ:0-599]
        [--mix all|ends]

Everything runs as in a lab (`fleetslam certs`): the cloud is the Zenoh router with mutual
TLS and access control. Two runs of robot r1 (point 3, frames at the recorded rate), one
quiet and one under flood:
- an attacker holding robot r2's valid certificate sends ``--rate`` messages per second for
  ``--seconds``, round robin over every fleet key: its own keys (garbage, truncated and
  hostile frames that decode, fake keyframe uploads, bad hellos and JSON) and r1's, the
  cloud's and unknown robots' keys (forged ends, frames, uploads, merge requests, hellos
  for new ids), which the access control drops;
- an outsider without a certificate of the lab tries to connect twice a second.
With ``--mix ends`` the attacker instead opens a session on its own key and floods it with
``end`` messages that name a last frame never sent (issue 27: 7,500 ends at 500/s took a
cloud from 27 to 257 threads and 8.9 MB of log in 15 s).
The cloud's resident memory and threads are sampled every 0.25 s, its log's size read at
the end; r1's ATE is scored against ground truth after each run. Prints a table and writes
bench/results/flood.json (flood_ends.json with ``--mix ends``).

    .venv/bin/python bench/flood.py --valid 1 [--frame-rate 60] [--seconds 20]

``--valid N``: instead, N hostile robots (h1..hN, each with its own valid certificate and
session) send valid point-0 frames (real images, seq and timestamps moving forward) at
``--frame-rate`` each, ignoring flow control, beside r1. One run; what the cloud holds and
dropped per robot comes from its status at the flood's end (bench/results/flood_valid_N.json).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import struct
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from shared_data import SEVEN_SCENES  # noqa: E402

from fleetslam.config import Config  # noqa: E402
from fleetslam.datasets.recording import open_source  # noqa: E402
from fleetslam.datasets.tum import RgbdSequence  # noqa: E402
from fleetslam.evaluation.fleet import trajectory_ate  # noqa: E402
from fleetslam.launch import CloudClient, free_endpoint, start_cloud, start_robot, stop  # noqa: E402
from fleetslam.backend.robot_slam import RobotSlam  # noqa: E402
from fleetslam.pipeline.split import run_stages  # noqa: E402
from fleetslam.pipeline.states import CapturedFrame  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402
from fleetslam.transport import keys, protocol  # noqa: E402
from fleetslam.transport.certs import make_lab  # noqa: E402
from fleetslam.wire.envelope import Kind, seal  # noqa: E402
from fleetslam.wire.frames import _write_state, encode_frame_message  # noqa: E402
from fleetslam.wire.messages import KeyframeUpload, encode_keyframe  # noqa: E402

POINT = 3
ATTACKER, VICTIM = "r2", "r1"
# The payload of a frame message opens with (camera digest, index, timestamp).
HEAD = struct.Struct("<Iqd")


def attack_messages(folder: Path) -> list[tuple[str, bytes, str]]:
    """(key, payload, what) the attacker cycles through: made from real frames."""
    seq = RgbdSequence(folder)
    camera, config = seq.camera, Config()
    pipeline = RobotSlam.new(config, camera)
    states, frames = [], []
    for i, f in enumerate(seq):
        if i == 4:
            break
        frame = CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m)
        states.append(run_stages(pipeline.split(POINT)[0], frame, pipeline.sides))
        frames.append(f)
    good = states[1]
    nan_kp = good.keypoints.copy()
    nan_kp[0, 0] = np.nan
    outside = good.keypoints.copy()
    outside[:, 0] += camera.width
    hostile = [replace(good, keypoints=nan_kp), replace(good, keypoints=outside),
               replace(good, uv=good.uv + [300.0, 0.0]),
               replace(good, depth=np.full_like(good.depth, np.inf))]
    rng = np.random.default_rng(7)

    def frame(state, robot: str, seq_no: int) -> bytes:
        return encode_frame_message(state, POINT, robot, seq_no, camera, config.wire)

    hello = protocol.encode({"type": "hello", "protocol": protocol.PROTOCOL,
                             "offload_at": POINT, "camera": camera.to_dict(),
                             "source": "flood"})
    upload = KeyframeUpload.from_frame(frames[0].index, frames[0].timestamp, frames[0].rgb,
                                       frames[0].depth_raw, config.map.pixel_stride)
    kf = encode_keyframe(ATTACKER, 0, upload, config.wire)
    real = frame(states[2], ATTACKER, 5)
    out: list[tuple[str, bytes, str]] = [(keys.control(ATTACKER), hello, "hello")]
    for i, state in enumerate(hostile):
        out.append((keys.frame(ATTACKER), frame(state, ATTACKER, 10 + i), "hostile frame"))
    out += [
        (keys.frame(ATTACKER), frame(states[3], ATTACKER, 2**63 - 1), "seq 2^63"),
        (keys.frame(ATTACKER), frame(states[0], ATTACKER, 1), "timestamp backwards"),
        (keys.frame(ATTACKER), real[: len(real) // 2], "truncated frame"),
        (keys.frame(ATTACKER), rng.bytes(3000), "garbage"),
        (keys.keyframe(ATTACKER), kf, "keyframe not of the session"),
        (keys.keyframe(ATTACKER), rng.bytes(20000), "garbage"),
        (keys.control(ATTACKER), b"{" * 5000, "bad JSON"),
        (keys.control(ATTACKER), json.dumps({"type": "hello", "camera": {"fx": "x"}}).encode(),
         "bad hello"),
        # Not its keys: the access control drops these at the router.
        (keys.control(VICTIM), protocol.encode({"type": "end", "last_seq": 0}), "forged end"),
        (keys.frame(VICTIM), frame(states[3], VICTIM, 2**63 - 1), "forged frame"),
        (keys.keyframe(VICTIM), encode_keyframe(VICTIM, 0, upload, config.wire),
         "forged upload"),
        (keys.feedback(VICTIM), rng.bytes(200), "forged feedback"),
        (keys.CLOUD_CONTROL, protocol.encode(protocol.Request("merge")), "merge request"),
        (keys.control("x{:04d}"), hello, "hello for a new id"),
    ]
    return out


def end_messages(folder: Path) -> list[tuple[str, bytes, str]]:
    """The end flood: a hello (a session on the attacker's own key), then ends for a last
    frame that never comes, so each waits for it (the grace period)."""
    camera = RgbdSequence(folder).camera
    hello = protocol.encode({"type": "hello", "protocol": protocol.PROTOCOL,
                             "offload_at": POINT, "camera": camera.to_dict(),
                             "source": "flood"})
    end = protocol.encode(protocol.End(1000))
    return [(keys.control(ATTACKER), hello, "hello")] + \
        [(keys.control(ATTACKER), end, "end before any frame")] * 499


def _threads(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("Threads:"):
            return int(line.split()[1])
    return -1


def flood(endpoint: str, lab: dict[str, str], rate: float, seconds: float,
          messages: list[tuple[str, bytes, str]], result: Any) -> None:
    """The attacker's process: r2's certificate, and an outsider without one."""
    import zenoh

    from fleetslam.transport.zenoh_session import open_connecting

    session = open_connecting(endpoint, 30.0, lab[ATTACKER])
    start = time.monotonic()
    sent = refused = outsider_attempts = 0
    next_outsider = start
    n = int(rate * seconds)
    for i in range(n):
        key, data, _ = messages[i % len(messages)]
        if "{" in key:
            key = key.format(i % 10_000)
        session.put(key, data, congestion_control=zenoh.CongestionControl.DROP)
        sent += 1
        now = time.monotonic()
        if now >= next_outsider:
            next_outsider = now + 0.5
            outsider_attempts += 1
            config = zenoh.Config()
            config.insert_json5("mode", '"client"')
            config.insert_json5("connect/endpoints", json.dumps([endpoint]))
            config.insert_json5("connect/timeout_ms", "300")
            config.insert_json5("connect/exit_on_failure", "true")
            try:
                zenoh.open(config).close()
            except zenoh.ZError:
                refused += 1
        ahead = start + (i + 1) / rate - time.monotonic()
        if ahead > 0:
            time.sleep(ahead)
    session.close()
    result.put({"sent": sent, "seconds": time.monotonic() - start,
                "outsider_attempts": outsider_attempts, "outsider_refused": refused})


def valid_flood(endpoint: str, lab: dict[str, str], hostiles: list[str], frame_rate: float,
                seconds: float, folder: str, result: Any) -> None:
    """The hostile robots' process: each says hello, then sends valid point-0 frames at
    ``frame_rate`` without waiting for feedback. One real frame is encoded once; each message
    gets its own seq, index and timestamp (rewritten in the payload's head and the envelope),
    so encoding costs nothing and the cloud decodes and tracks every frame as valid."""
    import zenoh

    from fleetslam.transport.zenoh_session import open_connecting

    seq = RgbdSequence(Path(folder))
    f = next(iter(seq))
    writer, _ = _write_state(CapturedFrame(0, 0.0, f.rgb, f.depth_m), 0, seq.camera,
                             Config().wire)
    payload = b"".join(writer.sections())
    digest = HEAD.unpack_from(payload)[0]
    hello = protocol.encode({"type": "hello", "protocol": protocol.PROTOCOL, "offload_at": 0,
                             "camera": seq.camera.to_dict(), "source": "valid flood"})
    sessions = {r: open_connecting(endpoint, 30.0, lab[r]) for r in hostiles}
    for r, z in sessions.items():
        z.put(keys.control(r), hello)
    time.sleep(1.0)  # welcomed (a frame before the session opens is only refused)
    start = time.monotonic()
    sent = 0
    n = int(frame_rate * seconds)
    for i in range(1, n + 1):
        timestamp = 1.0 + i / frame_rate
        body = HEAD.pack(digest, i, timestamp) + payload[HEAD.size:]
        for r, z in sessions.items():
            z.put(keys.frame(r), seal(Kind.FRAME, r, i, timestamp, 0, body, compress=False),
                  congestion_control=zenoh.CongestionControl.DROP)
            sent += 1
        ahead = start + i / frame_rate - time.monotonic()
        if ahead > 0:
            time.sleep(ahead)
    for z in sessions.values():
        z.close()
    result.put({"sent": sent, "seconds": time.monotonic() - start,
                "frame_bytes": len(payload)})


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def run(name: str, runs: Path, lab: dict[str, str], source: str, flood_args: dict | None,
        hostiles: list[str] | None = None) -> dict:
    """One run of r1; ``flood_args`` with ``hostiles``: the valid-frame flood by those."""
    endpoint = free_endpoint().replace("tcp/127.0.0.1", "tls/localhost")
    out = runs / name
    cloud = start_cloud(endpoint, out, out / "cloud.log", zenoh_config=lab["cloud"])
    samples: list[tuple[float, float]] = []
    threads: list[int] = []
    attacker = None
    ctx = mp.get_context("spawn")
    result = ctx.Queue()
    t0 = time.monotonic()
    robots_at_end: dict = {}
    try:
        client = CloudClient(endpoint, 60.0, lab["client"])
        client.status(timeout=60.0)
        samples.append((time.monotonic() - t0, _rss_mb(cloud.pid)))  # its baseline
        if flood_args is not None and hostiles:
            attacker = ctx.Process(
                target=valid_flood, args=(endpoint, lab, hostiles, flood_args["frame_rate"],
                                          flood_args["seconds"], flood_args["folder"], result),
                daemon=True)
            attacker.start()
            time.sleep(3.0)  # the flood is on before the robot starts
        elif flood_args is not None:
            attacker = ctx.Process(
                target=flood, args=(endpoint, lab, flood_args["rate"], flood_args["seconds"],
                                    flood_args["messages"], result), daemon=True)
            attacker.start()
            time.sleep(3.0)  # the flood is on before the robot starts
        robot = start_robot(endpoint, VICTIM, source, POINT, out / "r1.log",
                            out / "r1_report.json", extra=["--rate", "recorded"],
                            zenoh_config=lab[VICTIM])
        deadline = time.monotonic() + 900.0
        while (robot.poll() is None or (attacker is not None and attacker.is_alive())) \
                and time.monotonic() < deadline:
            samples.append((time.monotonic() - t0, _rss_mb(cloud.pid)))
            threads.append(_threads(cloud.pid))
            if hostiles and attacker is not None and attacker.is_alive():
                robots_at_end = client.status(timeout=30.0, gather_s=0.0)["robots"]
            time.sleep(0.25)
        if robot.poll() != 0:
            raise RuntimeError(f"robot r1 failed: {robot.returncode} (see {out / 'r1.log'})")
        answered = client.status(timeout=30.0)["type"] == "status"
        threads.append(_threads(cloud.pid))
        client.close()
    finally:
        if attacker is not None and attacker.is_alive():
            attacker.terminate()
        stop(cloud)
    flood_stats = result.get(timeout=10.0) if flood_args is not None else {}
    robot_json = json.loads((out / VICTIM / "robot.json").read_text())
    ate = trajectory_ate(out / VICTIM / "trajectory.tum", open_source(source))
    rss = np.array([s[1] for s in samples])
    return {"run": name, "frames": robot_json["frames"], "keyframes": robot_json["keyframes"],
            "rss_mb_baseline": float(rss[0]), "robots_at_flood_end": robots_at_end,
            "transport": robot_json["transport"], "ate_m": ate["rmse_m"] if ate else None,
            "rss_mb_start": float(rss[0]), "rss_mb_max": float(rss.max()),
            "rss_mb_end": float(rss[-1]), "rss_samples": samples,
            "status_answered_after": answered, "wall_s": time.monotonic() - t0,
            "threads_start": threads[0], "threads_max": max(threads),
            "threads_end": threads[-1], "log_bytes": (out / "cloud.log").stat().st_size,
            "log_tracebacks": (out / "cloud.log").read_text(errors="replace").count(
                "Traceback"), **flood_stats}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=2000.0, help="messages per second")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--source", default=f"{SEVEN_SCENES}:0-599")
    parser.add_argument("--mix", choices=("all", "ends"), default="all",
                        help="every hostile message, or a flood of ends on the attacker's key")
    parser.add_argument("--out", default=None)
    parser.add_argument("--valid", type=int, default=0,
                        help="hostile robots sending valid point-0 frames (0: the mixed flood)")
    parser.add_argument("--frame-rate", type=float, default=60.0,
                        help="frames per second of each hostile robot (--valid)")
    args = parser.parse_args()
    runs = Path("/tmp") / f"fleetslam-flood-{time.strftime('%Y%m%d-%H%M%S')}"
    if args.valid:
        return main_valid(args, runs)
    name = "flood" if args.mix == "all" else "flood_ends"
    args.out = args.out or str(Path(__file__).parent / "results" / f"{name}.json")
    lab = {k: str(v) for k, v in make_lab(runs / "lab", ["localhost"], [VICTIM, ATTACKER]).items()}
    folder = Path(args.source.split(":")[0])
    messages = attack_messages(folder) if args.mix == "all" else end_messages(folder)
    quiet = run("quiet", runs, lab, args.source, None)
    flooded = run("flood", runs, lab, args.source, {"rate": args.rate, "seconds": args.seconds,
                                                    "messages": messages})
    rows = []
    for r in (quiet, flooded):
        t = r["transport"]
        rows.append([r["run"], r.get("sent", 0), r.get("sent", 0) / r.get("seconds", 1) if
                     r.get("sent") else 0, r["frames"], t.get("frames dropped (session busy)", 0),
                     sum(v for k, v in t.items() if k.startswith("rejected")),
                     100 * r["ate_m"], r["rss_mb_start"], r["rss_mb_max"], r["rss_mb_end"],
                     f"{r['threads_start']}/{r['threads_max']}/{r['threads_end']}",
                     r["log_bytes"] / 1e3, r["log_tracebacks"]])
    change = 100 * (flooded["ate_m"] - quiet["ate_m"]) / quiet["ate_m"]
    print(f"robot r1 on {args.source} (point {POINT}, recorded rate) over mutual TLS with "
          f"access control; attacker with r2's certificate")
    print(format_table(["run", "msgs sent", "msgs/s", "r1 frames", "r1 dropped",
                        "r1 rejected", "ATE cm", "cloud RSS start MB", "max MB", "end MB",
                        "threads start/max/end", "log kB", "tracebacks"],
                       rows))
    print(f"ATE change under flood: {change:+.2f} %; outsider connections refused: "
          f"{flooded.get('outsider_refused')} of {flooded.get('outsider_attempts')}; the "
          f"cloud answered status after the flood: {flooded['status_answered_after']}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"source": args.source, "rate": args.rate, "mix": args.mix,
                               "seconds": args.seconds, "ate_change_percent": change,
                               "attack_mix": sorted({w for _, _, w in messages}),
                               "runs": [quiet, flooded]}, indent=2))
    print(f"wrote {out}")


def main_valid(args: argparse.Namespace, runs: Path) -> None:
    hostiles = [f"h{i + 1}" for i in range(args.valid)]
    lab = {k: str(v) for k, v in make_lab(runs / "lab", ["localhost"],
                                          [VICTIM, *hostiles]).items()}
    r = run("valid flood", runs, lab, args.source,
            {"frame_rate": args.frame_rate, "seconds": args.seconds,
             "folder": args.source.split(":")[0]}, hostiles)
    robots = r["robots_at_flood_end"]
    rows = [[h, robots.get(h, {}).get("frames"), robots.get(h, {}).get("held_peak_mb", "-"),
             robots.get(h, {}).get("dropped_over_budget", "-")] for h in hostiles]
    t = r["transport"]
    print(f"{args.valid} hostile robot(s) sending valid point-0 frames at {args.frame_rate}/s "
          f"each for {args.seconds} s, ignoring flow control; r1 on {args.source} (point "
          f"{POINT}, recorded rate)")
    print(format_table(["hostile", "frames tracked", "held MB peak", "dropped over budget"],
                       rows))
    print(f"r1: {r['frames']} frames, ATE {100 * r['ate_m']:.2f} cm, dropped (session busy) "
          f"{t.get('frames dropped (session busy)', 0)}, dropped over budget "
          f"{t.get('frames dropped unread (over memory budget)', '-')}; cloud RSS baseline "
          f"{r['rss_mb_baseline']:.0f} MB, max {r['rss_mb_max']:.0f} MB, end "
          f"{r['rss_mb_end']:.0f} MB; hostile frames sent {r.get('sent')}")
    out = Path(args.out or Path(__file__).parent / "results" / f"flood_valid_{args.valid}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"source": args.source, "hostiles": args.valid,
                               "frame_rate": args.frame_rate, "seconds": args.seconds,
                               "run": r}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
