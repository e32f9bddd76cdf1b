"""What a robot's cloud session must keep across a cloud restart or a takeover by another
worker, and its checkpoint: the session as data (wire/data_tree.py), made only of the
classes listed here.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from fleetslam import config
from fleetslam.backend.local_map import Keyframe, LocalMap
from fleetslam.backend.place_recognition import KeyframeDatabase
from fleetslam.backend.pose_graph import PoseEdge
from fleetslam.backend.state import BackEndState, LoopClosingState, LoopDetection
from fleetslam.backend.vocabulary import BowDatabase
from fleetslam.camera import Camera
from fleetslam.pipeline.front_end import FrontEndState
from fleetslam.pipeline.states import FeatureFrame
from fleetslam.transport.protocol import Hello
from fleetslam.wire import data_tree
from fleetslam.wire.merger_keyframes import KeyframeSummary


@dataclass
class TrajectoryRow:
    index: int
    timestamp: float
    T_world_camera: np.ndarray
    tracked: bool
    is_keyframe: bool
    # Reference keyframe (-1: none) and the pose relative to it (see BackEndState.final_poses).
    reference_keyframe: int = -1
    T_reference_camera: np.ndarray | None = None


@dataclass
class SessionState:
    """Everything a session must keep across a cloud restart or a takeover by another
    worker (checkpointed at keyframes and at the end: wire/data_tree.py)."""

    robot_id: str
    hello: Hello
    tracking: BackEndState
    # The front end's state, when the robot offloads before its stages end (points 0-2).
    front_end: FrontEndState | None = None
    last_seq: int = -1
    last_index: int = -1
    rows: list[TrajectoryRow] = field(default_factory=list)
    # Keyframe poses reported by a robot that tracks itself (offloading point 6), by frame
    # index: with each keyframe's features, and at its end.
    robot_keyframe_poses: dict[int, np.ndarray] = field(default_factory=dict)
    # The keyframes with features such a robot sent, numbered 0, 1, ... as the merger takes
    # them (one lost on the link leaves no gap), and each one's id in the robot's own map.
    robot_keyframes: list[KeyframeSummary] = field(default_factory=list)
    robot_keyframe_ids: list[int] = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)
    stage_seconds: dict[str, float] = field(default_factory=dict)
    cloud_ms: list[float] = field(default_factory=list)
    latency_ms: list[float] = field(default_factory=list)
    first_frame_time: float | None = None
    last_frame_time: float | None = None
    # The robot ended its stream and the cloud wrote its outputs: a worker restoring the
    # session (a restart, a failover, the merge) has its finished map without the robot.
    ended: bool = False


_CONFIGS = [c for c in vars(config).values()
            if isinstance(c, type) and dataclasses.is_dataclass(c)
            and c.__module__ == config.__name__]
# Every class a session is made of; checkpoints written before the back-end's redesign name
# its two states by their old names.
CHECKPOINT_CLASSES = data_tree.classes_of(
    SessionState, TrajectoryRow, Hello, Camera, BackEndState, FrontEndState, LocalMap,
    Keyframe, FeatureFrame, KeyframeSummary, KeyframeDatabase, LoopClosingState,
    LoopDetection, PoseEdge, BowDatabase, *_CONFIGS,
    aliases={"CloudSession": BackEndState, "EdgeSession": FrontEndState})


def capture(state: SessionState) -> data_tree.Capture:
    """The session as it is now (quick: the file's bytes are made later, by
    ``Capture.to_bytes`` on the checkpoint writer's thread)."""
    return data_tree.capture(state, CHECKPOINT_CLASSES)


def load(data: bytes, where: str, max_bytes: int) -> SessionState:
    """A checkpoint's session (its shape is checked by checkpoint_shape.py); a
    CheckpointError naming ``where`` and what is wrong if it is not one. ``max_bytes``: the
    most the file and all it holds may take (``transport.max_checkpoint_bytes``)."""
    state = data_tree.loads(data, where, CHECKPOINT_CLASSES, max_bytes)
    if not isinstance(state, SessionState):
        raise data_tree.CheckpointError(where, f"holds a {type(state).__name__}, not a "
                                               f"robot's session")
    return state
