"""Fleet-wide bundle adjustment after a join (COVINS' and ORB-SLAM3's step after a merge):
the keyframes of every robot of a joined group and the landmarks they share, optimised
together, so each robot's drift away from where it joined is corrected wherever the robots
saw the same places, not only at the join.

The pose graph (merger.py) ties two robots' maps at the keyframe pairs it has edges for; a
robot's keyframes between those pairs follow its own odometry, and its drift bends them away
from the other robot's. Here the landmarks are associated anew from what the merger holds
of each keyframe (its ORB features with depth): every keyframe with the next ones of its
own robot and with the keyframes the graph puts nearest it (any robot of the group,
camera centres within ``merge.proximity_distance_m``, optical axes within
``merge.proximity_angle_deg``). A pair's descriptor matches count only when a rigid fit of
their depth-backed 3D points agrees (RANSAC, loop closing's bounds) and that fit is near
where the graph puts the pair (``merge.fleet_ba_max_disagreement_*``): the graph already
has the robots within centimetres, so a pair of look-alike places elsewhere is no
association. Matches chain into landmarks (a landmark seen twice in one keyframe is
dropped as ambiguous), and the problem is local BA's (backend/local_ba.py: stereo factors
with Huber kernels, a robust pass, then the inliers), all keyframes free except the group's
anchor keyframe and a loaded map's (held). Keyframes without an associated landmark move
with the nearest keyframe of their robot that has one.

No ground truth is read here; it runs only in the final merge (the global map), never on a
tracking thread.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from fleetslam.backend.geometric_verification import ransac_rigid
from fleetslam.backend.local_ba import LocalBAProblem, solve_local_ba
from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.registration.metrics import transform_error
from fleetslam.transforms import invert
from fleetslam.wire.merger_keyframes import KeyframeSummary

log = logging.getLogger("fleetslam.merge")

# Graph keys of keyframes: robot i's keyframe k is i * KEY_STRIDE + k (below local BA's
# landmark offset).
KEY_STRIDE = 1_000_000


@dataclass
class FleetRobot:
    """One member of the group as the adjustment reads it."""

    name: str
    camera: Camera
    keyframes: list[KeyframeSummary]
    poses: np.ndarray  # K x 4 x 4, the group's frame (the pose graph's)
    own: np.ndarray  # K x 4 x 4, the robot's own map frame (its relative poses: priors)
    held: bool = False  # a loaded map's robot: its keyframes stay


@dataclass
class FleetBAReport:
    """What an adjustment did (summary.json's ``fleet_ba``)."""

    pairs_tried: int = 0
    pairs_associated: int = 0  # pairs whose matches were kept
    pairs_between_robots: int = 0  # of those, between two robots
    landmarks: int = 0
    shared_landmarks: int = 0  # seen by more than one robot
    observations: int = 0
    outliers: int = 0
    keyframes: int = 0  # keyframes in the problem
    associate_seconds: float = 0.0
    solve_seconds: float = 0.0
    # Largest pose change of a keyframe: degrees, metres.
    max_rotation_deg: float = 0.0
    max_translation_m: float = 0.0
    skipped: str | None = None  # why nothing was adjusted
    per_robot: dict[str, dict[str, float]] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass
class _Points:
    """One keyframe's depth-backed keypoints."""

    uv: np.ndarray  # M x 2, in the reference camera's pixels
    depth: np.ndarray  # M
    octave: np.ndarray  # M int
    descriptors: np.ndarray  # M x 32 uint8
    xyz: np.ndarray  # M x 3, its own camera frame


def _points(summary: KeyframeSummary, camera: Camera, reference: Camera,
            max_depth_m: float) -> _Points:
    f = summary.features
    keep = np.flatnonzero((f.depth > 0) & (f.depth <= max_depth_m) & np.isfinite(f.depth))
    uv, depth = f.uv[keep].astype(np.float64), f.depth[keep].astype(np.float64)
    xyz = camera.backproject(uv, depth)
    # Another robot's camera: its ideal pixels as the reference camera would see the ray.
    uv_ref = np.stack([xyz[:, 0] / depth * reference.fx + reference.cx,
                       xyz[:, 1] / depth * reference.fy + reference.cy], axis=1)
    return _Points(uv_ref, depth, f.keypoints[keep, 5].astype(np.int64),
                   np.ascontiguousarray(f.descriptors[keep]), xyz)


def candidate_pairs(poses: np.ndarray, robot_of: np.ndarray, index_of: np.ndarray,
                    sequential: int, nearest: int, distance_m: float, angle_deg: float
                    ) -> np.ndarray:
    """(i, j), i < j, rows of ``poses``: each keyframe with the next ``sequential`` of its
    own robot, and with the ``nearest`` keyframes of other robots whose camera centre is
    within ``distance_m`` and optical axis within ``angle_deg``, nearest first."""
    n = len(poses)
    pairs: set[tuple[int, int]] = set()
    order = np.lexsort((index_of, robot_of))
    for step in range(1, sequential + 1):
        a, b = order[:-step], order[step:]
        same = robot_of[a] == robot_of[b]
        pairs.update(zip(np.minimum(a, b)[same].tolist(), np.maximum(a, b)[same].tolist()))
    if n > 1 and nearest > 0:
        centres, axes = poses[:, :3, 3], poses[:, :3, 2]
        gap = np.linalg.norm(centres[:, None] - centres[None], axis=2)
        gap[(axes @ axes.T) < np.cos(np.deg2rad(angle_deg))] = np.inf
        gap[robot_of[:, None] == robot_of[None]] = np.inf
        gap[gap > distance_m] = np.inf
        ranked = np.argsort(gap, axis=1)[:, :nearest]
        for i in range(n):
            for j in ranked[i][np.isfinite(gap[i, ranked[i]])].tolist():
                pairs.add((min(i, j), max(i, j)))
    return np.array(sorted(pairs), np.int64).reshape(-1, 2)


def _associate(a: _Points, b: _Points, T_a_b: np.ndarray, config: Config, seed: int
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """Indices (into a, into b) of the matches a rigid fit keeps, None if too few agree or
    the fit is far from ``T_a_b`` (where the graph puts b relative to a)."""
    if len(a.xyz) < 3 or len(b.xyz) < 3:
        return None
    mcfg, lcfg = config.merge, config.loop_closing
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True)
    matches = [m for m in matcher.match(b.descriptors, a.descriptors)
               if m.distance <= mcfg.fleet_ba_max_hamming]
    if len(matches) < lcfg.min_ransac_inliers:
        return None
    ib = np.array([m.queryIdx for m in matches], np.int64)
    ia = np.array([m.trainIdx for m in matches], np.int64)
    threshold = np.maximum(lcfg.ransac_inlier_m, lcfg.ransac_inlier_depth_ratio * b.depth[ib])
    rigid = ransac_rigid(b.xyz[ib], a.xyz[ia], threshold, lcfg.ransac_iterations,
                         lcfg.min_ransac_inliers, np.random.default_rng(seed))
    if rigid is None:
        return None
    off = transform_error(rigid.T_target_source, T_a_b)
    if off.rotation_deg > mcfg.fleet_ba_max_disagreement_deg \
            or off.translation_m > mcfg.fleet_ba_max_disagreement_m:
        return None
    return ia[rigid.inliers], ib[rigid.inliers]


def fleet_bundle_adjustment(robots: list[FleetRobot], config: Config
                            ) -> tuple[dict[str, np.ndarray], FleetBAReport]:
    """Every robot's keyframe poses after the adjustment (the group's frame), and what it
    did. The first robot's first keyframe, and held robots' keyframes, stay."""
    report = FleetBAReport()
    out = {r.name: r.poses.copy() for r in robots}
    start = time.perf_counter()
    cfg = config.merge
    reference = robots[0].camera
    max_depth = config.tracking.close_depth_baselines * config.tracking.virtual_baseline_m
    rows = [(i, k) for i, r in enumerate(robots) for k in range(len(r.poses))]
    if len(robots) < 2 or len(rows) < 2:
        report.skipped = "fewer than two robots with keyframes"
        return out, report
    robot_of = np.array([i for i, _ in rows], np.int64)
    index_of = np.array([k for _, k in rows], np.int64)
    poses = np.array([robots[i].poses[k] for i, k in rows]).reshape(-1, 4, 4)
    points = [_points(robots[i].keyframes[k], robots[i].camera, reference, max_depth)
              for i, k in rows]
    pairs = candidate_pairs(poses, robot_of, index_of, cfg.fleet_ba_sequential,
                            cfg.fleet_ba_nearest, cfg.proximity_distance_m,
                            cfg.proximity_angle_deg)
    offsets = np.concatenate([[0], np.cumsum([len(p.xyz) for p in points])])
    edges_a, edges_b = [], []
    for i, j in pairs.tolist():
        report.pairs_tried += 1
        found = _associate(points[i], points[j], invert(poses[i]) @ poses[j], config,
                           cfg.seed + i * len(rows) + j)
        if found is None:
            continue
        report.pairs_associated += 1
        report.pairs_between_robots += int(robot_of[i] != robot_of[j])
        edges_a.append(offsets[i] + found[0])
        edges_b.append(offsets[j] + found[1])
    report.associate_seconds = time.perf_counter() - start
    if not edges_a:
        report.skipped = "no keyframe pair associated"
        return out, report
    problem, rows_in = _problem(robots, rows, poses, points, offsets,
                                np.concatenate(edges_a), np.concatenate(edges_b), config,
                                report)
    if problem is None:
        return out, report
    solution = solve_local_ba(problem)
    report.solve_seconds = time.perf_counter() - start - report.associate_seconds
    if solution is None:
        report.skipped = "the adjustment's system was indeterminate"
        return out, report
    report.outliers = int(solution.outlier.sum())
    _write_back(robots, rows, rows_in, problem, solution.poses, out, report)
    log.info("fleet BA: %d keyframes, %d landmarks (%d shared between robots), %d of %d "
             "pairs associated (%d between robots), largest move %.2f deg / %.1f cm, %.1f s",
             report.keyframes, report.landmarks, report.shared_landmarks,
             report.pairs_associated, report.pairs_tried, report.pairs_between_robots,
             report.max_rotation_deg, 100 * report.max_translation_m,
             time.perf_counter() - start)
    return out, report


def _problem(robots: list[FleetRobot], rows: list[tuple[int, int]], poses: np.ndarray,
             points: list[_Points], offsets: np.ndarray, edge_a: np.ndarray,
             edge_b: np.ndarray, config: Config, report: FleetBAReport
             ) -> tuple[LocalBAProblem | None, np.ndarray]:
    """Local BA's problem over the landmarks the matches chain into; and the rows (into
    ``rows``) of the keyframes in it."""
    n = int(offsets[-1])
    graph = coo_matrix((np.ones(len(edge_a)), (edge_a, edge_b)), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    used = np.zeros(n, bool)
    used[edge_a] = used[edge_b] = True
    obs = np.flatnonzero(used)
    lm = label[obs]
    row = np.searchsorted(offsets, obs, side="right") - 1
    # A landmark seen twice by one keyframe is a wrong chain: dropped.
    key = lm.astype(np.int64) * len(rows) + row
    uniq, counts = np.unique(key, return_counts=True)
    twice = np.unique(uniq[counts > 1] // len(rows))
    keep = ~np.isin(lm, twice)
    obs, lm, row = obs[keep], lm[keep], row[keep]
    landmarks, lm_slot = np.unique(lm, return_inverse=True)
    if len(landmarks) == 0:
        report.skipped = "every associated landmark was ambiguous"
        return None, np.zeros(0, np.int64)
    local = obs - offsets[row]
    robot_of = np.array([rows[r][0] for r in row], np.int64)
    robots_per_lm = np.zeros((len(landmarks), len(robots)), bool)
    robots_per_lm[lm_slot, robot_of] = True
    report.shared_landmarks = int((robots_per_lm.sum(axis=1) > 1).sum())
    report.landmarks, report.observations = len(landmarks), len(obs)
    # Each landmark starts at the mean of its observations' points in the group's frame.
    xyz_cam = np.concatenate([points[r].xyz[i][None] for r, i in zip(row, local)]) \
        if len(obs) else np.zeros((0, 3))
    world = np.einsum("nij,nj->ni", poses[row, :3, :3], xyz_cam) + poses[row, :3, 3]
    xyz = np.zeros((len(landmarks), 3))
    np.add.at(xyz, lm_slot, world)
    xyz /= np.bincount(lm_slot, minlength=len(landmarks))[:, None]
    keys = np.array([rows[r][0] * KEY_STRIDE + rows[r][1] for r in range(len(rows))], np.int64)
    rows_in = np.unique(row)
    kfs = keys[rows_in]  # sorted: rows are in key order
    held = np.array([robots[rows[r][0]].held for r in rows_in], bool)
    fixed_mask = held | (kfs == keys[0])
    if not fixed_mask.any():
        fixed_mask[0] = True
    report.keyframes = len(kfs)
    uv = np.concatenate([points[r].uv[i][None] for r, i in zip(row, local)])
    depth = np.array([points[r].depth[i] for r, i in zip(row, local)])
    octave = np.array([points[r].octave[i] for r, i in zip(row, local)], np.int64)
    return LocalBAProblem(
        int(kfs[0]), kfs, kfs[fixed_mask], kfs[~fixed_mask], poses[rows_in].copy(),
        np.arange(len(landmarks), dtype=np.int64), xyz, keys[row], lm_slot.astype(np.int64),
        uv, depth, octave, np.zeros(0, np.int64), np.zeros(0, np.int64), robots[0].camera,
        config.tracking.virtual_baseline_m, config.orb.scale_factor,
        tuple(config.merge.fleet_ba_iterations),
        between=_own_graph(robots, [rows[r] for r in rows_in], config)), rows_in


def _own_graph(robots: list[FleetRobot], in_problem: list[tuple[int, int]], config: Config
               ) -> list[tuple[int, int, np.ndarray, float, float]]:
    """Each robot's own relative poses between its consecutive keyframes in the problem, as
    the fleet's pose graph weighs them (merge.odometry_sigma_*), scaled by
    merge.fleet_ba_prior_scale (0: none)."""
    cfg = config.merge
    if cfg.fleet_ba_prior_scale <= 0:
        return []
    sr = np.deg2rad(cfg.odometry_sigma_rotation_deg) * cfg.fleet_ba_prior_scale
    st = cfg.odometry_sigma_translation_m * cfg.fleet_ba_prior_scale
    out = []
    for (i, k0), (j, k1) in zip(in_problem, in_problem[1:]):
        if i == j:
            own = robots[i].own
            out.append((i * KEY_STRIDE + k0, i * KEY_STRIDE + k1,
                        invert(own[k0]) @ own[k1], sr, st))
    return out


def _write_back(robots: list[FleetRobot], rows: list[tuple[int, int]], rows_in: np.ndarray,
                problem: LocalBAProblem, solved: np.ndarray, out: dict[str, np.ndarray],
                report: FleetBAReport) -> None:
    """Solved poses into ``out``; a keyframe outside the problem moves with its robot's
    nearest keyframe (by id) inside it, a robot with none stays."""
    for i, r in enumerate(robots):
        if r.held:
            continue
        mine = [(rows[row][1], slot) for slot, row in enumerate(rows_in.tolist())
                if rows[row][0] == i]
        if not mine:
            continue
        ids = np.array([k for k, _ in mine])
        # A fixed keyframe (held by a tight prior) stays exactly where it was.
        fixed = set(problem.fixed.tolist())
        corrections = {k: np.eye(4) if i * KEY_STRIDE + k in fixed
                       else solved[s] @ invert(problem.T_old[s]) for k, s in mine}
        moved = r.poses.copy()
        for k in range(len(r.poses)):
            nearest = int(ids[np.argmin(np.abs(ids - k))])
            moved[k] = corrections[nearest] @ r.poses[k]
        changes = [transform_error(moved[k], r.poses[k]) for k in range(len(r.poses))]
        report.per_robot[r.name] = {
            "keyframes_in_problem": len(mine),
            "max_rotation_deg": max(c.rotation_deg for c in changes),
            "max_translation_m": max(c.translation_m for c in changes)}
        report.max_rotation_deg = max(report.max_rotation_deg,
                                      report.per_robot[r.name]["max_rotation_deg"])
        report.max_translation_m = max(report.max_translation_m,
                                       report.per_robot[r.name]["max_translation_m"])
        out[r.name] = moved
