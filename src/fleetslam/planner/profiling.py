"""Measuring a profile (planner/profile.py): the whole pipeline run on real frames, each
stage timed and the state at every split point encoded as the wire would. It runs the
back-end, so it needs the cloud's libraries; a robot can plan from a saved profile.
"""

from __future__ import annotations

import platform
from typing import Any, Callable

import numpy as np

from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.config import Config
from fleetslam.datasets.source import RecordedSource
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.planner.profile import Profile
from fleetslam.planner.robot_profiling import run_timed, timed_summary
from fleetslam.wire.frames import encode_frame_message
from fleetslam.wire.messages import KeyframeUpload, encode_keyframe


def measure_profile(sequence: RecordedSource, source: str, config: Config, frames: int,
                    progress: Callable[[int], None] | None = None) -> Profile:
    """Run the whole pipeline on the first ``frames`` frames, timing each stage and encoding
    the state at every split point (and each keyframe's upload) as the wire would."""
    pipeline = RobotSlam.new(config, sequence.camera)
    n = min(frames, len(sequence))
    if n < 2:
        raise ValueError(f"{source}: a profile needs at least 2 frames, the source has {n}")
    stage_s: list[list[float]] = [[] for _ in pipeline.stages]
    sizes: list[list[int]] = [[] for _ in range(len(pipeline.stages) + 1)]
    keyframe_sizes: list[int] = []
    keypoints: list[int] = []
    camera, wire = sequence.camera, config.wire
    for i in range(n):
        frame = sequence[i]
        state: Any = CapturedFrame(frame.index, frame.timestamp, frame.rgb, frame.depth_m)
        sizes[0].append(len(encode_frame_message(state, 0, "profile", i, camera, wire)))
        state = run_timed(pipeline.stages, pipeline.sides, state, stage_s, sizes, camera,
                          wire, i)
        keypoints.append(len(state.posed.matched.features.keypoints))
        if state.is_keyframe:
            upload = KeyframeUpload.from_frame(frame.index, frame.timestamp, frame.rgb,
                                               frame.depth_raw, config.map.pixel_stride)
            keyframe_sizes.append(len(encode_keyframe("profile", i, upload, wire)))
        if progress is not None:
            progress(i + 1)
    return Profile(
        source=source, label="measured", frames=n, stages=pipeline.stage_names,
        **timed_summary(stage_s, sizes),
        keyframe_bytes=float(np.mean(keyframe_sizes)) if keyframe_sizes else 0.0,
        keyframe_fraction=len(keyframe_sizes) / n, keypoints_mean=float(np.mean(keypoints)),
        host=f"{platform.machine()} {platform.processor() or ''}".strip())
