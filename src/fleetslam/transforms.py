"""SE(3) helpers on 4x4 float64 matrices: quaternions, inverse, interpolation, errors."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


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


def T_from_tum(values: np.ndarray) -> np.ndarray:
    """(tx ty tz qx qy qz qw) rows (N, 7) to poses (N, 4, 4)."""
    values = np.atleast_2d(values)
    T = np.tile(np.eye(4), (len(values), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(values[:, 3:7]).as_matrix()
    T[:, :3, 3] = values[:, :3]
    return T


def tum_from_T(T: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) to (tx ty tz qx qy qz qw) rows (N, 7)."""
    T = np.asarray(T).reshape(-1, 4, 4)
    R = np.stack([orthonormalize(r) for r in T[:, :3, :3]])
    return np.hstack([T[:, :3, 3], Rotation.from_matrix(R).as_quat()])


def interpolate_poses(times: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses at ``query`` times: linear in translation, slerp in rotation. ``query`` must lie
    within [times[0], times[-1]]."""
    rot = Slerp(times, Rotation.from_matrix(poses[:, :3, :3]))(query)
    out = np.tile(np.eye(4), (len(query), 1, 1))
    out[:, :3, :3] = rot.as_matrix()
    for k in range(3):
        out[:, k, 3] = np.interp(query, times, poses[:, k, 3])
    return out


def rotation_angle_deg(R: np.ndarray) -> float:
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def random_perturbation(rng: np.random.Generator, max_rot_deg: float, max_trans_m: float) -> np.ndarray:
    """A transform with rotation of exactly ``max_rot_deg`` about a random axis and a
    translation of exactly ``max_trans_m`` in a random direction (worst case of the bound)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    R = Rotation.from_rotvec(axis * np.radians(max_rot_deg)).as_matrix()
    return make_T(R, direction * max_trans_m)


def transforms_agree(A: np.ndarray, B: np.ndarray, at: np.ndarray, rotation_deg: float,
                     translation_m: float) -> bool:
    """Two estimates of one transform agree: the same rotation within ``rotation_deg`` and
    the same image of the point ``at`` within ``translation_m`` (where it is used, so a
    small rotation far from the origin is not mistaken for a large shift)."""
    D = invert(A) @ B
    moved = np.linalg.norm((A[:3, :3] @ at + A[:3, 3]) - (B[:3, :3] @ at + B[:3, 3]))
    return rotation_angle_deg(D[:3, :3]) <= rotation_deg and moved <= translation_m
