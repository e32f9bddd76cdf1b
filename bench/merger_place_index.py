"""The merger's place search as a robot's map grows: the exact index (every stored
descriptor) against the approximate one (exact up to ``merge.place_index_exact_up_to``
keyframes, then a graph index), side by side on the same real descriptors. Ground truth
is not used: the exact answer is the reference.

    .venv/bin/python bench/merger_place_index.py [--keyframes 600] [--queries 40]
        [--out bench/results/merger_place_index.json]

The map: 7-Scenes redkitchen's colour frames, played forth and back until ``--keyframes``
(each frame a keyframe of the other robot's map, as the merger stores them). At each size
in the table, ``--queries`` frames of the sequence (every 15th) ask both indexes, as a
new keyframe of another robot does: median and p95 ms a query, ms to add a keyframe, and
how often the exact best place is the approximate first (top-1) or among its
``merge.candidates`` (the candidates the merger verifies).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from shared_data import SEVEN_SCENES

from fleetslam.backend.place_recognition import ApproximateKeyframeDatabase, KeyframeDatabase
from fleetslam.backend.vocabulary import image_descriptors
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.tables import format_table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=600)
    parser.add_argument("--queries", type=int, default=40)
    parser.add_argument("--out", default="bench/results/merger_place_index.json")
    args = parser.parse_args()
    config = Config()
    pr, merge = config.place_recognition, config.merge
    seq = RgbdSequence(SEVEN_SCENES)
    n = len(seq)
    print(f"ORB descriptors of {n} frames ...", flush=True)
    descriptors = [image_descriptors(seq.rgb_paths[i], config) for i in range(n)]
    played = [i if (i // n) % 2 == 0 else n - 1 - i % n for i in range(args.keyframes)]
    queries = [descriptors[i] for i in range(0, n, 15)][:args.queries]
    exact = KeyframeDatabase(pr)
    approximate = ApproximateKeyframeDatabase(pr, merge.place_index_exact_up_to,
                                              merge.place_index_links,
                                              merge.place_index_breadth)
    sizes = sorted({s for s in (50, 100, 200, 300, 400, 600, 800, 1000, 1500, 2000)
                    if s <= args.keyframes} | {args.keyframes})
    add_ms: dict[str, list[float]] = {"exact": [], "approximate": []}
    rows, results = [], []
    for size_index, size in enumerate(sizes):
        start = sizes[size_index - 1] if size_index else 0
        for k in range(start, size):
            for name, db in (("exact", exact), ("approximate", approximate)):
                t = time.perf_counter()
                db.add(k, descriptors[played[k]])
                add_ms[name].append(1000 * (time.perf_counter() - t))
        query_ms: dict[str, list[float]] = {"exact": [], "approximate": []}
        top1 = among = 0
        for q in queries:
            answers = {}
            for name, db in (("exact", exact), ("approximate", approximate)):
                t = time.perf_counter()
                answers[name] = db.query(q, top_k=merge.candidates)
                query_ms[name].append(1000 * (time.perf_counter() - t))
            a, b = answers["exact"], answers["approximate"]
            top1 += bool(a and b and a[0].key == b[0].key)
            among += bool(a and b and a[0].key in [c.key for c in b])
        result = {"keyframes": size, "rows": int(len(exact.owner)),
                  "graph": approximate.index is not None,
                  "top1_same": top1 / len(queries), "best_among_candidates": among / len(queries)}
        for name in ("exact", "approximate"):
            result[f"{name}_query_ms_median"] = float(np.median(query_ms[name]))
            result[f"{name}_query_ms_p95"] = float(np.percentile(query_ms[name], 95))
            result[f"{name}_add_ms_median"] = float(np.median(add_ms[name][start:size]))
        results.append(result)
        rows.append([size, result["rows"], "graph" if result["graph"] else "exact",
                     result["exact_query_ms_median"], result["exact_query_ms_p95"],
                     result["approximate_query_ms_median"], result["approximate_query_ms_p95"],
                     result["exact_add_ms_median"], result["approximate_add_ms_median"],
                     f"{top1}/{len(queries)}", f"{among}/{len(queries)}"])
        print(f"  {size} keyframes done", flush=True)
    print(format_table(["keyframes", "rows", "approximate is", "exact ms median", "exact p95",
                        "approx. ms median", "approx. p95", "exact add ms", "approx. add ms",
                        "same top-1", f"exact best in top-{merge.candidates}"], rows))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"sequence": str(SEVEN_SCENES), "queries": len(queries),
                               "exact_up_to": merge.place_index_exact_up_to,
                               "links": merge.place_index_links,
                               "breadth": merge.place_index_breadth, "sizes": results},
                              indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
