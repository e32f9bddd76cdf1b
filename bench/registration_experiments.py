"""The paper's registration experiments on real pairs: FS-HICP against point-to-point and
point-to-plane ICP (time before / after voxel filtering, time per method, fitness score per
iteration, E_rr after 30 / 40 / 60 iterations).

    .venv/bin/python bench/registration_experiments.py [--quick] [--starts 5] [--raw-starts 2]
        [--raw-max-points 250000] [--plots bench/results/registration]
        [--out bench/results/registration_experiments.json]

Pairs (real data from ../shared/data, each with a known true transform T_target_source):
  3dmatch      3DMatch fragments of 7-Scenes redkitchen: cloud_bin_4 onto cloud_bin_0,
               T from the 7-Scenes poses (README of that folder). These are TSDF-fused
               fragments, so their "raw" cloud is the fragment as shipped.
  7sc-350      7-Scenes redkitchen: map B (frames 250-599) onto map A (0-349), keyframes every
               10th frame, each map in its own first camera's frame, built at ground-truth
               poses by the project's build_dense_map (2 px stride, <= 4 m, 0.02 m voxels);
               T_true = inv(gt[first_A]) @ gt[first_B].
  7sc-200      the same with A = 0-199, B = 150-349.
  tum-rpy      TUM fr1_rpy: B = 60-149 onto A = 0-79, keyframes every 5th frame.
"Raw" clouds (table 1 only) are the keyframes' back-projected points before any voxel filter
(the same pixels build_dense_map samples), keyframes evenly thinned until each map has at most
--raw-max-points points (ICP on the full ~2.4M-point raw maps costs ~4 s per iteration here).

Starts: the true transform spoiled by 10 deg about the source centroid and 0.3 m, --starts
seeded starts per pair, the same for every method. Medians over starts are reported.
Methods: FS-HICP with the project's default config (Config().fshicp, never tuned here);
the ICP baselines of fleetslam.registration.baselines at FS-HICP's fine voxel (0.05 m), each
with its max correspondence distance swept over CORR_SWEEP_M and its best setting per pair
(lowest median E_rr) used everywhere below. Every method runs with the same thread count
(FsHicpConfig.num_threads, 2); times include voxel filtering, KD-trees and normals.

Measured:
  1. time before / after voxel filtering (the paper's table "Running time comparison of the
     mapping process"): each method from the raw points, without and with the 0.05 m voxel
     filter (filter time included), first --raw-starts starts;
  2. time per method (paper Fig. 11), run to convergence (ICP: 100 iterations at most);
  3. fitness score per ICP iteration (Fig. 12): PCL's getFitnessScore (mean squared NN
     distance, all points) of the 0.05 m source onto the whole target input. ICP baselines are
     replayed one iteration per call from the same start (equal, to ~1e-7, to a run capped at
     that many iterations: checked and stored); FS-HICP is traced by recording each Align
     (2 ICP iterations) and replaying its accept / best-score rules, so its state at an
     iteration budget is what it would return if stopped there;
  4. E_rr (paper eq. 6) of each method capped at 30, 40 and 60 ICP iterations (Fig. 13).
Target checked per pair (not tuned to): "FS-HICP reaches an error equal to or lower than
point-to-point ICP in <= 1/5 of its time": median E_rr(FS-HICP) <= median E_rr(p2p) and
median time(FS-HICP) <= median time(p2p) / 5, against p2p at 0.05 m and p2p on raw points.
"""

from __future__ import annotations

import argparse
import bisect
import contextlib
import json
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import small_gicp  # noqa: E402
from shared_data import DATA, SEVEN_SCENES, TUM_RPY  # noqa: E402

import fleetslam.registration.fshicp as fshicp_module  # noqa: E402
from fleetslam.config import Config, FsHicpConfig  # noqa: E402
from fleetslam.datasets.tum import RgbdSequence  # noqa: E402
from fleetslam.io.ply import read_ply  # noqa: E402
from fleetslam.mapping.dense_map import build_dense_map  # noqa: E402
from fleetslam.registration.baselines import NORMAL_NEIGHBOURS, IcpMethod, run_icp  # noqa: E402
from fleetslam.registration.fshicp import FsHicpStep, drop_invalid, fshicp, voxel_filter  # noqa: E402
from fleetslam.registration.metrics import build_tree, fitness_score, transform_error  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402
from fleetslam.registration.metrics import random_perturbation  # noqa: E402
from fleetslam.transforms import invert, make_T, transform_points  # noqa: E402

