"""What a merge could reach with the robots it is given (issue 46): each robot of the shared
merge cases tracked on its own, then joined to the others by *ideal* inter-robot
constraints (ground truth's relative pose at every keyframe pair where the robots overlap),
and the drift of the robots' own keyframe-to-keyframe poses, from the tracker and from a
chain of dense (GICP) edges.

    .venv/bin/python bench/merge_bounds.py [--only rk-2 ...] [--case NAME=SOURCE,SOURCE ...]
                                           [--out bench/results/merge_bounds.json]

Two tables:
- **Odometry by span**: for keyframes i and i+N of a robot, the error against ground truth of
  their relative pose as the tracker has it and as N consecutive-keyframe GICP edges
  compose it (merging/dense_constraint.py's ``register`` on the keyframes' depth clouds,
  each started from the tracker's; a refused edge keeps the tracker's), medians over i;
  and each one's rotation scale about the camera's x, y, z axes (least squares of the
  edges' rotation vectors against ground truth's).
- **Ideal constraints**: each robot after the first placed in the frame of the robots
  placed before it through ideal constraints at the keyframe pairs where they overlap
  (camera centres within merge.proximity_distance_m, optical axes within
  merge.proximity_angle_deg, by ground truth): through one pair (the median over the pairs
  taken one at a time: a join at one place) and through all of them (the chordal mean of
  the transforms they imply). Joint ATE (one SE(3) alignment for all robots, as
  bench/merge_fleet.py scores), map-to-map error, and the separately aligned bound.
  Ground truth makes the constraints, so these numbers are bounds for evaluation, never
  something the system could run on.
- **In the fleet's graph**: the same pairs as edges of a pose graph built as the merger
  builds its own (each robot's keyframe-to-keyframe poses at merge.odometry_sigma_*, the
  inter-robot edges at merge.inter_sigma_*), so the robots may bend as the merge bends them:
  with ground truth's relative pose ("truth"), and with what depth says there ("depth":
  GICP of the two keyframes' clouds started from ground truth's pose, as a perfect place
  search followed by the merger's dense registration would measure it). Every frame follows
  its reference keyframe, as the merge's global trajectories do.
- **Depth against ground truth**: how far that GICP moves ground truth's relative pose, at
  the overlapping pairs (keyframes far apart in time) and at each robot's consecutive
  keyframes (near in time: the registration's own floor).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from fleetslam.backend.pose_graph import PoseEdge, optimise_pose_graph
from fleetslam.config import Config, load_config
from fleetslam.datasets.recording import open_source
from fleetslam.evaluation.fleet import ate_summary, map_to_map
from fleetslam.merging.dense_constraint import DenseCloud, prepare, register
from fleetslam.system import track_robot
from fleetslam.tables import format_table
from fleetslam.transforms import poses_from_references, rotation_angles_deg
from merge_fleet import joined_cases, parse_case

SPANS = (1, 2, 4, 8, 16)
THROUGH = {"one": "one pair (median), rigid", "all": "all pairs, rigid",
           "graph_truth": "all pairs in the fleet's graph", "graph_depth":
           "all pairs in the fleet's graph, depth's edges"}
# Depth points for a keyframe's cloud: every second pixel up to this range (the merger's
# uploads are decimated by 2 as well).
CLOUD_STRIDE, CLOUD_RANGE_M = 2, 4.0


class Robot:
    """One robot tracked on its own: every frame's pose, its keyframes, ground truth."""

    def __init__(self, spec: str, config: Config) -> None:
        self.spec = spec
        self.sequence = open_source(spec)
        run = track_robot(spec, spec, self.sequence, config, show_progress=False)
        self.poses = run.poses
        self.keyframes = np.asarray(run.keyframe_indices)
        self.references, self.T_reference_camera = run.references, run.T_reference_camera
        gt = self.sequence.gt_poses
        if gt is None:
            raise SystemExit(f"{spec}: no ground truth, and this bench is scored against it")
        self.gt = gt
        self._clouds: dict[int, DenseCloud] = {}

    def cloud(self, frame: int, config: Config) -> DenseCloud:
        """A keyframe's depth cloud, prepared for GICP (once)."""
        if frame not in self._clouds:
            points, _ = self.sequence.camera.backproject_image(
                self.sequence[frame].depth_m, stride=CLOUD_STRIDE, max_depth_m=CLOUD_RANGE_M)
            self._clouds[frame] = prepare(points, config.merge)
        return self._clouds[frame]

    def follow(self, keyframe_poses: np.ndarray) -> np.ndarray:
        """Every frame's pose with its keyframes at ``keyframe_poses`` (K x 4 x 4)."""
        return poses_from_references(keyframe_poses, self.references, self.T_reference_camera,
                                     self.poses)

    def dense_edges(self, config: Config) -> tuple[list[np.ndarray], int]:
        """Consecutive keyframes' relative poses from GICP (the tracker's where refused), and
        how many were accepted."""
        clouds = [self.cloud(int(i), config) for i in self.keyframes]
        T = self.poses[self.keyframes]
        edges, accepted = [], 0
        for k in range(len(T) - 1):
            start = np.linalg.solve(T[k], T[k + 1])
            found = register(clouds[k], clouds[k + 1], start, config.merge)
            accepted += found.accepted
            edges.append(found.T_dense if found.accepted else start)
        return edges, accepted


