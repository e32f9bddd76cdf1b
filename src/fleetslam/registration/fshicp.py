"""FS-HICP: fitness-score hierarchical ICP (paper section IV.B; our reading of it: the
project's shared/paper-notes.md §2, outside this repository).

:func:`fshicp` registers a source map onto a target map from an initial guess (the merge
refines each joined robot's map with it: merging/global_map.py).

Reading of the paper taken here, where it is loose:

* Align = small_gicp point-to-point ICP with ``align_iterations`` (2) internal iterations,
  started from the accumulated transform. Passing the accumulated FinalTrans as the initial
  guess is the same as the paper's "Source = source * trans; FinalTrans = FinalTrans * trans".
* Fitness score = PCL's getFitnessScore (mean squared nearest-neighbour distance) on the
  clouds of the current level, in one of three forms (``FsHicpConfig.fitness``), each with
  the level's *starting* max correspondence distance r (0.2 m coarse, 0.1 m fine), fixed for
  the level so its scores stay comparable while the fine level shrinks the distance:
  "pcl", all points, the paper's literal call: on partially overlapping maps dominated by
  points with no counterpart (real 7-Scenes pair, 12 starts 10 deg / 0.3 m off: 8 ended
  within 5 deg / 10 cm); "inliers", points within r only (11/12 there, but it rewards
  sliding off a planar overlap until a small patch still fits: on the synthetic demo maps
  it slid 1.4 m from a 2 deg / 5 cm start); "truncated" (default), mean of min(d^2, r^2),
  where losing a neighbour costs r^2 and a far point no more.
* Coarse level: the paper loops while score >= 50 % of the initial score. A pair that starts
  close, or overlaps partially, may never halve its score; the loop then sits at a fixed point
  of ICP. We also leave it when the score changes by less than ``score_epsilon`` (that fixed
  point; the paper's "convergence precision") or after ``max_coarse_steps``.
* Fine level: a non-improving step is accepted with probability 0.3 (seeded), the counter of
  non-improving steps resets on any decrease. Returned: the best-scoring transform seen at
  the fine level, not the last accepted one (see :func:`_fine_level`). The shrinking
  correspondence distance stops at ``fine_voxel_m`` (after 50 decreases; with the default
  score never reached on the data tried), as a shorter one would drop true neighbours.

Reproducibility: the random acceptance draws from ``numpy.random.default_rng(config.seed)``.
With ``num_threads=1`` a run is bit-identical for the same inputs. With more threads
small_gicp sums its normal equations in a run-dependent order, so transforms can differ in
the last bits (~1e-16); the accept/reject decisions are the same in practice.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import small_gicp

from fleetslam.config import FsHicpConfig
from fleetslam.registration.metrics import as_points, as_rigid_transform, squared_nn_distances

# ICP needs a few points to fix 6 degrees of freedom; fewer than this after filtering is an error.
MIN_POINTS = 10


@dataclass(frozen=True)
class FsHicpStep:
    """One Align call."""

    level: Literal["coarse", "fine"]
    max_corr_m: float  # correspondence distance the Align ran with
    score: float  # fitness score (m^2) of the Align result on this level's clouds
    accepted: bool  # coarse steps are always accepted


@dataclass
class FsHicpResult:
    T_target_source: np.ndarray  # returned transform: best fine-level score
    T_last: np.ndarray  # the literal paper output: last accepted state of the fine level
    # Fine-level fitness score (0.05 m clouds, the level's score range; inf if no point is in
    # range) of the initial guess and of T_target_source, m^2: comparable with each other.
    initial_fitness: float
    final_fitness: float
    rmse: float  # RMS NN distance (m) of T_target_source over points within fine_max_corr_m
    inlier_fraction: float  # fraction of fine source points within fine_max_corr_m
    coarse_steps: int
    fine_steps: int
    seconds: float  # wall time of the whole call, preprocessing included
    history: list[FsHicpStep] = field(default_factory=list)


@dataclass
class _Level:
    """One level's clouds: voxel-filtered source and target, target KD-tree."""

    source: small_gicp.PointCloud
    source_xyz: np.ndarray  # (N, 3) copy for scoring
    target: small_gicp.PointCloud
    tree: small_gicp.KdTree
    score_range_m: float  # range of this level's fitness score (inf: all points)
    num_threads: int
    mode: str  # FsHicpConfig.fitness

    def score(self, T_target_source: np.ndarray, max_range: float | None = None,
              ) -> tuple[float, float]:
        """(PCL fitness score within max_range, default the level's score range; fraction of
        source points within that range)."""
        if max_range is None:
            max_range = self.score_range_m
        sq = squared_nn_distances(self.source_xyz, self.tree, T_target_source, self.num_threads)
        inside = sq <= max_range * max_range
        fraction = float(inside.mean())
        if self.mode == "truncated":
            return float(np.minimum(sq, max_range * max_range).mean()), fraction
        inliers = sq[inside] if math.isfinite(max_range) else sq
        return (float(inliers.mean()) if len(inliers) else math.inf), fraction

    def align(self, T_init: np.ndarray, max_corr_m: float, iterations: int) -> np.ndarray:
        result = small_gicp.align(
            self.target, self.source, self.tree, init_T_target_source=T_init,
            registration_type="ICP", max_correspondence_distance=max_corr_m,
            num_threads=self.num_threads, max_iterations=iterations,
            # Zero tolerances: every Align runs its full internal iterations; FS-HICP's own
            # score rules decide when to stop.
            rotation_epsilon=0.0, translation_epsilon=0.0)
        return np.asarray(result.T_target_source)


