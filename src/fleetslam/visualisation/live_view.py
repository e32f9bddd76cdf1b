"""The cloud's live view in rerun: per robot its camera (frustum and pose) as it tracks, its
trajectory, keyframes and growing dense map, placed in the global frame once merged; the
inter-robot constraints; each robot's offloading point, cloud time per frame and link
throughput as time series.

Sessions, the server and the merger call a tiny interface (:class:`NullView` is the one used
when the view is off). Each call only puts an update on a bounded queue and returns; one
thread of the view's own turns updates into rerun entities. When that thread falls behind,
new updates are dropped (and counted), never waited for: the view cannot slow tracking.
Heavy work (back-projecting a keyframe's depth) happens on the view's thread, decimated.

Entities (``<r>`` a robot id):

- ``world/<r>``: the robot's map frame in the global frame (identity until it is merged)
- ``world/<r>/camera``: its camera's pose and pinhole frustum, every frame
- ``world/<r>/trajectory/<segment>``: its trajectory, one line strip per segment of frames
- ``world/<r>/keyframe_centres``: where its keyframes are
- ``world/<r>/keyframes/<frame>``: one keyframe's pose; ``.../points`` its points
- ``world/constraints``: inter-robot constraints as lines (green kept, red rejected by GNC)
- ``robots/<r>/{split_point,cloud_ms,link_kB_per_s}``: time series

Timelines: ``frame_<r>`` (the robot's frame index) and ``wall_time``.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.mapping.dense_map import voxel_downsample
from fleetslam.visualisation.recording import (
    close_recording,
    import_rerun,
    open_recording,
)

log = logging.getLogger("fleetslam.view")

# Robot colours, in the order robots are first seen.
PALETTE = [(230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180),
           (70, 240, 240), (240, 50, 230), (128, 128, 0)]
KEPT, REJECTED, UNTESTED = (40, 200, 40), (220, 30, 30), (230, 200, 30)
# How far in front of the camera its frustum is drawn (m).
FRUSTUM_DEPTH_M = 0.15


def frame_timeline(robot: str) -> str:
    return f"frame_{robot}"


def robot_colour(index: int) -> tuple[int, int, int]:
    return PALETTE[index % len(PALETTE)]


def moved(a: np.ndarray, b: np.ndarray, translation_m: float, rotation_deg: float) -> bool:
    """Whether pose ``b`` differs from ``a`` by more than these bounds."""
    if np.linalg.norm(a[:3, 3] - b[:3, 3]) > translation_m:
        return True
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, cos)))) > rotation_deg


class NullView:
    """The view when it is off: every call does nothing."""

    enabled = False
    dropped = 0

    def robot(self, robot: str, camera: Camera) -> None:
        pass

    def received(self, robot: str, nbytes: int) -> None:
        pass

    def frame(self, robot: str, index: int, T_map_camera: np.ndarray, tracked: bool,
              is_keyframe: bool, split_point: int, cloud_ms: float,
              timestamp: float | None = None) -> None:
        """A frame the cloud tracked (``timestamp``: its capture time, seconds)."""

    def keyframe_poses(self, robot: str, frames: Sequence[int], poses: np.ndarray) -> None:
        pass

    def keyframe_points(self, robot: str, index: int, T_map_keyframe: np.ndarray,
                        rgb: np.ndarray, depth_raw: np.ndarray, decimated_by: int) -> None:
        pass

    def merged(self, T_global_map: dict[str, np.ndarray],
               constraints: list[tuple[np.ndarray, np.ndarray, bool | None]],
               fleet: list[str] | None = None) -> None:
        """Where the merger places each robot's map (``fleet``: the robots of the group
        whose frame is ``map``, none while no robots have joined)."""

    def fleet_map(self, run_dir: Path, summary: dict[str, Any]) -> None:
        """A merge wrote its outputs in ``run_dir`` (``summary``: its summary.json)."""

    def close(self) -> None:
        pass


class _Robot:
    """What the view's thread keeps of one robot."""

    def __init__(self, name: str, camera: Camera, colour: tuple[int, int, int]) -> None:
        self.name = name
        self.camera = camera
        self.colour = colour
        self.timeline = frame_timeline(name)
        self.last_frame = -1
        self.frames_seen = 0
        self.segment: list[np.ndarray] = []  # trajectory points not logged yet (+ the last)
        self.segments = 0
        self.keyframes: dict[int, np.ndarray] = {}  # frame -> pose last logged
        self.with_points: set[int] = set()
        self.T_global_map = np.eye(4)
        self.bytes_sampled = 0