def rotation_scale(estimated: list[np.ndarray], truth: list[np.ndarray]) -> list[float]:
    """Per camera axis, the least-squares scale of the estimated relative rotations'
    rotation vectors against ground truth's."""
    e = Rotation.from_matrix(np.array([T[:3, :3] for T in estimated])).as_rotvec()
    g = Rotation.from_matrix(np.array([T[:3, :3] for T in truth])).as_rotvec()
    return [float(np.sum(e[:, a] * g[:, a]) / np.sum(g[:, a] ** 2)) for a in range(3)]


def odometry(robot: Robot, config: Config) -> dict[str, Any]:
    T, G = robot.poses[robot.keyframes], robot.gt[robot.keyframes]
    dense, accepted = robot.dense_edges(config)
    truth = [np.linalg.solve(G[k], G[k + 1]) for k in range(len(G) - 1)]
    tracker = [np.linalg.solve(T[k], T[k + 1]) for k in range(len(T) - 1)]
    spans = []
    for n in SPANS:
        errors: dict[str, list[tuple[float, float]]] = {"tracker": [], "dense": []}
        for k in range(len(T) - n):
            g = np.linalg.solve(G[k], G[k + n])
            chain = np.linalg.multi_dot([np.eye(4), *dense[k:k + n]])
            for name, X in (("tracker", np.linalg.solve(T[k], T[k + n])), ("dense", chain)):
                E = np.linalg.solve(g, X)
                errors[name].append((rotation_angles_deg(E[None, :3, :3])[0],
                                     float(np.linalg.norm(E[:3, 3]))))
        if errors["tracker"]:
            spans.append({"span": n, **{f"{name}_{q}": float(np.median([e[i] for e in v]))
                                        for name, v in errors.items()
                                        for i, q in enumerate(("rotation_deg", "translation_m"))}})
    return {"robot": robot.spec, "keyframes": len(T), "dense_accepted": accepted,
            "tracker_rotation_scale": rotation_scale(tracker, truth),
            "dense_rotation_scale": rotation_scale(dense, truth), "spans": spans}


def overlapping_pairs(a: Robot, b: Robot, config: Config) -> list[tuple[int, int]]:
    """(keyframe of a, keyframe of b): each keyframe of b with a's nearest keyframe by
    ground truth, where they overlap."""
    pairs = []
    ka = a.keyframes
    for j in b.keyframes:
        near = np.linalg.norm(a.gt[ka, :3, 3] - b.gt[j, :3, 3], axis=1)
        turned = rotation_angles_deg(np.transpose(a.gt[ka, :3, :3], (0, 2, 1))
                                     @ b.gt[j, :3, :3])
        ok = (near <= config.merge.proximity_distance_m) \
            & (turned <= config.merge.proximity_angle_deg)
        if ok.any():
            pairs.append((int(ka[np.flatnonzero(ok)[np.argmin(near[ok])]]), int(j)))
    return pairs


def mean_transform(transforms: list[np.ndarray]) -> np.ndarray:
    M = np.eye(4)
    M[:3, :3] = Rotation.from_matrix(np.array([T[:3, :3] for T in transforms])).mean().as_matrix()
    M[:3, 3] = np.mean([T[:3, 3] for T in transforms], axis=0)
    return M