def drop_invalid(points: np.ndarray, name: str = "points",
                 max_depth_m: float | None = None) -> np.ndarray:
    """``points`` without non-finite rows and, if ``max_depth_m`` is given (a cloud in its
    camera's frame, z = depth), without the paper's invalid depths z <= 0 or z > max_depth_m.
    ValueError if the cloud is empty or fewer than ``MIN_POINTS`` remain."""
    points = as_points(points, name)
    if len(points) == 0:
        raise ValueError(f"{name}: empty point cloud")
    keep = np.isfinite(points).all(axis=1)
    if max_depth_m is not None:
        with np.errstate(invalid="ignore"):
            keep &= (points[:, 2] > 0.0) & (points[:, 2] <= max_depth_m)
    kept = points[keep]
    if len(kept) < MIN_POINTS:
        rule = "NaN/inf"
        if max_depth_m is not None:
            rule += f" and depth outside (0, {max_depth_m}] m"
        raise ValueError(f"{name}: {len(kept)} valid points of {len(points)} "
                         f"(need >= {MIN_POINTS}; {rule} are dropped)")
    return kept


def preprocess(points: np.ndarray, config: FsHicpConfig, camera_frame: bool,
               name: str = "points") -> np.ndarray:
    """Paper step 1 without the voxel filter: drop invalid points. Non-finite points always;
    with ``camera_frame=True`` also depth 0 or beyond ``max_depth_m`` (paper: "depth 0 or
    greater than 7000" mm). A map in a world frame has no depth to test."""
    return drop_invalid(points, name, config.max_depth_m if camera_frame else None)


def voxel_filter(points: np.ndarray, voxel_m: float) -> small_gicp.PointCloud:
    """Voxel-grid filter (centroid per voxel, like PCL's VoxelGrid). Single-threaded on
    purpose: small_gicp's threaded version returns a run-dependent point set."""
    return small_gicp.voxelgrid_sampling(points, voxel_m, 1)


def _make_level(source: np.ndarray, target: np.ndarray, voxel_m: float, score_range_m: float,
                num_threads: int, mode: str) -> _Level:
    src = voxel_filter(source, voxel_m)
    tgt = voxel_filter(target, voxel_m)
    for name, cloud in (("source", src), ("target", tgt)):
        if cloud.size() < MIN_POINTS:
            raise ValueError(f"{name}: {cloud.size()} points after the {voxel_m} m voxel filter "
                             f"(need >= {MIN_POINTS}; coordinates beyond the voxel grid's 21-bit "
                             "range are dropped)")
    return _Level(src, src.points()[:, :3].copy(), tgt, small_gicp.KdTree(tgt, num_threads),
                  score_range_m, num_threads, mode)


def _coarse_level(level: _Level, T: np.ndarray, config: FsHicpConfig,
                  history: list[FsHicpStep]) -> tuple[np.ndarray, int]:
    """Paper steps 2-3: Align and accept, while score >= fraction * initial score."""
    initial, _ = level.score(T)
    score = initial
    steps = 0
    while score >= config.coarse_score_fraction * initial and steps < config.max_coarse_steps:
        T = level.align(T, config.coarse_max_corr_m, config.align_iterations)
        new_score, _ = level.score(T)
        steps += 1
        history.append(FsHicpStep("coarse", config.coarse_max_corr_m, new_score, True))
        # (inf == inf: no point in range, ICP cannot move; stop rather than spin.)
        converged = new_score == score or abs(new_score - score) < config.score_epsilon
        score = new_score
        if converged:
            break
    return T, steps


