"""What every source of RGB-D frames gives the robot and the in-process runs.

Two kinds:
- a recorded source (``RecordedSource``: a TUM / 7-Scenes folder, a ROS 1 or ROS 2 bag)
  is played frame by frame, with random access by index (an older keyframe's images are
  read again for an upload or the dense map) and, where the recording has it, ground truth
  for evaluation only;
- a live source (``datasets.live.LiveSource``: a RealSense, ROS 2 topics, a recording
  replayed on the camera's clock) delivers frames whether or not the robot keeps up; the
  robot takes the newest one and counts those it skipped.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from fleetslam.camera import Camera


@dataclass
class Frame:
    """One RGB-D frame: colour and depth registered to the same pixel grid."""

    index: int
    timestamp: float
    rgb: np.ndarray  # H x W x 3 uint8, RGB order
    depth_raw: np.ndarray  # H x W uint16 sensor units (camera.depth_scale per metre)
    depth_m: np.ndarray  # H x W float32 metres, 0 = no measurement


@runtime_checkable
class RecordedSource(Protocol):
    """A recording played frame by frame (``datasets.tum.RgbdSequence``,
    ``datasets.bag.BagSequence``)."""

    folder: Path  # the recording on disk: a sequence folder, a bag file or a bag folder
    camera: Camera
    camera_source: str  # where the camera model came from, for tables and logs
    timestamps: np.ndarray  # per played frame, seconds, increasing
    first: int  # the recording's index of the first played frame

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Frame: ...

    @property
    def gt_poses(self) -> np.ndarray | None:
        """Ground-truth camera-to-world pose per frame (NaN where none), for evaluation."""
        ...

    @property
    def has_ground_truth(self) -> bool: ...