FRAGMENTS = DATA / "3dmatch_7scenes-redkitchen_fragments"
PERTURB_DEG = 10.0
PERTURB_M = 0.3
CORR_SWEEP_M = (0.05, 0.1, 0.2, 0.3, 0.5)
ITERATION_CAPS = (30, 40, 60)
# run_icp's default cap: the traces then end where a run to convergence ends.
MAX_ICP_ITERATIONS = 100
# Fitness scores for Fig. 12 are all taken on the source at this voxel (uniform density, so
# no method is scored on points it never saw more of) against the whole target input.
EVAL_SOURCE_VOXEL_M = 0.05
# The paper's target: FS-HICP within this fraction of point-to-point ICP's time.
TARGET_TIME_FRACTION = 0.2
BASELINES: dict[str, IcpMethod] = {"p2p ICP": "point_to_point", "p2pl ICP": "point_to_plane"}
SMALL_GICP_TYPE = {"point_to_point": "ICP", "point_to_plane": "PLANE_ICP"}
FS = "FS-HICP"
COLOURS = {FS: "tab:red", "p2p ICP": "tab:blue", "p2pl ICP": "tab:green"}


# --- pairs ------------------------------------------------------------------------------------

@dataclass
class Pair:
    name: str
    description: str
    source: np.ndarray  # registration input (dense map or fragment), source frame
    target: np.ndarray
    raw_source: np.ndarray  # raw back-projected points (table 1)
    raw_target: np.ndarray
    T_true: np.ndarray  # T_target_source
    raw_note: str
    starts: list[np.ndarray] = field(default_factory=list)


def perturbed_guess(T_target_source: np.ndarray, source_points: np.ndarray,
                    rng: np.random.Generator, rotation_deg: float, translation_m: float
                    ) -> np.ndarray:
    """The true transform spoiled by ``rotation_deg`` about a random axis through the source
    centroid (about a far origin the same angle would also shift the map by metres) and a
    shift of ``translation_m``. Same rule as bench/merge_real.py's, kept here so this file
    does not depend on a benchmark that changes on its own."""
    noise = random_perturbation(rng, rotation_deg, translation_m)
    centre = transform_points(T_target_source, source_points).mean(axis=0)
    return make_T(np.eye(3), centre) @ noise @ make_T(np.eye(3), -centre) @ T_target_source


def thin_keyframes(clouds: list[np.ndarray], max_points: int) -> tuple[np.ndarray, int]:
    """All keyframe clouds stacked, keeping every k-th keyframe (the first always) with the
    smallest k that fits ``max_points``: raw density is kept, only views are dropped."""
    step = 1
    while sum(len(c) for c in clouds[::step]) > max_points and step < len(clouds):
        step += 1
    return np.vstack(clouds[::step]), step


def robot_map(seq: RgbdSequence, first: int, last: int, every: int, config: Config,
              raw_max_points: int) -> tuple[np.ndarray, np.ndarray, str]:
    """(dense map, raw cloud, note) of frames first..last, keyframes every ``every`` frames,
    in the first camera's frame at ground-truth poses."""
    assert seq.gt_poses is not None
    anchor = invert(seq.gt_poses[first])
    ids = list(range(first, last + 1, every))
    frames = [seq[i] for i in ids]
    poses = [anchor @ seq.gt_poses[i] for i in ids]
    if not all(np.isfinite(T).all() for T in poses):
        raise ValueError(f"{seq.folder}: ground truth missing in frames {first}-{last}")
    dense, _ = build_dense_map(seq.camera, ((f.rgb, f.depth_m, T) for f, T in zip(frames, poses)),
                               config.map)
    # The pixels build_dense_map samples (its stride and depth limit), before any voxel filter.
    raw_parts = [transform_points(T, seq.camera.backproject_image(
        f.depth_m, stride=config.map.pixel_stride, max_depth_m=config.map.max_depth_m)[0])
        for f, T in zip(frames, poses)]
    full = sum(len(p) for p in raw_parts)
    raw, step = thin_keyframes(raw_parts, raw_max_points)
    note = (f"{len(raw_parts[::step])}/{len(ids)} keyframes (every {every * step}th frame), "
            f"{len(raw)} of {full} raw points")
    return dense, raw, note


def map_pair(name: str, folder: Path, range_a: tuple[int, int], range_b: tuple[int, int],
             every: int, config: Config, raw_max_points: int) -> Pair:
    seq = RgbdSequence(folder)
    assert seq.gt_poses is not None
    target, raw_target, note_a = robot_map(seq, *range_a, every, config, raw_max_points)
    source, raw_source, note_b = robot_map(seq, *range_b, every, config, raw_max_points)
    T_true = invert(seq.gt_poses[range_a[0]]) @ seq.gt_poses[range_b[0]]
    return Pair(name, f"{folder.name}: {range_b[0]}-{range_b[1]} onto {range_a[0]}-{range_a[1]}, "
                f"keyframes every {every}th frame", source, target, raw_source, raw_target,
                T_true, f"raw source {note_b}; raw target {note_a}")


