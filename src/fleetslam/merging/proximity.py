"""More edges between joined robots than features found: where the global graph puts two
robots' keyframes near each other (camera centres close, optical axes alike), the two
keyframes' depth clouds are registered from where the graph puts them.

Features find a place two robots share only where their views match well enough (on the
shared 7-Scenes pair, 9 of 259 keyframe pairs within 1 m and 45 deg pass the check, all in
one stretch); the join places the robots, and then depth can check every other stretch
where they overlap. Each edge is kept only by the dense bounds (converged, enough overlap,
near the graph's start: dense_constraint.register) and then judged by GNC like any edge
found after a join. No ground truth is read.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from fleetslam.config import MergeConfig
from fleetslam.merging.constraint import Constraint
from fleetslam.merging.dense_constraint import DenseCloud, feature_information, register
from fleetslam.merging.inter_robot import PlaceMatch
from fleetslam.merging.place_search import pair_key
from fleetslam.transforms import invert
from fleetslam.wire.merger_keyframes import KeyframeSummary


def near_keyframes(poses_a: np.ndarray, poses_b: np.ndarray, distance_m: float,
                   angle_deg: float) -> list[tuple[int, int]]:
    """(keyframe of a, keyframe of b): for each keyframe of b, the nearest keyframe of a
    whose camera centre is within ``distance_m`` and optical axis within ``angle_deg``."""
    if not len(poses_a) or not len(poses_b):
        return []
    gap = np.linalg.norm(poses_b[:, None, :3, 3] - poses_a[None, :, :3, 3], axis=2)
    cos = np.einsum("bi,ai->ba", poses_b[:, :3, 2], poses_a[:, :3, 2])
    gap[cos < np.cos(np.deg2rad(angle_deg))] = np.inf
    nearest = np.argmin(gap, axis=1)
    return [(int(k_a), k_b) for k_b, k_a in enumerate(nearest) if gap[k_b, k_a] <= distance_m]


def proximity_constraints(groups: list[list[str]], poses: dict[str, np.ndarray],
                          keyframes: dict[str, list[KeyframeSummary]], loaded: set[str],
                          checked: set[tuple[tuple[str, int], ...]],
                          cloud: Callable[[str, int], DenseCloud | None], cfg: MergeConfig
                          ) -> tuple[list[Constraint], list[float]]:
    """The edges registered between keyframes of robots of one group (``groups``) that the
    graph (``poses``: each robot's keyframes in its group's frame) puts near each other
    (merge.proximity_*): each keyframe with the nearest keyframe of another robot of its
    group, so the work is bounded by the keyframes, however many robots; and the seconds of
    each registration tried. A pair in ``checked`` (matched or tried before) is not tried
    again, and is added to it once tried; a loaded map's robots (``loaded``) seek none of
    their own. ``cloud``: a keyframe's prepared depth cloud (None: not at hand, tried
    later)."""
    found: list[Constraint] = []
    seconds: list[float] = []
    for members in groups:
        for b in members:
            if b in loaded:
                continue  # a loaded map's keyframes had theirs when it was made
            others = [(a, k) for a in members if a != b for k in range(len(poses[a]))]
            if not others:
                continue
            stacked = np.array([poses[a][k] for a, k in others])
            for j, k_b in near_keyframes(stacked, poses[b], cfg.proximity_distance_m,
                                         cfg.proximity_angle_deg):
                a, k_a = others[j]
                place, query = keyframes[a][k_a], keyframes[b][k_b]
                key = pair_key(query, place)
                if key in checked:
                    continue
                place_cloud, query_cloud = cloud(a, k_a), cloud(b, k_b)
                if place_cloud is None or query_cloud is None:
                    continue
                checked.add(key)
                start = time.perf_counter()
                dense = register(place_cloud, query_cloud,
                                 invert(poses[a][k_a]) @ poses[b][k_b], cfg)
                seconds.append(time.perf_counter() - start)
                if not dense.accepted:
                    continue
                # No feature estimate to fuse with, and GICP's Hessian alone is far stiffer
                # than such an edge is right (rk-2: 0.6-4.8 cm off against a 2 mm stiffest
                # sigma): the feature edge's sigmas.
                dense.information = feature_information(cfg)
                match = PlaceMatch(query, place, dense.T_place_query, 0.0, 0, 0)
                found.append(Constraint(match, trusted=False, dense=dense, proximity=True))
    return found, seconds
