"""Motion-only bundle adjustment for RGB-D: refine one camera pose against matched landmarks.

Each match gives a reprojection residual (u, v); a match whose keypoint has depth also
gives a "virtual right camera" residual u - bf/z (as ORB-SLAM's RGB-D mode does), which
constrains depth with the Kinect's growing uncertainty. Gauss-Newton with Huber weights,
then a chi-square inlier test; all vectorised over matches.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from fleetslam.camera import Camera
from fleetslam.transforms import invert, orthonormalize

# Chi-square 95% thresholds for 2 and 3 degrees of freedom.
CHI2_MONO = 5.991
CHI2_STEREO = 7.815
# A Gauss-Newton round stops once a step is below this (rotation rad and translation m
# together: 10 um, 0.0006 deg, far below depth noise). Measured against 1e-7: 31 % fewer
# iterations, ATE the same to 1 um on redkitchen 0-599 and fr1_rpy (1e-4 moved it 0.13 mm).
CONVERGED_STEP = 1e-5


def _se3_exp(delta: np.ndarray) -> np.ndarray:
    """The 4 x 4 pose increment of ``delta`` (rotation vector, translation). The rotation is
    scipy's ``Rotation.from_rotvec(v).as_matrix()`` written out (its quaternion, with the
    small-angle series below 1e-3 rad, then the matrix; the same operations in the same
    order, so the same bits) without its ~100 us of array-API overhead per call."""
    v0, v1, v2, t0, t1, t2 = delta.tolist()
    angle = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if angle <= 1e-3:
        a2 = angle * angle
        scale = 0.5 - a2 / 48 + a2 * a2 / 3840
    else:
        scale = math.sin(angle / 2) / angle
    x, y, z, w = scale * v0, scale * v1, scale * v2, math.cos(angle / 2)
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw), t0],
                     [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw), t1],
                     [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2, t2],
                     [0.0, 0.0, 0.0, 1.0]])


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
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    bf = fx * virtual_baseline_m
    u, v = uv[:, 0], uv[:, 1]
    ur_meas = u - bf / np.where(stereo, depth, 1.0)
    info = 1.0 / octave_scale**2
    threshold = np.where(stereo, CHI2_STEREO, CHI2_MONO)
    # Huber's threshold on the whitened residual norm.
    k = np.sqrt(threshold)
    damping = 1e-9 * np.eye(6)
    # Residuals (u, v, virtual right u) by row, and their Jacobian for a left perturbation
    # (rotation, translation) of T_camera_world, parameter by row: each entry a contiguous
    # run over the matches, filled in place each iteration (the always-zero ones stay so).
    r = np.zeros((3, n))
    J = np.zeros((6, 3, n))
    for _ in range(rounds):
        for _ in range(iterations):
            P = xyz_world @ T_cw[:3, :3].T + T_cw[:3, 3]
            X, Y, Z_raw = P[:, 0], P[:, 1], P[:, 2]
            Z = np.maximum(Z_raw, 1e-6)
            iz = 1.0 / Z
            iz2 = iz**2
            u_hat = fx * X * iz + cx
            np.subtract(u_hat, u, out=r[0])
            r[1] = fy * Y * iz + cy - v
            r[2] = np.where(stereo, u_hat - bf * iz - ur_meas, 0.0)
            # d(residual)/dP, rows (a, 0, b), (0, c, d), stereo only (a, 0, e) ...
            a = fx * iz
            b = -fx * X * iz2
            c = fy * iz
            d = -fy * Y * iz2
            a_s = np.where(stereo, a, 0.0)
            e_s = np.where(stereo, b + bf * iz2, 0.0)
            # ... times dP/d(delta) = [-[P]x | I], written out per entry.
            np.multiply(b, Y, out=J[0, 0])
            J[1, 0] = a * Z_raw + b * -X
            J[2, 0] = a * -Y
            J[3, 0] = a
            J[5, 0] = b
            J[0, 1] = c * -Z_raw + d * Y
            J[1, 1] = d * -X
            np.multiply(c, X, out=J[2, 1])
            J[4, 1] = c
            J[5, 1] = d
            np.multiply(e_s, Y, out=J[0, 2])
            J[1, 2] = a_s * Z_raw + e_s * -X
            J[2, 2] = a_s * -Y
            J[3, 2] = a_s
            J[5, 2] = e_s
            chi2 = (r[0]**2 + r[1]**2 + r[2]**2) * info
            norm = np.sqrt(chi2)
            w = np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-12)) * info * inlier
            # Normal equations as two matrix products: H = sum w J^T J, g = sum w J^T r.
            Jf = J.reshape(6, -1)
            Jw = (J * w).reshape(6, -1)
            H = Jw @ Jf.T
            g = Jw @ r.reshape(-1)
            try:
                delta = -np.linalg.solve(H + damping, g)
            except np.linalg.LinAlgError:
                break
            T_cw = _se3_exp(delta) @ T_cw
            if np.linalg.norm(delta) < CONVERGED_STEP:
                break
        P = xyz_world @ T_cw[:3, :3].T + T_cw[:3, 3]
        Z = np.maximum(P[:, 2], 1e-6)
        r0 = fx * P[:, 0] / Z + cx - u
        r1 = fy * P[:, 1] / Z + cy - v
        r2 = np.where(stereo, fx * P[:, 0] / Z + cx - bf / Z - ur_meas, 0.0)
        chi2 = (r0**2 + r1**2 + r2**2) * info
        inlier = (chi2 < threshold) & (P[:, 2] > 0)
    # Each step multiplies the pose by an increment, and each frame starts from the last
    # two frames' product (the motion model): the rotation's error from orthonormal grew
    # with every frame (1e-9 after 300 frames of redkitchen, past 1e-6 after 409, where a
    # cloud refuses a point-6 robot's pose as not rigid). Projected back each frame.
    T_cw[:3, :3] = orthonormalize(T_cw[:3, :3])
    return invert(T_cw), inlier


def pnp_pose(camera: Camera, xyz_world: np.ndarray, uv: np.ndarray, depth: np.ndarray,
             octave_scale: np.ndarray, virtual_baseline_m: float, T_guess: np.ndarray,
             ransac_iterations: int, ransac_reproj_px: float, ransac_confidence: float,
             min_inliers: int, refine_all: bool = True) -> tuple[np.ndarray, np.ndarray] | None:
    """A camera pose from 2D-3D matches: PnP with RANSAC (AP3P minimal samples, the cheapest
    of OpenCV's solvers; docs/decisions.md [tracking]), then the RGB-D motion-only
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
        flags=cv2.SOLVEPNP_AP3P)
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
