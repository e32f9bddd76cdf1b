"""The keyframes a worker sends the merger on another worker
(``fleet/cloud/keyframes/<robot>``): a keyframe's summary, its robot's camera and that
robot's current keyframe poses, as data in the data-tree format (never a pickle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetslam.camera import Camera
from fleetslam.pipeline.states import FeatureFrame
from fleetslam.wire import data_tree
from fleetslam.wire.envelope import MAX_PAYLOAD_BYTES


@dataclass
class KeyframeSummary:
    """What the merger learns of one keyframe: its features and where its robot put it."""

    robot: str
    keyframe: int  # id in the robot's map (0, 1, ... in insertion order)
    frame_index: int
    timestamp: float
    features: FeatureFrame
    T_map_keyframe: np.ndarray  # 4 x 4, the robot's map frame


CLASSES = data_tree.classes_of(Camera, KeyframeSummary, FeatureFrame)


def encode_merger_keyframe(camera: Camera, summary: KeyframeSummary, poses: np.ndarray,
                           localising: bool = False) -> bytes:
    """A keyframe for the merger on another worker (``fleet/cloud/keyframes/<robot>``);
    ``localising``: its robot localises only (it never moves nor extends the loaded map)."""
    return data_tree.dumps({"camera": camera, "summary": summary,
                            "poses": np.asarray(poses, np.float64),
                            "localising": localising}, CLASSES)


def decode_merger_keyframe(data: bytes, robot: str
                           ) -> tuple[Camera, KeyframeSummary, np.ndarray, bool]:
    """What :func:`encode_merger_keyframe` wrote, for ``robot``; ValueError saying what is
    wrong."""
    where = f"keyframe summary of robot {robot}"
    # A message: no bigger than any payload may be (wire/envelope.py).
    tree = data_tree.loads(data, where, CLASSES, MAX_PAYLOAD_BYTES)
    if not isinstance(tree, dict) or not isinstance(tree.get("camera"), Camera) \
            or not isinstance(tree.get("summary"), KeyframeSummary) \
            or not isinstance(tree.get("poses"), np.ndarray):
        raise ValueError(f"{where}: not a camera, a keyframe summary and poses")
    summary, poses = tree["summary"], tree["poses"]
    if summary.robot != robot or poses.ndim != 3 or poses.shape[1:] != (4, 4) \
            or not 0 <= summary.keyframe < len(poses):
        raise ValueError(f"{where}: robot {summary.robot!r}, keyframe {summary.keyframe} of "
                         f"poses {poses.shape}")
    localising = tree.get("localising", False)
    if not isinstance(localising, bool):
        raise ValueError(f"{where}: localising is not true or false")
    return tree["camera"], summary, poses, localising
