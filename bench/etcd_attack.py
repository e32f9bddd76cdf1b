"""etcd under attack while a fleet runs: what an outsider can do to the coordination service
(nothing), and what someone holding a worker's etcd credentials can (roll a pointer back,
point it at a missing file, write a lease-less owner, delete the owner and the pointer,
squat a robot for a worker that does not exist),
measured as the robots feel it.

    .venv/bin/python bench/etcd_attack.py [--cases outsider,rollback,...] [--rate 10]

Each case is one run of ``fleetslam demo --workers 2`` (a router, two workers, etcd with
mutual TLS from the run's lab, all on loopback) with two robot processes playing 7-Scenes
redkitchen 0-199 and 130-329 at ``--rate`` fps. Once the robots have sent ``--at`` of
their frames the attack is made on robot r0's keys, through the run's own etcd, with the
workers' certificate (``<run>/tls/etcd``) unless the case is the outsider's:

  outsider        writes to r0's owner key over plain http, over https without a
                  certificate, and with robot r1's certificate of the lab: each must fail;
  rollback        r0's pointer moved back to its previous checkpoint, then r0's worker
                  killed (SIGKILL), so the next owner reads the pointer;
  missing-file    r0's pointer set to a file that is not there, then r0's worker killed;
  leaseless-owner r0's owner key overwritten without a lease (r0's worker still serves);
  delete-both     r0's owner key and pointer deleted;
  squat           r0's owner key overwritten under the attacker's own lease (60 s),
                  naming a worker that does not exist (w9): r0's worker loses its grant
                  at its next checkpoint, and nobody hears w9.

Measured per case: the outsider's writes refused; per robot its exit status (0, or 3: the
cloud kept less than it sent, said in its report), frames sent and in the cloud's
trajectory, keyframes acknowledged and of those missing from the final checkpoint
(acknowledged keyframes lost: must be 0), the longest pause between two feedbacks (what
the attack and its recovery cost), whether it finished (robots stuck: must be 0).
Writes bench/results/etcd_attack.json.
"""

from __future__ import annotations

import argparse
import json
import signal
import ssl
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

from shared_data import SEVEN_SCENES

from fleetslam.cloud.coordination.etcd_gateway import EtcdClient, EtcdError, EtcdTls, b64
from fleetslam.cloud.coordination.fenced_store import newest_blob, stored_run
from fleetslam.cloud.coordination.ownership import Keys
from fleetslam.demo import run_demo
from fleetslam.tables import format_table

PIECES = ["0-199", "130-329"]
CASES = ["outsider", "rollback", "missing-file", "leaseless-owner", "delete-both", "squat"]
KEYS = Keys()


def _endpoint_and_certs(workers: list) -> tuple[str, Path]:
    """The run's etcd and its TLS folder, as the demo gave them to its workers."""
    args = list(workers[0].args)
    return (args[args.index("--coordination") + 1],
            Path(args[args.index("--coordination-certs") + 1]))


def _outsider_writes(endpoint: str, certs: Path, lab: Path) -> list[dict[str, Any]]:
    """Writes to r0's owner key without the workers' certificate: (how, refused, why)."""
    body = json.dumps({"key": b64(KEYS.owner("r0")), "value": b64("outsider")}).encode()
    anonymous = ssl.create_default_context(cafile=str(certs / "ca.pem"))
    robot = ssl.create_default_context(cafile=str(certs / "ca.pem"))
    robot.load_cert_chain(str(lab / "r1.pem"), str(lab / "r1.key"))
    tries = [("plain http", endpoint.replace("https://", "http://"), None),
             ("https, no certificate", endpoint, anonymous),
             ("https, robot r1's certificate", endpoint, robot)]
    out = []
    for how, url, context in tries:
        request = urllib.request.Request(f"{url}/v3/kv/put", data=body, method="POST")
        try:
            with urllib.request.urlopen(request, timeout=5, context=context) as reply:
                refused, why = b"error" in reply.read(), f"HTTP {reply.status}"
        except (OSError, ssl.SSLError) as exc:
            refused, why = True, type(exc).__name__ + ": " + str(exc)[:80]
        out.append({"how": how, "refused": refused, "why": why})
    return out


