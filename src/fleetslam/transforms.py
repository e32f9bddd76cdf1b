"""SE(3) helpers on 4x4 float64 matrices: quaternions, inverse, interpolation, errors.

numpy only (a robot installs no SciPy); tests/test_transforms.py checks the quaternion and
slerp functions against SciPy's."""

from __future__ import annotations

from typing import Sequence

import numpy as np


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def orthonormalize(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return R


def matrix_from_quaternion(q: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) as x y z w (normalised here) to rotation matrices (N, 3, 3)."""
    q = np.asarray(q, np.float64).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = x * x - y * y - z * z + w * w
    R[:, 1, 1] = -x * x + y * y - z * z + w * w
    R[:, 2, 2] = -x * x - y * y + z * z + w * w
    R[:, 0, 1] = 2 * (x * y - z * w)
    R[:, 1, 0] = 2 * (x * y + z * w)
    R[:, 0, 2] = 2 * (x * z + y * w)
    R[:, 2, 0] = 2 * (x * z - y * w)
    R[:, 1, 2] = 2 * (y * z - x * w)
    R[:, 2, 1] = 2 * (y * z + x * w)
    return R


def quaternion_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) to unit quaternions (N, 4) x y z w: from the largest of the
    trace and the diagonal (Shepperd), so no branch divides by a small number."""
    R = np.asarray(R, np.float64).reshape(-1, 3, 3)
    trace = np.trace(R, axis1=1, axis2=2)
    diagonal = np.diagonal(R, axis1=1, axis2=2)
    choice = np.argmax(np.column_stack([diagonal, trace]), axis=1)
    q = np.empty((len(R), 4))
    rows = np.flatnonzero(choice == 3)
    q[rows, 0] = R[rows, 2, 1] - R[rows, 1, 2]
    q[rows, 1] = R[rows, 0, 2] - R[rows, 2, 0]
    q[rows, 2] = R[rows, 1, 0] - R[rows, 0, 1]
    q[rows, 3] = 1 + trace[rows]
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        rows = np.flatnonzero(choice == i)
        q[rows, i] = 1 - trace[rows] + 2 * R[rows, i, i]
        q[rows, j] = R[rows, j, i] + R[rows, i, j]
        q[rows, k] = R[rows, k, i] + R[rows, i, k]
        q[rows, 3] = R[rows, k, j] - R[rows, j, k]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def rotation_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of rotation matrices (N, 3, 3), angles in [0, pi]."""
    q = quaternion_from_matrix(R)
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)  # w >= 0: the angle is at most pi
    s = np.linalg.norm(q[:, :3], axis=1)
    angle = 2 * np.arctan2(s, q[:, 3])
    # angle / sin(angle / 2), with its limit 2 near the identity.
    small = s < 1e-12
    scale = np.where(small, 2.0, angle / np.where(small, 1.0, s))
    return q[:, :3] * scale[:, None]


def rotation_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (N, 3, 3) of rotation vectors (N, 3)."""
    rotvec = np.asarray(rotvec, np.float64).reshape(-1, 3)
    angle = np.linalg.norm(rotvec, axis=1)
    small = angle < 1e-12
    # sin(angle / 2) / angle, with its limit 1/2 near zero.
    scale = np.where(small, 0.5, np.sin(angle / 2) / np.where(small, 1.0, angle))
    q = np.column_stack([rotvec * scale[:, None], np.cos(angle / 2)])
    return matrix_from_quaternion(q)


def T_from_tum(values: np.ndarray) -> np.ndarray:
    """(tx ty tz qx qy qz qw) rows (N, 7) to poses (N, 4, 4)."""
    values = np.atleast_2d(values)
    T = np.tile(np.eye(4), (len(values), 1, 1))
    T[:, :3, :3] = matrix_from_quaternion(values[:, 3:7])
    T[:, :3, 3] = values[:, :3]
    return T


def tum_from_T(T: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) to (tx ty tz qx qy qz qw) rows (N, 7)."""
    T = np.asarray(T).reshape(-1, 4, 4)
    R = np.stack([orthonormalize(r) for r in T[:, :3, :3]])
    return np.hstack([T[:, :3, 3], quaternion_from_matrix(R)])


def interpolate_poses(times: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses at ``query`` times: linear in translation, slerp in rotation (the shorter way
    between the two poses around each query). ``query`` must lie within
    [times[0], times[-1]]."""
    times, query = np.asarray(times, np.float64), np.asarray(query, np.float64)
    out = np.tile(np.eye(4), (len(query), 1, 1))
    R = poses[:, :3, :3]
    if len(times) == 1:  # the one pose, wherever asked
        out[:, :3, :3] = R[0]
    else:
        i = np.clip(np.searchsorted(times, query, side="right") - 1, 0, len(times) - 2)
        span = times[i + 1] - times[i]
        fraction = np.where(span > 0, (query - times[i]) / np.where(span > 0, span, 1.0), 0.0)
        delta = rotation_log(np.transpose(R[i], (0, 2, 1)) @ R[i + 1])
        out[:, :3, :3] = R[i] @ rotation_exp(delta * fraction[:, None])
    for k in range(3):
        out[:, k, 3] = np.interp(query, times, poses[:, k, 3])
    return out


def rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    """Angle of each rotation of a stack (N, 3, 3), degrees (evo's so3_log_angle)."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def rotation_angle_deg(R: np.ndarray) -> float:
    return float(rotation_angles_deg(np.asarray(R)[None])[0])


def transforms_agree(A: np.ndarray, B: np.ndarray, at: np.ndarray, rotation_deg: float,
                     translation_m: float) -> bool:
    """Two estimates of one transform agree: the same rotation within ``rotation_deg`` and
    the same image of the point ``at`` within ``translation_m`` (where it is used, so a
    small rotation far from the origin is not mistaken for a large shift)."""
    D = invert(A) @ B
    moved = np.linalg.norm((A[:3, :3] @ at + A[:3, 3]) - (B[:3, :3] @ at + B[:3, 3]))
    return rotation_angle_deg(D[:3, :3]) <= rotation_deg and moved <= translation_m


def poses_from_references(keyframe_poses: np.ndarray, references: Sequence[int],
                          T_reference_camera: Sequence[np.ndarray | None],
                          otherwise: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """Frames' poses as keyframe_poses[reference] @ T_reference_camera (N x 4 x 4), so they
    follow every later move of their keyframes; a frame without a reference (or beyond
    ``keyframe_poses``) keeps its pose from ``otherwise``."""
    refs = np.asarray(references, np.int64)
    out = np.array(otherwise, dtype=np.float64).reshape(-1, 4, 4)
    has = [i for i in np.flatnonzero((refs >= 0) & (refs < len(keyframe_poses)))
           if T_reference_camera[i] is not None]
    if has:
        T_rel = np.array([T_reference_camera[i] for i in has])
        out[has] = keyframe_poses[refs[has]] @ T_rel
    return out
