"""Local mapping (ORB-SLAM's LocalMapping): what happens to the map when the tracker makes
a keyframe.

    insert keyframe -> fuse (known landmarks seen again) -> new landmarks -> cull -> local BA

Insertion, fusion and culling run in-line, at the keyframe, on the thread that tracks.
Local BA runs in-line too when ``tracking.local_mapping`` is "inline": the next frame is
matched against the map as local BA left it, so poses are the same in every process and at
every split point (the exactness tests rely on it). In the cloud it is "async": the problem
is copied out of the map (``local_ba_problem``) and solved in a worker process
(backend/workers.py), and the solution is written back at the start of a later frame
(``LocalMapper.poll``), on the tracking thread, so the map is only ever changed by one
thread and between frames. At most one solve is in flight; the newest keyframe's waits
(backend/jobs.py). A solution computed on a map that a loop correction has moved since
(``LocalMap.epoch``) is dropped. A flush (before a loop correction, at the end of a run)
waits for the worker at most ``tracking.worker_wait_s``, then solves here (backend/jobs.py).
"""

from __future__ import annotations

import logging
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetslam.backend.jobs import Job, LatestOnly, duration_stats
from fleetslam.backend.local_ba import (
    LocalBAProblem,
    LocalBASolution,
    apply_local_ba,
    local_ba_problem,
    reprojection_chi2,
    solve_local_ba,
)
from fleetslam.backend.local_map import Keyframe
from fleetslam.backend.matching import match_free_keypoints
from fleetslam.backend.pose_optimizer import CHI2_MONO, CHI2_STEREO
from fleetslam.backend.state import BackEndState
from fleetslam.backend.workers import SessionWorkers
from fleetslam.pipeline.states import FeatureFrame, PosedFrame

log = logging.getLogger(__name__)


@dataclass
class InsertedKeyframe:
    keyframe: Keyframe
    # World-frame correction local BA applied to the keyframe: T_new = correction @ T_old.
    correction: np.ndarray


