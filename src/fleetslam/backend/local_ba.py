"""Local bundle adjustment at keyframe insertion: ORB-SLAM's local mapping.

When a keyframe is inserted, the poses of a window of keyframes (the new one and the
keyframes that share the most landmarks with it) and the positions of the landmarks they
observe are optimised together with gtsam. Keyframes outside the window that also observe
those landmarks enter the problem with their poses held fixed (they anchor the window to the
rest of the map), and the first keyframe, which defines the map frame, is always fixed.

Each observation is an RGB-D measurement: with depth it is a stereo measurement of a virtual
right camera (u_left, u_right = u_left - b*fx/z, v), as ORB-SLAM's RGB-D mode, a
``GenericStereoFactor3D``; without depth a plain projection factor. Noise grows with the
keypoint's pyramid scale; a Huber kernel at the 95% chi-square bound limits outliers.
As ORB-SLAM: a first robust pass, drop observations beyond the chi-square bound, a second
pass on the inliers (it keeps the kernel, which is plain least squares on inliers), then
erase the observations that are still outliers from the map. Landmarks seen by a single
keyframe carry no information on poses: they stay out of the problem and move rigidly with
their keyframe.

It comes in three steps so that the solve can run elsewhere (local mapping's worker
process, see ``workers``): ``local_ba_problem`` copies what the solve needs out
of the map, ``solve_local_ba`` optimises it (a pure function of plain numpy, the only place
gtsam objects live), and ``apply_local_ba`` writes the result back into the map, naming
observations by (keyframe, landmark) so that rows the map gained meanwhile are untouched.
``local_bundle_adjustment`` runs the three in a row (the deterministic in-line mode).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import gtsam
import numpy as np

from fleetslam.camera import Camera
from fleetslam.backend.local_map import LocalMap
from fleetslam.backend.pose_optimizer import CHI2_MONO, CHI2_STEREO

# gtsam keys: keyframe poses use their id, landmarks this offset + their id.
LANDMARK_KEY = 1 << 40
# A Levenberg-Marquardt pass ends once an iteration lowers the error by less than this
# fraction, unless the problem says otherwise (gtsam's default; the global BA keeps it,
# local BA takes tracking.local_ba_relative_tolerance).
RELATIVE_TOLERANCE = 1e-5
# A fixed keyframe is held by a prior this tight (gtsam's NonlinearEquality makes the
# multifrontal Cholesky solve indeterminate); its pose is never written back anyway.
FIXED_SIGMA = 1e-6


@dataclass
class LocalBAProblem:
    """Everything the solve reads, copied out of the map (plain numpy: it pickles)."""

    kf_id: int  # the keyframe the window is built around
    kfs: np.ndarray  # keyframe ids in the problem, sorted (free and fixed)
    fixed: np.ndarray  # ids held fixed (anchors)
    free: np.ndarray  # ids whose poses are optimised
    T_old: np.ndarray  # (len(kfs), 4, 4) poses at the time of the copy
    landmarks: np.ndarray  # landmark ids in the graph, sorted
    xyz: np.ndarray  # (len(landmarks), 3) their positions at the time of the copy
    obs_kf: np.ndarray  # one entry per observation row in the problem
    obs_lm: np.ndarray
    obs_uv: np.ndarray
    obs_depth: np.ndarray
    obs_oct: np.ndarray
    # Landmarks seen by one free keyframe only: not optimised, they follow that keyframe.
    follower_kf: np.ndarray
    follower_lm: np.ndarray
    camera: Camera
    baseline_m: float
    scale_factor: float
    iterations: tuple[int, int]
    # What the map was when copied (``LocalMap.epoch``): a result computed on an older map
    # (a loop correction moved it since) is not applied.
    epoch: int = 0
    # A Levenberg-Marquardt iteration that lowers the error by less than this fraction ends
    # a pass.
    relative_tolerance: float = RELATIVE_TOLERANCE


@dataclass
class LocalBASolution:
    poses: np.ndarray  # (len(kfs), 4, 4)
    xyz: np.ndarray  # (len(landmarks), 3)
    outlier: np.ndarray  # bool per observation row of the problem
    seconds: float  # solve time (wherever it ran)
    # The solving process's CPU seconds, and time.monotonic() when the solve began (the
    # clock is the machine's, so the cloud can tell a BA's wait in its worker's queue).
    cpu_seconds: float = 0.0
    started: float = 0.0


@dataclass
class LocalBAResult:
    window: np.ndarray  # keyframe ids whose poses were optimised
    fixed: np.ndarray  # keyframe ids held fixed
    n_landmarks: int  # landmarks optimised
    n_observations: int  # observation rows in the problem
    n_outliers: int  # observation rows erased from the map
    # World-frame correction of the newest keyframe: T_new = correction @ T_old.
    correction: np.ndarray
    seconds: float


def select_window(lmap: LocalMap, kf_id: int, size: int, min_shared: int) -> np.ndarray:
    """The new keyframe and its ``size - 1`` most covisible keyframes (at least
    ``min_shared`` landmarks in common: ORB-SLAM's covisibility edge), sorted by id."""
    ids, shared = lmap.covisible(kf_id)
    ids = ids[shared >= min_shared][: max(size - 1, 0)]
    return np.sort(np.append(ids, kf_id)).astype(np.int64)


def reprojection_chi2(camera: Camera, bf: float, T_world_camera: np.ndarray, xyz: np.ndarray,
                      uv: np.ndarray, depth: np.ndarray, octave_scale: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Whitened squared error of each observation (rows: camera pose (n, 4, 4), world point,
    pixel, depth (0 = none), pyramid scale). Returns (chi2, camera-frame z)."""
    R, t = T_world_camera[:, :3, :3], T_world_camera[:, :3, 3]
    P = np.einsum("nji,nj->ni", R, xyz - t)  # R^T (X - t)
    z = P[:, 2]
    iz = 1.0 / np.where(np.abs(z) > 1e-9, z, 1e-9)
    u = camera.fx * P[:, 0] * iz + camera.cx
    v = camera.fy * P[:, 1] * iz + camera.cy
    stereo = depth > 0
    ur_meas = uv[:, 0] - bf / np.where(stereo, depth, 1.0)
    e_r = np.where(stereo, u - bf * iz - ur_meas, 0.0)
    chi2 = ((u - uv[:, 0]) ** 2 + (v - uv[:, 1]) ** 2 + e_r**2) / octave_scale**2
    return chi2, z


def _noise_models(n_levels: int, scale_factor: float) -> tuple[list, list]:
    huber_stereo = gtsam.noiseModel.mEstimator.Huber.Create(np.sqrt(CHI2_STEREO))
    huber_mono = gtsam.noiseModel.mEstimator.Huber.Create(np.sqrt(CHI2_MONO))
    stereo, mono = [], []
    for level in range(n_levels):
        sigma = scale_factor**level
        stereo.append(gtsam.noiseModel.Robust.Create(
            huber_stereo, gtsam.noiseModel.Isotropic.Sigma(3, sigma)))
        mono.append(gtsam.noiseModel.Robust.Create(
            huber_mono, gtsam.noiseModel.Isotropic.Sigma(2, sigma)))
    return stereo, mono


def _optimise(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, landmark_keys: list[int],
              pose_keys: list[int], iterations: int, relative_tolerance: float
              ) -> gtsam.Values | None:
    # Eliminate landmarks first, then poses: the Schur-complement order of bundle adjustment
    # (every landmark block is independent given the poses), fixed rather than left to
    # COLAMD, so the fill-in is only the small dense pose block.
    ordering = gtsam.Ordering()
    for key in landmark_keys + pose_keys:
        ordering.push_back(key)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    params.setRelativeErrorTol(relative_tolerance)
    params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    params.setOrdering(ordering)
    try:
        return gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError:  # an indeterminate system: keep the map as it was
        return None


def local_ba_problem(lmap: LocalMap, camera: Camera, kf_id: int, *, baseline_m: float,
                     scale_factor: float, window_size: int = 10, min_shared: int = 15,
                     iterations: tuple[int, int] = (5, 10), window: np.ndarray | None = None,
                     relative_tolerance: float = RELATIVE_TOLERANCE) -> LocalBAProblem | None:
    """Copy out of ``lmap`` the problem around keyframe ``kf_id`` (or the given ``window``
    of keyframe ids: all of them is a global bundle adjustment); None if nothing is free."""
    n_kf = len(lmap.keyframes)
    if window is None:
        window = select_window(lmap, kf_id, window_size, min_shared)
    in_window = np.zeros(n_kf, bool)
    in_window[window] = True
    local = np.zeros(lmap.n_landmarks, bool)
    local[lmap.obs_landmark[in_window[lmap.obs_keyframe]]] = True
    local &= lmap.alive
    rows = np.flatnonzero(local[lmap.obs_landmark])
    n_rows_of = np.bincount(lmap.obs_landmark[rows], minlength=lmap.n_landmarks)
    # A landmark seen by one keyframe only constrains nothing but itself: it is left out
    # of the problem and follows its keyframe rigidly.
    in_graph = local & (n_rows_of >= 2)
    follower = local & (n_rows_of == 1)
    rows = rows[in_graph[lmap.obs_landmark[rows]]]
    kfs = np.unique(lmap.obs_keyframe[rows])
    fixed_mask = ~in_window[kfs] | (kfs == 0)
    if not fixed_mask.any() and len(kfs):
        fixed_mask[0] = True  # nothing anchors the window: hold its oldest keyframe
    fixed, free = kfs[fixed_mask], kfs[~fixed_mask]
    if len(free) == 0 or len(rows) == 0:
        return None
    landmarks = np.flatnonzero(in_graph)
    f_rows = np.flatnonzero(follower[lmap.obs_landmark])
    f_kf, f_lm = lmap.obs_keyframe[f_rows], lmap.obs_landmark[f_rows]
    moved = np.isin(f_kf, free)
    return LocalBAProblem(
        kf_id, kfs, fixed, free, lmap.keyframe_poses(kfs), landmarks, lmap.xyz[landmarks].copy(),
        lmap.obs_keyframe[rows], lmap.obs_landmark[rows], lmap.obs_uv[rows],
        lmap.obs_depth[rows], lmap.obs_octave[rows], f_kf[moved], f_lm[moved], camera,
        baseline_m, scale_factor, tuple(iterations), lmap.epoch, relative_tolerance)


def solve_local_ba(p: LocalBAProblem) -> LocalBASolution | None:
    """Optimise the problem (two passes, see the module's docstring); None if the system is
    indeterminate (the map stays as it was)."""
    began, cpu_start = time.monotonic(), time.process_time()
    camera, kfs, landmarks = p.camera, p.kfs, p.landmarks
    obs_kf, obs_lm, obs_uv, obs_depth, obs_oct = p.obs_kf, p.obs_lm, p.obs_uv, p.obs_depth, p.obs_oct
    stereo = obs_depth > 0
    octave_scale = p.scale_factor ** obs_oct.astype(np.float64)
    bf = camera.fx * p.baseline_m
    threshold = np.where(stereo, CHI2_STEREO, CHI2_MONO)
    kf_slot = np.searchsorted(kfs, obs_kf)
    lm_slot = np.searchsorted(landmarks, obs_lm)

    # --- the graph (the one per-observation Python loop: gtsam has no batch API) ---
    K_stereo = gtsam.Cal3_S2Stereo(camera.fx, camera.fy, 0.0, camera.cx, camera.cy, p.baseline_m)
    K_mono = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
    noise_stereo, noise_mono = _noise_models(int(obs_oct.max()) + 1, p.scale_factor)
    values = gtsam.Values()
    for k, T in zip(kfs.tolist(), p.T_old):
        values.insert(k, gtsam.Pose3(T))
    for lm, xyz in zip((landmarks + LANDMARK_KEY).tolist(), p.xyz):
        values.insert(lm, xyz)
    anchor_noise = gtsam.noiseModel.Isotropic.Sigma(6, FIXED_SIGMA)
    anchors = [gtsam.PriorFactorPose3(k, gtsam.Pose3(p.T_old[np.searchsorted(kfs, k)]),
                                      anchor_noise) for k in p.fixed.tolist()]
    factors = []
    u_l, v_l = obs_uv[:, 0].tolist(), obs_uv[:, 1].tolist()
    u_r = (obs_uv[:, 0] - bf / np.where(stereo, obs_depth, 1.0)).tolist()
    lm_keys = (obs_lm + LANDMARK_KEY).tolist()
    Stereo, Projection = gtsam.GenericStereoFactor3D, gtsam.GenericProjectionFactorCal3_S2
    Point, Point2 = gtsam.StereoPoint2, gtsam.Point2
    for i, (k, lm, o, s) in enumerate(zip(obs_kf.tolist(), lm_keys, obs_oct.tolist(),
                                          stereo.tolist())):
        if s:
            factors.append(Stereo(Point(u_l[i], u_r[i], v_l[i]), noise_stereo[o], k, lm, K_stereo))
        else:
            factors.append(Projection(Point2(u_l[i], v_l[i]), noise_mono[o], k, lm, K_mono))

    def build(use: np.ndarray) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        present = np.zeros(len(kfs), bool)
        present[kf_slot[use]] = True
        for k, anchor in zip(p.fixed.tolist(), anchors):
            if present[np.searchsorted(kfs, k)]:
                graph.add(anchor)
        for i in np.flatnonzero(use).tolist():
            graph.add(factors[i])
        return graph

    def chi2_of(poses: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return reprojection_chi2(camera, bf, poses[kf_slot], xyz[lm_slot], obs_uv, obs_depth,
                                 octave_scale)

    # --- pass 1: robust, from the current estimates ---
    result = _optimise(build(np.ones(len(obs_kf), bool)), values,
                       (landmarks + LANDMARK_KEY).tolist(), kfs.tolist(), p.iterations[0],
                       p.relative_tolerance)
    if result is None:
        return None
    poses = np.array([result.atPose3(k).matrix() for k in kfs.tolist()])
    xyz = gtsam.utilities.extractPoint3(result).reshape(-1, 3)
    chi2, z = chi2_of(poses, xyz)
    inlier = (chi2 <= threshold) & (z > 0)

    # --- pass 2: inliers only. A landmark keeps its pass-1 position if its inliers no
    # longer determine it (one observation without depth); same for a pose. ---
    constraint = np.where(stereo, 3, 2) * inlier
    determined = np.bincount(lm_slot, weights=constraint, minlength=len(landmarks)) >= 3
    use = inlier & determined[lm_slot]
    if use.any() and p.iterations[1] > 0:
        used_kfs = np.unique(obs_kf[use])
        used_lms = landmarks[determined]
        values2 = gtsam.Values()
        for k in used_kfs.tolist():
            values2.insert(k, gtsam.Pose3(poses[np.searchsorted(kfs, k)]))
        for lm, xyz_lm in zip((used_lms + LANDMARK_KEY).tolist(), xyz[determined]):
            values2.insert(lm, xyz_lm)
        result2 = _optimise(build(use), values2, (used_lms + LANDMARK_KEY).tolist(),
                            used_kfs.tolist(), p.iterations[1], p.relative_tolerance)
        if result2 is not None:
            poses[np.searchsorted(kfs, used_kfs)] = [result2.atPose3(k).matrix()
                                                     for k in used_kfs.tolist()]
            xyz[determined] = gtsam.utilities.extractPoint3(result2).reshape(-1, 3)
    chi2, z = chi2_of(poses, xyz)
    outlier = (chi2 > threshold) | (z <= 0)
    return LocalBASolution(poses, xyz, outlier, time.monotonic() - began,
                           time.process_time() - cpu_start, began)


def apply_local_ba(lmap: LocalMap, p: LocalBAProblem, s: LocalBASolution) -> LocalBAResult:
    """Write a solution into ``lmap``: free poses, landmark positions, followers, removal of
    the outlier observations. The map may have grown since the copy (newer keyframes,
    landmarks, observations); those are left as they are."""
    slot = np.searchsorted(p.kfs, p.free)
    for k, T in zip(p.free.tolist(), s.poses[slot]):
        lmap.keyframes[k].T_world_camera = T
    lmap.xyz[p.landmarks] = s.xyz
    if len(p.follower_lm):
        C = s.poses[slot] @ np.linalg.inv(p.T_old[slot])
        C = C[np.searchsorted(p.free, p.follower_kf)]
        lmap.xyz[p.follower_lm] = (np.einsum("nij,nj->ni", C[:, :3, :3], lmap.xyz[p.follower_lm])
                                   + C[:, :3, 3])
    # The outliers by (keyframe, landmark): each pair is one row (see LocalMap).
    n = lmap.n_landmarks
    bad = p.obs_kf[s.outlier] * n + p.obs_lm[s.outlier]
    lmap.remove_observations(np.isin(lmap.obs_keyframe * n + lmap.obs_landmark, bad))
    correction = np.eye(4)
    if p.kf_id in p.free:
        i = np.searchsorted(p.kfs, p.kf_id)
        correction = s.poses[i] @ np.linalg.inv(p.T_old[i])
    return LocalBAResult(p.free, p.fixed, len(p.landmarks), len(p.obs_kf), int(s.outlier.sum()),
                         correction, s.seconds)


def local_bundle_adjustment(lmap: LocalMap, camera: Camera, kf_id: int, *, baseline_m: float,
                            scale_factor: float, window_size: int = 10, min_shared: int = 15,
                            iterations: tuple[int, int] = (5, 10),
                            window: np.ndarray | None = None) -> LocalBAResult:
    """Optimise the window around keyframe ``kf_id`` (or the given ``window`` of keyframe
    ids: all of them is a global bundle adjustment) and write poses, landmark positions and
    the removal of outlier observations back into ``lmap``, in-line."""
    start = time.perf_counter()
    problem = local_ba_problem(lmap, camera, kf_id, baseline_m=baseline_m,
                               scale_factor=scale_factor, window_size=window_size,
                               min_shared=min_shared, iterations=iterations, window=window)
    solution = None if problem is None else solve_local_ba(problem)
    if problem is None or solution is None:
        return LocalBAResult(np.zeros(0, np.int64), np.zeros(0, np.int64), 0, 0, 0, np.eye(4),
                             time.perf_counter() - start)
    result = apply_local_ba(lmap, problem, solution)
    result.seconds = time.perf_counter() - start
    return result
