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
under load) runs in a worker process (backend/workers.py, one query in flight, the newest
waiting: backend/jobs.py); verification and correction stay on the tracking thread, at the
start of the frame its answer lands (``LoopCloser.poll``). Every keyframe enters the
database after its own query, so a keyframe never finds itself.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable

import numpy as np

from fleetslam.backend.geometric_verification import ransac_rigid
from fleetslam.backend.jobs import LatestOnly, duration_stats
from fleetslam.backend.local_ba import local_bundle_adjustment
from fleetslam.backend.local_map import Keyframe
from fleetslam.backend.matching import descriptor_match, guided_match
from fleetslam.backend.place_recognition import snapshot
from fleetslam.backend.pose_graph import PoseEdge, optimise_pose_graph
from fleetslam.backend.pose_optimizer import optimize_pose
from fleetslam.backend.state import BackEndState, LoopDetection
from fleetslam.backend.worker_places import PlaceMirror
from fleetslam.backend.workers import SessionWorkers, query_places
from fleetslam.transforms import invert, rotation_angle_deg, transforms_agree

log = logging.getLogger(__name__)


class LoopCloser:
    """One robot's loop closing (see the module's docstring). ``settle_map`` runs before a
    correction moves the whole map: local BA in flight lands first."""

    def __init__(self, backend: BackEndState, settle_map: Callable[[], None],
                 workers: SessionWorkers | None = None) -> None:
        self.backend = backend
        self.settle_map = settle_map
        self.workers = workers
        # "taken_back": queried here at a flush, the worker being late; "reseeded": sent
        # again with the whole database, the worker's copy not matching.
        self.counts: dict[str, int] = {"submitted": 0, "answered": 0, "superseded": 0,
                                       "stale": 0, "failed": 0, "taken_back": 0,
                                       "reseeded": 0}
        # What the worker holds of the keyframe database (it is sent what is new).
        self.mirror = PlaceMirror(workers.session) if workers is not None else None
        # Seconds each database query took (in the worker: unpickling, adding, searching).
        self.search_seconds: list[float] = []
        # The database query in flight and the newest keyframe whose query waits for it
        # (with the database as it was then).
        self.jobs = LatestOnly("loop query", backend.config.tracking.local_ba_timeout_s,
                               self.counts, overdue="failed",
                               wait_s=backend.config.tracking.worker_wait_s)

    def close_loops(self, kf: Keyframe) -> np.ndarray | None:
        """Loop closing for the newest keyframe. Returns the world-frame correction applied
        to it when a loop was closed (the tracker moves its motion model with it), else
        None. With workers the database query goes to them instead, and its candidates are
        verified at the start of a later frame (``poll``)."""
        backend = self.backend
        cfg = backend.config.loop_closing
        candidates = None
        if cfg.enabled and kf.id >= cfg.min_keyframes:
            allowed = allowed_candidates(backend, kf)
            asynchronous = (cfg.query_in_worker and self.workers is not None
                            and not self.workers.broken)
            if asynchronous and allowed.any():
                # The database as it is now, without this keyframe (it never finds itself).
                self.request(kf.id, allowed)
            else:
                start = time.perf_counter()
                candidates = backend.places.query(kf.features.descriptors, allowed)
                query_s = time.perf_counter() - start
        self.remember(kf.id, kf.features.descriptors)
        if candidates is None:
            return None
        return self.on_candidates(kf.id, candidates, query_s)

    def remember(self, kf_id: int, descriptors: np.ndarray) -> None:
        """Keyframe ``kf_id`` enters the database (after its own query), and the list of
        what its worker is to be sent."""
        self.backend.places.add(kf_id, descriptors)
        cfg = self.backend.config.loop_closing
        if self.mirror is not None and cfg.enabled and cfg.query_in_worker \
                and not self.workers.broken:
            self.mirror.added(kf_id, descriptors)

    def on_candidates(self, kf_id: int, candidates: list, query_s: float
                      ) -> np.ndarray | None:
        """Verify the place-recognition candidates of keyframe ``kf_id`` (best first, the
        first that passes), check consistency with the detections of the keyframes before
        it, and correct. ``query_s``: how long the database query took. Returns the
        world-frame correction of that keyframe when a loop was closed."""
        backend = self.backend
        cfg = backend.config.loop_closing
        state = backend.loops
        kf = backend.map.keyframes[kf_id]
        detection = None
        start = time.perf_counter()
        for candidate in candidates:
            state.candidates_verified += 1
            detection = verify(backend, kf, candidate.key, candidate.score)
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
            d.correction, detection.correction, kf.T_world_camera[:3, 3],
            cfg.consistency_rotation_deg, cfg.consistency_translation_m)]
        state.detections.append(detection)
        if len(agreeing) + 1 < cfg.consistent_detections:
            return None
        start = time.perf_counter()
        self.settle_map()
        T_before = kf.T_world_camera.copy()
        accepted = correct(backend, agreeing + [detection])
        state.correction_seconds.append(time.perf_counter() - start)
        state.detections = []
        if not accepted:
            return None
        return kf.T_world_camera @ invert(T_before)

    # -- in the workers ------------------------------------------------------------------

    def request(self, kf_id: int, allowed: np.ndarray) -> None:
        """Place recognition for keyframe ``kf_id`` in a worker, against the database as it
        is now; the answer is verified at the frame it lands (``poll``)."""
        # The live database grows while the query waits.
        frozen = snapshot(self.backend.places)
        if self.jobs.idle:
            self._submit(kf_id, frozen, allowed)
        else:
            self.jobs.wait((kf_id, frozen, allowed))

    def poll(self, wait_s: float = 0.0) -> None:
        """Verify a finished query's candidates (waiting at most ``wait_s``); then submit the
        waiting one."""
        job = self.jobs.finished(wait_s)
        if job is None:
            return
        try:
            candidates, query_s = job.future.result()
            if candidates is None and self.mirror is not None:
                # The worker's copy of the database is missing or differs (only a worker
                # answers None): the query goes again, with the database whole.
                self.counts["reseeded"] += 1
                self.mirror.reseed()
                frozen, _, allowed = job.payload
                self._submit(job.request, frozen, allowed)
                return
        except BrokenProcessPool as exc:
            if self.workers is not None:
                self.workers.fail(exc)
            candidates, query_s = None, 0.0
        except Exception as exc:  # a bug in the query must not end the robot's session
            log.error("loop query of keyframe %d failed: %r", job.request, exc)
            candidates, query_s = None, 0.0
        if candidates is None:
            self.counts["failed"] += 1
        elif job.epoch != self.backend.map.epoch:
            # A loop was corrected meanwhile: the candidates' place may be merged already.
            self.counts["stale"] += 1
        else:
            self.counts["answered"] += 1
            self.search_seconds.append(query_s)
            self.jobs.landed(job)
            correction = self.on_candidates(job.request, candidates, query_s)
            if correction is not None:
                self.backend.correct_motion(correction)
        if self.jobs.waiting is not None and not (self.workers is not None
                                                  and self.workers.broken):
            self._submit(*self.jobs.take_waiting())

    def flush(self, timeout_s: float | None = None) -> None:
        """Verify the queries in flight and waiting now: at the end of a run. The worker gets
        ``timeout_s`` (default tracking.worker_wait_s); past it, each is queried here (as
        ``LocalMapper.flush`` solves)."""
        self.jobs.settle(_query, self.poll, timeout_s)

    def _submit(self, kf_id: int, frozen: Any, allowed: np.ndarray) -> None:
        # Kept with the job: what a flush queries here if the worker is late.
        query = (frozen, self.backend.map.keyframes[kf_id].features.descriptors, allowed)
        future = self.jobs.here_if_late(_query, query)
        if future is None and self.workers is not None and self.mirror is not None:
            future = self.workers.submit_query(self.mirror.request(*query))
        if future is None:
            self.counts["failed"] += 1
            return
        self.jobs.started(future, kf_id, query, self.backend.map.epoch)

    def release(self) -> None:
        """The session ended: its worker forgets its keyframe database."""
        if self.workers is not None:
            self.workers.close()

    def summary(self) -> dict[str, Any]:
        sent = np.asarray(self.mirror.sent_bytes if self.mirror is not None else [])
        return {**self.counts,
                "request_to_answered": duration_stats(self.jobs.lag_seconds),
                "database_query": duration_stats(self.search_seconds),
                # Bytes sent to the worker per query (a delta; whole when "full").
                "bytes_sent": {"n": len(sent),
                               "median": float(np.median(sent)) if len(sent) else None,
                               "max": int(sent.max()) if len(sent) else None,
                               "last": int(sent[-1]) if len(sent) else None,
                               "full": self.mirror.full_sends if self.mirror else 0},
                # The database's arrays now: about what each query sent when the worker
                # was sent the whole database.
                "database_bytes": sum(a.nbytes for a in vars(self.backend.places).values()
                                      if isinstance(a, np.ndarray))}