def fragment_pair() -> Pair:
    p0, _ = read_ply(FRAGMENTS / "cloud_bin_0.ply")
    p4, _ = read_ply(FRAGMENTS / "cloud_bin_4.ply")
    T_0_4 = np.loadtxt(FRAGMENTS / "T_0_4_from_7scenes_poses.txt")  # p0 = T_0_4 @ p4
    p0, p4 = p0.astype(np.float64), p4.astype(np.float64)
    return Pair("3dmatch", "3DMatch redkitchen cloud_bin_4 onto cloud_bin_0", p4, p0, p4, p0,
                T_0_4, "fused fragments as shipped (no raw back-projection exists)")


def load_pairs(config: Config, raw_max_points: int) -> list[Pair]:
    return [
        fragment_pair(),
        map_pair("7sc-350", SEVEN_SCENES, (0, 349), (250, 599), 10, config, raw_max_points),
        map_pair("7sc-200", SEVEN_SCENES, (0, 199), (150, 349), 10, config, raw_max_points),
        map_pair("tum-rpy", TUM_RPY, (0, 79), (60, 149), 5, config, raw_max_points),
    ]


# --- running methods --------------------------------------------------------------------------

def errors(T_est: np.ndarray, T_true: np.ndarray) -> dict[str, float]:
    e = transform_error(T_est, T_true)
    return {"eq6": e.eq6, "rot_deg": e.rotation_deg, "trans_m": e.translation_m}


def fshicp_align_calls(history: list[FsHicpStep]) -> int:
    """Align calls behind a history: a fine step after a rejected one reuses its candidate."""
    calls, reuse = 0, False
    for step in history:
        if step.level == "coarse" or not reuse:
            calls += 1
        reuse = step.level == "fine" and not step.accepted
    return calls


def run_fshicp(source: np.ndarray, target: np.ndarray, T0: np.ndarray, T_true: np.ndarray,
               config: FsHicpConfig, extra_seconds: float = 0.0) -> dict[str, Any]:
    result = fshicp(source, target, T0, config)
    return {"seconds": result.seconds + extra_seconds,
            "iterations": config.align_iterations * fshicp_align_calls(result.history),
            "coarse_steps": result.coarse_steps, "fine_steps": result.fine_steps,
            "converged": True, **errors(result.T_target_source, T_true)}


def run_baseline(method: IcpMethod, source: np.ndarray, target: np.ndarray, T0: np.ndarray,
                 T_true: np.ndarray, corr: float, voxel_m: float | None, threads: int
                 ) -> dict[str, Any]:
    result = run_icp(method, source, target, T0, voxel_m=voxel_m, max_corr_m=corr,
                     max_iterations=MAX_ICP_ITERATIONS, num_threads=threads)
    return {"seconds": result.seconds, "iterations": result.iterations,
            "converged": result.converged, "T": result.T_target_source,
            **errors(result.T_target_source, T_true)}


def median(runs: list[dict[str, Any]], key: str) -> float:
    return float(np.median([r[key] for r in runs]))