def ideal_merge(robots: list[Robot], config: Config, how: str) -> dict[str, Any] | None:
    """Place each robot in the first's frame through ideal constraints with the robots placed
    before it ("one": each pair alone, the median pair by joint ATE; "all": their mean)."""
    placed = {0: np.eye(4)}
    per_robot: list[list[np.ndarray]] = []
    for r in range(1, len(robots)):
        implied = []
        for p, M_p in placed.items():
            a, b = robots[p], robots[r]
            for i, j in overlapping_pairs(a, b, config):
                ideal = np.linalg.solve(a.gt[i], b.gt[j])  # b's camera in a's, by truth
                implied.append(M_p @ a.poses[i] @ ideal @ np.linalg.inv(b.poses[j]))
        if not implied:
            return None
        per_robot.append(implied)
        placed[r] = mean_transform(implied)
    if how == "one":
        # Each robot through one pair at a time (the others through their mean).
        results = []
        for r, implied in enumerate(per_robot, start=1):
            for M in implied:
                results.append(score({**placed, r: M}, robots))
        results.sort(key=lambda s: s["joint_ate_m"])
        middle = results[len(results) // 2]
        return {**middle, "pairs": sum(len(v) for v in per_robot)}
    return {**score(placed, robots), "pairs": sum(len(v) for v in per_robot)}


def depth_says(a: Robot, i: int, b: Robot, j: int, config: Config) -> np.ndarray | None:
    """b's keyframe (frame j) in a's (frame i) as GICP of their depth finds it from ground
    truth's relative pose; None when the registration is refused."""
    found = register(a.cloud(i, config), b.cloud(j, config), np.linalg.solve(a.gt[i], b.gt[j]),
                     config.merge)
    return found.T_dense if found.accepted else None


def graph_merge(robots: list[Robot], config: Config, edges_from: str) -> dict[str, Any] | None:
    """The robots in one pose graph as the merger builds it (merging/merger.py ``_solve``:
    odometry between consecutive keyframes, inter-robot edges trusted), the inter-robot edges
    at every overlapping pair from ground truth ("truth") or from depth ("depth"), started
    from the rigid placement through all pairs."""
    cfg = config.merge
    start = ideal_merge(robots, config, "all")
    if start is None:
        return None
    odometry = (np.deg2rad(cfg.odometry_sigma_rotation_deg), cfg.odometry_sigma_translation_m)
    inter = (np.deg2rad(cfg.inter_sigma_rotation_deg), cfg.inter_sigma_translation_m)
    stride = 1_000_000
    values: dict[int, np.ndarray] = {}
    edges: list[PoseEdge] = []
    for r, robot in enumerate(robots):
        K = robot.poses[robot.keyframes]
        for k in range(len(K)):
            values[r * stride + k] = start["placed"][r] @ K[k]
            if k:
                edges.append(PoseEdge(r * stride + k - 1, r * stride + k,
                                      np.linalg.solve(K[k - 1], K[k]), "odometry", odometry))
    refused = 0
    for b in range(1, len(robots)):
        for a in range(b):
            A, B = robots[a], robots[b]
            for i, j in overlapping_pairs(A, B, config):
                T = np.linalg.solve(A.gt[i], B.gt[j]) if edges_from == "truth" \
                    else depth_says(A, i, B, j, config)
                if T is None:
                    refused += 1
                    continue
                edges.append(PoseEdge(a * stride + int(np.searchsorted(A.keyframes, i)),
                                      b * stride + int(np.searchsorted(B.keyframes, j)),
                                      T, "loop", inter, trusted=True))
    result = optimise_pose_graph(values, edges, 0, *odometry)
    est = [robot.follow(np.array([result.poses[r * stride + k]
                                  for k in range(len(robot.keyframes))]))
           for r, robot in enumerate(robots)]
    return {**score_poses(est, robots), "pairs": sum(e.kind == "loop" for e in edges),
            "refused": refused}


def depth_against_truth(robots: list[Robot], config: Config) -> dict[str, Any]:
    """How far GICP moves ground truth's relative pose: at the robots' overlapping pairs
    (far apart in time) and at each robot's consecutive keyframes (near in time)."""
    def moved(pairs: list[tuple[Robot, int, Robot, int]]) -> dict[str, Any]:
        out = []
        for a, i, b, j in pairs:
            T = depth_says(a, i, b, j, config)
            if T is not None:
                E = np.linalg.solve(np.linalg.solve(a.gt[i], b.gt[j]), T)
                out.append((rotation_angles_deg(E[None, :3, :3])[0],
                            float(np.linalg.norm(E[:3, 3]))))
        e = np.array(out).reshape(-1, 2)
        return {"pairs": len(pairs), "accepted": len(e),
                **({"rotation_deg_median": float(np.median(e[:, 0])),
                    "translation_m_median": float(np.median(e[:, 1])),
                    "translation_m_max": float(e[:, 1].max())} if len(e) else {})}

    far = [(robots[a], i, robots[b], j) for b in range(1, len(robots)) for a in range(b)
           for i, j in overlapping_pairs(robots[a], robots[b], config)]
    near = [(r, int(i), r, int(j)) for r in robots for i, j in zip(r.keyframes, r.keyframes[1:])]
    return {"far": moved(far), "near": moved(near)}


def score(placed: dict[int, np.ndarray], robots: list[Robot]) -> dict[str, Any]:
    return {**score_poses([placed[r] @ robot.poses for r, robot in enumerate(robots)], robots),
            "placed": placed}


def score_poses(est: list[np.ndarray], robots: list[Robot]) -> dict[str, Any]:
    gt = [robot.gt for robot in robots]
    joint = ate_summary(np.concatenate(est), np.concatenate(gt))
    apart = map_to_map([robot.spec for robot in robots], est, gt)
    return {"joint_ate_m": joint["rmse_m"] if joint else float("nan"),
            "bound_m": apart.get("separately_aligned_bound_m"),
            "map_to_map": apart.get("map_to_map", [])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="cases to run (default: all)")
    parser.add_argument("--case", action="append", default=[], metavar="NAME=SOURCE,SOURCE...",
                        help="a case of these sources besides the shared ones (repeatable; "
                             "as bench/merge_fleet.py's)")
    parser.add_argument("--config", help="a TOML file over the defaults")
    parser.add_argument("--out", default="bench/results/merge_bounds.json")
    args = parser.parse_args()
    config = load_config(args.config)
    chosen = {**joined_cases(), **dict(parse_case(text) for text in args.case)}
    unknown = set(args.only or []) - set(chosen)
    if unknown:
        raise SystemExit(f"--only: no case {sorted(unknown)}; known: {sorted(chosen)}")
    results = []
    odometry_rows, ideal_rows, depth_rows = [], [], []
    for name, specs in chosen.items():
        if args.only and name not in args.only:
            continue
        print(f"{name}: tracking {len(specs)} robots ...", flush=True)
        robots = [Robot(spec, config) for spec in specs]
        odo = [odometry(robot, config) for robot in robots]
        ideal = {how: ideal_merge(robots, config, how) for how in ("one", "all")}
        ideal.update({f"graph_{edges}": graph_merge(robots, config, edges)
                      for edges in ("truth", "depth")})
        check = depth_against_truth(robots, config)
        alone = [ate_summary(r.poses, r.gt)["rmse_m"] for r in robots]
        results.append({"case": name, "alone_m": alone, "odometry": odo, "depth_against_truth":
                        check, "ideal": {how: {k: v for k, v in res.items() if k != "placed"}
                                         if res else None for how, res in ideal.items()}})
        depth_rows.append([name] + [
            f"{c['accepted']} of {c['pairs']}: {c['rotation_deg_median']:.2f} / "
            f"{100 * c['translation_m_median']:.2f} (max {100 * c['translation_m_max']:.2f})"
            if c["accepted"] else f"0 of {c['pairs']}" for c in (check["far"], check["near"])])
        for r, o in zip(robots, odo):
            for s in o["spans"]:
                odometry_rows.append([name, Path(r.spec).name.split(":")[-1], s["span"],
                                      f"{s['tracker_rotation_deg']:.2f} / {s['dense_rotation_deg']:.2f}",
                                      f"{100 * s['tracker_translation_m']:.2f} / "
                                      f"{100 * s['dense_translation_m']:.2f}",
                                      " ".join(f"{v:.2f}" for v in o["tracker_rotation_scale"])
                                      + " / " + " ".join(f"{v:.2f}" for v in o["dense_rotation_scale"])
                                      if s["span"] == 1 else "",
                                      f"{o['dense_accepted']} of {o['keyframes'] - 1}"
                                      if s["span"] == 1 else ""])
        for how, res in ideal.items():
            if res is None:
                ideal_rows.append([name, how, "no overlap", "", "", "", ""])
                continue
            m2m = "; ".join(f"{m['rotation_deg']:.1f} deg / {100 * m['translation_m']:.1f} cm"
                            for m in res["map_to_map"])
            ideal_rows.append([name, THROUGH[how], res["pairs"], " / ".join(f"{100 * a:.2f}" for a in alone),
                               f"{100 * res['bound_m']:.2f}", f"{100 * res['joint_ate_m']:.2f}",
                               m2m])
    print("\nOdometry by span (medians over the keyframe pairs N apart; tracker / dense chain):")
    print(format_table(["case", "robot", "N", "rotation err deg", "translation err cm",
                        "rotation scale x y z", "dense edges accepted"], odometry_rows))
    print("\nIdeal inter-robot constraints (ground truth's relative pose where robots overlap):")
    print(format_table(["case", "through", "pairs", "alone cm", "bound cm", "joint ATE cm",
                        "map-to-map"], ideal_rows))
    print("\nDepth against ground truth (GICP from ground truth's relative pose; median deg / cm):")
    print(format_table(["case", "overlapping pairs (far in time)",
                        "consecutive keyframes (near in time)"], depth_rows))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "cores": os.cpu_count(),
                               "results": results}, indent=2, default=float))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
