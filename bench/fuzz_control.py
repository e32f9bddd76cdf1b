"""End-to-end fuzz of the control path: hostile control messages and orders through a real
cloud process, while a genuine robot runs.

    .venv/bin/python bench/fuzz_control.py [--source SEQ:0-89] [--out FILE.json]

A cloud process listens on loopback (plain TCP). A genuine robot (point 3, recorded rate)
starts first; then each case sends its messages on its own robot id's control key (or the
cloud's): hello / end / need / ack / merge / status and unknown types with wrong types,
huge numbers, NaN and infinities, missing keys, oversize and deeply nested JSON, and in
hostile orders (end before hello, end twice, ack for unknown frames, a changed offloading
point, floods of ends and of hellos under made-up ids). After each case the cloud must still
answer a status request; the table gives that round trip per case (the slowest case), the
cloud's threads before and after, the exceptions in its log (anything but a clean
rejection: target 0) and whether the genuine robot's session was served to its end.
Writes bench/results/fuzz_control.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))
from shared_data import SEVEN_SCENES  # noqa: E402

from fleetslam.datasets.tum import RgbdSequence  # noqa: E402
from fleetslam.launch import (  # noqa: E402
    CloudClient,
    free_endpoint,
    start_cloud,
    start_robot,
    stop,
)
from fleetslam.tables import format_table  # noqa: E402
from fleetslam.transport import keys, protocol  # noqa: E402
from fleetslam.transport.zenoh_session import open_connecting, put  # noqa: E402

# A case's hello waits this long for its answer (a welcome, or a refusal) before going on.
HELLO_WAIT_S = 3.0

# One case: its name and the (key, payload) messages it sends, in order.
Case = tuple[str, list[tuple[str, bytes]]]

# Values of the wrong type or out of any range, for every field a case replaces; raw JSON
# text, so NaN, Infinity and 400-digit integers go as a hostile client writes them.
HOSTILE = {
    "string": '"x"', "empty string": '""', "list": "[1, 2]", "object": '{"a": 1}',
    "null": "null", "true": "true", "negative": "-1", "2^62": str(2 ** 62),
    "2^64": str(2 ** 64), "400 digits": "9" * 400, "1e308": "1e308", "NaN": "NaN",
    "Infinity": "Infinity", "-Infinity": "-Infinity", "float": "0.5",
    "long string": '"' + "a" * 100_000 + '"',
}


def _json(message: dict[str, object], **raw: str) -> bytes:
    """``message`` as JSON, with each ``raw`` field's value as the given JSON text."""
    text = json.dumps(message)
    for name, value in raw.items():
        text = text[:-1] + (", " if len(text) > 2 else "") + f'"{name}": {value}' + "}"
    return text.encode()