class LocalMapper:
    """One robot's local mapping: keyframe insertion in-line, local BA in-line or in the
    cloud's workers (``workers``; None: always in-line)."""

    def __init__(self, backend: BackEndState, workers: SessionWorkers | None = None) -> None:
        self.backend = backend
        self.workers = workers
        # "empty": a keyframe whose window had nothing to adjust (no solve asked).
        # "taken_back": solved here at a flush, the worker being late.
        self.counts: dict[str, int] = {"submitted": 0, "applied": 0, "superseded": 0,
                                       "stale": 0, "abandoned": 0, "failed": 0, "inline": 0,
                                       "empty": 0, "taken_back": 0}
        # The solve in flight and the newest keyframe whose solve waits for it.
        self.jobs = LatestOnly("local BA", backend.config.tracking.local_ba_timeout_s,
                               self.counts, overdue="abandoned",
                               wait_s=backend.config.tracking.worker_wait_s)
        # Of each solve that landed from a worker: seconds from its request to its start (its
        # wait in the worker's queue) and the CPU seconds it took there.
        self.queued_seconds: list[float] = []
        self.solve_cpu_seconds: list[float] = []

    def insert_keyframe(self, state: PosedFrame) -> InsertedKeyframe:
        """Add the frame as a keyframe: its inlier matches become observations (plus those
        fusion finds), its other keypoints with depth become landmarks; then cull recent
        landmarks and bundle-adjust the keyframe's neighbourhood (or ask a worker to)."""
        backend = self.backend
        cfg = backend.config.tracking
        lmap = backend.map
        f = state.matched.features
        matched_ids = np.where(state.inliers, state.matched.landmark_ids, -1)
        if cfg.fuse_at_keyframe and lmap.keyframes and state.tracked:
            matched_ids = fuse_search(backend, f, state.T_world_camera, matched_ids)
        kf = lmap.add_keyframe(backend.camera, f, state.T_world_camera, matched_ids)
        if cfg.cull_landmarks:
            backend.culled_landmarks += lmap.cull_recent(
                kf.id, cfg.cull_min_found_ratio, cfg.cull_min_observation_weight,
                cfg.cull_probation_keyframes)
        if cfg.cull_keyframes:
            backend.culled_keyframes += len(cull_keyframes(backend, kf.id))
        correction = np.eye(4)
        if cfg.local_ba and kf.id > 0:
            if self.workers is not None:
                self.request(kf.id)
            else:
                problem = build_problem(backend, kf.id)
                if problem is not None:
                    correction = apply_solution(backend, problem, solve_local_ba(problem))
        update_reference(backend)
        return InsertedKeyframe(kf, correction)

    def busy(self) -> bool:
        """A local BA is still in a worker (never in-line: it is done by then)."""
        return not self.jobs.idle

    def settling(self) -> bool:
        """The newest keyframe's local BA is in a worker or waits for one (never in-line)."""
        keyframes = self.backend.map.keyframes
        return bool(keyframes) and self.jobs.pending(keyframes[-1].id)

    # -- in the workers ------------------------------------------------------------------

    def request(self, kf_id: int) -> None:
        """Local BA around keyframe ``kf_id``: submitted now, or after the one in flight."""
        self.poll()
        if self.jobs.idle:
            self._submit(kf_id)
        else:
            self.jobs.wait(kf_id)

    def poll(self) -> None:
        """Apply a finished solution (never waits); then submit the waiting keyframe's."""
        job = self.jobs.finished()
        if job is None:
            return
        self._finish(job)
        if self.jobs.waiting is not None:
            self._submit(self.jobs.take_waiting())

    def flush(self, timeout_s: float | None = None) -> None:
        """Land the solve in flight and the waiting one now: before a loop correction and at
        the end of a run. The worker gets ``timeout_s`` (default tracking.worker_wait_s);
        past it, each is solved here: the same answer, without tracking waiting on a
        worker that, niced below it, it starves."""
        self.jobs.settle(solve_local_ba, self.poll, timeout_s)

    def _submit(self, kf_id: int) -> None:
        problem = build_problem(self.backend, kf_id)
        if problem is None:
            self.counts["empty"] += 1
            return
        future = self.jobs.here_if_late(solve_local_ba, problem)
        if future is None and self.workers is not None:
            future = self.workers.submit_local_ba(problem)
        if future is not None:
            self.jobs.started(future, kf_id, problem, problem.epoch)
            return
        self.counts["inline"] += 1
        self.land(problem, solve_local_ba(problem))

    def _finish(self, job: Job) -> None:
        problem: LocalBAProblem = job.payload
        try:
            solution: LocalBASolution | None = job.future.result()
        except BrokenProcessPool as exc:
            if self.workers is not None:
                self.workers.fail(exc)
            self.counts["inline"] += 1
            solution = solve_local_ba(problem)
        except Exception as exc:  # a bug in the solve must not end the robot's session
            log.error("local BA of keyframe %d failed: %r", problem.kf_id, exc)
            self.counts["failed"] += 1
            return
        if problem.epoch != self.backend.map.epoch:
            self.counts["stale"] += 1
            return
        self.land(problem, solution)
        self.counts["applied"] += 1
        self.jobs.landed(job)
        if solution is not None:
            self.queued_seconds.append(max(solution.started - job.submitted, 0.0))
            self.solve_cpu_seconds.append(solution.cpu_seconds)

    def land(self, problem: LocalBAProblem, solution: LocalBASolution | None) -> None:
        """Write a solution into the map. The frames tracked since moved with the map: so
        does the motion model; and the keyframe test's reference is counted again."""
        self.backend.correct_motion(apply_solution(self.backend, problem, solution))
        update_reference(self.backend)

    def summary(self) -> dict[str, Any]:
        return {**self.counts, "request_to_applied": duration_stats(self.jobs.lag_seconds),
                "queued": duration_stats(self.queued_seconds),
                "solve_cpu": duration_stats(self.solve_cpu_seconds)}


