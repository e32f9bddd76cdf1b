"""What the stages remember between frames, split by side of the offloading point.

* ``EdgeSession``: the robot's side, read only by the stages before the offloading point
  (the ORB extractor, the stale-depth check).
* ``CloudSession``: the back-end's side, read only by the stages after it: the tracking map,
  the keyframe database, the motion model, loop-closing state and counters. It is what a
  cloud checkpoints.

A ``Session`` pairs them for whoever runs both sides (one process, or a robot at point 6);
the robot holds only its edge part and the cloud only its cloud part.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Sequence

import cv2
import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.pipeline.local_map import LocalMap
from fleetslam.pipeline.loop_closer import LoopClosingState
from fleetslam.pipeline.place_recognition import KeyframeDatabase, make_database
from fleetslam.pipeline.states import FeatureFrame

if TYPE_CHECKING:
    from fleetslam.pipeline.local_mapping_worker import AsyncLocalMapping
    from fleetslam.pipeline.states import PosedFrame
    from fleetslam.pipeline.vocabulary import BowDatabase


@dataclass
class EdgeSession:
    config: Config
    camera: Camera
    # Digest of the previous depth image, to spot a repeated (stale) one, and how many
    # frames went on without depth because of it.
    last_depth_digest: bytes | None = None
    stale_depth_frames: int = 0
    _orb: cv2.ORB | None = None

    @property
    def orb(self) -> cv2.ORB:
        # Created lazily: cv2 objects cannot be pickled.
        if self._orb is None:
            cfg = self.config.orb
            self._orb = cv2.ORB_create(
                nfeatures=2 * cfg.n_features, scaleFactor=cfg.scale_factor,
                nlevels=cfg.n_levels, fastThreshold=cfg.fast_threshold)
        return self._orb

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_orb"] = None
        return state


def duration_stats(seconds: list[float]) -> dict:
    """Count, median and p95 (ms) of durations in seconds, for summary.json."""
    ms = 1000.0 * np.asarray(seconds)
    return {"n": len(ms), "median_ms": float(np.median(ms)) if len(ms) else None,
            "p95_ms": float(np.percentile(ms, 95)) if len(ms) else None}


@dataclass
class CloudSession:
    config: Config
    camera: Camera
    map: LocalMap = field(default_factory=LocalMap)
    # Place recognition over this robot's keyframes (entry i = keyframe i).
    places: "KeyframeDatabase | BowDatabase | None" = None
    loops: LoopClosingState = field(default_factory=LoopClosingState)
    # Last two estimated poses, for the constant-velocity motion model.
    T_last: np.ndarray | None = None
    T_before_last: np.ndarray | None = None
    last_tracked: bool = True
    lost_frames: int = 0
    # Frames that were lost (pose not estimated from measurements).
    lost_total: int = 0
    # Episodes of loss (a run of lost frames counts once), and those ended by
    # relocalisation against the keyframes.
    loss_events: int = 0
    relocalisations: int = 0
    resets: int = 0
    repeated_frames: int = 0
    # Inliers of the first frame tracked after the newest keyframe (keyframe decision).
    inliers_after_keyframe: int = 0
    # Local mapping statistics: wall time of each local bundle adjustment, observations it
    # erased as outliers, landmarks culled, observations added by fusion at keyframes.
    local_ba_seconds: list[float] = field(default_factory=list)
    local_ba_outliers: int = 0
    culled_landmarks: int = 0
    fused_observations: int = 0
    # Established landmarks (enough observations) of the newest keyframe: the reference of
    # ORB-SLAM's keyframe test.
    reference_tracked: int = 0
    _keyframe_was_last: bool = False
    _last_features: FeatureFrame | None = None
    # Where local BA runs when not in-line (a cloud's worker processes; see
    # local_mapping_worker). Not part of the session's state: never checkpointed.
    local_mapping: "AsyncLocalMapping | None" = None

    def __post_init__(self) -> None:
        if self.places is None:
            self.places = make_database(self.config.place_recognition)

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.pop("local_mapping", None)
        return state

    def predict_pose(self) -> np.ndarray:
        if self.T_last is None:
            return np.eye(4)
        if self.T_before_last is None:
            return self.T_last.copy()
        velocity = np.linalg.solve(self.T_before_last, self.T_last)
        return self.T_last @ velocity

    def tracking_landmarks(self) -> np.ndarray | None:
        """Ids of the landmarks tracking may match (the local map), or None for all of them
        (see ``tracking.local_map_scope``)."""
        cfg = self.config.tracking
        lmap = self.map
        if cfg.local_map_scope == "all" or not lmap.keyframes:
            return None
        if cfg.local_map_scope != "covisible":
            raise ValueError(f"tracking.local_map_scope {cfg.local_map_scope!r}: "
                             f"'covisible' or 'all'")
        newest = lmap.keyframes[-1].id
        neighbours, _ = lmap.covisible(newest)
        members = np.zeros(len(lmap.keyframes), bool)
        members[neighbours[:cfg.local_map_covisible]] = True
        members[max(newest - cfg.local_map_keyframes + 1, 0):] = True
        ids = np.unique(lmap.obs_landmark[members[lmap.obs_keyframe]])
        return ids[lmap.alive[ids]]

    def correct_motion(self, correction: np.ndarray) -> None:
        """The map moved under the camera (local BA, loop correction): move the motion
        model's poses with it, so its velocity is kept."""
        if self.T_last is not None:
            self.T_last = correction @ self.T_last
        if self.T_before_last is not None:
            self.T_before_last = correction @ self.T_before_last

    def is_repeat_of_last(self, features: FeatureFrame) -> bool:
        last = self._last_features
        if last is None or len(last.keypoints) != len(features.keypoints) or not len(last.keypoints):
            return False
        same_place = np.all(np.abs(last.keypoints[:, :2] - features.keypoints[:, :2]) < 1e-3, axis=1)
        same_desc = np.all(last.descriptors == features.descriptors, axis=1)
        return bool((same_place & same_desc).mean() >= self.config.tracking.repeated_frame_fraction)

    def reference_pose(self, T_world_camera: np.ndarray) -> tuple[int, np.ndarray]:
        """(newest keyframe id, pose relative to it): a frame's pose is kept relative to its
        reference keyframe, so the final trajectory follows every later map correction
        (ORB-SLAM's relative frame poses). (-1, pose) before the first keyframe."""
        if not self.map.keyframes:
            return -1, T_world_camera.copy()
        kf = self.map.keyframes[-1]
        return kf.id, np.linalg.solve(kf.T_world_camera, T_world_camera)

    def final_poses(self, references: Sequence[int],
                    T_reference_camera: Sequence[np.ndarray | None],
                    online: Sequence[np.ndarray]) -> np.ndarray:
        """Every frame's pose from its reference keyframe's current pose (N x 4 x 4); a frame
        without a reference (-1, relative pose None) keeps its ``online`` pose."""
        return poses_from_references(self.map.keyframe_poses(), references, T_reference_camera,
                                     online)

    def loop_summary(self) -> dict:
        """Loop closing and relocalisation counts and times, for summary.json."""
        loops = self.loops

        return {
            "loops_accepted": sum(1 for e in loops.events if e["accepted"]),
            "loops_rejected_by_graph": sum(1 for e in loops.events if not e["accepted"]),
            "loop_queries": loops.queries, "candidates_verified": loops.candidates_verified,
            "verified_detections": loops.detections_total,
            "loop_query": duration_stats(loops.query_seconds),
            "loop_correction": duration_stats(loops.correction_seconds),
            "local_ba": duration_stats(self.local_ba_seconds),
            "local_mapping": self.local_mapping_summary(),
            "relocalisations": self.relocalisations, "loss_events": self.loss_events,
            "events": loops.events,
        }

    def local_mapping_summary(self) -> dict:
        """Where local BA ran and, in the workers, what became of the requests."""
        mapping = self.local_mapping
        if mapping is None:
            return {"mode": "inline"}
        return {"mode": "inline (worker failed)" if mapping.broken else "async",
                **mapping.counts, "request_to_applied": duration_stats(mapping.lag_seconds),
                "loop_queries": {**mapping.loop_counts,
                                 "request_to_answered": duration_stats(mapping.loop_lag_seconds)}}

    def record(self, posed: "PosedFrame", features: FeatureFrame, is_keyframe: bool) -> None:
        """Bookkeeping after a frame: motion model, loss counters, repeat detection."""
        if posed.matched.repeated:
            self.repeated_frames += 1
        if posed.tracked:
            self.lost_frames = 0
        else:
            if self.lost_frames == 0:
                self.loss_events += 1
            self.lost_frames += 1
            self.lost_total += 1
            if is_keyframe:
                self.lost_frames = 0
        if self._keyframe_was_last and posed.tracked and not posed.matched.repeated:
            self.inliers_after_keyframe = int(posed.inliers.sum())
            self._keyframe_was_last = False
        if is_keyframe:
            self._keyframe_was_last = True
            self.inliers_after_keyframe = 0
        self.last_tracked = posed.tracked
        self.T_before_last = self.T_last
        self.T_last = posed.T_world_camera.copy()
        self._last_features = features


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


@dataclass
class Session:
    """Both sides of one robot's pipeline; a process holds only the sides it runs."""

    edge: EdgeSession | None = None
    cloud: CloudSession | None = None

    @staticmethod
    def full(config: Config, camera: Camera) -> "Session":
        return Session(EdgeSession(config, camera), CloudSession(config, camera))

    def part(self, side: str) -> EdgeSession | CloudSession:
        part = self.edge if side == "edge" else self.cloud if side == "cloud" else None
        if part is None:
            raise ValueError(f"this process holds no {side} session (stage on the wrong side "
                             f"of the offloading point)")
        return part
