"""The tracking map of one robot: keyframes, the 3D landmarks they created, and the
observations that tie them together.

Everything is stored as growing numpy arrays (no per-point objects), so the map pickles
with the session and every query is vectorised:

* landmarks: position, descriptor, fusion weight, pyramid level and distance of the
  newest view, an ``alive`` flag (culled landmarks are flagged, never deleted, so ids stay
  valid), the keyframe that created it, and ORB-SLAM's visible/found counters;
* observations: one row per (keyframe, landmark) pair with the keypoint's undistorted
  pixel, depth (0 = none) and octave. Local bundle adjustment reads these rows and drops
  the ones it finds to be outliers.

A landmark seen again from a later keyframe gets its position fused (inverse-variance
weighted, the depth noise of a Kinect grows with z^2) and its descriptor refreshed to the
newest view, so tracking keeps matching as the viewpoint changes; local bundle adjustment
then refines positions and keyframe poses together.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fleetslam.camera import Camera
from fleetslam.pipeline.states import FeatureFrame
from fleetslam.transforms import transform_points


@dataclass
class Keyframe:
    id: int
    frame_index: int
    timestamp: float
    T_world_camera: np.ndarray
    # The keyframe's own features, for place recognition, loop verification and
    # relocalisation, and the landmark each keypoint observes (-1 = none; matched inliers
    # and those it created, renamed when a loop merges landmarks).
    features: FeatureFrame
    keypoint_landmark: np.ndarray

    @property
    def landmark_ids(self) -> np.ndarray:
        """The landmarks this keyframe observes, sorted."""
        return np.unique(self.keypoint_landmark[self.keypoint_landmark >= 0])


def _empty(dtype=np.float64, *shape: int) -> np.ndarray:
    return np.zeros((0, *shape), dtype)


@dataclass
class LocalMap:
    keyframes: list[Keyframe] = field(default_factory=list)
    # --- landmarks (one entry per id) ---
    xyz: np.ndarray = field(default_factory=lambda: _empty(np.float64, 3))
    descriptors: np.ndarray = field(default_factory=lambda: _empty(np.uint8, 32))
    weight: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    last_keyframe: np.ndarray = field(default_factory=lambda: _empty(np.int64))
    # Pyramid level and camera distance of the newest observation: together they predict
    # the level at which the landmark appears from another distance.
    octave: np.ndarray = field(default_factory=lambda: _empty(np.int64))
    distance: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    # False once culled (or left without observations); dead landmarks are never matched.
    alive: np.ndarray = field(default_factory=lambda: _empty(bool))
    first_keyframe: np.ndarray = field(default_factory=lambda: _empty(np.int64))
    # ORB-SLAM's counters: frames in which the landmark was predicted in view, and frames
    # in which it was matched as a pose inlier. found/visible is its usefulness.
    n_visible: np.ndarray = field(default_factory=lambda: _empty(np.int64))
    n_found: np.ndarray = field(default_factory=lambda: _empty(np.int64))
    # --- observations (one row per keyframe x landmark) ---
    obs_keyframe: np.ndarray = field(default_factory=lambda: _empty(np.int64))
    obs_landmark: np.ndarray = field(default_factory=lambda: _empty(np.int64))
    obs_uv: np.ndarray = field(default_factory=lambda: _empty(np.float64, 2))
    obs_depth: np.ndarray = field(default_factory=lambda: _empty(np.float64))
    obs_octave: np.ndarray = field(default_factory=lambda: _empty(np.int64))
    # Counts the changes that move or rename landmarks wholesale (a loop correction): work
    # computed on a copy of an older epoch no longer fits the map.
    epoch: int = 0

    @property
    def n_landmarks(self) -> int:
        return len(self.xyz)

    @property
    def n_observations(self) -> int:
        return len(self.obs_keyframe)

    def keyframe_poses(self, ids: np.ndarray | None = None) -> np.ndarray:
        """T_world_camera of keyframes ``ids`` (all if None), (K, 4, 4)."""
        kfs = self.keyframes if ids is None else [self.keyframes[i] for i in ids]
        return np.array([kf.T_world_camera for kf in kfs]).reshape(-1, 4, 4)

    def local_landmarks(self, n_keyframes: int) -> np.ndarray:
        """Ids of the live landmarks observed by the last ``n_keyframes`` keyframes."""
        if not self.keyframes:
            return np.zeros(0, np.int64)
        newest = self.keyframes[-1].id
        return np.flatnonzero((self.last_keyframe > newest - n_keyframes) & self.alive)

    def created_since(self, kf_id: int) -> np.ndarray:
        """Ids of the landmarks (live or not) created by keyframe ``kf_id`` or later: a tail
        of the ids, which are given in keyframe order."""
        start = int(np.searchsorted(self.first_keyframe, kf_id))
        return np.arange(start, self.n_landmarks)

    def place_landmarks(self, kf_id: int, n_neighbours: int) -> np.ndarray:
        """Ids of the live landmarks observed by keyframe ``kf_id`` and its ``n_neighbours``
        most covisible keyframes: the map of one place."""
        neighbours, _ = self.covisible(kf_id)
        members = np.zeros(len(self.keyframes), bool)
        members[kf_id] = True
        members[neighbours[:n_neighbours]] = True
        ids = np.unique(self.obs_landmark[members[self.obs_keyframe]])
        return ids[self.alive[ids]]

    def covisibility_counts(self) -> np.ndarray:
        """K x K matrix of live landmarks shared by every pair of keyframes."""
        from scipy.sparse import csr_matrix
        live = self.alive[self.obs_landmark]
        A = csr_matrix((np.ones(int(live.sum())), (self.obs_keyframe[live],
                                                     self.obs_landmark[live])),
                       shape=(len(self.keyframes), self.n_landmarks))
        counts = (A @ A.T).toarray()
        np.fill_diagonal(counts, 0)
        return counts.astype(np.int64)

    def predicted_level(self, ids: np.ndarray, distance: np.ndarray, scale_factor: float
                        ) -> np.ndarray:
        """Unclipped (fractional) pyramid level of landmarks ``ids`` seen from ``distance``."""
        ratio = self.distance[ids] / np.maximum(distance, 1e-6)
        return self.octave[ids] + np.log(ratio) / np.log(scale_factor)

    def predicted_octave(self, ids: np.ndarray, distance: np.ndarray, scale_factor: float,
                         n_levels: int) -> np.ndarray:
        """Pyramid level at which landmarks ``ids`` should appear from ``distance``."""
        level = self.predicted_level(ids, distance, scale_factor)
        return np.clip(np.round(level), 0, n_levels - 1).astype(np.int64)

    def in_view(self, camera: Camera, T_world_camera: np.ndarray, min_depth: float,
                max_depth: float, ids: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Live landmarks (of ``ids``, all if None) that project inside the image from
        ``T_world_camera`` within the depth range. Returns (ids, pixels (n, 2), camera-frame
        points (n, 3))."""
        ids = np.flatnonzero(self.alive) if ids is None else ids[self.alive[ids]]
        # np.take: fancy indexing gathers short rows several times slower.
        P = (np.take(self.xyz, ids, axis=0) - T_world_camera[:3, 3]) @ T_world_camera[:3, :3]
        front = (P[:, 2] > min_depth) & (P[:, 2] < max_depth)
        ids, P = ids[front], P[front]
        proj = camera.project(P)
        inside = ((proj[:, 0] >= 0) & (proj[:, 0] < camera.width)
                  & (proj[:, 1] >= 0) & (proj[:, 1] < camera.height))
        return ids[inside], proj[inside], P[inside]

    # ------------------------------------------------------------------ updates

    def add_keyframe(self, camera: Camera, features: FeatureFrame, T_world_camera: np.ndarray,
                     matched_ids: np.ndarray) -> Keyframe:
        """Insert the frame ``features`` as a keyframe. ``matched_ids`` (N, -1 = none) are
        inlier matches; they become observations of this keyframe and, with depth, are fused
        with this view. Keypoints with depth and no match become new landmarks."""
        kf_id = len(self.keyframes)
        uv, depth, descriptors = features.uv, features.depth, features.descriptors
        octave = features.keypoints[:, 5].astype(np.int64)
        depth64 = depth.astype(np.float64)
        has_depth = depth > 0
        local = camera.backproject(uv, depth64)
        distance = np.linalg.norm(local, axis=1)
        points = transform_points(T_world_camera, local)
        # Inverse variance of depth noise ~ 1/z^4, normalised at 1 m.
        w_new = 1.0 / np.maximum(depth64, 0.1) ** 4

        # A landmark matched twice in one frame keeps the first keypoint only.
        matched = np.flatnonzero(matched_ids >= 0)
        seen, first = np.unique(matched_ids[matched], return_index=True)
        seen_kp = matched[first]
        fuse = has_depth[seen_kp]
        ids, src = seen[fuse], seen_kp[fuse]
        w_old = self.weight[ids]
        self.xyz[ids] = (self.xyz[ids] * w_old[:, None] + points[src] * w_new[src, None]) / (
            w_old + w_new[src])[:, None]
        self.weight[ids] = w_old + w_new[src]
        self.descriptors[ids] = descriptors[src]
        self.octave[ids] = octave[src]
        self.distance[ids] = distance[src]
        self.last_keyframe[seen] = kf_id

        create = np.flatnonzero((matched_ids < 0) & has_depth)
        n_new = len(create)
        start = self.n_landmarks
        new_ids = np.arange(start, start + n_new)
        self.xyz = np.vstack([self.xyz, points[create]])
        self.descriptors = np.vstack([self.descriptors, descriptors[create]])
        self.weight = np.concatenate([self.weight, w_new[create]])
        self.octave = np.concatenate([self.octave, octave[create]])
        self.distance = np.concatenate([self.distance, distance[create]])
        self.last_keyframe = np.concatenate([self.last_keyframe, np.full(n_new, kf_id, np.int64)])
        self.alive = np.concatenate([self.alive, np.ones(n_new, bool)])
        self.first_keyframe = np.concatenate(
            [self.first_keyframe, np.full(n_new, kf_id, np.int64)])
        # As ORB-SLAM: a new landmark starts as seen once and found once.
        self.n_visible = np.concatenate([self.n_visible, np.ones(n_new, np.int64)])
        self.n_found = np.concatenate([self.n_found, np.ones(n_new, np.int64)])

        kp = np.concatenate([seen_kp, create])
        self._add_observations(kf_id, np.concatenate([seen, new_ids]), uv[kp],
                               np.where(has_depth[kp], depth64[kp], 0.0), octave[kp])
        keypoint_landmark = np.full(len(uv), -1, np.int64)
        keypoint_landmark[kp] = np.concatenate([seen, new_ids])
        keyframe = Keyframe(kf_id, features.index, features.timestamp, T_world_camera.copy(),
                            features, keypoint_landmark)
        self.keyframes.append(keyframe)
        return keyframe

    def _add_observations(self, kf_id: int, landmarks: np.ndarray, uv: np.ndarray,
                          depth: np.ndarray, octave: np.ndarray) -> None:
        self.obs_keyframe = np.concatenate(
            [self.obs_keyframe, np.full(len(landmarks), kf_id, np.int64)])
        self.obs_landmark = np.concatenate([self.obs_landmark, landmarks.astype(np.int64)])
        self.obs_uv = np.vstack([self.obs_uv, uv.astype(np.float64)])
        self.obs_depth = np.concatenate([self.obs_depth, depth.astype(np.float64)])
        self.obs_octave = np.concatenate([self.obs_octave, octave.astype(np.int64)])

    def remove_observations(self, rows: np.ndarray) -> int:
        """Drop observation rows (bool mask or indices). A landmark left without any
        observation dies. Returns the number of landmarks that died."""
        keep = np.ones(self.n_observations, bool)
        keep[rows] = False
        touched = np.unique(self.obs_landmark[~keep])
        self.obs_keyframe = self.obs_keyframe[keep]
        self.obs_landmark = self.obs_landmark[keep]
        self.obs_uv = self.obs_uv[keep]
        self.obs_depth = self.obs_depth[keep]
        self.obs_octave = self.obs_octave[keep]
        remaining = np.bincount(self.obs_landmark, minlength=self.n_landmarks)
        orphan = touched[(remaining[touched] == 0) & self.alive[touched]]
        self.alive[orphan] = False
        return len(orphan)

    def merge_landmarks(self, keep: np.ndarray, drop: np.ndarray) -> int:
        """Landmark ``drop[i]`` is the same point as ``keep[i]`` (a loop closed on it): its
        observations move to ``keep[i]`` (one per keyframe) and it dies. Returns how many
        were merged."""
        ok = (keep != drop) & self.alive[keep] & self.alive[drop]
        keep, drop = keep[ok], drop[ok]
        _, first = np.unique(drop, return_index=True)
        keep, drop = keep[first], drop[first]
        # A landmark both kept and dropped would chain: keep the first role only.
        chained = np.isin(keep, drop)
        keep, drop = keep[~chained], drop[~chained]
        if not len(drop):
            return 0
        self.epoch += 1
        target = np.arange(self.n_landmarks)
        target[drop] = keep
        self.obs_landmark = target[self.obs_landmark]
        # A keyframe that observed both keeps one observation.
        pair = self.obs_keyframe * self.n_landmarks + self.obs_landmark
        _, unique_rows = np.unique(pair, return_index=True)
        duplicate = np.ones(self.n_observations, bool)
        duplicate[unique_rows] = False
        self.obs_keyframe = self.obs_keyframe[~duplicate]
        self.obs_landmark = self.obs_landmark[~duplicate]
        self.obs_uv = self.obs_uv[~duplicate]
        self.obs_depth = self.obs_depth[~duplicate]
        self.obs_octave = self.obs_octave[~duplicate]
        self.n_visible[keep] += self.n_visible[drop]
        self.n_found[keep] += self.n_found[drop]
        self.last_keyframe[keep] = np.maximum(self.last_keyframe[keep], self.last_keyframe[drop])
        self.alive[drop] = False
        for kf in self.keyframes:
            kf.keypoint_landmark = np.where(kf.keypoint_landmark >= 0,
                                            target[np.maximum(kf.keypoint_landmark, 0)], -1)
        return len(drop)

    def move_landmarks_with_keyframes(self, corrections: dict[int, np.ndarray]) -> None:
        """Keyframe poses changed by T_new = C @ T_old: every landmark moves rigidly with the
        keyframe that created it."""
        self.epoch += 1
        C = np.tile(np.eye(4), (len(self.keyframes), 1, 1))
        for k, Ck in corrections.items():
            C[k] = Ck
        Cl = C[self.first_keyframe]
        self.xyz = np.einsum("nij,nj->ni", Cl[:, :3, :3], self.xyz) + Cl[:, :3, 3]

    def count_views(self, visible: np.ndarray, found: np.ndarray) -> None:
        """One tracked frame: landmarks ``visible`` were predicted in view, ``found`` were
        matched as pose inliers (a found landmark counts as visible too). Touches only
        those: not an array the size of the map."""
        self.n_visible[np.union1d(visible, found)] += 1
        self.n_found[np.unique(found)] += 1

    def redundant_keyframes(self, candidates: np.ndarray, max_depth: float, n_levels: int,
                            min_observers: int, fraction: float) -> np.ndarray:
        """ORB-SLAM's KeyFrameCulling test on keyframes ``candidates``: those for which more
        than ``fraction`` of their live landmarks observed with depth in (0, ``max_depth``)
        are each observed by at least ``min_observers`` other keyframes at the same or a
        finer scale (octave at most one above this keyframe's)."""
        if not len(candidates):
            return candidates
        is_candidate = np.zeros(len(self.keyframes), bool)
        is_candidate[candidates] = True
        own = np.flatnonzero(is_candidate[self.obs_keyframe] & self.alive[self.obs_landmark]
                             & (self.obs_depth > 0) & (self.obs_depth < max_depth))
        if not len(own):
            return candidates[:0]
        # Per landmark of theirs, how many observations are at octave <= o (o = 0..top).
        landmarks, slot = np.unique(self.obs_landmark[own], return_inverse=True)
        of_them = np.flatnonzero(np.isin(self.obs_landmark, landmarks))
        at = np.searchsorted(landmarks, self.obs_landmark[of_them])
        octave = np.clip(self.obs_octave[of_them], 0, n_levels - 1)
        hist = np.zeros((len(landmarks), n_levels), np.int64)
        np.add.at(hist, (at, octave), 1)
        up_to = np.cumsum(hist, axis=1)
        # Others at a scale no coarser than one octave above this observation's (minus the
        # observation itself, which is among them).
        level = np.minimum(self.obs_octave[own] + 1, n_levels - 1)
        others = up_to[slot, level] - 1
        kf = self.obs_keyframe[own]
        total = np.bincount(kf, minlength=len(self.keyframes))
        redundant = np.bincount(kf, weights=others >= min_observers, minlength=len(self.keyframes))
        return candidates[redundant[candidates] > fraction * total[candidates]]

    def drop_keyframe_observations(self, kf_ids: np.ndarray) -> int:
        """Culled keyframes: their observation rows go (a landmark left without any
        dies). The keyframes stay, with their poses and features. Returns the rows dropped."""
        rows = np.isin(self.obs_keyframe, kf_ids)
        self.remove_observations(rows)
        return int(rows.sum())

    # ------------------------------------------------------------------ queries

    def observing(self) -> np.ndarray:
        """Per keyframe, whether it still observes a landmark (a culled keyframe does not:
        it is no place to relocalise or close a loop on)."""
        return np.bincount(self.obs_keyframe, minlength=len(self.keyframes)) > 0

    def covisible(self, kf_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Other keyframes sharing live landmarks with ``kf_id``, most shared first (ties:
        newest first). Returns (keyframe ids, shared landmark counts)."""
        mine = np.zeros(self.n_landmarks, bool)
        mine[self.obs_landmark[self.obs_keyframe == kf_id]] = True
        mine &= self.alive
        rows = mine[self.obs_landmark]
        shared = np.bincount(self.obs_keyframe[rows], minlength=len(self.keyframes))
        shared[kf_id] = 0
        ids = np.flatnonzero(shared)
        order = np.lexsort((-ids, -shared[ids]))
        return ids[order], shared[ids[order]]

    def observation_weight(self, stereo_weight: int = 2) -> np.ndarray:
        """Per landmark, ORB-SLAM's observation count: an observation with depth counts
        ``stereo_weight`` (it constrains the point alone), one without counts 1."""
        w = np.where(self.obs_depth > 0, stereo_weight, 1)
        return np.bincount(self.obs_landmark, weights=w, minlength=self.n_landmarks)

    def tracked_by_keyframe(self, kf_id: int, min_weight: int) -> int:
        """Live landmarks observed by keyframe ``kf_id`` whose observation weight is at
        least ``min_weight`` (ORB-SLAM's KeyFrame::TrackedMapPoints)."""
        lm = self.obs_landmark[self.obs_keyframe == kf_id]
        weight = np.bincount(self.obs_landmark, weights=np.where(self.obs_depth > 0, 2, 1),
                             minlength=self.n_landmarks)
        return int(((weight[lm] >= min_weight) & self.alive[lm]).sum())

    # ------------------------------------------------------------------ culling

    def cull_recent(self, kf_id: int, min_found_ratio: float, min_observation_weight: int,
                    probation_keyframes: int) -> int:
        """ORB-SLAM's map-point culling of recently created landmarks (created within the
        last ``probation_keyframes`` keyframes): a landmark dies if it was matched in fewer
        than ``min_found_ratio`` of the frames that should have seen it, or if, two
        keyframes after its creation, its observation weight is still below
        ``min_observation_weight``. Returns how many died."""
        age = kf_id - self.first_keyframe
        recent = self.alive & (age <= probation_keyframes)
        ratio = self.n_found / np.maximum(self.n_visible, 1)
        weight = self.observation_weight()
        die = recent & ((ratio < min_found_ratio)
                        | ((age >= 2) & (weight < min_observation_weight)))
        self.alive[die] = False
        if die.any():
            self.remove_observations(die[self.obs_landmark])
        return int(die.sum())
