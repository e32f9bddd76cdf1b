"""Whether a decoded checkpoint is shaped like a robot's session, checked before any of it
is used: every field of every rebuilt object has its declared type (the dataclass's own
annotations), every array its dtype and shape, and every index points inside what it
indexes. A file that decodes yet is wrong (a field of another type, a pose of 3 x 3, a
landmark id past the map) is refused here, by a CheckpointError naming the file, instead of
failing later in the tracker with an AttributeError or IndexError.

The walk recurses once per level of the tree, whose depth wire/data_tree.py bounded.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from collections import Counter
from typing import Any

import numpy as np

from fleetslam.backend.local_map import Keyframe, LocalMap
from fleetslam.backend.place_recognition import KeyframeDatabase
from fleetslam.backend.pose_graph import PoseEdge
from fleetslam.backend.state import BackEndState, LoopDetection
from fleetslam.backend.vocabulary import BowDatabase
from fleetslam.camera import Camera
from fleetslam.cloud.session.session_state import SessionState, TrajectoryRow
from fleetslam.config import Config, check_config
from fleetslam.pipeline.states import FeatureFrame
from fleetslam.transport.protocol import Hello
from fleetslam.wire.data_tree import CheckpointError
from fleetslam.wire.merger_keyframes import KeyframeSummary

# An array's dtype kinds and shape; a letter names a length shared by the object's arrays.
Spec = tuple[str, tuple[int | str, ...]]
_POSE: Spec = ("f", (4, 4))
# Arrays whose every value must be finite (a NaN pose or landmark poisons every later pose).
_FINITE = {(TrajectoryRow, "T_world_camera"), (BackEndState, "T_last"),
           (BackEndState, "T_before_last"), (Keyframe, "T_world_camera"), (LocalMap, "xyz"),
           (KeyframeSummary, "T_map_keyframe")}
_ARRAYS: dict[type, dict[str, Spec]] = {
    TrajectoryRow: {"T_world_camera": _POSE, "T_reference_camera": _POSE},
    BackEndState: {"T_last": _POSE, "T_before_last": _POSE},
    LoopDetection: {"T_world_query": _POSE, "correction": _POSE},
    PoseEdge: {"T_a_b": _POSE},
    # The map's indices are signed (-1: none; numpy's bincount refuses uint64).
    Keyframe: {"T_world_camera": _POSE, "keypoint_landmark": ("i", ("n",))},
    KeyframeSummary: {"T_map_keyframe": _POSE},
    FeatureFrame: {"keypoints": ("f", ("n", 7)), "descriptors": ("u", ("n", 32)),
                   "depth": ("f", ("n",)), "uv": ("f", ("n", 2))},
    KeyframeDatabase: {"descriptors": ("u", ("D", 32)), "owner": ("iu", ("D",))},
    BowDatabase: {"words": ("iu", ("W",)), "weights": ("f", ("W",)), "owner": ("iu", ("W",))},
    LocalMap: {"xyz": ("f", ("N", 3)), "descriptors": ("u", ("N", 32)), "weight": ("f", ("N",)),
               "last_keyframe": ("i", ("N",)), "octave": ("i", ("N",)),
               "distance": ("f", ("N",)), "alive": ("b", ("N",)),
               "first_keyframe": ("i", ("N",)), "n_visible": ("i", ("N",)),
               "n_found": ("i", ("N",)), "obs_keyframe": ("i", ("M",)),
               "obs_landmark": ("i", ("M",)), "obs_uv": ("f", ("M", 2)),
               "obs_depth": ("f", ("M",)), "obs_octave": ("i", ("M",))},
}


class _Refused(Exception):
    """What is wrong, and where in the session (the walk adds the path)."""


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def check(state: Any, where: str) -> SessionState:
    """``state`` if it is a whole robot's session; CheckpointError naming ``where``."""
    try:
        _value(state, SessionState, "session")
        _indices(state)
        _hello(state)
    except _Refused as exc:
        raise CheckpointError(where, f"not a robot's session: {exc}") from None
    return state