def build_problem(backend: BackEndState, kf_id: int) -> LocalBAProblem | None:
    """The local BA problem around keyframe ``kf_id``, as the config asks."""
    cfg = backend.config.tracking
    return local_ba_problem(
        backend.map, backend.camera, kf_id, baseline_m=cfg.virtual_baseline_m,
        scale_factor=backend.config.orb.scale_factor, window_size=cfg.local_ba_window,
        min_shared=cfg.covisibility_min_shared, iterations=tuple(cfg.local_ba_iterations),
        relative_tolerance=cfg.local_ba_relative_tolerance)


def apply_solution(backend: BackEndState, problem: LocalBAProblem,
                   solution: LocalBASolution | None) -> np.ndarray:
    """Write a local BA solution into the session's map (None: the solve failed, nothing
    changes). Returns the world-frame correction of the problem's keyframe."""
    if solution is None:
        return np.eye(4)
    result = apply_local_ba(backend.map, problem, solution)
    backend.local_ba_seconds.append(result.seconds)
    backend.local_ba_outliers += result.n_outliers
    return result.correction


def cull_keyframes(backend: BackEndState, kf_id: int) -> np.ndarray:
    """ORB-SLAM's KeyFrameCulling around new keyframe ``kf_id``: its covisible keyframes
    (never the first, never itself) that are redundant lose their observations. Returns
    their ids."""
    cfg, lmap = backend.config.tracking, backend.map
    neighbours, _ = lmap.covisible(kf_id)
    neighbours = neighbours[neighbours > 0]
    culled = lmap.redundant_keyframes(
        neighbours, cfg.close_depth_baselines * cfg.virtual_baseline_m,
        backend.config.orb.n_levels, cfg.keyframe_redundant_observers,
        cfg.keyframe_redundant_fraction)
    if len(culled):
        lmap.drop_keyframe_observations(culled)
    return culled


def update_reference(backend: BackEndState) -> None:
    """ORB-SLAM's reference for the keyframe test: the newest keyframe's landmarks with
    enough observations (3, or 2 while the map has at most two keyframes; with depth
    counts 2)."""
    lmap = backend.map
    min_weight = 3 if len(lmap.keyframes) > 2 else 2
    backend.reference_tracked = lmap.tracked_by_keyframe(lmap.keyframes[-1].id, min_weight)


def fuse_search(backend: BackEndState, f: FeatureFrame, T_world_camera: np.ndarray,
                matched_ids: np.ndarray) -> np.ndarray:
    """At a keyframe, search the keypoints tracking left unmatched against the live landmarks
    projected from the keyframe's pose, within a few pixels (ORB-SLAM's Fuse): a match that
    is also consistent with the keypoint's depth becomes an observation of the old landmark
    instead of a duplicate landmark. Returns the updated ``matched_ids``."""
    cfg, orb, lmap = backend.config.tracking, backend.config.orb, backend.map
    if not (matched_ids < 0).any():
        return matched_ids
    ids = match_free_keypoints(backend, f, T_world_camera, matched_ids, cfg.fuse_radius_px,
                               cfg.fuse_max_hamming, 1.0, scale_check=False)
    kp = np.flatnonzero((ids >= 0) & (matched_ids < 0))
    if not len(kp):
        return matched_ids
    lm = ids[kp]
    depth = f.depth[kp].astype(np.float64)
    chi2, z = reprojection_chi2(backend.camera, backend.camera.fx * cfg.virtual_baseline_m,
                                np.broadcast_to(T_world_camera, (len(kp), 4, 4)), lmap.xyz[lm],
                                f.uv[kp], depth, orb.scale_factor ** f.keypoints[kp, 5])
    ok = (chi2 <= np.where(depth > 0, CHI2_STEREO, CHI2_MONO)) & (z > 0)
    out = matched_ids.copy()
    out[kp[ok]] = lm[ok]
    backend.fused_observations += int(ok.sum())
    return out
