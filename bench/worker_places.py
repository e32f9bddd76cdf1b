"""A loop query's trip to the worker as a robot's keyframe database grows: the whole
database pickled to the worker with each query (as before the worker kept it) against the
keyframes added since the last query (backend/worker_places.py), side by side in one pool.

    .venv/bin/python bench/worker_places.py [--keyframes 50,200,800] [--queries 5]
        [--out bench/results/worker_places.json]

The database: ``orb.n_features`` random ORB-sized descriptors a keyframe (a brute-force
search costs the same on any bits). At each size, ``--queries`` queries each way, one
keyframe added before each: the bytes sent, the parent's CPU time to send it (pickling
holds the GIL the tracking thread needs) and the time from submission to the answer
(median). Both ways must give the same candidates. The machine's core count and load
average are printed with the table.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import time
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.backend.place_recognition import KeyframeDatabase, snapshot
from fleetslam.backend.worker_places import PlaceMirror
from fleetslam.backend.workers import LocalMappingPool, SessionWorkers, query_places
from fleetslam.config import Config
from fleetslam.tables import format_table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", default="50,200,800")
    parser.add_argument("--queries", type=int, default=5)
    parser.add_argument("--out", default="bench/results/worker_places.json")
    args = parser.parse_args()
    config = Config()
    sizes = sorted(int(k) for k in args.keyframes.split(","))
    rng = np.random.default_rng(0)
    features = config.orb.n_features
    pool = LocalMappingPool(1)
    rows: list[dict[str, Any]] = []
    try:
        session = SessionWorkers(pool)
        mirror = PlaceMirror(session.session)
        database = KeyframeDatabase(config.place_recognition)
        for size in sizes:
            while len(database) < size - args.queries:
                add(database, mirror, rng, features)
            whole, delta = [], []
            for _ in range(args.queries):
                add(database, mirror, rng, features)
                query = rng.integers(0, 256, (features, 32), dtype=np.uint8)
                allowed = np.ones(len(database), bool)
                frozen = snapshot(database)
                whole.append(trip(lambda: pool.call(session.lane, query_places, frozen, query,
                                                    allowed),
                                  len(pickle.dumps((frozen, query, allowed)))))
                blob: list[bytes] = []
                delta.append(trip(lambda: pool.submit_query(
                    keep(blob, mirror.request(frozen, query, allowed)), session.lane),
                    None, blob))
                if whole[-1]["candidates"] != delta[-1]["candidates"]:
                    raise AssertionError(f"{size} keyframes: the answers differ")
            rows.append({"keyframes": size, "whole": medians(whole), "delta": medians(delta)})
            print(f"  {size} keyframes", flush=True)
    finally:
        pool.close()
    table = [[r["keyframes"], r[way]["kB"], r[way]["send_cpu_ms"], r[way]["round_trip_ms"], way]
             for r in rows for way in ("whole", "delta")]
    print(format_table(["keyframes", "kB sent", "parent CPU ms to send", "round trip ms",
                        "sent"], table))
    load = os.getloadavg()
    print(f"{os.cpu_count()} cores, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"rows": rows, "cores": os.cpu_count(),
                                          "load_average": load}, indent=1))
    print(f"wrote {args.out}")


def add(database: KeyframeDatabase, mirror: PlaceMirror, rng: np.random.Generator,
        features: int) -> None:
    d = rng.integers(0, 256, (features, 32), dtype=np.uint8)
    mirror.added(len(database), d)
    database.add(len(database), d)


def keep(store: list[bytes], blob: bytes) -> bytes:
    store.append(blob)
    return blob


def trip(send: Any, size: int | None, blob: list[bytes] | None = None) -> dict[str, Any]:
    """One query: bytes sent, the parent's CPU seconds until its answer (pickling, most of
    it, as the worker searches on its own CPU) and the round trip."""
    cpu, start = time.process_time(), time.perf_counter()
    candidates, _ = send().result(timeout=600)
    return {"bytes": size if size is not None else len((blob or [b""])[-1]),
            "send_cpu_s": time.process_time() - cpu,
            "round_trip_s": time.perf_counter() - start, "candidates": candidates}


def medians(trips: list[dict[str, Any]]) -> dict[str, float]:
    return {"kB": float(np.median([t["bytes"] for t in trips])) / 1000,
            "send_cpu_ms": 1000 * float(np.median([t["send_cpu_s"] for t in trips])),
            "round_trip_ms": 1000 * float(np.median([t["round_trip_s"] for t in trips]))}


if __name__ == "__main__":
    main()
