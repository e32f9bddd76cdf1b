"""What a robot's cloud session must keep across a cloud restart or a takeover by another
worker, and its checkpoint: the session as data (wire/data_tree.py), made only of the
classes listed here.
"""

from __future__ import annotations

import copy
import dataclasses
import threading
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

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
from fleetslam.cloud.session import array_log
from fleetslam.cloud.session.array_log import ArrayBase, ArrayPatch, Logged, LoggedArrays
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


@dataclass
class RowBlock:
    """``ROW_BLOCK`` consecutive trajectory rows, all tracked already: they never change
    again, so a checkpoint keeps them as a chunk written once (only in checkpoints; a loaded
    session's rows are rows again)."""

    rows: list[TrajectoryRow]


# Rows per chunk of the trajectory: a long run's checkpoint names a few hundred chunks
# instead of holding thousands of small arrays.
ROW_BLOCK = 256
# Checkpoints a robot's folder keeps at most: the current one and the one before
# (cloud/coordination/fenced_store.py keeps both, for a reader that read the pointer just
# before it moved; store.py's own layout keeps one). A chunk neither names can go.
KEPT_CHECKPOINTS = 2


@dataclass
class ArrayBlock:
    """Rows [start, start + len(rows)) of an array that only grows at its end: a chunk of the
    place database in checkpoints written before its arrays were logged (array_log.py); read
    only."""

    start: int
    rows: np.ndarray


@dataclass
class AppendOnly:
    """Such an array in those checkpoints: its full blocks (chunks) and the rows after them."""

    blocks: list[ArrayBlock]
    tail: np.ndarray


# The arrays of a session kept as logs (array_log.py) rather than whole in every checkpoint:
# the map's landmarks and observations, and the place database's, by class.
LOGGED_ARRAYS: dict[type, tuple[str, ...]] = {
    LocalMap: ("xyz", "descriptors", "weight", "last_keyframe", "octave", "distance", "alive",
               "first_keyframe", "n_visible", "n_found", "obs_keyframe", "obs_landmark",
               "obs_uv", "obs_depth", "obs_octave"),
    KeyframeDatabase: ("descriptors", "owner"),
    BowDatabase: ("words", "weights", "owner"),
}
# Read from older checkpoints: the place database's arrays as blocks.
_APPEND_ONLY = ("descriptors", "owner")


def _content_name(value: Any) -> str | None:
    """A chunk's name from its content (the same content, the same name: a chunk file any
    worker writes is the one every other would write)."""
    if type(value) is FeatureFrame:
        f = value
        return f"f{f.index:07d}-" + array_log.content_digest(
            np.float64(f.timestamp).tobytes(),
            *(np.ascontiguousarray(a).tobytes() for a in (f.keypoints, f.descriptors, f.depth,
                                                          f.uv)))
    if type(value) is RowBlock:
        rows = value.rows
        poses = np.stack([r.T_world_camera for r in rows])
        refs = np.stack([np.full((4, 4), np.nan) if r.T_reference_camera is None
                         else r.T_reference_camera for r in rows])
        table = np.array([(r.index, r.timestamp, r.tracked, r.is_keyframe,
                           r.reference_keyframe) for r in rows], np.float64)
        return f"r{rows[0].index:07d}-" + array_log.content_digest(
            table.tobytes(), poses.tobytes(), refs.tobytes())
    if type(value) is ArrayBase or type(value) is ArrayPatch:
        return array_log.chunk_name(value)
    if type(value) is np.ndarray:  # a keyframe's landmark table
        return f"k{len(value):07d}-" + array_log.content_digest(*array_log.array_parts(value))
    if type(value) is ArrayBlock:
        rows = np.ascontiguousarray(value.rows)
        return f"a{value.start:07d}-" + array_log.content_digest(*array_log.array_parts(rows))
    return None


