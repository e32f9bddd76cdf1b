"""Request / reply with a running cloud: fresh client sessions, each asking `status` at once.

    .venv/bin/python bench/control_requests.py [--clients 200] [--secure] [--out FILE.json]

A real cloud process listens on loopback; each client opens its own Zenoh session (as
`fleetslam merge --connect` does), asks `status` immediately, and closes. A request that is
lost is resent (same id) every second until its reply arrives; the table gives the latency
from the first send to the reply, and how many were answered within the deadline. With
``--secure``, as a lab deploys it: mutual TLS, the cloud as the Zenoh router with access
control, the clients holding the operator's certificate.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from fleetslam.launch import CloudClient, free_endpoint, start_cloud, stop
from fleetslam.tables import format_table
from fleetslam.transport.certs import make_lab


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=200)
    parser.add_argument("--deadline-s", type=float, default=30.0)
    parser.add_argument("--secure", action="store_true")
    parser.add_argument("--out")
    args = parser.parse_args()
    name = "control_requests_secure" if args.secure else "control_requests"
    args.out = args.out or str(Path(__file__).parent / "results" / f"{name}.json")
    endpoint = free_endpoint()
    runs = Path("/tmp") / f"fleetslam-control-{time.strftime('%Y%m%d-%H%M%S')}"
    cloud_config = client_config = None
    if args.secure:
        lab = make_lab(runs / "lab", ["localhost"], [])
        cloud_config, client_config = str(lab["cloud"]), str(lab["client"])
        endpoint = endpoint.replace("tcp/127.0.0.1", "tls/localhost")
    cloud = start_cloud(endpoint, runs / "cloud", runs / "cloud.log", zenoh_config=cloud_config)
    latencies, open_s, failures = [], [], []
    try:
        for i in range(args.clients):
            start = time.perf_counter()
            client = CloudClient(endpoint, args.deadline_s, client_config)
            opened = time.perf_counter()
            try:
                client.status(timeout=args.deadline_s)
                latencies.append(time.perf_counter() - opened)
            except TimeoutError as exc:
                failures.append(f"client {i}: {exc}")
            finally:
                client.close()
            open_s.append(opened - start)
    finally:
        stop(cloud)
    ms = np.array(latencies) * 1000
    rows = [["status after open", len(latencies), len(failures), np.median(ms),
             np.percentile(ms, 95), ms.max()],
            ["session open", len(open_s), 0, 1000 * np.median(open_s),
             1000 * np.percentile(open_s, 95), 1000 * max(open_s)]]
    print(f"{args.clients} fresh client sessions against one cloud ({endpoint})")
    print(format_table(["what", "answered", "unanswered", "median ms", "p95 ms", "max ms"], rows))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"clients": args.clients, "answered": len(latencies),
                               "failures": failures, "status_ms": ms.tolist(),
                               "open_ms": (np.array(open_s) * 1000).tolist()}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