def _value(v: Any, hint: Any, path: str) -> None:
    """Raise _Refused unless ``v`` is of type ``hint`` (annotations as the classes have them)."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        for option in args:
            try:
                return _value(v, option, path)
            except _Refused:
                continue
        raise _Refused(f"{path} is a {type(v).__name__}, not {hint}")
    if hint is type(None):
        if v is not None:
            raise _Refused(f"{path} is a {type(v).__name__}, not None")
    elif hint is bool or hint is int or hint is float:
        ok = {bool: (bool,), int: (int,), float: (int, float)}[hint]
        if not isinstance(v, ok) or (hint is not bool and isinstance(v, bool)):
            raise _Refused(f"{path} is a {type(v).__name__}, not a {hint.__name__}")
    elif hint in (str, bytes):
        if not isinstance(v, hint):
            raise _Refused(f"{path} is a {type(v).__name__}, not a {hint.__name__}")
    elif hint is np.ndarray:
        if not isinstance(v, np.ndarray):
            raise _Refused(f"{path} is a {type(v).__name__}, not an array")
    elif hint is Counter or origin is Counter:
        if not isinstance(v, Counter):
            raise _Refused(f"{path} is a {type(v).__name__}, not a Counter")
    elif origin is list or hint is list:
        if not isinstance(v, list):
            raise _Refused(f"{path} is a {type(v).__name__}, not a list")
        for i, x in enumerate(v):
            _value(x, args[0] if args else Any, f"{path}[{i}]")
    elif origin is dict or hint is dict:
        if not isinstance(v, dict):
            raise _Refused(f"{path} is a {type(v).__name__}, not a mapping")
        for k, x in v.items():
            _value(k, args[0] if args else Any, f"{path} key {k!r}")
            _value(x, args[1] if args else Any, f"{path}[{k!r}]")
    elif origin is tuple or hint is tuple:
        if not isinstance(v, tuple):
            raise _Refused(f"{path} is a {type(v).__name__}, not a tuple")
        if len(args) == 2 and args[1] is Ellipsis:
            args = (args[0],) * len(v)
        if args and len(args) != len(v):
            raise _Refused(f"{path} has {len(v)} items, not {len(args)}")
        for i, (x, a) in enumerate(zip(v, args)):
            _value(x, a, f"{path}[{i}]")
    elif isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if type(v) is not hint:
            raise _Refused(f"{path} is a {type(v).__name__}, not a {hint.__name__}")
        _object(v, path)
    elif isinstance(hint, type) and getattr(hint, "_is_protocol", False):
        # A place database: one of the rebuilt classes (the decoder made nothing else).
        if dataclasses.is_dataclass(v):
            _object(v, path)
    # Anything else (Any, Hashable, cv2.ORB, plain dict values): data the decoder made.


def _object(obj: Any, path: str) -> None:
    """A rebuilt object's fields: every declared one present (or defaulted), of its type; no
    attribute hiding a method; its arrays as _ARRAYS says."""
    cls = type(obj)
    attributes = vars(obj)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for name in attributes:
        if name not in fields and hasattr(cls, name):
            raise _Refused(f"{path}.{name} would hide {cls.__name__}.{name}")
    for name, f in fields.items():
        if name not in attributes:
            # A field newer than the checkpoint takes its default; one without is missing.
            if f.default is not dataclasses.MISSING:
                attributes[name] = f.default
            elif f.default_factory is not dataclasses.MISSING:
                attributes[name] = f.default_factory()
            else:
                raise _Refused(f"{path}.{name} is missing")
        _value(attributes[name], _hints(cls)[name], f"{path}.{name}")
    sizes: dict[str, int] = {}
    for name, (kinds, shape) in _ARRAYS.get(cls, {}).items():
        array = attributes[name]
        if array is None:
            continue  # a field that may be None was checked above
        if array.dtype.kind not in kinds or array.ndim != len(shape):
            raise _Refused(f"{path}.{name} is {array.dtype} {array.shape}, expected "
                           f"{shape}")
        for n, expected in zip(array.shape, shape):
            expected = sizes.setdefault(expected, n) if isinstance(expected, str) else expected
            if n != expected:
                raise _Refused(f"{path}.{name} has shape {array.shape}, expected {shape} "
                               f"(sizes {sizes})")
        if (cls, name) in _FINITE and not np.isfinite(array).all():
            raise _Refused(f"{path}.{name} is not finite")
    if cls is Camera:
        try:  # the checks of a hello's camera: positive focal lengths, a size, ...
            Camera.from_dict(obj.to_dict(), path)
        except ValueError as exc:
            raise _Refused(str(exc)) from None
    if cls is Config:
        try:  # the ranges a config file is held to (a local_map_scope "x" fails later)
            check_config(obj, path)
        except ValueError as exc:
            raise _Refused(str(exc)) from None


def _in_range(values: np.ndarray, low: int, high: int, what: str) -> None:
    if values.size and (values.min() < low or values.max() >= high):
        raise _Refused(f"{what} outside {low}..{high - 1}")


def _indices(state: SessionState) -> None:
    """Indices point inside what they index (the tracker and place recognition index with
    them unchecked): landmarks, keyframes (whose ids are their positions), database rows."""
    lmap = state.tracking.map
    n_landmarks = len(lmap.xyz)
    if [kf.id for kf in lmap.keyframes] != list(range(len(lmap.keyframes))):
        raise _Refused("the map's keyframe ids are not 0, 1, 2, ...")
    _in_range(lmap.obs_landmark, 0, n_landmarks, "map observations' landmarks")
    _in_range(lmap.obs_keyframe, 0, len(lmap.keyframes), "map observations' keyframes")
    for kf in lmap.keyframes:
        _in_range(kf.keypoint_landmark, -1, n_landmarks, f"keyframe {kf.id}'s landmarks")
    places = state.tracking.places
    owner, keys = getattr(places, "owner", None), getattr(places, "keys", None)
    if not isinstance(owner, np.ndarray) or owner.dtype.kind not in "iu" or owner.ndim != 1 \
            or not isinstance(keys, list):
        raise _Refused("the place database has no entries and owners")
    _in_range(owner, 0, len(keys), "place database owners")
    for index, T in state.robot_keyframe_poses.items():
        if T.shape != (4, 4):
            raise _Refused(f"robot keyframe pose {index} has shape {T.shape}")
    _robot_keyframes(state)


def _robot_keyframes(state: SessionState) -> None:
    """The keyframes a robot that tracks itself sent: numbered 0, 1, ... (the merger's
    order), its own, each with a pose, their ids in its map increasing."""
    kfs, ids = state.robot_keyframes, state.robot_keyframe_ids
    if [kf.keyframe for kf in kfs] != list(range(len(kfs))) or len(ids) != len(kfs):
        raise _Refused(f"robot keyframes numbered {[kf.keyframe for kf in kfs][:8]}... with "
                       f"{len(ids)} ids for {len(kfs)}")
    if any(b <= a for a, b in zip(ids, ids[1:])) or (ids and ids[0] < 0):
        raise _Refused("robot keyframe ids are not increasing")
    for kf in kfs:
        if kf.robot != state.robot_id or kf.frame_index not in state.robot_keyframe_poses:
            raise _Refused(f"robot keyframe {kf.keyframe} is robot {kf.robot!r}'s, frame "
                           f"{kf.frame_index} without a pose")


def _hello(state: SessionState) -> None:
    """The hello passes the checks a robot's hello passes on the wire."""
    try:
        Hello.parse(state.hello.message(None))
    except ValueError as exc:
        raise _Refused(f"hello: {exc}") from None