class Chunks:
    """A session's chunker (wire/data_tree.Chunker): each keyframe's features and observed
    landmarks and each full block of its trajectory are chunks, named once by their content
    and written once; the map's and the place database's arrays are logs of chunks
    (array_log.py). A checkpoint's cost stays about that of what changed since the last
    (the keyframe poses, which do change, stay in every checkpoint)."""

    def __init__(self, exists: Callable[[str], bool],
                 remove: Callable[[Iterable[str]], None] = lambda names: None) -> None:
        """``exists``: whether the store holds a chunk (asked once per unknown name);
        ``remove``: deletes chunks no checkpoint will name again (the writer's thread)."""
        self._exists = exists
        self._remove = remove
        self._names: dict[int, tuple[Any, str]] = {}  # id(value) -> (value, its name)
        self._seen: dict[int, tuple[Any, str]] = {}
        self._written: set[str] = set()
        self._blocks: dict[int, RowBlock] = {}  # first row's position -> its block
        # Ids of the keyframes' features and landmark tables now (neither changes in place:
        # a loop's landmark merge gives each keyframe a new table).
        self._keyframe_parts: set[int] = set()
        self._logs: dict[str, array_log.ArrayLog] = {}  # "map", "places" -> its log
        # What the newest checkpoints written name (the store's kept ones), newest last.
        self._kept: list[frozenset[str]] = []
        self._lock = threading.Lock()

    def name_of(self, value: Any) -> str | None:
        kind = type(value)
        if kind is ArrayBase or kind is ArrayPatch:
            for log in self._logs.values():
                if (name := log.name_of(value)) is not None:
                    return name
            return _content_name(value)
        if kind is not RowBlock and id(value) not in self._keyframe_parts:
            return None  # the last frame's features change with every frame
        known = self._names.get(id(value))
        name = known[1] if known is not None and known[0] is value else _content_name(value)
        self._seen[id(value)] = (value, name)
        return name

    def written(self, name: str) -> bool:
        with self._lock:
            if name in self._written:
                return True
        if self._exists(name):
            with self._lock:
                self._written.add(name)
            return True
        return False

    def confirm(self, blob: data_tree.Capture, ended: bool = False) -> None:
        """``blob`` is durably written with its chunks: logs whose new base is among them
        delete the chains it replaced. ``ended`` (the robot has finished, no checkpoint but
        this one may follow): every chunk neither this checkpoint nor the one before names
        goes too (the chains a log would delete with its next base, culled keyframes'
        parts), as the folder keeps no other checkpoint (KEPT_CHECKPOINTS)."""
        names = set(blob.chunks)
        retired = [n for log in list(self._logs.values()) for n in log.written(names)]
        self._kept = (self._kept + [blob.named])[-KEPT_CHECKPOINTS:]
        with self._lock:
            self._written.update(names)
            self._written.difference_update(retired)
            if ended:
                unnamed = self._written.difference(*self._kept)
                self._written -= unnamed
                retired += sorted(unnamed)
        if retired:
            self._remove(retired)

    def capture(self, state: SessionState) -> data_tree.Capture:
        view = copy.copy(state)  # shallow: only what is put in blocks or logs is replaced
        view.rows = self._blocked(state.rows)
        view.tracking = copy.copy(state.tracking)
        view.tracking.map = self._logged("map", state.tracking.map)
        view.tracking.places = self._logged("places", state.tracking.places)
        keyframes = state.tracking.map.keyframes
        self._keyframe_parts = {id(kf.features) for kf in keyframes} | \
            {id(kf.keypoint_landmark) for kf in keyframes} | \
            {id(kf.features) for kf in state.robot_keyframes}
        self._seen = {}
        try:
            return data_tree.capture(view, CHECKPOINT_CLASSES, self)
        finally:
            # Names of values no longer in the session (culled keyframes) are forgotten.
            self._names, self._seen = self._seen, {}

    def _logged(self, role: str, obj: Any) -> Any:
        names = LOGGED_ARRAYS.get(type(obj))
        if names is None:
            return obj
        log = self._logs.get(role)
        if log is None or log.names != names:
            log = self._logs[role] = array_log.ArrayLog(names)
        return log.logged(obj)

    def _blocked(self, rows: list[TrajectoryRow]) -> list[Any]:
        full = len(rows) // ROW_BLOCK * ROW_BLOCK
        out: list[Any] = []
        for start in range(0, full, ROW_BLOCK):
            block = self._blocks.get(start)
            if block is None or block.rows[0] is not rows[start] \
                    or block.rows[-1] is not rows[start + ROW_BLOCK - 1]:
                block = self._blocks[start] = RowBlock(rows[start:start + ROW_BLOCK])
            out.append(block)
        return out + rows[full:]


_CONFIGS = [c for c in vars(config).values()
            if isinstance(c, type) and dataclasses.is_dataclass(c)
            and c.__module__ == config.__name__]
# Every class a session is made of; checkpoints written before the back-end's redesign name
# its two states by their old names.
CHECKPOINT_CLASSES = data_tree.classes_of(
    SessionState, TrajectoryRow, Hello, Camera, BackEndState, FrontEndState, LocalMap,
    Keyframe, FeatureFrame, KeyframeSummary, KeyframeDatabase, LoopClosingState,
    LoopDetection, PoseEdge, BowDatabase, RowBlock, ArrayBlock, AppendOnly, ArrayBase,
    ArrayPatch, LoggedArrays, Logged, *_CONFIGS,
    aliases={"CloudSession": BackEndState, "EdgeSession": FrontEndState})


