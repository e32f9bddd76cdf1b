"""One robot's SLAM as one object, ORB-SLAM's ``System`` for a robot: track a frame from
wherever the robot stopped (its offloading point), finish, and read its keyframes and poses.

    slam = RobotSlam.new(config, camera)
    for frame in frames:
        out = slam.track(frame)          # a CapturedFrame: every stage, as in one process
    slam.finish()                        # the last local BA and loop queries land

A cloud session tracks what its robot sent at point k (``slam.track(sent, at=k)``, the
stages from k on) over the same two states, so every process computes the same poses
(tests/test_split.py). The states are the front end's (``FrontEndState``, ORB extraction)
and the back-end's (``BackEndState``, the tracking map); a checkpoint restores both.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fleetslam.backend.back_end import CloudBackEnd
from fleetslam.backend.state import BackEndState
from fleetslam.backend.workers import LocalMappingPool
from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.pipeline.front_end import FrontEndState, front_end_stages
from fleetslam.pipeline.split import (CLOUD_TRACKS, FRONT_END_LENGTH, Sides, Stage, StageTimer,
                                      run_stages)
from fleetslam.pipeline.states import TrackedFrame


class RobotSlam:
    """``front_end`` None: made by the first frame that needs it (a cloud session whose
    robot runs the front end never holds one); ``state``: a restored back-end state;
    ``workers``: the cloud's worker processes for local BA and loop queries (None: all in
    line, as on a robot)."""

    def __init__(self, config: Config, camera: Camera, workers: LocalMappingPool | None = None,
                 front_end: FrontEndState | None = None,
                 state: BackEndState | None = None) -> None:
        self.config, self.camera = config, camera
        self.front_end = front_end
        self.back_end = CloudBackEnd(config, camera, state, workers)
        self.stages: list[Stage] = [*front_end_stages(), *self.back_end.stages]
        self.sides = Sides(front_end, self.back_end.state)
        # Per stage, every frame's time (a caller timing one frame passes its own).
        self.timer = StageTimer()

    @staticmethod
    def new(config: Config, camera: Camera,
            workers: LocalMappingPool | None = None) -> RobotSlam:
        """A robot's SLAM before its first frame, front end included."""
        return RobotSlam(config, camera, workers, FrontEndState(config, camera))

    @property
    def state(self) -> BackEndState:
        """The back-end's state: the tracking map, loops, counts."""
        return self.back_end.state

    @property
    def stage_names(self) -> list[str]:
        return [s.name for s in self.stages]

    def split(self, k: int) -> tuple[list[Stage], list[Stage]]:
        """(robot stages, cloud stages) for offloading point ``k`` in 0..len(stages)."""
        if not 0 <= k <= len(self.stages):
            raise ValueError(f"offloading point {k} outside 0..{len(self.stages)}")
        return self.stages[:k], self.stages[k:]

    def track(self, sent: Any, at: int = 0, timer: StageTimer | None = None) -> TrackedFrame:
        """The frame's pose from what the robot sent at offloading point ``at`` (at 0 a
        CapturedFrame: every stage). What workers answered meanwhile lands first."""
        if at not in CLOUD_TRACKS:
            raise ValueError(f"the cloud tracks frames sent at points "
                             f"{', '.join(map(str, CLOUD_TRACKS))}, not {at}")
        if self.front_end is None and at < FRONT_END_LENGTH:
            self.front_end = self.sides.edge = FrontEndState(self.config, self.camera)
        self.back_end.poll()
        return run_stages(self.stages[at:], sent, self.sides,
                          self.timer if timer is None else timer)

    def finish(self) -> None:
        """The last keyframes' loop queries and local BA belong in the final map."""
        self.back_end.finish()

    def close(self) -> None:
        """The session ends (finished or not): what the workers keep of it goes."""
        self.back_end.close()

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Every keyframe's current pose, by frame index."""
        return {kf.frame_index: kf.T_world_camera for kf in self.state.map.keyframes}

    def summary(self) -> dict[str, Any]:
        """Loop closing and local mapping counts and times, for summary.json."""
        return self.back_end.summary()
