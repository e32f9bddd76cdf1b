"""Motion-only bundle adjustment for RGB-D: refine one camera pose against matched landmarks.

Each match gives a reprojection residual (u, v); a match whose keypoint has depth also
gives a "virtual right camera" residual u - bf/z (as ORB-SLAM's RGB-D mode does), which
constrains depth with the Kinect's growing uncertainty. Gauss-Newton with Huber weights,
then a chi-square inlier test; all vectorised over matches.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from fleetslam.camera import Camera
from fleetslam.transforms import invert

# Chi-square 95% thresholds for 2 and 3 degrees of freedom.
CHI2_MONO = 5.991
CHI2_STEREO = 7.815


def _se3_exp(delta: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(delta[:3]).as_matrix()
    T[:3, 3] = delta[3:]
    return T


def optimize_pose(camera: Camera, T_world_camera: np.ndarray, xyz_world: np.ndarray,
                  uv: np.ndarray, depth: np.ndarray, octave_scale: np.ndarray,
                  virtual_baseline_m: float, iterations: int = 10, rounds: int = 3
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Refine ``T_world_camera``. ``octave_scale`` is the pyramid scale of each keypoint
    (its pixel noise grows with it). Returns (pose, inlier mask)."""
    T_cw = invert(T_world_camera)
    n = len(xyz_world)
    inlier = np.ones(n, bool)
    stereo = depth > 0
    bf = camera.fx * virtual_baseline_m
    ur_meas = uv[:, 0] - bf / np.where(stereo, depth, 1.0)
    info = 1.0 / octave_scale**2
    for _ in range(rounds):
        for _ in range(iterations):
            P = xyz_world @ T_cw[:3, :3].T + T_cw[:3, 3]
            X, Y, Z = P[:, 0], P[:, 1], np.maximum(P[:, 2], 1e-6)
            iz = 1.0 / Z
            r = np.zeros((n, 3))
            r[:, 0] = camera.fx * X * iz + camera.cx - uv[:, 0]
            r[:, 1] = camera.fy * Y * iz + camera.cy - uv[:, 1]
            r[:, 2] = np.where(stereo, camera.fx * X * iz + camera.cx - bf * iz - ur_meas, 0.0)
            # d(residual)/dP, then dP/d(delta) = [-[P]x | I] for a left perturbation.
            J_p = np.zeros((n, 3, 3))
            J_p[:, 0, 0] = camera.fx * iz
            J_p[:, 0, 2] = -camera.fx * X * iz**2
            J_p[:, 1, 1] = camera.fy * iz
            J_p[:, 1, 2] = -camera.fy * Y * iz**2
            J_p[:, 2, 0] = np.where(stereo, camera.fx * iz, 0.0)
            J_p[:, 2, 2] = np.where(stereo, -camera.fx * X * iz**2 + bf * iz**2, 0.0)
            skew = np.zeros((n, 3, 3))
            skew[:, 0, 1], skew[:, 0, 2] = -P[:, 2], P[:, 1]
            skew[:, 1, 0], skew[:, 1, 2] = P[:, 2], -P[:, 0]
            skew[:, 2, 0], skew[:, 2, 1] = -P[:, 1], P[:, 0]
            J = np.concatenate([J_p @ -skew, J_p], axis=2)  # n x 3 x 6
            chi2 = (r**2).sum(axis=1) * info
            threshold = np.where(stereo, CHI2_STEREO, CHI2_MONO)
            # Huber weight on the whitened residual norm.
            k = np.sqrt(threshold)
            norm = np.sqrt(chi2)
            w = np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-12)) * info * inlier
            # Normal equations as two matrix products (a 3-operand einsum takes numpy's
            # slow generic path): H = sum w J^T J, g = sum w J^T r.
            Jw = (J * w[:, None, None]).reshape(-1, 6)
            H = Jw.T @ J.reshape(-1, 6)
            g = Jw.T @ r.reshape(-1)
            try:
                delta = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
            except np.linalg.LinAlgError:
                break
            T_cw = _se3_exp(delta) @ T_cw
            if np.linalg.norm(delta) < 1e-7:
                break
        P = xyz_world @ T_cw[:3, :3].T + T_cw[:3, 3]
        Z = np.maximum(P[:, 2], 1e-6)
        r0 = camera.fx * P[:, 0] / Z + camera.cx - uv[:, 0]
        r1 = camera.fy * P[:, 1] / Z + camera.cy - uv[:, 1]
        r2 = np.where(stereo, camera.fx * P[:, 0] / Z + camera.cx - bf / Z - ur_meas, 0.0)
        chi2 = (r0**2 + r1**2 + r2**2) * info
        inlier = (chi2 < np.where(stereo, CHI2_STEREO, CHI2_MONO)) & (P[:, 2] > 0)
    return invert(T_cw), inlier


def pnp_pose(camera: Camera, xyz_world: np.ndarray, uv: np.ndarray, depth: np.ndarray,
             octave_scale: np.ndarray, virtual_baseline_m: float, T_guess: np.ndarray,
             ransac_iterations: int, ransac_reproj_px: float, ransac_confidence: float,
             min_inliers: int, refine_all: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """A camera pose from 2D-3D matches: PnP with RANSAC (SQPnP), then the RGB-D motion-only
    refinement, on all matches (tracking: few outliers) or, ``refine_all=False``, on the
    RANSAC inliers only (relocalisation, loops: many outliers, which could pull the
    refinement away). Returns (T_world_camera, inlier mask over the matches), or None when
    fewer than ``min_inliers`` agree."""
    if len(xyz_world) < max(min_inliers, 4):
        return None
    T_cw = invert(T_guess)
    rvec, _ = cv2.Rodrigues(T_cw[:3, :3])
    ok, rvec, tvec, ransac_inliers = cv2.solvePnPRansac(
        xyz_world, uv, camera.K, None, rvec=rvec, tvec=T_cw[:3, 3].copy(),
        useExtrinsicGuess=False, iterationsCount=ransac_iterations,
        reprojectionError=ransac_reproj_px, confidence=ransac_confidence,
        flags=cv2.SOLVEPNP_SQPNP)
    if not ok or ransac_inliers is None or len(ransac_inliers) < min_inliers:
        return None
    R, _ = cv2.Rodrigues(rvec)
    T_cw = np.eye(4)
    T_cw[:3, :3], T_cw[:3, 3] = R, tvec.ravel()
    if refine_all:
        return optimize_pose(camera, invert(T_cw), xyz_world, uv, depth, octave_scale,
                             virtual_baseline_m)
    sub = ransac_inliers.ravel()
    T_wc, _ = optimize_pose(camera, invert(T_cw), xyz_world[sub], uv[sub], depth[sub],
                            octave_scale[sub], virtual_baseline_m)
    # Inliers of every match at that pose (no further iteration).
    return optimize_pose(camera, T_wc, xyz_world, uv, depth, octave_scale, virtual_baseline_m,
                         iterations=0, rounds=1)