class LiveView(NullView):
    """Logs to a rerun recording from its own thread (see the module's doc)."""

    enabled = True

    def __init__(self, config: Config, recording: Any) -> None:
        self.rr = import_rerun()
        self.config = config
        self.cfg = config.view
        self.recording = recording
        self.dropped = 0
        self.logged = 0
        self._queue: queue.Queue = queue.Queue(max(1, self.cfg.queue_size))
        self._lock = threading.Lock()
        self._robots: dict[str, _Robot] = {}  # the view thread's
        self._received: dict[str, int] = {}  # bytes per robot, from the callers' threads
        self._cameras: dict[str, Camera] = {}  # robots announced, from the server's thread
        self._sampled_at = time.monotonic()
        self._constraints_logged: list[Any] | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="view", daemon=True)
        recording.log("world", self.rr.ViewCoordinates.RDF, static=True)
        self._thread.start()

    @staticmethod
    def open(config: Config, save: Path | None, live: bool) -> "LiveView":
        return LiveView(config, open_recording(config.view, save, live))

    # -- the interface: called on sessions', the server's and the merger's threads ---------

    def _put(self, item: tuple) -> None:
        try:
            self._queue.put_nowait((time.time(), *item))
        except queue.Full:
            self.dropped += 1  # (racy across threads; a count for the log, not a ledger)

    def robot(self, robot: str, camera: Camera) -> None:
        # Not queued: a robot's updates must find its camera even if this came when the
        # queue was full.
        with self._lock:
            self._cameras.setdefault(robot, camera)

    def received(self, robot: str, nbytes: int) -> None:
        with self._lock:
            self._received[robot] = self._received.get(robot, 0) + nbytes

    def frame(self, robot: str, index: int, T_map_camera: np.ndarray, tracked: bool,
              is_keyframe: bool, split_point: int, cloud_ms: float,
              timestamp: float | None = None) -> None:
        self._put(("frame", robot, index, T_map_camera, tracked, is_keyframe, split_point,
                   cloud_ms))

    def keyframe_poses(self, robot: str, frames: Sequence[int], poses: np.ndarray) -> None:
        self._put(("keyframe_poses", robot, list(frames), poses))

    def keyframe_points(self, robot: str, index: int, T_map_keyframe: np.ndarray,
                        rgb: np.ndarray, depth_raw: np.ndarray, decimated_by: int) -> None:
        self._put(("keyframe_points", robot, index, T_map_keyframe, rgb, depth_raw,
                   decimated_by))

    def merged(self, T_global_map: dict[str, np.ndarray],
               constraints: list[tuple[np.ndarray, np.ndarray, bool | None]],
               fleet: list[str] | None = None) -> None:
        self._put(("merged", T_global_map, constraints))

    def close(self) -> None:
        """Write what is queued (at most ``view.close_timeout_s``), then close the
        recording (a file gets its footer)."""
        if self._closed:
            return
        self._closed = True
        deadline = time.monotonic() + self.cfg.close_timeout_s
        while True:  # the end marker must get in even if the queue is full
            try:
                self._queue.put(None, timeout=0.1)
                break
            except queue.Full:
                if time.monotonic() > deadline:
                    break
        self._thread.join(max(0.1, deadline - time.monotonic()))
        if self._thread.is_alive():
            log.warning("view: still writing after %.0f s; closing without the rest",
                        self.cfg.close_timeout_s)
        if self.dropped:
            log.warning("view: %d updates dropped (the view fell behind the robots)",
                        self.dropped)
        close_recording(self.recording)

    # -- the view's thread ----------------------------------------------------------------

    def _run(self) -> None:
        next_sample = time.monotonic() + self.cfg.throughput_every_s
        while True:
            try:
                item = self._queue.get(timeout=max(0.01, next_sample - time.monotonic()))
            except queue.Empty:
                item = ()
            if item is None:
                break
            if item:
                try:
                    getattr(self, "_on_" + item[1])(item[0], *item[2:])
                    self.logged += 1
                except Exception:  # a bad update must not end the view
                    log.exception("view: %s update failed", item[1])
            if time.monotonic() >= next_sample:
                next_sample = time.monotonic() + self.cfg.throughput_every_s
                self._sample_throughput(time.time())
        for r in self._robots.values():
            self._log_segment(r, time.time(), final=True)
        self._sample_throughput(time.time())

    def _at(self, t: float, robot: _Robot | None = None, frame: int | None = None) -> None:
        rec = self.recording
        rec.reset_time()
        rec.set_time("wall_time", timestamp=t)
        if robot is not None:
            rec.set_time(robot.timeline, sequence=robot.last_frame if frame is None else frame)

    def _robot(self, name: str) -> _Robot | None:
        """The robot, set up in the recording the first time one of its updates comes."""
        r = self._robots.get(name)
        if r is not None:
            return r
        with self._lock:
            camera = self._cameras.get(name)
        if camera is None:
            return None
        return self._add_robot(time.time(), name, camera)

    def _add_robot(self, t: float, name: str, camera: Camera) -> _Robot:
        rr, rec = self.rr, self.recording
        r = self._robots[name] = _Robot(name, camera, robot_colour(len(self._robots)))
        rec.log(f"world/{name}/camera", rr.Pinhole(
            image_from_camera=camera.K, resolution=[camera.width, camera.height],
            image_plane_distance=FRUSTUM_DEPTH_M, color=r.colour), static=True)
        for series, label in (("split_point", "offloading point"),
                              ("cloud_ms", "cloud ms / frame"),
                              ("link_kB_per_s", "received kB/s")):
            rec.log(f"robots/{name}/{series}", rr.SeriesLines(
                colors=[r.colour], names=[f"{name} {label}"]), static=True)
        self._at(t, r, 0)
        rec.log(f"world/{name}", rr.Transform3D(translation=[0.0, 0.0, 0.0]))
        return r

    def _on_frame(self, t: float, name: str, index: int, T: np.ndarray, tracked: bool,
                  is_keyframe: bool, split_point: int, cloud_ms: float) -> None:
        r = self._robot(name)
        if r is None:
            return
        rr, rec = self.rr, self.recording
        r.last_frame = index
        self._at(t, r)
        rec.log(f"robots/{name}/split_point", rr.Scalars(float(split_point)))
        rec.log(f"robots/{name}/cloud_ms", rr.Scalars(float(cloud_ms)))
        if not tracked:
            return
        if r.frames_seen % max(1, self.cfg.pose_every_frames) == 0 or is_keyframe:
            rec.log(f"world/{name}/camera",
                    rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        r.frames_seen += 1
        r.segment.append(np.array(T[:3, 3], dtype=np.float32))
        if len(r.segment) > self.cfg.trajectory_segment_frames:
            self._log_segment(r, t)
        if is_keyframe and index not in r.keyframes:
            self._log_keyframe(r, index, T)
            self._log_centres(r)

    def _log_segment(self, r: _Robot, t: float, final: bool = False) -> None:
        if len(r.segment) < 2:
            return
        self._at(t, r)
        self.recording.log(f"world/{r.name}/trajectory/{r.segments:05d}", self.rr.LineStrips3D(
            [np.array(r.segment)], colors=[r.colour], radii=[0.004]))
        r.segments += 1
        r.segment = [r.segment[-1]]

    def _log_keyframe(self, r: _Robot, index: int, T: np.ndarray) -> None:
        self.recording.log(f"world/{r.name}/keyframes/{index:06d}",
                           self.rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        r.keyframes[index] = np.array(T, dtype=np.float64)

    def _log_centres(self, r: _Robot) -> None:
        centres = np.array([T[:3, 3] for T in r.keyframes.values()]).reshape(-1, 3)
        self.recording.log(f"world/{r.name}/keyframe_centres", self.rr.Points3D(
            centres, colors=[r.colour], radii=[0.015]))

    def _on_keyframe_poses(self, t: float, name: str, frames: list[int],
                           poses: np.ndarray) -> None:
        """Local BA and loop closing moved keyframes: move their entities (and so their
        points) where they moved more than the bounds."""
        r = self._robot(name)
        if r is None:
            return
        self._at(t, r)
        changed = False
        for index, T in zip(frames, poses):
            known = r.keyframes.get(index)
            if known is None or moved(known, T, self.cfg.move_translation_m,
                                      self.cfg.move_rotation_deg):
                self._log_keyframe(r, index, T)
                changed = True
        if changed:
            self._log_centres(r)

    def _on_keyframe_points(self, t: float, name: str, index: int, T: np.ndarray,
                            rgb: np.ndarray, depth_raw: np.ndarray, decimated_by: int) -> None:
        r = self._robot(name)
        if r is None:
            return
        camera, map_cfg = r.camera, self.config.map
        depth_m = camera.depth_to_metres(depth_raw)
        local, vu = camera.backproject_image(
            depth_m, stride=max(1, map_cfg.pixel_stride // decimated_by),
            max_depth_m=map_cfg.max_depth_m, decimated_by=decimated_by)
        points, colours = voxel_downsample(local, rgb[vu[:, 0], vu[:, 1]],
                                           self.cfg.keyframe_voxel_m)
        cap = self.cfg.max_points_per_keyframe
        if len(points) > cap:
            keep = np.linspace(0, len(points) - 1, cap).astype(np.int64)
            points, colours = points[keep], colours[keep]
        self._at(t, r, index)
        if index not in r.keyframes:
            self._log_keyframe(r, index, T)
            self._log_centres(r)
        self.recording.log(f"world/{name}/keyframes/{index:06d}/points", self.rr.Points3D(
            points.astype(np.float32), colors=colours,
            radii=[self.cfg.keyframe_voxel_m / 2]))
        r.with_points.add(index)

    def _on_merged(self, t: float, T_global_map: dict[str, np.ndarray],
                   constraints: list[tuple[np.ndarray, np.ndarray, bool | None]]) -> None:
        rr, rec = self.rr, self.recording
        for name, T in T_global_map.items():
            r = self._robot(name)
            if r is None or not moved(r.T_global_map, T, 1e-4, 0.01):
                continue
            self._at(t, r)
            rec.log(f"world/{name}", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            r.T_global_map = np.array(T, dtype=np.float64)
        key = [(tuple(np.round(a, 3)), tuple(np.round(b, 3)), kept)
               for a, b, kept in constraints]
        if constraints and key != self._constraints_logged:
            self._at(t)
            colours = [KEPT if kept else REJECTED if kept is False else UNTESTED
                       for _, _, kept in constraints]
            rec.log("world/constraints", rr.LineStrips3D(
                [np.array([a, b]) for a, b, _ in constraints], colors=colours, radii=[0.006]))
            self._constraints_logged = key

    def _sample_throughput(self, t: float) -> None:
        now = time.monotonic()
        elapsed, self._sampled_at = max(now - self._sampled_at, 1e-3), now
        with self._lock:
            received = dict(self._received)
        for name, total in received.items():
            r = self._robot(name)
            if r is None:
                continue
            rate = (total - r.bytes_sampled) / elapsed / 1000.0
            r.bytes_sampled = total
            self._at(t, r)
            self.recording.log(f"robots/{name}/link_kB_per_s", self.rr.Scalars(rate))