def _query(query: tuple[Any, np.ndarray, np.ndarray]) -> tuple[list, float]:
    return query_places(*query)


def allowed_candidates(backend: BackEndState, kf: Keyframe) -> np.ndarray:
    """Keyframes a loop may close on: old enough, not culled, and not already tied to the
    query by shared landmarks (tracking handles those)."""
    cfg = backend.config.loop_closing
    allowed = np.zeros(len(backend.places), bool)
    allowed[: max(kf.id - cfg.min_keyframe_gap + 1, 0)] = True
    allowed &= backend.map.observing()[: len(allowed)]
    ids, shared = backend.map.covisible(kf.id)
    near = ids[shared >= backend.config.tracking.covisibility_min_shared]
    allowed[near[near < len(allowed)]] = False
    return allowed


def verify(backend: BackEndState, kf: Keyframe, candidate: int, score: float
           ) -> LoopDetection | None:
    """Geometric check of ``kf`` against the place around keyframe ``candidate``: depth-backed
    descriptor matches give a 3D-3D RANSAC pose; the place's landmarks projected from it are
    searched and the pose refined (reprojection with depth). None if either step has too few
    inliers."""
    cfg, tcfg = backend.config.loop_closing, backend.config.tracking
    orb, lmap, cam = backend.config.orb, backend.map, backend.camera
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


