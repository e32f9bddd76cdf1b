"""The tracking map of one robot: keyframes and the 3D landmarks they created.

Landmarks are stored as growing numpy arrays. A landmark seen again from a later
keyframe gets its position fused (inverse-variance weighted, the depth noise of a
Kinect grows with z^2) and its descriptor refreshed to the newest view, so tracking keeps
matching as the viewpoint changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fleetslam.camera import Camera
from fleetslam.transforms import transform_points


@dataclass
class Keyframe:
    id: int
    frame_index: int
    timestamp: float
    T_world_camera: np.ndarray
    landmark_ids: np.ndarray  # landmarks observed (matched inliers + created)


@dataclass
class LocalMap:
    keyframes: list[Keyframe] = field(default_factory=list)
    xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    weight: np.ndarray = field(default_factory=lambda: np.zeros(0))
    last_keyframe: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    # Pyramid level and camera distance of the newest observation: together they predict
    # the level at which the landmark appears from another distance.
    octave: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    distance: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def n_landmarks(self) -> int:
        return len(self.xyz)

    def local_landmarks(self, n_keyframes: int) -> np.ndarray:
        """Ids of the landmarks observed by the last ``n_keyframes`` keyframes."""
        if not self.keyframes:
            return np.zeros(0, np.int64)
        newest = self.keyframes[-1].id
        return np.flatnonzero(self.last_keyframe > newest - n_keyframes)

    def predicted_octave(self, ids: np.ndarray, distance: np.ndarray, scale_factor: float,
                         n_levels: int) -> np.ndarray:
        """Pyramid level at which landmarks ``ids`` should appear from ``distance``."""
        ratio = self.distance[ids] / np.maximum(distance, 1e-6)
        level = self.octave[ids] + np.log(ratio) / np.log(scale_factor)
        return np.clip(np.round(level), 0, n_levels - 1).astype(np.int64)

    def add_keyframe(self, camera: Camera, frame_index: int, timestamp: float,
                     T_world_camera: np.ndarray, uv: np.ndarray, depth: np.ndarray,
                     descriptors: np.ndarray, octave: np.ndarray, matched_ids: np.ndarray
                     ) -> Keyframe:
        """Insert a keyframe. ``matched_ids`` (N, -1 = none) are inlier matches; they are
        fused with this view. Keypoints with depth and no match become new landmarks."""
        kf_id = len(self.keyframes)
        has_depth = depth > 0
        local = camera.backproject(uv, depth.astype(np.float64))
        distance = np.linalg.norm(local, axis=1)
        points = transform_points(T_world_camera, local)
        # Inverse variance of depth noise ~ 1/z^4, normalised at 1 m.
        w_new = 1.0 / np.maximum(depth.astype(np.float64), 0.1) ** 4

        fuse = (matched_ids >= 0) & has_depth
        ids = matched_ids[fuse]
        # A landmark matched twice in one frame keeps the first update only.
        ids, first = np.unique(ids, return_index=True)
        src = np.flatnonzero(fuse)[first]
        w_old = self.weight[ids]
        self.xyz[ids] = (self.xyz[ids] * w_old[:, None] + points[src] * w_new[src, None]) / (
            w_old + w_new[src])[:, None]
        self.weight[ids] = w_old + w_new[src]
        self.descriptors[ids] = descriptors[src]
        self.octave[ids] = octave[src]
        self.distance[ids] = distance[src]
        seen = matched_ids[matched_ids >= 0]
        self.last_keyframe[seen] = kf_id

        create = (matched_ids < 0) & has_depth
        start = self.n_landmarks
        self.xyz = np.vstack([self.xyz, points[create]])
        self.descriptors = np.vstack([self.descriptors, descriptors[create]])
        self.weight = np.concatenate([self.weight, w_new[create]])
        self.octave = np.concatenate([self.octave, octave[create].astype(np.int64)])
        self.distance = np.concatenate([self.distance, distance[create]])
        self.last_keyframe = np.concatenate(
            [self.last_keyframe, np.full(int(create.sum()), kf_id, np.int64)])
        new_ids = np.arange(start, self.n_landmarks)
        observed = np.unique(np.concatenate([seen, new_ids]))
        keyframe = Keyframe(kf_id, frame_index, timestamp, T_world_camera.copy(), observed)
        self.keyframes.append(keyframe)
        return keyframe
