"""Four robots at once on one cloud process: the frame rate the cloud sustains and its
per-frame latency.

    .venv/bin/python bench/fleet.py [--robots 4] [--frames 300] [--load 0.8]
        [--local-mapping inline,async]

The robots' messages (offloading point 3, the paper's) are made from the real 7-Scenes
frames before the clock starts, so that robot computation on this same machine does not
take CPU from the cloud being measured; the bench then publishes them over Zenoh to a
separate cloud process, as robots do, and times each frame from publish to feedback.
  1. saturation: every robot sends all its frames at once; the cloud works through its
     queues; sustained rate = frames / (last feedback - first publish).
  2. paced: fresh sessions, each robot at (load x sustained / robots) frames per second;
     latency median and p95 (publish -> feedback; includes any queueing).
Both on a cloud with local BA in-line and on one with it in a worker process
(``--local-mapping``, tracking.local_mapping), one after the other; ``async-query-inline``
keeps the loop closer's database query on the tracking thread.
Writes bench/results/fleet.json.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np
from shared_data import SEVEN_SCENES

from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.launch import free_endpoint, start_cloud, stop
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.pipeline.split import run_stages
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.tables import format_table
from fleetslam.transport import keys, protocol
from fleetslam.transport.protocol import PROTOCOL
from fleetslam.transport.zenoh_session import open_connecting, put
from fleetslam.wire.frames import encode_frame_message
from fleetslam.wire.messages import decode_feedback

SEQ = SEVEN_SCENES
K = 3


def robot_messages(robot_id: str, first: int, frames: int, source: Path = SEQ
                   ) -> tuple[list[bytes], dict]:
    seq = RgbdSequence(source, first=first, last=first + frames - 1)
    pipeline = RobotSlam.new(Config(), seq.camera)
    stages = pipeline.split(K)[0]
    msgs = []
    for n, f in enumerate(seq):
        state = run_stages(stages, CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m),
                           pipeline.sides)
        msgs.append(encode_frame_message(state, K, robot_id, n, seq.camera, Config().wire))
    return msgs, seq.camera.to_dict()


class Fleet:
    """Publishes prepared messages for several robots and times their feedback."""

    def __init__(self, session, robots: dict[str, tuple[list[bytes], dict]]) -> None:
        self.z = session
        self.robots = robots
        self.sent: dict[tuple[str, int], float] = {}
        self.got: dict[tuple[str, int], float] = {}
        self.cloud_ms: list[float] = []
        # Each robot's poses as the cloud answered them (online tracking): (timestamp, pose).
        self.answered: dict[str, list[tuple[float, np.ndarray]]] = {rid: [] for rid in robots}
        self.done = threading.Event()
        self.total = sum(len(m) for m, _ in robots.values())
        self.replies: queue.Queue = queue.Queue()
        self.subs = []
        for rid in robots:
            self.subs.append(session.declare_subscriber(
                keys.feedback(rid), lambda s, rid=rid: self._on_feedback(rid, s)))
            self.subs.append(session.declare_subscriber(
                keys.reply(rid),
                lambda s, rid=rid: self.replies.put((rid, json.loads(s.payload.to_bytes())))))

    def _on_feedback(self, rid: str, sample) -> None:
        header, fb = decode_feedback(sample.payload.to_bytes())
        self.got[(rid, header.seq)] = time.monotonic()
        self.cloud_ms.append(fb.cloud_ms)
        if fb.tracked:
            self.answered[rid].append((fb.timestamp, fb.T_world_camera))
        if len(self.got) == self.total:
            self.done.set()

    def hello(self) -> None:
        waiting = set(self.robots)
        for _ in range(50):
            for rid in waiting:
                put(self.z, keys.control(rid), json.dumps({
                    "type": "hello", "protocol": PROTOCOL, "offload_at": K,
                    "camera": self.robots[rid][1], "source": str(SEQ)}).encode())
            deadline = time.monotonic() + 1.0
            while waiting and time.monotonic() < deadline:
                try:
                    rid, reply = self.replies.get(timeout=0.1)
                except queue.Empty:
                    continue
                if reply["type"] == "welcome":
                    waiting.discard(rid)
            if not waiting:
                return
        raise RuntimeError(f"no welcome for {sorted(waiting)}")

    def send(self, fps_per_robot: float | None) -> None:
        ids = sorted(self.robots)
        n = max(len(self.robots[r][0]) for r in ids)
        start = time.monotonic()
        for i in range(n):
            if fps_per_robot is not None:
                wait = start + i / fps_per_robot - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            for rid in ids:
                msgs = self.robots[rid][0]
                if i < len(msgs):
                    self.sent[(rid, i)] = time.monotonic()
                    put(self.z, keys.frame(rid), msgs[i])

    def result(self, idle_s: float) -> dict:
        """When every frame has its feedback, or none came for ``idle_s`` (the cloud drops
        the oldest waiting frames of a robot beyond transport.max_queued_frames)."""
        seen = -1
        while not self.done.wait(idle_s):
            if len(self.got) == seen:
                print(f"  no feedback for {idle_s:.0f} s: {self.total - seen} of "
                      f"{self.total} frames were dropped", flush=True)
                break
            seen = len(self.got)
        lat = np.array([1000 * (self.got[k] - self.sent[k]) for k in self.got if k in self.sent])
        span = max(self.got.values()) - min(self.sent.values())
        return {"frames_sent": len(self.sent), "frames_tracked": len(self.got),
                "frames_dropped": len(self.sent) - len(self.got),
                "cloud_fps": len(self.got) / span, "span_s": span,
                "latency_ms_median": float(np.median(lat)),
                "latency_ms_p95": float(np.percentile(lat, 95)),
                "cloud_ms_median": float(np.median(self.cloud_ms)),
                "cloud_ms_p95": float(np.percentile(self.cloud_ms, 95))}

    def online_ate_cm(self, sequences: dict[str, Path]) -> dict[str, float]:
        """ATE (cm, SE(3) alignment) of each robot's answered poses against the ground truth
        of its sequence (evaluation after the run: what tracking under this load gave)."""
        from fleetslam.datasets.tum import RgbdSequence
        from fleetslam.evaluation.fleet import ate_summary, ground_truth_at

        out = {}
        for rid, answered in self.answered.items():
            if len(answered) < 3:
                continue
            answered = sorted(answered, key=lambda a: a[0])
            times = np.array([t for t, _ in answered])
            poses = np.array([T for _, T in answered])
            ok, gt = ground_truth_at(times, RgbdSequence(sequences[rid]))
            ate = ate_summary(poses[ok], gt)
            if ate is not None:
                out[rid] = 100 * ate["rmse_m"]
        return out

    def end(self, timeout_s: float) -> int:
        """Every robot ends its session as a robot does at its end (no keyframe images: this
        fleet uploads none), so the next phase's robots find the cloud's sessions free
        (transport.max_sessions counts ended sessions no more). Robots whose "ended" came
        within ``timeout_s``."""
        waiting = set(self.robots)
        deadline = time.monotonic() + timeout_s
        while waiting and time.monotonic() < deadline:
            for rid in waiting:
                last = len(self.robots[rid][0]) - 1
                put(self.z, keys.control(rid), protocol.encode(protocol.End(
                    last, unavailable=frozenset(range(last + 1)))))
            resend = min(deadline, time.monotonic() + 10.0)
            while waiting and time.monotonic() < resend:
                try:
                    rid, reply = self.replies.get(timeout=0.2)
                except queue.Empty:
                    continue
                if reply.get("type") == "ended" or (reply.get("type") == "error"
                                                    and reply.get("answer_to") == "end"):
                    waiting.discard(rid)
        return len(self.robots) - len(waiting)

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=4)
    parser.add_argument("--frames", type=int, default=300, help="frames per robot")
    parser.add_argument("--load", type=float, default=0.8,
                        help="paced run: offered rate as a fraction of the sustained rate")
    parser.add_argument("--local-mapping", default="inline,async",
                        help="cloud runs, side by side: tracking.local_mapping of each "
                        "(inline, async, or async-query-inline: the loop query on the "
                        "tracking thread)")
    parser.add_argument("--out", default="bench/results/fleet.json")
    args = parser.parse_args()
    if not SEQ.exists():
        sys.exit(f"{SEQ} missing: this benchmark needs ../shared/data")
    starts = np.linspace(0, 600 - args.frames, args.robots).astype(int)
    print(f"preparing {args.robots} x {args.frames} messages (robot stages, point {K}) ...",
          flush=True)
    prepared = [robot_messages(f"r{i}", int(s), args.frames) for i, s in enumerate(starts)]
    out = Path(args.out)
    work = out.parent / "fleet-runs" / time.strftime("%Y%m%d-%H%M%S")
    results: dict[str, dict] = {}
    for mode in args.local_mapping.split(","):
        results[mode] = run_cloud(mode, prepared, args.robots, args.load, work / mode)
    rows = [[mode, phase, r["frames_tracked"], r["frames_dropped"],
             "all at once" if r["offered_fps_per_robot"] is None
             else f"{r['offered_fps_per_robot'] * args.robots:.1f}",
             r["cloud_fps"], r["latency_ms_median"], r["latency_ms_p95"],
             r["cloud_ms_median"], r["cloud_ms_p95"]]
            for mode, phases in results.items() for phase, r in phases.items()]
    print(format_table(["local mapping", "run", "frames", "dropped", "offered fps", "cloud fps",
                        "latency ms median", "latency ms p95", "cloud ms median",
                        "cloud ms p95"], rows))
    print(f"{args.robots} robots x {args.frames} frames of {SEQ.name}, offloading point {K}; "
          f"cores: {os.cpu_count()}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"robots": args.robots, "frames_per_robot": args.frames,
                               "cores": os.cpu_count(), "results": results}, indent=2))
    print(f"wrote {out}")


def run_cloud(mode: str, prepared: list, n_robots: int, load: float, work: Path) -> dict:
    """Both phases on a fresh cloud process whose local mapping runs ``mode``."""
    work.mkdir(parents=True, exist_ok=True)
    config = work / "cloud.toml"
    # "async-query-inline": local BA in the worker, the loop closer's database query on the
    # tracking thread (loop_closing.query_in_worker = false), to compare with "async".
    local_mapping = "async" if mode.startswith("async") else mode
    config.write_text(f'[tracking]\nlocal_mapping = "{local_mapping}"\n'
                      + ("[loop_closing]\nquery_in_worker = false\n"
                         if mode == "async-query-inline" else ""))
    endpoint = free_endpoint()
    cloud = start_cloud(endpoint, work / "cloud", work / "cloud.log", config_path=str(config))
    z = open_connecting(endpoint)
    results: dict[str, dict] = {}
    try:
        for phase in ("saturation", "paced"):
            tag = "s" if phase == "saturation" else "p"
            robots = {}
            for i, (msgs, cam) in enumerate(prepared):
                rid = f"{tag}{i}"
                # Re-sealed with this phase's robot id (ids are in the signed header).
                robots[rid] = (robot_messages_for(rid, msgs), cam)
            fleet = Fleet(z, robots)
            fleet.hello()
            fps = None
            if phase == "paced":
                fps = load * results["saturation"]["cloud_fps"] / n_robots
            print(f"{mode} local mapping, {phase}: {n_robots} robots "
                  f"{'all at once' if fps is None else f'at {fps:.1f} fps each'} ...", flush=True)
            fleet.send(fps)
            results[phase] = fleet.result(idle_s=20.0)
            results[phase]["offered_fps_per_robot"] = fps
            fleet.close()
    finally:
        z.close()
        stop(cloud)
    return results


def robot_messages_for(robot_id: str, messages: list[bytes]) -> list[bytes]:
    from fleetslam.wire.envelope import open_message, seal

    out = []
    for data in messages:
        header, payload = open_message(data)
        out.append(seal(header.kind, robot_id, header.seq, header.timestamp, header.split_point,
                        payload, compress=header.compressed))
    return out


if __name__ == "__main__":
    main()
