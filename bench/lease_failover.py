"""Failover time set by the lease (cloud/coordination/ownership.py): worker A owns a robot, its link
to etcd is cut (a TCP relay, tests/link_cutter.py; etcd and worker B go on), B asks for the robot
every ``--poll`` seconds until granted.

    .venv/bin/python bench/lease_failover.py [--trials 10] [--lease-s 2] [--poll 0.02] [--watch]

Per trial, from one monotonic clock: A's last renewal before the cut, the cut, A's fence, the
owner key's disappearance at etcd (the lease's expiry, seen by a third client polling every
10 ms) and B's grant. Reports cut -> grant (what a lost machine costs), expiry -> grant (B's
polling), and fence -> grant (the margin by which the two owners never overlap). ``--watch``:
B also watches the owner key (etcd_gateway.Watch) and asks at once when it is deleted (its
polling then every 0.5 s, a fallback).
Writes bench/results/lease_failover.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src"), str(ROOT / "tests")]

from link_cutter import LinkCutter  # noqa: E402

from fleetslam.cloud.coordination.coordination_service import EtcdService  # noqa: E402
from fleetslam.cloud.coordination.etcd_gateway import EtcdClient, Watch  # noqa: E402
from fleetslam.cloud.coordination.ownership import Keys, Ownership  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402


def trial(etcd: EtcdService, n: int, lease_s: int, poll_s: float, watch_owner: bool
          ) -> dict[str, float]:
    keys = Keys(f"bench/{n}/")
    link = LinkCutter(etcd.client_port)
    fenced: list[float] = []
    a = Ownership(EtcdClient(link.endpoint), "wa", lease_s,
                  lambda robots: fenced.append(time.monotonic()), keys).start()
    b = Ownership(EtcdClient(etcd.endpoint), "wb", lease_s, None, keys).start()
    watcher = EtcdClient(etcd.endpoint)
    freed = threading.Event()
    owner_watch = None
    if watch_owner:
        owner_watch = Watch(etcd.endpoint, keys.owner("r1"), lambda events: any(
            e.deleted for e in events) and freed.set()).start()
        if not owner_watch.created.wait(5.0):
            raise TimeoutError("the owner key's watch did not open within 5 s")
    try:
        epoch_a = a.grant("r1")
        assert epoch_a is not None
        # The cut falls anywhere in a renewal period.
        time.sleep(lease_s / 3 * (1 + (n % 7) / 7))
        expired: list[float] = []

        def watch() -> None:
            deadline = time.monotonic() + lease_s * 4
            while time.monotonic() < deadline:
                kv = watcher.get(keys.owner("r1"))
                if kv is None or kv.create_revision != epoch_a:  # gone, or B's already
                    break
                time.sleep(0.01)
            expired.append(time.monotonic())

        cut = time.monotonic()
        link.cut()
        watching = threading.Thread(target=watch, daemon=True)
        watching.start()
        while (epoch := b.grant("r1")) is None:
            if time.monotonic() - cut > lease_s * 4:
                raise TimeoutError(f"B was not granted r1 within {lease_s * 4} s of the cut")
            freed.wait(poll_s)
            freed.clear()
        granted = time.monotonic()
        watching.join(lease_s * 4)
        assert fenced and fenced[0] < granted, "two owners overlapped"
        return {"cut_to_grant_s": granted - cut, "expiry_to_grant_s": granted - expired[0],
                "fence_to_grant_s": granted - fenced[0], "cut_to_fence_s": fenced[0] - cut,
                "epoch_b": epoch}
    finally:
        if owner_watch is not None:
            owner_watch.close()
        link.close()
        a.close()
        b.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--lease-s", type=int, default=2)
    parser.add_argument("--poll", type=float, default=None,
                        help="B asks every this many seconds (default 0.02; 0.5 with --watch)")
    parser.add_argument("--watch", action="store_true")
    parser.add_argument("--out", default="bench/results/lease_failover.json")
    args = parser.parse_args()
    if args.poll is None:
        args.poll = 0.5 if args.watch else 0.02
    with tempfile.TemporaryDirectory() as tmp, EtcdService(Path(tmp) / "etcd") as etcd:
        runs = [trial(etcd, n, args.lease_s, args.poll, args.watch) for n in range(args.trials)]
    names = ["cut_to_grant_s", "expiry_to_grant_s", "fence_to_grant_s", "cut_to_fence_s"]
    rows = [[name, round(statistics.median(r[name] for r in runs), 3),
             round(min(r[name] for r in runs), 3), round(max(r[name] for r in runs), 3)]
            for name in names]
    print(f"lease_s {args.lease_s}, {args.trials} trials, B polls every {args.poll} s"
          f"{' and watches' if args.watch else ''}, "
          f"{os.cpu_count()} cores")
    print(format_table(["interval", "median s", "min s", "max s"], rows))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"lease_s": args.lease_s, "poll_s": args.poll, "watch": args.watch,
                               "cores": os.cpu_count(), "trials": runs}, indent=2) + "\n")


if __name__ == "__main__":
    main()