def map_edges(backend: BackEndState) -> list[PoseEdge]:
    """The map's own edges: consecutive keyframes (odometry) and keyframes sharing many
    landmarks (covisibility), each measured by the current poses."""
    lmap = backend.map
    T = lmap.keyframe_poses()
    edges = [PoseEdge(i - 1, i, invert(T[i - 1]) @ T[i], "odometry")
             for i in range(1, len(T))]
    counts = lmap.covisibility_counts()
    a, b = np.nonzero(np.triu(counts >= backend.config.loop_closing.pose_graph_min_shared, 2))
    edges += [PoseEdge(int(i), int(j), invert(T[i]) @ T[j], "covisibility")
              for i, j in zip(a, b)]
    return edges


def correct(backend: BackEndState, detections: list[LoopDetection]) -> bool:
    """Optimise the pose graph with the detections' loop edges; if the graph keeps them,
    move keyframes and landmarks, merge the landmarks seen again and (optionally) run a
    global bundle adjustment. Returns whether the loop was accepted."""
    cfg = backend.config.loop_closing
    lmap, state = backend.map, backend.loops
    T_old = lmap.keyframe_poses()
    new_edges = [PoseEdge(d.candidate, d.query,
                          invert(T_old[d.candidate]) @ d.T_world_query, "loop")
                 for d in detections]
    result = optimise_pose_graph(
        {k: T_old[k] for k in range(len(T_old))}, map_edges(backend) + state.edges + new_edges,
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
        tcfg = backend.config.tracking
        ba = local_bundle_adjustment(
            lmap, backend.camera, newest.query, baseline_m=tcfg.virtual_baseline_m,
            scale_factor=backend.config.orb.scale_factor,
            iterations=tuple(cfg.global_ba_iterations),
            window=np.arange(len(lmap.keyframes)))
        ba_seconds = ba.seconds
    event.update(accepted=True, edges_kept=[bool(k) for k in kept], landmarks_merged=merged,
                 global_ba_seconds=ba_seconds)
    state.events.append(event)
    return True
