"""A robust pose graph over keyframes (gtsam): odometry, covisibility and loop edges.

Every edge is a measured relative pose T_a_b between two keyframes. Odometry and
covisibility edges come from the map itself (tracking and local bundle adjustment) and are
declared known inliers; loop edges come from place recognition and may be wrong. The graph
is solved with graduated non-convexity (gtsam's GncLMOptimizer, truncated least squares):
a loop edge that would bend the map beyond what the other edges allow ends with weight 0
and is reported as rejected, instead of distorting the map.

gtsam objects live only inside ``optimise_pose_graph``: callers keep plain numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

# Chi-square probability at which GNC's truncated loss stops trusting an edge.
GNC_INLIER_PROBABILITY = 0.99


@dataclass
class PoseEdge:
    a: int
    b: int
    T_a_b: np.ndarray  # 4 x 4: pose of b in a's frame
    kind: str  # "odometry", "covisibility" or "loop" (tested by GNC)
    # (rotation rad, translation m) of this edge; None: the graph's default.
    sigmas: tuple[float, float] | None = None
    # A "loop" edge declared an inlier anyway (already checked by consistency).
    trusted: bool = False
    # 6 x 6 information in gtsam's tangent order [rotation, translation] (a dense
    # refinement's); when given, it replaces ``sigmas``.
    information: np.ndarray | None = None


@dataclass
class PoseGraphResult:
    poses: dict[int, np.ndarray]  # optimised T_world_node
    # Per loop edge (in the order given): GNC's weight > 0.5, i.e. kept as an inlier.
    loop_inliers: list[bool]
    error_before: float
    error_after: float


def optimise_pose_graph(poses: dict[int, np.ndarray], edges: list[PoseEdge],
                        fixed: int | list[int], sigma_rotation_rad: float,
                        sigma_translation_m: float,
                        max_iterations: int = 100) -> PoseGraphResult:
    """Optimise ``poses`` (T_world_node by node id) under ``edges``; node ``fixed`` holds
    the frame (several: each stays where it is). Loop edges are tested by GNC (unless
    trusted); the others are known inliers. ``loop_inliers`` lists every loop edge, trusted
    ones included."""

    def noise_of(rotation_rad: float, translation_m: float) -> gtsam.noiseModel.Base:
        return gtsam.noiseModel.Diagonal.Sigmas(
            np.array([rotation_rad] * 3 + [translation_m] * 3))

    default_noise = noise_of(sigma_rotation_rad, sigma_translation_m)
    graph = gtsam.NonlinearFactorGraph()
    held = [fixed] if isinstance(fixed, int) else list(fixed)
    for node in held:
        graph.add(gtsam.PriorFactorPose3(node, gtsam.Pose3(poses[node]),
                                         gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    known, loop_factor = list(range(len(held))), []
    for edge in edges:
        index = graph.size()
        if edge.information is not None:
            noise = gtsam.noiseModel.Gaussian.Information(edge.information)
        else:
            noise = default_noise if edge.sigmas is None else noise_of(*edge.sigmas)
        graph.add(gtsam.BetweenFactorPose3(edge.a, edge.b, gtsam.Pose3(edge.T_a_b), noise))
        if edge.kind == "loop":
            loop_factor.append(index)
        if edge.kind != "loop" or edge.trusted:
            known.append(index)
    values = gtsam.Values()
    for node, T in poses.items():
        values.insert(node, gtsam.Pose3(T))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(max_iterations)
    params = gtsam.GncLMParams(lm)
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(known)
    optimizer = gtsam.GncLMOptimizer(graph, values, params)
    optimizer.setInlierCostThresholdsAtProbability(GNC_INLIER_PROBABILITY)
    result = optimizer.optimize()
    weights = np.asarray(optimizer.getWeights())
    inliers = [bool(weights[i] > 0.5) for i in loop_factor]
    # The error of the graph as GNC left it: rejected loops do not count.
    kept = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        if i not in loop_factor or weights[i] > 0.5:
            kept.add(graph.at(i))
    out = {node: result.atPose3(node).matrix() for node in poses}
    return PoseGraphResult(out, inliers, float(kept.error(values)), float(kept.error(result)))
