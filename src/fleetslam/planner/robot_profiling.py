"""Measuring the robot's side of a profile where the robot runs, with the base install
(numpy, OpenCV, zstd): the front end's stages timed on real frames, the frame message at
every point up to them encoded as the wire would, and a keyframe upload's bytes. Nothing of
the back-end runs (it needs the cloud extra), so the cloud's stage times, the later points'
bytes and how often keyframes come stay the cloud's profile's (profile.py:
``Profile.with_robot_side``).
"""

from __future__ import annotations

import platform
import time
from typing import Any, Callable

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config, WireConfig
from fleetslam.datasets.source import RecordedSource
from fleetslam.pipeline.front_end import FrontEndState, front_end_stages
from fleetslam.pipeline.split import Sides
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.planner.profile import RobotSideProfile
from fleetslam.wire.frames import encode_frame_message
from fleetslam.wire.messages import KeyframeUpload, encode_keyframe


def run_timed(stages: list, sides: Sides, state: Any, stage_s: list[list[float]],
              sizes: list[list[int]], camera: Camera, wire: WireConfig, index: int) -> Any:
    """Frame ``index`` through ``stages``: each stage's seconds appended to ``stage_s[k]``,
    and the state after it, encoded as the wire would, to ``sizes[k + 1]``; the last state."""
    for k, stage in enumerate(stages):
        start = time.perf_counter()
        state = stage(state, sides.part(stage.side))
        stage_s[k].append(time.perf_counter() - start)
        sizes[k + 1].append(len(encode_frame_message(state, k + 1, "profile", index, camera,
                                                     wire)))
    return state


def timed_summary(stage_s: list[list[float]], sizes: list[list[int]]) -> dict[str, list[float]]:
    """Each stage's median and p95 ms and each point's mean bytes, as a profile has them;
    the first frame's times are left out (it warms OpenCV up and only builds the map)."""
    times = [np.array(s[1:]) * 1000 for s in stage_s]
    return {"stage_ms": [float(np.median(t)) for t in times],
            "stage_ms_p95": [float(np.percentile(t, 95)) for t in times],
            "frame_bytes": [float(np.mean(s)) for s in sizes]}


def measure_robot_side(sequence: RecordedSource, source: str, config: Config, frames: int,
                       progress: Callable[[int], None] | None = None) -> RobotSideProfile:
    """Run the robot's stages on the first ``frames`` frames, timing each, and encode the
    state at every point up to them and each frame's keyframe upload as the wire would."""
    stages = front_end_stages()
    sides = Sides(edge=FrontEndState(config, sequence.camera))
    n = min(frames, len(sequence))
    if n < 2:
        raise ValueError(f"{source}: a profile needs at least 2 frames, the source has {n}")
    stage_s: list[list[float]] = [[] for _ in stages]
    sizes: list[list[int]] = [[] for _ in range(len(stages) + 1)]
    upload_sizes: list[int] = []
    keypoints: list[int] = []
    camera, wire = sequence.camera, config.wire
    for i in range(n):
        frame = sequence[i]
        state: Any = CapturedFrame(frame.index, frame.timestamp, frame.rgb, frame.depth_m)
        sizes[0].append(len(encode_frame_message(state, 0, "profile", i, camera, wire)))
        state = run_timed(stages, sides, state, stage_s, sizes, camera, wire, i)
        keypoints.append(len(state.keypoints))
        # Which frames become keyframes is the back-end's to say; an upload is coded the
        # same whichever frame it is, so every frame's counts.
        upload = KeyframeUpload.from_frame(frame.index, frame.timestamp, frame.rgb,
                                           frame.depth_raw, config.map.pixel_stride)
        upload_sizes.append(len(encode_keyframe("profile", i, upload, wire)))
        if progress is not None:
            progress(i + 1)
    return RobotSideProfile(
        source=source, frames=n, stages=[stage.name for stage in stages],
        **timed_summary(stage_s, sizes), keyframe_bytes=float(np.mean(upload_sizes)),
        keypoints_mean=float(np.mean(keypoints)),
        host=f"{platform.machine()} {platform.processor() or ''}".strip())