def _fine_level(level: _Level, T: np.ndarray, config: FsHicpConfig,
                rng: np.random.Generator, history: list[FsHicpStep],
                ) -> tuple[np.ndarray, np.ndarray, int]:
    """Paper steps 5-6: Align; on a score decrease shrink the correspondence distance and
    accept; otherwise accept with probability ``accept_worse_probability``. Stop after
    ``max_no_improve`` non-decreases in a row or a score change below ``score_epsilon``.

    Returns (best, last accepted, steps). The paper's pseudo code returns its running
    FinalTrans, i.e. the last accepted state. We return the best-scoring state instead: the
    random acceptance exists to leave a local minimum in search of a *lower* score, and the
    level can stop right after accepting a worse step, which would hand back a transform
    its own criterion already rejected. Scores of this level are all taken on the same point
    set with the same range, so "best" is well defined. ``T_last`` keeps the literal reading.
    """
    score, _ = level.score(T)
    best_T, best_score = T, score
    corr = config.fine_max_corr_m
    # Never shrink below the voxel size: finer than that drops true correspondences.
    min_corr = config.fine_voxel_m
    no_improve = 0
    steps = 0
    candidate: tuple[np.ndarray, float] | None = None
    while steps < config.max_fine_steps:
        # A rejected step leaves the state and corr unchanged, so the next Align would
        # return the same candidate: reuse it rather than recompute.
        if candidate is None:
            cand_T = level.align(T, corr, config.align_iterations)
            candidate = (cand_T, level.score(cand_T)[0])
        cand_T, cand_score = candidate
        steps += 1
        ran_with = corr
        converged = cand_score == score or abs(cand_score - score) < config.score_epsilon
        if cand_score < score:
            accepted = True
            no_improve = 0
            corr = max(corr - config.fine_corr_shrink_m, min_corr)
        else:
            no_improve += 1
            accepted = bool(rng.random() < config.accept_worse_probability)
        if accepted:
            T, score, candidate = cand_T, cand_score, None
        history.append(FsHicpStep("fine", ran_with, cand_score, accepted))
        if score < best_score:
            best_T, best_score = T, score
        if converged or no_improve >= config.max_no_improve:
            break
    return best_T, T, steps


def _score_range(config: FsHicpConfig, level_corr_m: float) -> float:
    if config.fitness not in ("pcl", "inliers", "truncated"):
        raise ValueError(f"fshicp.fitness: unknown score '{config.fitness}' "
                         "(pcl, inliers or truncated)")
    return math.inf if config.fitness == "pcl" else level_corr_m


def fshicp(source: np.ndarray, target: np.ndarray, T_init: np.ndarray,
           config: FsHicpConfig | None = None, camera_frame: bool = False) -> FsHicpResult:
    """Register ``source`` onto ``target`` starting from the guess ``T_init``
    (= T_target_source: maps source points into the target frame). Points are (N, 3) metres.
    Raises ValueError on empty clouds, clouds without enough valid points, or a bad guess."""
    start = time.perf_counter()
    config = config or FsHicpConfig()
    T0 = as_rigid_transform(T_init, "T_init")
    source = preprocess(source, config, camera_frame, "source")
    target = preprocess(target, config, camera_frame, "target")
    rng = np.random.default_rng(config.seed)
    history: list[FsHicpStep] = []

    coarse = _make_level(source, target, config.coarse_voxel_m,
                         _score_range(config, config.coarse_max_corr_m), config.num_threads,
                         config.fitness)
    T, coarse_steps = _coarse_level(coarse, T0, config, history)

    fine = _make_level(source, target, config.fine_voxel_m,
                       _score_range(config, config.fine_max_corr_m), config.num_threads,
                       config.fitness)
    best_T, last_T, fine_steps = _fine_level(fine, T, config, rng, history)

    initial_fitness, _ = fine.score(T0)
    final_fitness, _ = fine.score(best_T)
    # RMSE over the overlap (points within the fine correspondence distance), whatever
    # score steered the levels.
    inlier_sq = squared_nn_distances(fine.source_xyz, fine.tree, best_T, fine.num_threads)
    inside = inlier_sq <= config.fine_max_corr_m**2
    inlier_fitness = float(inlier_sq[inside].mean()) if inside.any() else math.inf
    inlier_fraction = float(inside.mean())
    return FsHicpResult(
        T_target_source=best_T, T_last=last_T,
        initial_fitness=initial_fitness, final_fitness=final_fitness,
        rmse=math.sqrt(inlier_fitness), inlier_fraction=inlier_fraction,
        coarse_steps=coarse_steps, fine_steps=fine_steps,
        seconds=time.perf_counter() - start, history=history)