def capture(state: SessionState, chunks: Chunks | None = None) -> data_tree.Capture:
    """The session as it is now (quick: the file's bytes are made later, by
    ``Capture.to_bytes`` on the checkpoint writer's thread). With ``chunks``, the parts
    that never change are chunks (only those not yet written are captured)."""
    if chunks is not None:
        return chunks.capture(state)
    return data_tree.capture(state, CHECKPOINT_CLASSES)


# A chunk's bytes by name (where: the file it came from); CheckpointError if it is missing.
ReadChunk = Callable[[str, int], tuple[bytes, str]]
_CHUNK_TYPES = {"f": FeatureFrame, "r": RowBlock, "a": ArrayBlock, "b": ArrayBase,
                "p": ArrayPatch, "k": np.ndarray}


def load(data: bytes, where: str, max_bytes: int, read_chunk: ReadChunk | None = None
         ) -> SessionState:
    """A checkpoint's session (its shape is checked by checkpoint_shape.py); a
    CheckpointError naming ``where`` and what is wrong if it is not one. ``max_bytes``: the
    most the file and all it holds, its chunks too, may take
    (``transport.max_checkpoint_bytes``). ``read_chunk(name, limit)``: the chunks it names."""
    left = [max_bytes - len(data)]

    def load_chunk(name: str) -> Any:
        if read_chunk is None:
            raise data_tree.CheckpointError(where, f"names chunk {name}, and there are none")
        chunk, chunk_where = read_chunk(name, left[0])
        left[0] -= len(chunk)
        value = data_tree.loads(chunk, chunk_where, CHECKPOINT_CLASSES, max_bytes)
        try:
            same = type(value) is _CHUNK_TYPES.get(name[0]) and _content_name(value) == name
        except (AttributeError, TypeError, ValueError):  # parts of the wrong kind
            same = False
        if not same:
            raise data_tree.CheckpointError(chunk_where, "not the chunk its name says")
        return value

    state = data_tree.loads(data, where, CHECKPOINT_CLASSES, max_bytes, load_chunk)
    if not isinstance(state, SessionState):
        raise data_tree.CheckpointError(where, f"holds a {type(state).__name__}, not a "
                                               f"robot's session")
    if isinstance(state.rows, list):  # blocks of rows back to rows (shape checked later)
        state.rows = [r for item in state.rows
                      for r in (item.rows if isinstance(item, RowBlock)
                                and isinstance(item.rows, list) else [item])]
    tracking = getattr(state, "tracking", None)
    for role in ("map", "places"):
        if isinstance(logged := getattr(tracking, role, None), Logged):
            setattr(tracking, role, _unlogged(logged, where, max_bytes))
    places = getattr(tracking, "places", None)
    for name in _APPEND_ONLY:
        if isinstance(getattr(places, name, None), AppendOnly):
            setattr(places, name, _joined(getattr(places, name), where))
    return state


def _unlogged(logged: Logged, where: str, max_bytes: int) -> Any:
    """The object a Logged holds, its arrays restored from their log (CheckpointError if it
    is not one of the logged classes with exactly its logged arrays)."""
    obj = logged.rest
    names = LOGGED_ARRAYS.get(type(obj))
    arrays = array_log.restore(logged.arrays, where, max_bytes)
    if names is None or set(arrays) != set(names):
        raise data_tree.CheckpointError(where, f"damaged checkpoint (a logged "
                                               f"{type(obj).__name__} with arrays "
                                               f"{sorted(arrays)})")
    obj.__dict__.update(arrays)
    return obj


def _joined(array: AppendOnly, where: str) -> np.ndarray:
    """The array an AppendOnly holds, its blocks in place (CheckpointError if they are not
    consecutive arrays of one kind)."""
    parts = [b.rows for b in array.blocks if isinstance(b, ArrayBlock)] + [array.tail]
    starts = [b.start for b in array.blocks if isinstance(b, ArrayBlock)]
    if len(starts) != len(array.blocks) or not all(isinstance(p, np.ndarray) for p in parts) \
            or starts != [sum(len(p) for p in parts[:i]) for i in range(len(starts))] \
            or len({(p.dtype, p.shape[1:]) for p in parts}) != 1:
        raise data_tree.CheckpointError(where, "damaged checkpoint (an array in blocks that "
                                               "do not join)")
    return np.concatenate(parts)
