"""Loop closing (ORB-SLAM's LoopClosing): notice that a new keyframe shows a place the map
already holds, check it geometrically, and correct the drift accumulated in between.

    query (place recognition) -> verify (3D-3D RANSAC on depth-backed matches, then a
    projection search and motion-only refinement) -> consistent over consecutive keyframes
    -> correct (robust pose graph, landmarks follow their keyframes, duplicate landmarks
    merged, optional global bundle adjustment)

It runs in-line at each keyframe, after local mapping, on the thread that tracks: every
process computes the same poses (the exactness tests rely on this deterministic mode; the
RANSAC draws from a seeded generator). In a cloud with asynchronous local mapping, the
database query (a brute-force Hamming search that holds the GIL: 50-200 ms a keyframe
under load) runs in the local mapping worker; verification and correction stay on the
tracking thread, at the frame its answer lands. Every keyframe enters the database after
its own query, so a keyframe never finds itself.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from fleetslam.pipeline.geometric_verification import ransac_rigid
from fleetslam.pipeline.local_ba import local_bundle_adjustment
from fleetslam.pipeline.local_map import Keyframe
from fleetslam.pipeline.matching import descriptor_match, guided_match
from fleetslam.pipeline.pose_graph import PoseEdge, optimise_pose_graph
from fleetslam.pipeline.pose_optimizer import optimize_pose
from fleetslam.transforms import invert, rotation_angle_deg, transforms_agree

if TYPE_CHECKING:
    from fleetslam.pipeline.session import CloudSession


@dataclass
class LoopDetection:
    """A verified match of keyframe ``query`` to the place around keyframe ``candidate``."""

    query: int
    candidate: int
    # Where the old place says the query camera is, and the world-frame correction that
    # takes the query's current pose there: T_world_query_loop = correction @ T_world_query.
    T_world_query: np.ndarray
    correction: np.ndarray
    score: float
    ransac_inliers: int
    inliers: int
    # Landmarks of the query seen again in the place: (place landmark, query landmark).
    same_landmarks: tuple[np.ndarray, np.ndarray]


@dataclass
class LoopClosingState:
    detections: list[LoopDetection] = field(default_factory=list)
    # Accepted loop edges, kept for every later pose graph.
    edges: list[PoseEdge] = field(default_factory=list)
    # One record per loop the closer tried to correct (accepted or rejected by the graph).
    events: list[dict] = field(default_factory=list)
    queries: int = 0
    candidates_verified: int = 0
    detections_total: int = 0
    # Database query (in the worker when asynchronous) plus verification of its candidates.
    query_seconds: list[float] = field(default_factory=list)
    correction_seconds: list[float] = field(default_factory=list)


def close_loops(session: CloudSession, kf: Keyframe) -> np.ndarray | None:
    """Loop closing for the newest keyframe. Returns the world-frame correction applied to
    it when a loop was closed (the tracker moves its motion model with it), else None.

    In a cloud with asynchronous local mapping the database query (most of the time) goes
    to the local mapping worker instead, and ``on_candidates`` runs when its answer lands,
    at the start of a later frame (``AsyncLocalMapping.poll``)."""
    cfg = session.config.loop_closing
    candidates = None
    if cfg.enabled and kf.id >= cfg.min_keyframes:
        allowed = allowed_candidates(session, kf)
        asynchronous = (cfg.query_in_worker and session.local_mapping is not None
                        and not session.local_mapping.broken)
        if asynchronous and allowed.any():
            # The database as it is now, without this keyframe (it never finds itself).
            session.local_mapping.request_loop_query(session, kf.id, allowed)
        else:
            start = time.perf_counter()
            candidates = session.places.query(kf.features.descriptors, allowed)
            query_s = time.perf_counter() - start
    session.places.add(kf.id, kf.features.descriptors)
    if candidates is None:
        return None
    return on_candidates(session, kf.id, candidates, query_s)


def on_candidates(session: CloudSession, kf_id: int, candidates: list, query_s: float
                  ) -> np.ndarray | None:
    """Verify the place-recognition candidates of keyframe ``kf_id`` (best first, the first
    that passes), check consistency with the detections of the keyframes before it, and
    correct. ``query_s``: how long the database query took. Returns the world-frame
    correction of that keyframe when a loop was closed."""
    cfg = session.config.loop_closing
    state = session.loops
    kf = session.map.keyframes[kf_id]
    detection = None
    start = time.perf_counter()
    for candidate in candidates:
        state.candidates_verified += 1
        detection = verify(session, kf, candidate.key, candidate.score)
        if detection is not None:
            break
    state.queries += 1
    state.query_seconds.append(query_s + time.perf_counter() - start)
    # Detections too old to be consecutive with this keyframe no longer count.
    state.detections = [d for d in state.detections
                        if 0 <= kf.id - d.query < cfg.consistency_window_keyframes]
    if detection is None:
        return None
    state.detections_total += 1
    agreeing = [d for d in state.detections if transforms_agree(
        d.correction, detection.correction, kf.T_world_camera[:3, 3], cfg.consistency_rotation_deg,
        cfg.consistency_translation_m)]
    state.detections.append(detection)
    if len(agreeing) + 1 < cfg.consistent_detections:
        return None
    start = time.perf_counter()
    if session.local_mapping is not None:
        # The correction moves the whole map: local BA in flight lands first.
        session.local_mapping.flush(session)
    T_before = kf.T_world_camera.copy()
    accepted = correct(session, agreeing + [detection])
    state.correction_seconds.append(time.perf_counter() - start)
    state.detections = []
    if not accepted:
        return None
    return kf.T_world_camera @ invert(T_before)


def allowed_candidates(session: CloudSession, kf: Keyframe) -> np.ndarray:
    """Keyframes a loop may close on: old enough, and not already tied to the query by
    shared landmarks (tracking handles those)."""
    cfg = session.config.loop_closing
    allowed = np.zeros(len(session.places), bool)
    allowed[: max(kf.id - cfg.min_keyframe_gap + 1, 0)] = True
    ids, shared = session.map.covisible(kf.id)
    near = ids[shared >= session.config.tracking.covisibility_min_shared]
    allowed[near[near < len(allowed)]] = False
    return allowed


def verify(session: CloudSession, kf: Keyframe, candidate: int, score: float
           ) -> LoopDetection | None:
    """Geometric check of ``kf`` against the place around keyframe ``candidate``: depth-backed
    descriptor matches give a 3D-3D RANSAC pose; the place's landmarks projected from it are
    searched and the pose refined (reprojection with depth). None if either step has too few
    inliers."""
    cfg, tcfg = session.config.loop_closing, session.config.tracking
    orb, lmap, cam = session.config.orb, session.map, session.camera
    f = kf.features
    pool = lmap.place_landmarks(candidate, cfg.candidate_neighbours)
    # Landmarks the query already observes are not evidence of a loop.
    pool = pool[~np.isin(pool, kf.keypoint_landmark)]
    with_depth = np.flatnonzero(f.depth > 0)
    if len(pool) < cfg.min_ransac_inliers or len(with_depth) < cfg.min_ransac_inliers:
        return None
    ids = descriptor_match(f.descriptors[with_depth], lmap.descriptors[pool], pool,
                           tcfg.max_hamming, tcfg.match_ratio)
    kp = with_depth[ids >= 0]
    lm = ids[ids >= 0]
    if len(kp) < cfg.min_ransac_inliers:
        return None
    depth = f.depth[kp].astype(np.float64)
    src = cam.backproject(f.uv[kp], depth)
    threshold = np.maximum(cfg.ransac_inlier_m, cfg.ransac_inlier_depth_ratio * depth)
    rng = np.random.default_rng(cfg.seed + kf.id)
    rigid = ransac_rigid(src, lmap.xyz[lm], threshold, cfg.ransac_iterations,
                         cfg.min_ransac_inliers, rng)
    if rigid is None:
        return None
    T_wq = rigid.T_target_source
    # Search the whole place near its projections from that pose, then refine.
    visible, proj, P = lmap.in_view(cam, T_wq, tcfg.min_depth_m, tcfg.max_depth_m, ids=pool)
    level = lmap.predicted_octave(visible, np.linalg.norm(P, axis=1), orb.scale_factor,
                                  orb.n_levels)
    match = guided_match(f, lmap.descriptors, visible, proj, level, tcfg.local_map_radius_px,
                         orb.scale_factor, tcfg.max_hamming, tcfg.match_ratio)
    # The RANSAC inliers stay matched where the projection search found nothing.
    seed_kp, seed_lm = kp[rigid.inliers], lm[rigid.inliers]
    free = match[seed_kp] < 0
    taken = np.isin(seed_lm, match)
    match[seed_kp[free & ~taken]] = seed_lm[free & ~taken]
    matched = np.flatnonzero(match >= 0)
    T_wq, good = optimize_pose(cam, T_wq, lmap.xyz[match[matched]], f.uv[matched],
                               f.depth[matched].astype(np.float64),
                               orb.scale_factor ** f.keypoints[matched, 5],
                               tcfg.virtual_baseline_m)
    if good.sum() < cfg.min_refined_inliers:
        return None
    kp_in = matched[good]
    place_lm = match[kp_in]
    query_lm = kf.keypoint_landmark[kp_in]
    same = query_lm >= 0
    return LoopDetection(kf.id, candidate, T_wq, T_wq @ invert(kf.T_world_camera), score,
                         rigid.n_inliers, int(good.sum()), (place_lm[same], query_lm[same]))


def map_edges(session: CloudSession) -> list[PoseEdge]:
    """The map's own edges: consecutive keyframes (odometry) and keyframes sharing many
    landmarks (covisibility), each measured by the current poses."""
    lmap = session.map
    T = lmap.keyframe_poses()
    edges = [PoseEdge(i - 1, i, invert(T[i - 1]) @ T[i], "odometry")
             for i in range(1, len(T))]
    counts = lmap.covisibility_counts()
    a, b = np.nonzero(np.triu(counts >= session.config.loop_closing.pose_graph_min_shared, 2))
    edges += [PoseEdge(int(i), int(j), invert(T[i]) @ T[j], "covisibility")
              for i, j in zip(a, b)]
    return edges


def correct(session: CloudSession, detections: list[LoopDetection]) -> bool:
    """Optimise the pose graph with the detections' loop edges; if the graph keeps them,
    move keyframes and landmarks, merge the landmarks seen again and (optionally) run a
    global bundle adjustment. Returns whether the loop was accepted."""
    cfg = session.config.loop_closing
    lmap, state = session.map, session.loops
    T_old = lmap.keyframe_poses()
    new_edges = [PoseEdge(d.candidate, d.query,
                          invert(T_old[d.candidate]) @ d.T_world_query, "loop")
                 for d in detections]
    result = optimise_pose_graph(
        {k: T_old[k] for k in range(len(T_old))}, map_edges(session) + state.edges + new_edges,
        fixed=0, sigma_rotation_rad=np.deg2rad(cfg.edge_sigma_rotation_deg),
        sigma_translation_m=cfg.edge_sigma_translation_m)
    kept = result.loop_inliers[len(state.edges):]
    newest = detections[-1]
    event = {
        "query_keyframe": newest.query, "candidate_keyframe": newest.candidate,
        "query_frame": lmap.keyframes[newest.query].frame_index,
        "candidate_frame": lmap.keyframes[newest.candidate].frame_index,
        "detections": [[d.query, d.candidate] for d in detections],
        "detection_frames": [[lmap.keyframes[d.query].frame_index,
                              lmap.keyframes[d.candidate].frame_index] for d in detections],
        "T_candidate_query": [e.T_a_b.tolist() for e in new_edges],
        "inliers": [d.inliers for d in detections],
        "correction_rotation_deg": rotation_angle_deg(newest.correction[:3, :3]),
        "correction_translation_m": float(np.linalg.norm(
            newest.T_world_query[:3, 3] - T_old[newest.query][:3, 3])),
        "graph_error_before": result.error_before, "graph_error_after": result.error_after,
    }
    if not any(kept):
        event["accepted"] = False
        event["reason"] = "the pose graph (GNC) rejected every loop edge"
        state.events.append(event)
        return False
    corrections = {k: result.poses[k] @ invert(T_old[k]) for k in range(len(T_old))}
    for k in corrections:
        lmap.keyframes[k].T_world_camera = result.poses[k]
    lmap.move_landmarks_with_keyframes(corrections)
    merged = 0
    for d, edge, keep in zip(detections, new_edges, kept):
        if keep:
            merged += lmap.merge_landmarks(*d.same_landmarks)
            state.edges.append(edge)
    ba_seconds = None
    if cfg.global_ba:
        tcfg = session.config.tracking
        ba = local_bundle_adjustment(
            lmap, session.camera, newest.query, baseline_m=tcfg.virtual_baseline_m,
            scale_factor=session.config.orb.scale_factor,
            iterations=tuple(cfg.global_ba_iterations),
            window=np.arange(len(lmap.keyframes)))
        ba_seconds = ba.seconds
    event.update(accepted=True, edges_kept=[bool(k) for k in kept], landmarks_merged=merged,
                 global_ba_seconds=ba_seconds)
    state.events.append(event)
    return True
