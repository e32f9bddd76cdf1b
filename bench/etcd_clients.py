"""Which etcd client the cloud workers use: the latency of one ownership grant (a transaction:
"the robot has no owner key" -> put the owner key on the worker's lease, read it back) with
each client that works here, against one local etcd (coordination_service.py).

    .venv/bin/python bench/etcd_clients.py [--n 200] [--aetcd-python P] [--etcd3-python P]

Clients: ``gateway`` (cloud/coordination/etcd_gateway.py: etcd's JSON gateway over HTTP, standard
library), ``aetcd`` (asyncio gRPC) and ``etcd3`` (gRPC, unmaintained). The gRPC ones need grpcio and
protobuf, which the project does not install: give an interpreter that has them (a scratch venv,
``python -m venv /tmp/v && /tmp/v/bin/pip install aetcd``); each client runs in its own process with
its interpreter. A client that cannot be imported or fails is reported as such. Writes
bench/results/etcd_clients.json."""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

SRC = Path(__file__).resolve().parents[1] / "src"


def _summary(seconds: list[float]) -> dict[str, float]:
    ms = sorted(s * 1000 for s in seconds)
    return {"n": len(ms), "median_ms": round(statistics.median(ms), 3),
            "p95_ms": round(ms[int(0.95 * (len(ms) - 1))], 3), "max_ms": round(ms[-1], 3)}


def measure_gateway(endpoint: str, n: int) -> list[float]:
    from fleetslam.cloud.coordination.etcd_gateway import EtcdClient, compare, put_op, range_op

    client = EtcdClient(endpoint)
    lease, _ = client.lease_grant(10)
    times = []
    for i in range(n):
        key = f"bench/gateway/owner/r{i}"
        t = time.perf_counter()
        result = client.txn([compare(key, "CREATE", 0)], [put_op(key, "w1", lease),
                                                          range_op(key)])
        times.append(time.perf_counter() - t)
        assert result.succeeded and result.ranged(1)[0].create_revision > 0
    client.lease_revoke(lease)
    return times


def measure_aetcd(endpoint: str, n: int) -> list[float]:
    import asyncio

    import aetcd

    host, port = endpoint.removeprefix("http://").split(":")

    async def run() -> list[float]:
        async with aetcd.Client(host, int(port)) as client:
            lease = await client.lease(10)
            times = []
            for i in range(n):
                key = f"bench/aetcd/owner/r{i}".encode()
                t = time.perf_counter()
                ok, _ = await client.transaction(
                    compare=[client.transactions.create(key) == 0],
                    success=[client.transactions.put(key, b"w1", lease=lease),
                             client.transactions.get(key)], failure=[])
                times.append(time.perf_counter() - t)
                assert ok
            await lease.revoke()
            return times

    return asyncio.run(run())


def measure_etcd3(endpoint: str, n: int) -> list[float]:
    import etcd3

    host, port = endpoint.removeprefix("http://").split(":")
    client = etcd3.client(host, int(port))
    lease = client.lease(10)
    times = []
    for i in range(n):
        key = f"bench/etcd3/owner/r{i}"
        t = time.perf_counter()
        ok, _ = client.transaction(compare=[client.transactions.create(key) == 0],
                                   success=[client.transactions.put(key, "w1", lease),
                                            client.transactions.get(key)], failure=[])
        times.append(time.perf_counter() - t)
        assert ok
    lease.revoke()
    return times


MEASURES = {"gateway": measure_gateway, "aetcd": measure_aetcd, "etcd3": measure_etcd3}


def run_client(name: str, python: str, endpoint: str, n: int,
               env_extra: dict[str, str] | None = None) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(SRC), **(env_extra or {})}
    started = time.monotonic()
    proc = subprocess.run([python, __file__, "--measure", name, "--endpoint", endpoint,
                           "--n", str(n)], capture_output=True, text=True, env=env, timeout=300)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        return {"client": name, "works": False, "why": last[:200]}
    times = json.loads(proc.stdout.strip().splitlines()[-1])
    return {"client": name, "works": True, **_summary(times),
            "process_s": round(time.monotonic() - started, 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=200)
    parser.add_argument("--aetcd-python", default=sys.executable)
    parser.add_argument("--etcd3-python", default=sys.executable)
    parser.add_argument("--out", default="bench/results/etcd_clients.json")
    parser.add_argument("--measure", choices=sorted(MEASURES), help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:  # a child: one client, its times as JSON on the last line
        print(json.dumps(MEASURES[args.measure](args.endpoint, args.n)))
        return

    sys.path.insert(0, str(SRC))
    from fleetslam.cloud.coordination.coordination_service import EtcdService
    from fleetslam.tables import format_table

    rows = []
    with tempfile.TemporaryDirectory() as tmp, EtcdService(Path(tmp) / "etcd") as etcd:
        rows.append(run_client("gateway", sys.executable, etcd.endpoint, args.n))
        rows.append(run_client("aetcd", args.aetcd_python, etcd.endpoint, args.n))
        rows.append(run_client("etcd3", args.etcd3_python, etcd.endpoint, args.n))
        # etcd3's generated code predates protobuf 4: only the pure-Python parser takes it.
        rows.append({**run_client("etcd3", args.etcd3_python, etcd.endpoint, args.n,
                                  {"PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION": "python"}),
                     "client": "etcd3 (pure-Python protobuf)"})
    print(f"grant transaction latency, {args.n} grants, local etcd, {os.cpu_count()} cores")
    print(format_table(["client", "median ms", "p95 ms", "max ms", "note"],
                       [[r["client"], r.get("median_ms", "-"), r.get("p95_ms", "-"),
                         r.get("max_ms", "-"), "" if r["works"] else r["why"][:70]]
                        for r in rows]))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"n": args.n, "cores": os.cpu_count(), "clients": rows},
                              indent=2) + "\n")


if __name__ == "__main__":
    main()
