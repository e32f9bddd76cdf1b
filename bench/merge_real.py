"""Map merging on real data: FS-HICP against the paper's ICP baselines, side by side.

    .venv/bin/python bench/merge_real.py [--starts 5] [--run RUN_DIR] [--out bench/results/merge_real.json]

Cases (7-Scenes redkitchen from ../shared/data):
  pair-gt      robots A = frames 0-349, B = 250-599, each map built from keyframes (every
               10th frame) at ground-truth poses, in its own frame (its first camera):
               what registration alone achieves.
  pair-run     the same pair with the maps a `fleetslam run` built from its own tracking
               (--run DIR of `fleetslam run --robot SEQ:0-349 --robot SEQ:250-599`):
               registration plus tracking drift.
  known-motion map A moved by a known random transform and re-sampled (random half of the
               points, 3 mm noise), registered back from the identity.
Each start: the true transform perturbed by 10 deg about the source centroid and 0.3 m.
Methods: FS-HICP; point-to-point ICP on the unfiltered maps (the paper's classical ICP);
point-to-point and point-to-plane ICP at FS-HICP's fine voxel (0.05 m). Same starts for all.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import numpy as np  # noqa: E402
from shared_data import SEVEN_SCENES

from fleetslam.config import Config  # noqa: E402
from fleetslam.datasets.tum import RgbdSequence  # noqa: E402
from fleetslam.io.ply import read_ply  # noqa: E402
from fleetslam.mapping.dense_map import build_dense_map  # noqa: E402
from fleetslam.registration.baselines import point_to_plane_icp, point_to_point_icp  # noqa: E402
from fleetslam.registration.fshicp import fshicp  # noqa: E402
from fleetslam.registration.metrics import transform_error  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402
from fleetslam.transforms import (  # noqa: E402
    invert,
    make_T,
    random_perturbation,
    transform_points,
)

SEQ = SEVEN_SCENES
RANGES = {"A": (0, 349), "B": (250, 599)}


def perturbed_guess(T_target_source: np.ndarray, source_points: np.ndarray,
                    rng: np.random.Generator, rotation_deg: float, translation_m: float
                    ) -> np.ndarray:
    """A ground-truth-perturbed start (this benchmark only; the system finds its own guess):
    the true ``T_target_source`` spoiled by a rotation of ``rotation_deg`` about a random
    axis through the source map's centroid and a shift of ``translation_m``. About the
    centroid, because about a far-away origin the same angle would also shift the map by
    metres, hiding the stated translation."""
    noise = random_perturbation(rng, rotation_deg, translation_m)
    centre = transform_points(T_target_source, source_points).mean(axis=0)
    return make_T(np.eye(3), centre) @ noise @ make_T(np.eye(3), -centre) @ T_target_source


def gt_map(seq: RgbdSequence, first: int, last: int, config: Config) -> np.ndarray:
    anchor = invert(seq.gt_poses[first])
    frames = range(first, last + 1, 10)
    points, _ = build_dense_map(seq.camera, ((seq[i].rgb, seq[i].depth_m, anchor @ seq.gt_poses[i])
                                             for i in frames), config.map)
    return points


def methods(config: Config):
    fine = config.fshicp.fine_voxel_m
    return {
        "FS-HICP": lambda s, t, T: fshicp(s, t, T, config.fshicp),
        "p2p ICP unfiltered": lambda s, t, T: point_to_point_icp(s, t, T),
        f"p2p ICP voxel {fine}": lambda s, t, T: point_to_point_icp(s, t, T, voxel_m=fine),
        f"p2pl ICP voxel {fine}": lambda s, t, T: point_to_plane_icp(s, t, T, voxel_m=fine),
    }


def run_case(name: str, source: np.ndarray, target: np.ndarray, T_true: np.ndarray,
             starts: list[np.ndarray], config: Config, ok_deg: float, ok_m: float) -> list[dict]:
    rows = []
    for method, register in methods(config).items():
        errs, secs = [], []
        for T0 in starts:
            result = register(source, target, T0)
            err = transform_error(result.T_target_source, T_true)
            errs.append((err.rotation_deg, err.translation_m))
            secs.append(result.seconds)
        e = np.array(errs)
        rows.append({"case": name, "method": method, "starts": len(starts),
                     "success": int(((e[:, 0] <= ok_deg) & (e[:, 1] <= ok_m)).sum()),
                     "criterion": f"<= {ok_deg} deg and <= {ok_m * 100:g} cm",
                     "rot_deg_median": float(np.median(e[:, 0])),
                     "trans_cm_median": float(np.median(e[:, 1]) * 100),
                     "rot_deg_max": float(e[:, 0].max()), "trans_cm_max": float(e[:, 1].max() * 100),
                     "seconds_median": float(np.median(secs)), "errors": errs})
        print(f"  {name} / {method}: done", flush=True)
    fs = next(r for r in rows if r["method"] == "FS-HICP")["seconds_median"]
    for r in rows:
        r["time_vs_fshicp"] = r["seconds_median"] / fs
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--starts", type=int, default=5)
    parser.add_argument("--run", help="run folder of `fleetslam run` with robots r0=0-349, r1=250-599")
    parser.add_argument("--out", default="bench/results/merge_real.json")
    args = parser.parse_args()
    config = Config()
    seq = RgbdSequence(SEQ)
    rng = np.random.default_rng(0)
    T_true = invert(seq.gt_poses[RANGES["A"][0]]) @ seq.gt_poses[RANGES["B"][0]]
    map_a = gt_map(seq, *RANGES["A"], config)
    map_b = gt_map(seq, *RANGES["B"], config)
    print(f"maps from GT poses: A {len(map_a)} points, B {len(map_b)} points", flush=True)

    rows = []
    starts = [perturbed_guess(T_true, map_b, rng, 10.0, 0.3) for _ in range(args.starts)]
    rows += run_case("pair-gt", map_b, map_a, T_true, starts, config, 2.0, 0.05)
    if args.run:
        run_a, _ = read_ply(Path(args.run) / "r0" / "map.ply")
        run_b, _ = read_ply(Path(args.run) / "r1" / "map.ply")
        starts = [perturbed_guess(T_true, run_b, rng, 10.0, 0.3) for _ in range(args.starts)]
        rows += run_case("pair-run", run_b, run_a, T_true, starts, config, 2.0, 0.05)
    # Known motion: A moved and re-sampled; registered back onto A.
    G = random_perturbation(rng, 10.0, 0.3)
    keep = rng.random(len(map_a)) < 0.5
    moved = transform_points(G, map_a[keep]) + rng.normal(scale=0.003, size=(int(keep.sum()), 3))
    rows += run_case("known-motion", moved, map_a, invert(G), [np.eye(4)], config, 0.5, 0.01)

    headers = ["case", "method", "ok/starts", "rot deg med", "trans cm med", "rot deg max",
               "trans cm max", "s med", "time / FS-HICP"]
    print(format_table(headers, [[r["case"], r["method"], f"{r['success']}/{r['starts']}",
                                  r["rot_deg_median"], r["trans_cm_median"], r["rot_deg_max"],
                                  r["trans_cm_max"], r["seconds_median"], r["time_vs_fshicp"]]
                                 for r in rows]))
    print(f"cores: {os.cpu_count()}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(),
                               "rows": rows}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