def public(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Runs without their matrices, for the JSON."""
    return [{k: v for k, v in r.items() if k != "T"} for r in runs]


# --- per-iteration traces ---------------------------------------------------------------------

@dataclass
class FsHicpRecording:
    aligns: list[np.ndarray] = field(default_factory=list)
    fine_start_T: np.ndarray | None = None
    fine_start_score: float = math.inf


@contextlib.contextmanager
def recording_fshicp() -> Iterator[FsHicpRecording]:
    """Record every Align result and the fine level's starting state of the fshicp calls
    made inside, by wrapping two module internals (read-only: the algorithm is unchanged)."""
    rec = FsHicpRecording()
    level_cls = fshicp_module._Level
    original_align, original_fine = level_cls.align, fshicp_module._fine_level

    def align(self, T_init, max_corr_m, iterations):  # type: ignore[no-untyped-def]
        T = original_align(self, T_init, max_corr_m, iterations)
        rec.aligns.append(T)
        return T

    def fine_level(level, T, config, rng, history):  # type: ignore[no-untyped-def]
        rec.fine_start_T, rec.fine_start_score = T, level.score(T)[0]
        return original_fine(level, T, config, rng, history)

    level_cls.align = align
    fshicp_module._fine_level = fine_level
    try:
        yield rec
    finally:
        level_cls.align = original_align
        fshicp_module._fine_level = original_fine


def trace_fshicp(source: np.ndarray, target: np.ndarray, T0: np.ndarray, config: FsHicpConfig
                 ) -> tuple[list[int], list[np.ndarray]]:
    """(ICP iterations used, transform FS-HICP would return if stopped there), from 0 to its
    end: coarse level, the running transform; fine level, its best-scoring accepted state."""
    with recording_fshicp() as rec:
        result = fshicp(source, target, T0, config)
    per_align = config.align_iterations
    iters, states = [0], [T0]
    aligns = iter(rec.aligns)
    used = 0
    candidate: np.ndarray | None = None
    best_T, best_score = rec.fine_start_T, rec.fine_start_score
    for step in result.history:
        if step.level == "coarse":
            used += 1
            iters.append(used * per_align)
            states.append(next(aligns))
            continue
        if candidate is None:
            candidate = next(aligns)
            used += 1
        if step.accepted:
            if step.score < best_score:
                best_T, best_score = candidate, step.score
            candidate = None
        iters.append(used * per_align)
        states.append(best_T)
    # The replay must land where the run did, or the trace is of some other algorithm.
    if not np.allclose(states[-1], result.T_target_source, atol=1e-9):
        raise RuntimeError("FS-HICP replay does not reproduce its result")
    return iters, states


@dataclass
class IcpClouds:
    """A baseline's clouds as run_icp prepares them (0.05 m voxels; target tree, normals)."""

    source: small_gicp.PointCloud
    target: small_gicp.PointCloud
    tree: small_gicp.KdTree


def icp_clouds(method: IcpMethod, source: np.ndarray, target: np.ndarray, voxel_m: float,
               threads: int) -> IcpClouds:
    src = voxel_filter(drop_invalid(source, "source"), voxel_m)
    tgt = voxel_filter(drop_invalid(target, "target"), voxel_m)
    tree = small_gicp.KdTree(tgt, threads)
    if method == "point_to_plane":
        small_gicp.estimate_normals(tgt, tree, NORMAL_NEIGHBOURS, threads)
    return IcpClouds(src, tgt, tree)


def icp_steps(method: IcpMethod, clouds: IcpClouds, T0: np.ndarray, corr: float,
              iterations: int, threads: int) -> list[np.ndarray]:
    """T after 0, 1, ..., ``iterations`` ICP iterations: one iteration per align call from
    the previous result (zero tolerances, so each call runs exactly one iteration)."""
    states = [T0]
    for _ in range(iterations):
        result = small_gicp.align(
            clouds.target, clouds.source, clouds.tree, init_T_target_source=states[-1],
            registration_type=SMALL_GICP_TYPE[method], max_correspondence_distance=corr,
            num_threads=threads, max_iterations=1, rotation_epsilon=0.0, translation_epsilon=0.0)
        states.append(np.asarray(result.T_target_source))
    return states


def chaining_check(clouds: IcpClouds, T0: np.ndarray, corr: float, threads: int) -> float:
    """Largest entry difference between 10 chained single iterations and one 10-iteration
    call: shows the replay is the capped run, not an approximation of it."""
    chained = icp_steps("point_to_point", clouds, T0, corr, 10, threads)[-1]
    once = small_gicp.align(clouds.target, clouds.source, clouds.tree, init_T_target_source=T0,
                            registration_type="ICP", max_correspondence_distance=corr,
                            num_threads=threads, max_iterations=10, rotation_epsilon=0.0,
                            translation_epsilon=0.0)
    return float(np.abs(chained - np.asarray(once.T_target_source)).max())


def state_at(iters: list[int], states: list[np.ndarray], budget: int) -> np.ndarray:
    """The last state reached within ``budget`` iterations (later ones are beyond the cap)."""
    return states[bisect.bisect_right(iters, budget) - 1]


def curves(iters: list[int], states: list[np.ndarray], horizon: int,
           score: Callable[[np.ndarray], float], T_true: np.ndarray
           ) -> dict[str, list[float]]:
    """Fitness and E_rr at every iteration budget 0..horizon."""
    picked = [state_at(iters, states, k) for k in range(horizon + 1)]
    return {"fitness": [score(T) for T in picked],
            "eq6": [transform_error(T, T_true).eq6 for T in picked]}


# --- the experiments --------------------------------------------------------------------------

def sweep_baselines(pair: Pair, threads: int, voxel_m: float) -> dict[str, dict[float, list]]:
    """Every baseline at every correspondence distance from every start (0.05 m voxels)."""
    out: dict[str, dict[float, list]] = {}
    for label, method in BASELINES.items():
        out[label] = {corr: [run_baseline(method, pair.source, pair.target, T0, pair.T_true, corr,
                                          voxel_m, threads) for T0 in pair.starts]
                      for corr in CORR_SWEEP_M}
        print(f"  {pair.name} / {label}: sweep done", flush=True)
    return out


def best_corr(by_corr: dict[float, list]) -> float:
    """Lowest median E_rr; ties to the faster setting."""
    return min(by_corr, key=lambda c: (median(by_corr[c], "eq6"), median(by_corr[c], "seconds")))


def filtering_runs(pair: Pair, corr: dict[str, float], config: FsHicpConfig, n_starts: int,
                   voxel_m: float, threads: int) -> dict[str, dict[str, list]]:
    """Table 1: each method from the raw points, without and with the voxel filter."""
    out: dict[str, dict[str, list]] = {}
    starts = pair.starts[:n_starts]
    for label, method in BASELINES.items():
        out[label] = {
            variant: [run_baseline(method, pair.raw_source, pair.raw_target, T0, pair.T_true,
                                   corr[label], v, threads) for T0 in starts]
            for variant, v in (("raw", None), ("voxel", voxel_m))}
        print(f"  {pair.name} / {label}: raw and voxel done", flush=True)
    # FS-HICP filters internally (paper step 1): "raw" hands it the raw points; "voxel" hands
    # it clouds pre-filtered at the fine voxel, the filter's time added like run_icp counts it.
    raw_runs, voxel_runs = [], []
    for T0 in starts:
        raw_runs.append(run_fshicp(pair.raw_source, pair.raw_target, T0, pair.T_true, config))
        t = time.perf_counter()
        src = voxel_filter(pair.raw_source, voxel_m).points()[:, :3].copy()
        tgt = voxel_filter(pair.raw_target, voxel_m).points()[:, :3].copy()
        filter_s = time.perf_counter() - t
        voxel_runs.append(run_fshicp(src, tgt, T0, pair.T_true, config, filter_s))
    out[FS] = {"raw": raw_runs, "voxel": voxel_runs}
    return out


def trace_pair(pair: Pair, corr: dict[str, float], config: FsHicpConfig, voxel_m: float,
               threads: int) -> dict[str, Any]:
    """Per-start fitness and E_rr curves of every method (Fig. 12, Fig. 13)."""
    eval_source = voxel_filter(pair.source, EVAL_SOURCE_VOXEL_M).points()[:, :3].copy()
    eval_tree = build_tree(pair.target, threads)

    def score(T: np.ndarray) -> float:
        # PCL getFitnessScore with its default range: every source point counts.
        return fitness_score(eval_source, eval_tree, T_target_source=T, num_threads=threads)

    fs_traces = [trace_fshicp(pair.source, pair.target, T0, config) for T0 in pair.starts]
    horizon = max(MAX_ICP_ITERATIONS, max(it[-1] for it, _ in fs_traces))
    out: dict[str, Any] = {"horizon": horizon, "methods": {}, "checks": {}}
    out["methods"][FS] = [curves(it, st, horizon, score, pair.T_true) for it, st in fs_traces]
    out["checks"]["fshicp_total_iterations"] = [it[-1] for it, _ in fs_traces]
    for label, method in BASELINES.items():
        clouds = icp_clouds(method, pair.source, pair.target, voxel_m, threads)
        per_start = []
        for T0 in pair.starts:
            states = icp_steps(method, clouds, T0, corr[label], MAX_ICP_ITERATIONS, threads)
            per_start.append(curves(list(range(len(states))), states, horizon, score, pair.T_true))
        out["methods"][label] = per_start
        if method == "point_to_point":
            out["checks"]["chained_vs_capped_max_abs_diff"] = chaining_check(
                clouds, pair.starts[0], corr[label], threads)
    print(f"  {pair.name}: traces done", flush=True)
    return out


def at_caps(trace: dict[str, Any], key: str) -> dict[str, dict[int, float]]:
    """Median over starts of ``key`` at each iteration cap, per method."""
    return {m: {k: float(np.median([c[key][k] for c in per_start])) for k in ITERATION_CAPS}
            for m, per_start in trace["methods"].items()}


def target_check(fs_runs: list[dict], p2p_runs: list[dict]) -> dict[str, Any]:
    fs_e, p2p_e = median(fs_runs, "eq6"), median(p2p_runs, "eq6")
    fs_s, p2p_s = median(fs_runs, "seconds"), median(p2p_runs, "seconds")
    return {"fshicp_eq6": fs_e, "p2p_eq6": p2p_e, "fshicp_s": fs_s, "p2p_s": p2p_s,
            "time_ratio": fs_s / p2p_s, "error_ok": fs_e <= p2p_e,
            "time_ok": fs_s <= TARGET_TIME_FRACTION * p2p_s,
            "holds": fs_e <= p2p_e and fs_s <= TARGET_TIME_FRACTION * p2p_s}


# --- plots ------------------------------------------------------------------------------------

def grid(n: int, height: float = 3.2) -> tuple[plt.Figure, list[plt.Axes]]:
    fig, axes = plt.subplots(1, n, figsize=(4.2 * n, height), squeeze=False)
    return fig, list(axes[0])


def plot_filtering(pairs: list[str], table1: dict[str, dict], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(10, 4))
    methods = [FS, *BASELINES]
    width = 0.8 / (2 * len(methods))
    x = np.arange(len(pairs))
    for m_i, method in enumerate(methods):
        for v_i, variant in enumerate(("raw", "voxel")):
            offset = (2 * m_i + v_i) * width - 0.4 + width / 2
            values = [median(table1[p][method][variant], "seconds") for p in pairs]
            ax.bar(x + offset, values, width, color=COLOURS[method],
                   alpha=1.0 if variant == "voxel" else 0.45, edgecolor="black", linewidth=0.4,
                   label=f"{method} {'raw points' if variant == 'raw' else 'voxel 0.05 m'}")
    ax.set_xticks(x, pairs)
    ax.set_yscale("log")
    ax.set_ylim(top=ax.get_ylim()[1] * 30)  # headroom for the legend
    ax.set_ylabel("seconds (median)")
    ax.set_title("Registration time from raw points: unfiltered vs voxel filtered")
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_time_per_method(pairs: list[str], main: dict[str, dict[str, list]], path: Path) -> None:
    fig, (ax_t, ax_e) = plt.subplots(1, 2, figsize=(12, 4))
    methods = [FS, *BASELINES]
    width = 0.8 / len(methods)
    x = np.arange(len(pairs))
    for m_i, method in enumerate(methods):
        offset = m_i * width - 0.4 + width / 2
        for ax, key in ((ax_t, "seconds"), (ax_e, "eq6")):
            values = [median(main[p][method], key) for p in pairs]
            ax.bar(x + offset, values, width, color=COLOURS[method], label=method)
            for p_i, p in enumerate(pairs):  # every start, so the spread shows
                ys = [r[key] for r in main[p][method]]
                ax.scatter(np.full(len(ys), x[p_i] + offset), ys, s=8, color="black", zorder=3)
    for ax, label in ((ax_t, "seconds"), (ax_e, "E_rr (eq. 6)")):
        ax.set_xticks(x, pairs)
        ax.set_yscale("log")
        ax.set_ylabel(label)
        ax.legend(fontsize=8)
    ax_t.set_title("Time per method (bars: median; dots: starts)")
    ax_e.set_title("Final error per method")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_curves(pairs: list[str], traces: dict[str, dict], path: Path) -> None:
    fig, axes = plt.subplots(2, len(pairs), figsize=(4.2 * len(pairs), 6.4), squeeze=False)
    for p_i, p in enumerate(pairs):
        for row, (key, label) in enumerate((("fitness", "fitness score (m^2)"),
                                            ("eq6", "E_rr (eq. 6)"))):
            ax = axes[row][p_i]
            for method, per_start in traces[p]["methods"].items():
                values = np.array([c[key] for c in per_start])
                k = np.arange(values.shape[1])
                ax.plot(k, np.median(values, axis=0), color=COLOURS[method], label=method)
                ax.fill_between(k, values.min(axis=0), values.max(axis=0),
                                color=COLOURS[method], alpha=0.15)
            ax.set_yscale("log")
            ax.set_xlabel("ICP iterations")
            ax.set_ylabel(label)
            for cap in ITERATION_CAPS:
                ax.axvline(cap, color="grey", linewidth=0.5, linestyle=":")
            if row == 0:
                ax.set_title(p)
    axes[0][0].legend(fontsize=8)
    fig.suptitle("Fitness score and E_rr against iteration (median, band: min-max over starts)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_caps(pairs: list[str], caps: dict[str, dict], path: Path) -> None:
    fig, axes = grid(len(pairs))
    methods = [FS, *BASELINES]
    width = 0.8 / len(methods)
    x = np.arange(len(ITERATION_CAPS))
    for ax, p in zip(axes, pairs):
        for m_i, method in enumerate(methods):
            ax.bar(x + m_i * width - 0.4 + width / 2, [caps[p][method][k] for k in ITERATION_CAPS],
                   width, color=COLOURS[method], label=method)
        ax.set_xticks(x, [f"{k} it." for k in ITERATION_CAPS])
        ax.set_yscale("log")
        ax.set_title(p)
        ax.set_ylabel("E_rr (eq. 6), median")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_sweep(pairs: list[str], sweeps: dict[str, dict], main: dict[str, dict],
               path: Path) -> None:
    fig, axes = grid(len(pairs))
    for ax, p in zip(axes, pairs):
        for label, by_corr in sweeps[p].items():
            ax.plot(CORR_SWEEP_M, [median(by_corr[c], "eq6") for c in CORR_SWEEP_M], "o-",
                    color=COLOURS[label], label=label)
        ax.axhline(median(main[p][FS], "eq6"), color=COLOURS[FS], linestyle="--",
                   label=f"{FS} (default config)")
        ax.set_yscale("log")
        ax.set_xlabel("max correspondence distance (m)")
        ax.set_ylabel("E_rr (eq. 6), median")
        ax.set_title(p)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# --- main -------------------------------------------------------------------------------------

def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="2 starts, 1 raw start, raw maps of at most 150k points")
    parser.add_argument("--starts", type=int, default=5)
    parser.add_argument("--raw-starts", type=int, default=2,
                        help="starts (the first ones) run on the raw points for table 1")
    parser.add_argument("--raw-max-points", type=int, default=250_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plots", default="bench/results/registration")
    parser.add_argument("--out", default="bench/results/registration_experiments.json")
    args = parser.parse_args()
    if args.quick:
        args.starts, args.raw_starts, args.raw_max_points = 2, 1, 150_000
    started = time.perf_counter()
    config = Config()
    fs_config = config.fshicp  # the project's default, untouched
    threads = fs_config.num_threads
    voxel_m = fs_config.fine_voxel_m

    pairs = load_pairs(config, args.raw_max_points)
    for p_i, pair in enumerate(pairs):
        rng = np.random.default_rng(args.seed + p_i)
        pair.starts = [perturbed_guess(pair.T_true, pair.source, rng, PERTURB_DEG, PERTURB_M)
                       for _ in range(args.starts)]
    names = [p.name for p in pairs]
    print(format_table(
        ["pair", "source pts", "target pts", "raw source", "raw target", "raw clouds"],
        [[p.name, len(p.source), len(p.target), len(p.raw_source), len(p.raw_target), p.raw_note]
         for p in pairs]), flush=True)

    sweeps: dict[str, dict] = {}
    best: dict[str, dict[str, float]] = {}
    main_runs: dict[str, dict[str, list]] = {}
    table1: dict[str, dict] = {}
    traces: dict[str, dict] = {}
    for pair in pairs:
        print(f"{pair.name}: {pair.description}", flush=True)
        sweeps[pair.name] = sweep_baselines(pair, threads, voxel_m)
        best[pair.name] = {label: best_corr(by_corr) for label, by_corr in sweeps[pair.name].items()}
        main_runs[pair.name] = {FS: [run_fshicp(pair.source, pair.target, T0, pair.T_true,
                                                fs_config) for T0 in pair.starts]}
        for label in BASELINES:
            main_runs[pair.name][label] = sweeps[pair.name][label][best[pair.name][label]]
        traces[pair.name] = trace_pair(pair, best[pair.name], fs_config, voxel_m, threads)
        table1[pair.name] = filtering_runs(pair, best[pair.name], fs_config, args.raw_starts,
                                           voxel_m, threads)

    # Table 1: before / after voxel filtering.
    rows1 = []
    for p in names:
        for method in [FS, *BASELINES]:
            raw, vox = table1[p][method]["raw"], table1[p][method]["voxel"]
            rows1.append([p, method, best[p].get(method, "-"), len(raw),
                          median(raw, "seconds"), median(vox, "seconds"),
                          median(raw, "seconds") / median(vox, "seconds"),
                          median(raw, "iterations"), median(vox, "iterations"),
                          median(raw, "eq6"), median(vox, "eq6")])
    print("\nTable 1: time from the raw back-projected points, unfiltered vs voxel filtered "
          f"({voxel_m} m, filter time included; FS-HICP always filters inside)")
    print(format_table(["pair", "method", "corr m", "starts", "s raw", "s voxel", "raw/voxel",
                        "it raw", "it voxel", "E_rr raw", "E_rr voxel"], rows1))

    # Correspondence-distance sweep.
    rows_s = []
    for p in names:
        for label, by_corr in sweeps[p].items():
            for corr, runs in by_corr.items():
                rows_s.append([p, label, corr, median(runs, "eq6"), median(runs, "rot_deg"),
                               median(runs, "trans_m") * 100, median(runs, "seconds"),
                               median(runs, "iterations"),
                               "best" if corr == best[p][label] else ""])
    print(f"\nBaseline sweep of the max correspondence distance (voxel {voxel_m} m, medians "
          f"over {args.starts} starts)")
    print(format_table(["pair", "method", "corr m", "E_rr", "rot deg", "trans cm", "s", "iters",
                        ""], rows_s))
    overall: dict[str, float] = {}
    for label in BASELINES:
        # One setting for all pairs: lowest geometric mean of the per-pair median E_rr.
        overall[label] = min(CORR_SWEEP_M, key=lambda c: float(np.mean(
            [math.log(median(sweeps[p][label][c], "eq6")) for p in names])))
    print("single best setting over all pairs: "
          + ", ".join(f"{label} {c} m" for label, c in overall.items()))

    # Fig. 11: time per method.
    rows2 = []
    for p in names:
        fs_s = median(main_runs[p][FS], "seconds")
        for method, runs in main_runs[p].items():
            rows2.append([p, method, best[p].get(method, "default"), median(runs, "seconds"),
                          min(r["seconds"] for r in runs), max(r["seconds"] for r in runs),
                          median(runs, "iterations"), median(runs, "eq6"),
                          median(runs, "rot_deg"), median(runs, "trans_m") * 100,
                          median(runs, "seconds") / fs_s])
    print(f"\nFig. 11: time per method to convergence ({args.starts} starts, {threads} threads)")
    print(format_table(["pair", "method", "corr m", "s med", "s min", "s max", "iters", "E_rr",
                        "rot deg", "trans cm", "time / FS-HICP"], rows2))

    # Fig. 12: fitness score by iteration.
    shown = [0, 2, 10, 20, 30, 60, 100]
    rows3 = []
    for p in names:
        for method, per_start in traces[p]["methods"].items():
            values = np.array([c["fitness"] for c in per_start])
            rows3.append([p, method, *[float(np.median(values[:, k])) * 1e4 for k in shown]])
    print("\nFig. 12: fitness score (PCL, all source points; 1e-4 m^2) after k ICP iterations, "
          "median")
    print(format_table(["pair", "method", *[f"k={k}" for k in shown]], rows3))

    # Fig. 13: E_rr at iteration caps.
    caps = {p: at_caps(traces[p], "eq6") for p in names}
    rows4 = [[p, method, *[caps[p][method][k] for k in ITERATION_CAPS]]
             for p in names for method in caps[p]]
    print("\nFig. 13: E_rr (eq. 6) after 30 / 40 / 60 ICP iterations, median")
    print(format_table(["pair", "method", *[f"E_rr@{k}" for k in ITERATION_CAPS]], rows4))

    # The paper's target.
    targets: dict[str, dict] = {}
    rows5 = []
    for p in names:
        targets[p] = {
            f"p2p voxel {voxel_m}": target_check(main_runs[p][FS], main_runs[p]["p2p ICP"]),
            "p2p raw": target_check(table1[p][FS]["raw"], table1[p]["p2p ICP"]["raw"]),
        }
        for against, t in targets[p].items():
            rows5.append([p, against, t["fshicp_eq6"], t["p2p_eq6"], t["fshicp_s"], t["p2p_s"],
                          t["time_ratio"], "yes" if t["error_ok"] else "no",
                          "yes" if t["time_ok"] else "no", "HOLDS" if t["holds"] else "fails"])
    print("\nTarget: FS-HICP error <= point-to-point ICP's in <= 1/5 of its time (medians)")
    print(format_table(["pair", "against", "FS E_rr", "p2p E_rr", "FS s", "p2p s", "FS/p2p time",
                        "error ok", "time ok", "target"], rows5))
    checks = {p: traces[p]["checks"] for p in names}
    print("checks: chained single iterations vs one capped call, max |dT|: "
          + ", ".join(f"{p} {c['chained_vs_capped_max_abs_diff']:.1e}" for p, c in checks.items()))

    plots = Path(args.plots)
    plots.mkdir(parents=True, exist_ok=True)
    files = {"table1_time_voxel_filtering": plots / "time_voxel_filtering.png",
             "fig11_time_per_method": plots / "time_per_method.png",
             "fig12_fitness_vs_iteration": plots / "fitness_vs_iteration.png",
             "fig13_error_at_iterations": plots / "error_at_iterations.png",
             "corr_sweep": plots / "corr_sweep.png"}
    plot_filtering(names, table1, files["table1_time_voxel_filtering"])
    plot_time_per_method(names, main_runs, files["fig11_time_per_method"])
    plot_curves(names, traces, files["fig12_fitness_vs_iteration"])
    plot_caps(names, caps, files["fig13_error_at_iterations"])
    plot_sweep(names, sweeps, main_runs, files["corr_sweep"])

    elapsed = time.perf_counter() - started
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({
        "date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(), "threads": threads,
        "seconds_total": elapsed, "args": vars(args),
        "fshicp_config": vars(fs_config), "baseline_voxel_m": voxel_m,
        "perturbation": {"rotation_deg": PERTURB_DEG, "translation_m": PERTURB_M,
                         "about": "source centroid"},
        "fitness": "PCL getFitnessScore, max_range inf: mean squared NN distance of the "
                   f"{EVAL_SOURCE_VOXEL_M} m voxelised source to the whole target input",
        "pairs": {p.name: {"description": p.description, "source_points": len(p.source),
                           "target_points": len(p.target), "raw_source_points": len(p.raw_source),
                           "raw_target_points": len(p.raw_target), "raw_note": p.raw_note,
                           "T_true": p.T_true.tolist(),
                           "starts": [T.tolist() for T in p.starts]} for p in pairs},
        "table1_voxel_filtering": {p: {m: {v: public(r) for v, r in by_v.items()}
                                       for m, by_v in table1[p].items()} for p in names},
        "corr_sweep": {p: {label: {str(c): public(r) for c, r in by_corr.items()}
                           for label, by_corr in sweeps[p].items()} for p in names},
        "best_corr_per_pair": best, "best_corr_single_setting": overall,
        "fig11_time_per_method": {p: {m: public(r) for m, r in main_runs[p].items()}
                                  for p in names},
        "fig12_curves": {p: {"horizon": traces[p]["horizon"],
                             "methods": traces[p]["methods"]} for p in names},
        "fig13_eq6_at_caps": caps,
        "target": targets, "checks": checks,
        "plots": {k: str(v) for k, v in files.items()},
    }, indent=1))
    print(f"\ncores: {os.cpu_count()}, threads per method: {threads}, total {elapsed:.0f} s")
    print(f"wrote {out} and {plots}/*.png")


if __name__ == "__main__":
    main()