class Attack:
    """The demo's watch hook: makes the case's attack once the fleet is ``at`` through."""

    def __init__(self, case: str, at: float, total: int, out: Path) -> None:
        self.case, self.at, self.total, self.out = case, at, total, out
        self.done: dict[str, Any] | None = None

    def __call__(self, status: dict[str, Any], workers: list) -> None:
        frames = sum(r["frames"] for r in status["robots"].values())
        r0 = status["robots"].get("r0")
        if self.done is not None or frames < self.at * self.total or r0 is None \
                or r0.get("finished"):
            return
        endpoint, certs = _endpoint_and_certs(workers)
        stolen = EtcdClient(endpoint, tls=EtcdTls.from_folder(certs))
        victim = r0["worker"]
        self.done = {"at_frames": frames, "at_s": time.monotonic(), "owner": victim}
        if self.case == "outsider":
            self.done["writes"] = _outsider_writes(endpoint, certs, self.out / "tls")
        elif self.case in ("rollback", "missing-file"):
            pointer = json.loads(stolen.get(KEYS.current("r0")).value)
            if self.case == "rollback":
                blobs = sorted(p.name for p in (self.out / "r0").glob("session.*.ckpt")
                               if p.name != pointer["file"])
                older = [b for b in blobs if b < pointer["file"]] or blobs
                pointer["file"], pointer["seq"] = older[-1], max(pointer["seq"] - 1, 1)
            else:
                pointer["file"] = "session.999999.000001.ckpt"
            stolen.put(KEYS.current("r0"), json.dumps(pointer))
            self.done["pointer"] = pointer["file"]
            workers[int(victim[1:])].send_signal(signal.SIGKILL)  # the next owner reads it
            self.done["killed"] = victim
        elif self.case == "leaseless-owner":
            stolen.put(KEYS.owner("r0"), "attacker")
        elif self.case == "delete-both":
            stolen.delete(KEYS.owner("r0"))
            stolen.delete(KEYS.current("r0"))
        elif self.case == "squat":
            lease, _ = stolen.lease_grant(60)
            stolen.put(KEYS.owner("r0"), "w9", lease)
        print(f"  {self.case}: attacked r0 (owner {victim}) at {frames} frames", flush=True)


def _acknowledged_lost(store: Any, robot: dict[str, Any]) -> int:
    state = store.load_checkpoint(robot["name"])
    kept = set() if state is None else {kf.frame_index for kf in state.tracking.map.keyframes}
    return len(set(robot["robot"].get("acknowledged", [])) - kept)


def run(case: str, at: float, rate: str, work: Path, timeout_s: float) -> dict[str, Any]:
    sources = [f"{SEVEN_SCENES}:{piece}" for piece in PIECES]
    total = sum(int(p.split("-")[1]) - int(p.split("-")[0]) + 1 for p in PIECES)
    out = work / case
    attack = Attack(case, at, total, out)
    print(f"{case}: {len(sources)} robots at {rate} fps ...", flush=True)
    started = time.monotonic()
    try:
        summary = run_demo(sources, out, "3", None, link_args=["--rate", rate],
                           show_progress=False, workers=2, watch=attack, timeout_s=timeout_s)
    except (RuntimeError, EtcdError) as exc:
        return {"case": case, "attack": attack.done, "failed": str(exc)[:2000],
                "seconds": time.monotonic() - started}
    robots = {}
    with stored_run(out) as store:
        for r in summary["robots"]:
            report = r["robot"]
            robots[r["name"]] = {
                "incomplete": report.get("incomplete", []),
                "frames_sent": report["frames"], "cloud_frames": report.get("cloud_frames"),
                "acknowledged": len(report.get("acknowledged", [])),
                "acknowledged_lost": _acknowledged_lost(store, r),
                "takeovers": report.get("takeovers", 0),
                "pause_s": report.get("longest_feedback_gap_s"),
                "newest_blob": (newest_blob(out / r["name"]) or (0, 0, 0, None))[3]}
    return {"case": case, "attack": attack.done, "robots": robots, "stuck": 0,
            "seconds": time.monotonic() - started}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--rate", default="10", help="each robot's frames per second")
    parser.add_argument("--at", type=float, default=0.4,
                        help="attack when the robots have sent this share of their frames")
    parser.add_argument("--timeout", type=float, default=300.0,
                        help="a robot not finished by then counts as stuck")
    parser.add_argument("--out", default="bench/results/etcd_attack.json")
    args = parser.parse_args()
    if not SEVEN_SCENES.exists():
        sys.exit(f"{SEVEN_SCENES} missing: this benchmark needs ../shared/data")
    cases = [c for c in args.cases.split(",") if c]
    if not set(cases) <= set(CASES):
        sys.exit(f"--cases {args.cases}: choose among {', '.join(CASES)}")
    out = Path(args.out)
    work = out.parent / "etcd-attack-runs" / time.strftime("%Y%m%d-%H%M%S")
    results = [run(case, args.at, args.rate, work, args.timeout) for case in cases]
    rows = []
    for r in results:
        writes = (r["attack"] or {}).get("writes")
        refused = f"{sum(w['refused'] for w in writes)}/{len(writes)}" if writes else ""
        if "failed" in r:
            rows.append([r["case"], refused, "-", "-", "-", "-", "-", "-", "run failed"])
            continue
        for robot, v in r["robots"].items():
            rows.append([r["case"], refused, robot, v["frames_sent"], v["cloud_frames"],
                         v["acknowledged"], v["acknowledged_lost"], v["takeovers"],
                         v["pause_s"]])
    print(format_table(["case", "outsider writes refused", "robot", "frames sent",
                        "cloud kept", "KF acked", "acked KF lost", "takeovers",
                        "longest pause s"], rows))
    stuck = sum(1 for r in results if "failed" in r)
    print(f"runs that did not finish (robots stuck or failed): {stuck}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rate": args.rate, "at": args.at, "pieces": PIECES,
                               "results": results}, indent=2, default=str))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
