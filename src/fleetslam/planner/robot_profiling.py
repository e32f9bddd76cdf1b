"""Measuring the robot's side of a profile where the robot runs, with the base install
(numpy, OpenCV, zstd): the front end's stages timed on real frames, the frame message at
every point up to them encoded as the wire would, and a keyframe upload's bytes. Nothing of
the back-end runs (it needs the cloud extra), so the cloud's stage times, the later points'
bytes and how often keyframes come stay the cloud's profile's (profile.py:
``Profile.with_robot_side``).
"""

from __future__ import annotations

import platform
from typing import Any, Callable

import numpy as np

from fleetslam.config import Config, WireConfig
from fleetslam.datasets.source import Frame, RecordedSource
from fleetslam.pipeline.front_end import FrontEndState, front_end_stages
from fleetslam.pipeline.split import Sides, StageTimer, run_stages
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.planner.profile import RobotSideProfile
from fleetslam.wire.frames import encode_frame_message
from fleetslam.wire.messages import KeyframeUpload, encode_keyframe


class ProfileTimer:
    """A profile's measurement of its stages, frame by frame: each stage's seconds, and the
    frame message at every point (0 and after each stage) encoded as the wire would."""

    def __init__(self, stages: list, sides: Sides, sequence: RecordedSource, source: str,
                 frames: int, wire: WireConfig) -> None:
        self.stages, self.sides, self.camera, self.wire = stages, sides, sequence.camera, wire
        self.frames = min(frames, len(sequence))
        if self.frames < 2:
            raise ValueError(f"{source}: a profile needs at least 2 frames, the source has "
                             f"{self.frames}")
        self.timer = StageTimer()  # the pipeline's own, per stage name
        self.sizes: list[list[int]] = [[] for _ in range(len(stages) + 1)]

    def run(self, frame: Frame, index: int) -> Any:
        """Frame ``index`` through the stages, timed and encoded at every point; the state
        after the last stage."""
        state: Any = CapturedFrame(frame.index, frame.timestamp, frame.rgb, frame.depth_m)
        self.sizes[0].append(self._bytes(state, 0, index))
        for k, stage in enumerate(self.stages):  # one at a time: a message between each
            state = run_stages([stage], state, self.sides, self.timer)
            self.sizes[k + 1].append(self._bytes(state, k + 1, index))
        return state

    def _bytes(self, state: Any, point: int, index: int) -> int:
        return len(encode_frame_message(state, point, "profile", index, self.camera,
                                        self.wire))

    def summary(self) -> dict[str, Any]:
        """Each stage's median and p95 ms, each point's mean bytes, the frames and the host,
        as a profile has them; the first frame's times are left out (it warms OpenCV up and
        only builds the map)."""
        times = [np.array(self.timer.seconds[stage.name][1:]) * 1000 for stage in self.stages]
        return {"frames": self.frames,
                "stage_ms": [float(np.median(t)) for t in times],
                "stage_ms_p95": [float(np.percentile(t, 95)) for t in times],
                "frame_bytes": [float(np.mean(s)) for s in self.sizes],
                "host": f"{platform.machine()} {platform.processor() or ''}".strip()}


def measure_robot_side(sequence: RecordedSource, source: str, config: Config, frames: int,
                       progress: Callable[[int], None] | None = None) -> RobotSideProfile:
    """Run the robot's stages on the first ``frames`` frames, timing each, and encode the
    state at every point up to them and each frame's keyframe upload as the wire would."""
    stages = front_end_stages()
    timer = ProfileTimer(stages, Sides(edge=FrontEndState(config, sequence.camera)), sequence,
                         source, frames, config.wire)
    upload_sizes: list[int] = []
    keypoints: list[int] = []
    for i in range(timer.frames):
        frame = sequence[i]
        keypoints.append(len(timer.run(frame, i).keypoints))
        # Which frames become keyframes is the back-end's to say; an upload is coded the
        # same whichever frame it is, so every frame's counts.
        upload = KeyframeUpload.from_frame(frame.index, frame.timestamp, frame.rgb,
                                           frame.depth_raw, config.map.pixel_stride)
        upload_sizes.append(len(encode_keyframe("profile", i, upload, config.wire)))
        if progress is not None:
            progress(i + 1)
    return RobotSideProfile(
        source=source, stages=[stage.name for stage in stages], **timer.summary(),
        keyframe_bytes=float(np.mean(upload_sizes)), keypoints_mean=float(np.mean(keypoints)))
