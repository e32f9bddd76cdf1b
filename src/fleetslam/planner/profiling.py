"""Measuring a profile (planner/profile.py): the whole pipeline run on real frames, each
stage timed and the state at every split point encoded as the wire would. It runs the
back-end, so it needs the cloud's libraries; a robot can plan from a saved profile.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.config import Config
from fleetslam.datasets.source import RecordedSource
from fleetslam.planner.profile import Profile
from fleetslam.planner.robot_profiling import ProfileTimer
from fleetslam.wire.messages import KeyframeUpload, encode_keyframe


def measure_profile(sequence: RecordedSource, source: str, config: Config, frames: int,
                    progress: Callable[[int], None] | None = None) -> Profile:
    """Run the whole pipeline on the first ``frames`` frames, timing each stage and encoding
    the state at every split point (and each keyframe's upload) as the wire would."""
    pipeline = RobotSlam.new(config, sequence.camera)
    timer = ProfileTimer(pipeline.stages, pipeline.sides, sequence, source, frames, config.wire)
    keyframe_sizes: list[int] = []
    keypoints: list[int] = []
    for i in range(timer.frames):
        frame = sequence[i]
        state = timer.run(frame, i)
        keypoints.append(len(state.posed.matched.features.keypoints))
        if state.is_keyframe:
            upload = KeyframeUpload.from_frame(frame.index, frame.timestamp, frame.rgb,
                                               frame.depth_raw, config.map.pixel_stride)
            keyframe_sizes.append(len(encode_keyframe("profile", i, upload, config.wire)))
        if progress is not None:
            progress(i + 1)
    return Profile(
        source=source, label="measured", stages=pipeline.stage_names, **timer.summary(),
        keyframe_bytes=float(np.mean(keyframe_sizes)) if keyframe_sizes else 0.0,
        keyframe_fraction=len(keyframe_sizes) / timer.frames,
        keypoints_mean=float(np.mean(keypoints)))
