"""A robot session's outputs: when its robot ends, the robot's files (trajectory, keyframes,
dense map; outputs.py) and its entry of the summary (robot.json); for the merge, the finished
map and what the global map needs of the robot. The files are named and the summary's
schema kept by outputs.py, for the cloud as for one process (system.py).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.cloud.session.session_state import SessionState
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.mapping.dense_map import KeyframeClouds, fuse_clouds
from fleetslam.mapping.map_frame import mounting_up
from fleetslam.mapping.occupancy_grid import occupancy_grid
from fleetslam.merging.global_map import RobotTrack
from fleetslam.outputs import read_robot_summary, write_robot_files, write_robot_summary
from fleetslam.pipeline.split import ROBOT_TRACKS
from fleetslam.run_summary import CloudCounts, RobotSummary
from fleetslam.wire.data_tree import CheckpointError
from fleetslam.wire.envelope import WireError
from fleetslam.wire.messages import KeyframeUpload, decode_keyframe

log = logging.getLogger("fleetslam.cloud")


@dataclass
class FinishedMap:
    robot_id: str
    points: np.ndarray
    colors: np.ndarray
    track: RobotTrack
    summary: dict[str, Any]


class SessionOutputs:
    def __init__(self, state: SessionState, config: Config, store: CloudStore,
                 slam: RobotSlam, transport: Callable[[], dict[str, int]]) -> None:
        """``transport``: the session's transport counts as they are now (for the summary)."""
        self.state = state
        self.config = config
        self.store = store
        self.slam = slam
        self._transport = transport
        # Each stored keyframe's cloud, made as it arrives (keyframe_uploads.py): the end
        # only places and fuses them.
        self.clouds = KeyframeClouds(state.hello.camera, config.map)

    @property
    def robot_id(self) -> str:
        return self.state.robot_id

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Final pose of every keyframe (after local BA), by frame index."""
        if self.state.hello.offload_at == ROBOT_TRACKS:
            return dict(self.state.robot_keyframe_poses)
        return {kf.frame_index: kf.T_world_camera for kf in self.state.tracking.map.keyframes}

    def trajectory(self) -> np.ndarray:
        """Every frame's final pose (N x 4 x 4): relative to its reference keyframe, so loop
        and bundle-adjustment corrections reach every frame; as sent at point 6."""
        rows = self.state.rows
        online = np.array([r.T_world_camera for r in rows]).reshape(-1, 4, 4)
        if self.state.hello.offload_at == ROBOT_TRACKS:
            return online
        return self.state.tracking.final_poses([r.reference_keyframe for r in rows],
                                               [r.T_reference_camera for r in rows], online)

    def finish(self, camera: dict[str, Any] | None = None) -> FinishedMap:
        """Write the trajectory, keyframes and dense map; return the map for the merge.
        ``camera``: a live source's counts (the robot's end message), for the summary."""
        st = self.state
        out_dir = self.store.robot_dir(self.robot_id)
        rows = st.rows
        timestamps = np.array([r.timestamp for r in rows])
        kf_poses = self.keyframe_poses()
        kf_index = sorted(kf_poses)
        time_of = {r.index: r.timestamp for r in rows}

        mapped: list[np.ndarray] = []  # the poses of the keyframes with images

        def keyframes():
            for i in kf_index:
                cloud = self.clouds.get(i)
                if cloud is None:  # not prepared as it came (a restored session's)
                    upload = self._stored_upload(i)
                    if upload is None:
                        continue
                    cloud = self.clouds.add(i, upload.rgb, upload.depth_raw, upload.stride)
                mapped.append(kf_poses[i])
                yield (*cloud, kf_poses[i])

        scans: list = []
        points, colors = fuse_clouds(keyframes(), self.config.map, scans)
        grid = occupancy_grid(scans, np.array(mapped).reshape(-1, 4, 4), self.config.grid,
                              mounting_up(np.eye(4), st.hello.camera))
        write_robot_files(out_dir, self.robot_id, st.hello.source, timestamps, self.trajectory(),
                          np.array([time_of.get(i, np.nan) for i in kf_index]),
                          np.array([kf_poses[i] for i in kf_index]).reshape(-1, 4, 4),
                          points, colors,
                          np.array([r.T_world_camera for r in rows]).reshape(-1, 4, 4),
                          np.array([r.tracked for r in rows], bool), grid)
        summary = self.summary(len(points), camera)
        write_robot_summary(out_dir, summary)
        log.info("robot %s finished: %d frames, %d keyframes, %d map points", self.robot_id,
                 len(rows), len(kf_index), len(points))
        return FinishedMap(self.robot_id, points, colors, self.track(timestamps), summary)

    def finished_map(self) -> FinishedMap:
        """A finished session's map for the merge, as its worker wrote it (robot.json),
        without writing anything: another worker's robot, read from the store."""
        rows = self.state.rows
        written = read_robot_summary(self.store.robot_dir(self.robot_id))
        summary = written if written is not None else self.summary(0)
        return FinishedMap(self.robot_id, np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                           self.track(np.array([r.timestamp for r in rows])), summary)

    def track(self, timestamps: np.ndarray) -> RobotTrack:
        """What the global map needs of this robot; keyframe images from the store."""
        rows = self.state.rows
        camera = self.state.hello.camera

        def keyframe_image(index: int) -> tuple[np.ndarray, np.ndarray, int] | None:
            upload = self._stored_upload(index)
            if upload is None:
                return None
            return upload.rgb, camera.depth_to_metres(upload.depth_raw), upload.stride

        return RobotTrack(self.robot_id, camera, timestamps, self.trajectory(),
                          self._merger_references(), [r.T_reference_camera for r in rows],
                          keyframe_image)

    def _stored_upload(self, index: int) -> KeyframeUpload | None:
        """The keyframe's stored upload; None where there is none (the robot could not upload
        it: a live camera's, gone) or it cannot be read (damaged on disk: said, and the map
        is made without its images, never the robot's end held up)."""
        if not self.store.has_keyframe(self.robot_id, index):
            return None
        try:
            _, upload = decode_keyframe(self.store.keyframe(self.robot_id, index))
        except (WireError, CheckpointError) as exc:
            reason = exc.reason if isinstance(exc, CheckpointError) else str(exc)
            log.error("robot %s: stored keyframe %d cannot be read, so its images are left "
                      "out of the map: %s: %s", self.robot_id, index,
                      self.store.keyframe_file(self.robot_id, index), reason)
            return None
        return upload

    def _merger_references(self) -> np.ndarray:
        """Each frame's reference keyframe as the merger numbers keyframes (-1: none). A
        robot that tracks itself names its own ids: those the merger lacks (a keyframe lost
        on the link) become -1, and such a frame is moved with its robot's map frame."""
        references = np.array([r.reference_keyframe for r in self.state.rows], np.int64)
        if self.state.hello.offload_at != ROBOT_TRACKS:
            return references
        ids = np.asarray(self.state.robot_keyframe_ids, np.int64)
        position = np.searchsorted(ids, references)
        known = (position < len(ids)) & (ids[np.minimum(position, len(ids) - 1)] == references) \
            if len(ids) else np.zeros(len(references), bool)
        return np.where(known, position, -1)

    def summary(self, map_points: int, camera: dict[str, Any] | None = None
                ) -> dict[str, Any]:
        """The robot's entry of summary.json; ``camera``: a live source's counts."""
        st = self.state
        tracking = st.tracking
        kf_index = self.keyframe_poses()
        frames = len(st.rows)
        span_s = (st.last_frame_time or 0.0) - (st.first_frame_time or 0.0)
        cloud = CloudCounts(
            st.hello.offload_at, tuple(st.cloud_ms), tuple(st.latency_ms), self._transport(),
            camera, sum(not self.store.has_keyframe(self.robot_id, i) for i in kf_index))
        return RobotSummary(
            self.robot_id, st.hello.source, frames, len(kf_index),
            int(sum(not r.tracked for r in st.rows)), tracking.loss_events,
            tracking.repeated_frames, tracking.resets, map_points, self.slam.summary(),
            {k: 1000.0 * v / max(frames, 1) for k, v in st.stage_seconds.items()},
            frames / span_s if span_s > 0 else None, cloud=cloud).to_dict()