def cases(camera: dict[str, object]) -> Iterator[Case]:
    """Every case, each on its own robot id (fz<number>), the floods last."""
    n = iter(range(1_000_000))

    def rid() -> str:
        return f"fz{next(n)}"

    hello = {"type": "hello", "protocol": protocol.PROTOCOL, "offload_at": 3,
             "camera": camera, "source": "fuzz"}

    def hello_bytes(**changes: object) -> bytes:
        return json.dumps({**hello, **changes}).encode()

    for field in ("protocol", "offload_at", "camera", "adaptive", "source", "frames"):
        for what, value in HOSTILE.items():
            r = rid()
            rest = {k: v for k, v in hello.items() if k != field}
            yield f"hello {field} {what}", [(keys.control(r), _json(rest, **{field: value}))]
        r = rid()
        yield f"hello without {field}", [(keys.control(r), json.dumps(
            {k: v for k, v in hello.items() if k != field}).encode())]
    camera_values = {"string": "x", "negative": -1, "2^62": 2 ** 62, "NaN": float("nan"),
                     "Infinity": float("inf"), "list": [1, 2], "null": None}
    for field in ("fx", "width", "depth_scale", "distortion", "invalid_depth"):
        for what, value in camera_values.items():
            r = rid()
            yield f"hello camera {field} {what}", [
                (keys.control(r), hello_bytes(camera={**camera, field: value}))]
    # An end's fields, after a hello (a session exists), and the end before any frame.
    end = {"type": "end", "last_seq": -1}
    for field in ("last_seq", "keyframe_poses", "camera", "unavailable"):
        for what, value in HOSTILE.items():
            r = rid()
            rest = {k: v for k, v in end.items() if k != field}
            yield f"end {field} {what}", [(keys.control(r), hello_bytes()),
                                          (keys.control(r), _json(rest, **{field: value}))]
    poses = {"nan pose": '{"1": [[NaN, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}',
             "short pose": '{"1": [1, 2, 3]}', "key not int": '{"x": []}',
             "10k poses": json.dumps({str(i): [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],
                                               [0, 0, 0, 1]] for i in range(10_000)}),
             "pose of strings": '{"1": [["a"]]}'}
    for what, value in poses.items():
        r = rid()
        yield f"end keyframe_poses {what}", [(keys.control(r), hello_bytes()),
                                             (keys.control(r), _json(end, keyframe_poses=value))]
    r = rid()
    yield "end before hello", [(keys.control(r), json.dumps(end).encode())]
    r = rid()
    yield "end before any frame", [(keys.control(r), hello_bytes()),
                                   (keys.control(r), json.dumps(end).encode())]
    r = rid()
    yield "end twice", [(keys.control(r), hello_bytes())] + \
        [(keys.control(r), json.dumps(end).encode())] * 2
    r = rid()
    yield "end for frames never sent", [(keys.control(r), hello_bytes()),
                                        (keys.control(r), json.dumps(
                                            {"type": "end", "last_seq": 2 ** 62}).encode())]
    r = rid()
    yield "end, hello, end", [(keys.control(r), hello_bytes()),
                              (keys.control(r), json.dumps(end).encode()),
                              (keys.control(r), hello_bytes()),
                              (keys.control(r), json.dumps(end).encode())]
    r = rid()
    yield "hello twice", [(keys.control(r), hello_bytes())] * 2
    r = rid()
    yield "hello then a changed point", [(keys.control(r), hello_bytes()),
                                         (keys.control(r), hello_bytes(offload_at=0))]
    # Replies and requests sent the wrong way, unknown and malformed types.
    for kind in ("need", "ack", "ended", "welcome", "ending", "held", "error", "status",
                 "merge", "nonsense"):
        for what, fields in (("plain", {}), ("frames", {"frames": [0, 2 ** 62, -1]}),
                             ("frame_index", {"frame_index": 123456}),
                             ("hostile", {"frames": "x", "frame_index": None})):
            r = rid()
            yield f"{kind} ({what})", [(keys.control(r), hello_bytes()),
                                       (keys.control(r), json.dumps(
                                           {"type": kind, **fields}).encode())]
    r = rid()
    yield "ack for unknown frames", [(keys.control(r), hello_bytes())] + [
        (keys.control(r), protocol.encode(protocol.Ack(i))) for i in (0, 7, 2 ** 40)]
    for what, data in (("type not a string", b'{"type": 3}'), ("no type", b'{"a": 1}'),
                       ("a list", b"[1, 2]"), ("a number", b"3"), ("not JSON", b"{{{"),
                       ("not UTF-8", b"\xff\xfe{"), ("empty", b""),
                       ("deep nesting", b"[" * 100_000 + b"]" * 100_000),
                       ("over 1 MB", b'{"type": "end", "x": "' + b"a" * (1 << 20) + b'"}'),
                       ("NaN type", b'{"type": NaN}')):
        r = rid()
        yield f"control {what}", [(keys.control(r), data)]
        yield f"control {what} in a session", [(keys.control(r), hello_bytes()),
                                               (keys.control(r), data)]
    # The operator's key: requests with hostile ids and types.
    for what, data in (("merge id 2^64", _json({"type": "merge"}, id=str(2 ** 64))),
                       ("status id long", _json({"type": "status"}, id=HOSTILE["long string"])),
                       ("status id NaN", _json({"type": "status"}, id="NaN")),
                       ("unknown request", b'{"type": "reboot", "id": "a"}'),
                       ("garbage", b"\x00\x01")):
        yield f"cloud {what}", [(keys.CLOUD_CONTROL, data)]
    # Floods last: they may pause their robot or fill the cloud.
    r = rid()
    yield "flood of 500 ends", [(keys.control(r), hello_bytes())] + \
        [(keys.control(r), json.dumps({"type": "end", "last_seq": 1000}).encode())] * 500
    r = rid()
    yield "flood of 500 unknown types", [(keys.control(r), hello_bytes())] + \
        [(keys.control(r), b'{"type": "x"}')] * 500
    yield "500 hellos of made-up ids", [(keys.control(f"fake{i}"), hello_bytes())
                                        for i in range(500)]


