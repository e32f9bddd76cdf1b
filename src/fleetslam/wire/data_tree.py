"""Object trees as data, never code: one versioned ``.npz`` holding the tree as JSON and
every numpy array as an array (loaded with ``allow_pickle=False``). The cloud's session
checkpoints (cloud/session_state.py) and the keyframes workers send the merger
(wire/merger_keyframes.py) are written so.

Only the classes the caller lists are rebuilt, and they are rebuilt by setting their saved
attributes, never by running code named in the data; anything else is refused. So whoever
can write the cloud's output folder cannot make the cloud run code, and data of another
format version is refused with a message that names the file.
"""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile
from collections import Counter
from typing import Any

import numpy as np

FORMAT = "fleetslam-session-checkpoint"
VERSION = 1
_TREE = "__tree__"


# The classes a tree may hold, by the name written in the data.
Classes = dict[str, type]


def classes_of(*types: type, aliases: dict[str, type] | None = None) -> Classes:
    """A class list for :func:`capture` / :func:`loads`: each by its name, plus older names
    still read (``aliases``)."""
    return {**(aliases or {}), **{t.__name__: t for t in types}}


@dataclasses.dataclass
class Capture:
    """A state as it was when captured: its object tree (JSON) and copies of its arrays.
    Capturing is quick (the tracking thread does it at every keyframe); writing the file
    (:meth:`to_bytes`, most of the time: one zip member per array) can wait for another
    thread, since nothing here changes with the live state."""

    tree: str
    arrays: dict[str, np.ndarray]

    def to_bytes(self) -> bytes:
        buffer = io.BytesIO()
        np.savez(buffer, **{_TREE: np.frombuffer(self.tree.encode(), np.uint8)},
                 **self.arrays)
        return buffer.getvalue()


def dumps(state: Any, classes: Classes) -> bytes:
    return capture(state, classes).to_bytes()


def capture(state: Any, classes: Classes) -> Capture:
    """``state`` as a tree and copies of its arrays; TypeError for anything ``classes`` does
    not list."""
    arrays: dict[str, np.ndarray] = {}

    def enc(v: Any) -> Any:
        if v is None or isinstance(v, (bool, str, int, float)):
            return v
        if isinstance(v, bytes):
            return {"__bytes__": v.hex()}
        if isinstance(v, np.generic):
            return enc(v.item())
        if isinstance(v, np.ndarray):
            if v.dtype.hasobject:
                raise TypeError("an object array cannot be checkpointed as data")
            key = f"a{len(arrays)}"
            arrays[key] = v.copy()  # the live array may change before it is written
            return {"__nd__": key}
        if isinstance(v, Counter):
            return {"__counter__": [[enc(k), enc(x)] for k, x in v.items()]}
        if isinstance(v, dict):
            return {"__dict__": [[enc(k), enc(x)] for k, x in v.items()]}
        if isinstance(v, tuple):
            return {"__tuple__": [enc(x) for x in v]}
        if isinstance(v, list):
            return [enc(x) for x in v]
        name = type(v).__name__
        if classes.get(name) is type(v):
            # A class may leave out what cannot be saved (the front end's ORB extractor).
            attributes = v.__getstate__() or {}
            return {"__obj__": name, "attributes": {k: enc(x) for k, x in attributes.items()}}
        raise TypeError(f"a {type(v).__module__}.{name} cannot be checkpointed")

    tree = json.dumps({"format": FORMAT, "version": VERSION, "state": enc(state)})
    return Capture(tree, arrays)


def loads(data: bytes, where: str, classes: Classes) -> Any:
    """The state :func:`dumps` saved; ValueError naming ``where`` for anything else."""
    try:
        files = np.load(io.BytesIO(data), allow_pickle=False)
        tree = json.loads(bytes(files[_TREE]).decode())
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, UnicodeDecodeError) as exc:
        raise ValueError(f"{where}: not a fleetslam session checkpoint ({exc})") from None
    if not isinstance(tree, dict) or tree.get("format") != FORMAT:
        raise ValueError(f"{where}: not a fleetslam session checkpoint")
    if tree.get("version") != VERSION:
        raise ValueError(f"{where}: checkpoint format version {tree.get('version')!r}; this "
                         f"fleetslam reads version {VERSION}: not restored")

    def dec(v: Any) -> Any:
        if isinstance(v, list):
            return [dec(x) for x in v]
        if not isinstance(v, dict):
            return v
        if "__nd__" in v:
            return np.array(files[v["__nd__"]])
        if "__bytes__" in v:
            return bytes.fromhex(v["__bytes__"])
        if "__counter__" in v:
            return Counter({dec(k): dec(x) for k, x in v["__counter__"]})
        if "__dict__" in v:
            return {dec(k): dec(x) for k, x in v["__dict__"]}
        if "__tuple__" in v:
            return tuple(dec(x) for x in v["__tuple__"])
        if "__obj__" in v:
            cls = classes.get(v["__obj__"])
            if cls is None:
                raise ValueError(f"{where}: a {v['__obj__']!r} is not part of a session")
            obj = cls.__new__(cls)
            obj.__dict__.update({k: dec(x) for k, x in v["attributes"].items()})
            return obj
        raise ValueError(f"{where}: unexpected object in the checkpoint")

    try:
        return dec(tree.get("state"))
    except (KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{where}: damaged checkpoint ({exc})") from None