def threads_of(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("Threads:"):
            return int(line.split()[1])
    return -1


def exceptions_in(log_text: str) -> list[str]:
    """Log lines of exceptions (tracebacks, failures), not clean rejections."""
    lines = log_text.splitlines()
    return [line for line in lines if "Traceback" in line or " failed" in line
            or line.startswith("ERROR")]


def run_cases(endpoint: str, pid: int, all_cases: list[Case], settle_s: float = 0.05
              ) -> list[dict[str, object]]:
    """Send each case, then time a status round trip (the cloud still answers). A hello
    waits (at most HELLO_WAIT_S) for the cloud's answer before the case goes on, as a robot
    does when it has more to say: a robot nobody serves yet is elected first, and meanwhile
    the cloud keeps only its newest control message."""
    client = CloudClient(endpoint, 60.0)
    sender = open_connecting(endpoint, 60.0)
    answered: dict[str, threading.Event] = {}
    lock = threading.Lock()

    def on_reply(sample: Any) -> None:
        with lock:
            event = answered.get(str(sample.key_expr))
        if event is not None:
            event.set()

    sub = sender.declare_subscriber(f"{keys.ROOT}/*/reply", on_reply)
    out = []
    try:
        for name, messages in all_cases:
            start = time.perf_counter()
            for i, (key, data) in enumerate(messages):
                is_hello = key != keys.CLOUD_CONTROL and data.startswith(b'{"type": "hello"') \
                    and any(k == key for k, _ in messages[i + 1:])
                if is_hello:
                    event = threading.Event()
                    with lock:
                        answered[keys.reply(keys.robot_of(key))] = event
                put(sender, key, data)
                if is_hello:
                    event.wait(HELLO_WAIT_S)
            time.sleep(settle_s)
            sent = time.perf_counter()
            try:
                client.status(timeout=30.0)
                status_s: float | None = time.perf_counter() - sent
            except TimeoutError:
                status_s = None
            out.append({"case": name, "messages": len(messages), "send_s": sent - start,
                        "status_s": status_s, "threads": threads_of(pid)})
    finally:
        sub.undeclare()
        sender.close()
        client.close()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--source", default=f"{SEVEN_SCENES}:0-89")
    parser.add_argument("--expiry-wait-s", type=float, default=40.0,
                        help="then count the cloud's threads and sessions again")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" /
                                             "fuzz_control.json"))
    args = parser.parse_args()
    runs = Path("/tmp") / f"fleetslam-fuzz-control-{time.strftime('%Y%m%d-%H%M%S')}"
    endpoint = free_endpoint()
    camera = RgbdSequence(Path(args.source.split(":")[0])).camera.to_dict()
    all_cases = list(cases(camera))
    cloud = start_cloud(endpoint, runs / "cloud", runs / "cloud.log")
    robot = None
    client = CloudClient(endpoint, 60.0)
    try:
        client.status(timeout=60.0)
        threads_before = threads_of(cloud.pid)
        robot = start_robot(endpoint, "r1", args.source, 3, runs / "r1.log",
                            runs / "r1_report.json", extra=["--rate", "recorded"])
        results = run_cases(endpoint, cloud.pid, all_cases)
        threads_after = threads_of(cloud.pid)
        robot_rc = robot.wait(600)
        # The fuzz's sessions never tracked a frame: they expire (transport.idle_empty_session_s).
        time.sleep(args.expiry_wait_s)
        threads_expired = threads_of(cloud.pid)
        sessions_left = len(client.status(timeout=30.0)["robots"])
    finally:
        client.close()
        if robot is not None and robot.poll() is None:
            stop(robot)
        stop(cloud)
    log_text = (runs / "cloud.log").read_text(errors="replace")
    found = exceptions_in(log_text)
    robot_json = runs / "cloud" / "r1" / "robot.json"
    frames = json.loads(robot_json.read_text())["frames"] if robot_json.exists() else 0
    unanswered = [r["case"] for r in results if r["status_s"] is None]
    slowest = max((r for r in results if r["status_s"] is not None),
                  key=lambda r: r["status_s"])
    print(f"{len(results)} control-path cases against one cloud process ({endpoint})")
    print(format_table(
        ["cases", "messages", "exceptions in log", "status unanswered", "slowest case",
         "its status ms", "cloud threads before/after/expired", "sessions left", "log kB",
         "r1 exit", "r1 frames"],
        [[len(results), sum(r["messages"] for r in results), len(found), len(unanswered),
          slowest["case"], 1000 * slowest["status_s"],
          f"{threads_before}/{threads_after}/{threads_expired}", sessions_left,
          len(log_text.encode()) / 1e3, robot_rc, frames]]))
    for line in found[:10]:
        print("  ", line)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"source": args.source, "cases": results,
                               "exceptions": found, "unanswered": unanswered,
                               "threads_before": threads_before,
                               "threads_after": threads_after,
                               "threads_after_expiry": threads_expired,
                               "sessions_left": sessions_left, "log_bytes": len(log_text),
                               "robot_exit": robot_rc, "robot_frames": frames}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
