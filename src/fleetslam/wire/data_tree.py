"""Object trees as data, never code: one versioned ``.npz`` holding the tree as JSON and
every numpy array as an array (loaded with ``allow_pickle=False``). The cloud's session
checkpoints (cloud/session/session_state.py) and the keyframes workers send the merger
(wire/merger_keyframes.py) are written so.

Only the classes the caller lists are rebuilt, and they are rebuilt by setting their saved
attributes, never by running code named in the data; anything else is refused. So whoever
can write the cloud's output folder cannot make the cloud run code, and data of another
format version is refused with a message that names the file.
"""

from __future__ import annotations

import dataclasses
import json
import re
from collections import Counter
from typing import Any, Callable, Protocol

import numpy as np

from fleetslam.wire import npz_reader
from fleetslam.wire.npz_writer import write_npz

FORMAT = "fleetslam-session-checkpoint"
VERSION = 1
# A tree that names chunks (immutable parts kept in files of their own, written once: a
# session's keyframe features and full blocks of its trajectory) is version 2, so an older
# fleetslam refuses it by its version, not as damaged.
# Version 3: the map's and the place database's arrays as logs of chunks
# (cloud/session/array_log.py). Versions 1 and 2 are still read.
CHUNKED_VERSION = 3
READABLE_VERSIONS = (VERSION, 2, CHUNKED_VERSION)
# A chunk's name (it becomes a file name): nothing that could leave the chunks' folder.
CHUNK_NAME = re.compile(r"[a-z]\d{7,12}-[0-9a-f]{16}")
_TREE = "__tree__"
# Deepest nesting of arrays and objects a tree may have: a session's is 14 (fr1_rpy, 150
# frames), and decoding recurses once per level, far below Python's limit of 1000.
MAX_DEPTH = 64
# The tree (JSON) may take at most this share of the data's byte limit: a session's is
# ~1% of its checkpoint (72 kB of 7.1 MB, fr1_rpy 150 frames), and parsed JSON takes up to
# ~20 times its bytes as Python objects, so the parse stays within about the limit itself.
TREE_SHARE = 16
_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)
_DEPTH_CHUNK = 1 << 20
_HEX = re.compile(r"(?:[0-9a-fA-F]{2})*")
# What a mapping's keys may be once decoded (hashable data).
_KEY_TYPES = (str, int, float, bool, type(None), bytes, tuple)


def _hashable(key: Any) -> bool:
    if isinstance(key, tuple):
        return all(_hashable(k) for k in key)
    return isinstance(key, _KEY_TYPES)


# The classes a tree may hold, by the name written in the data.
Classes = dict[str, type]


def classes_of(*types: type, aliases: dict[str, type] | None = None) -> Classes:
    """A class list for :func:`capture` / :func:`loads`: each by its name, plus older names
    still read (``aliases``)."""
    return {**(aliases or {}), **{t.__name__: t for t in types}}


class Chunker(Protocol):
    """Which objects of a tree are kept as chunks (immutable, written once, named by their
    content), and which chunks are surely written already."""

    def name_of(self, value: Any) -> str | None:
        """The chunk name of ``value`` (matching CHUNK_NAME), None to keep it in the tree."""

    def written(self, name: str) -> bool:
        """Whether chunk ``name`` is durably written (a capture then leaves it out)."""


@dataclasses.dataclass
class Capture:
    """A state as it was when captured: its object tree (JSON) and copies of its arrays.
    Capturing is quick (the tracking thread does it at every keyframe); writing the file
    (:meth:`to_bytes`, most of the time: one zip member per array) can wait for another
    thread, since nothing here changes with the live state. ``chunks``: the chunks the tree
    names that are not known to be written yet, each captured on its own (write them, by
    name, before the tree that names them); ``named``: every chunk the tree names."""

    tree: str
    arrays: dict[str, np.ndarray]
    chunks: dict[str, "Capture"] = dataclasses.field(default_factory=dict)
    named: frozenset[str] = frozenset()

    def to_bytes(self) -> bytes:
        return write_npz({_TREE: np.frombuffer(self.tree.encode(), np.uint8), **self.arrays})


def dumps(state: Any, classes: Classes) -> bytes:
    return capture(state, classes).to_bytes()


def capture(state: Any, classes: Classes, chunker: Chunker | None = None) -> Capture:
    """``state`` as a tree and copies of its arrays; TypeError for anything ``classes`` does
    not list. With ``chunker``, the objects it names are chunks: the tree names them, and
    those not yet written are captured in ``Capture.chunks``."""
    arrays: dict[str, np.ndarray] = {}
    chunks: dict[str, Capture] = {}
    named: set[str] = set()

    def enc(v: Any) -> Any:
        if v is None or isinstance(v, (bool, str, int, float)):
            return v
        if chunker is not None and (name := chunker.name_of(v)) is not None:
            if not CHUNK_NAME.fullmatch(name):
                raise TypeError(f"chunk name {name!r} is not one")
            if name not in chunks and not chunker.written(name):
                chunks[name] = capture(v, classes)
            named.add(name)
            return {"__chunk__": name}
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

    encoded = enc(state)
    version = VERSION if chunker is None else CHUNKED_VERSION
    tree = json.dumps({"format": FORMAT, "version": version, "state": encoded})
    return Capture(tree, arrays, chunks, frozenset(named))


class CheckpointError(ValueError):
    """Data that cannot be restored: ``where`` (the file) and ``reason`` (what is wrong).
    The one exception :func:`loads` raises (and the checks of what it rebuilt, see
    cloud/session/checkpoint_shape.py)."""

    def __init__(self, where: str, reason: str) -> None:
        super().__init__(f"{where}: {reason}")
        self.where = where
        self.reason = reason


def nesting_depth(text: bytes) -> int:
    """How deeply the JSON ``text`` nests arrays and objects, found without parsing it (so
    without recursion): the running count of brackets outside strings."""
    codes = np.frombuffer(_JSON_STRING.sub(b'""', text), np.uint8)
    depth = deepest = 0
    for start in range(0, codes.size, _DEPTH_CHUNK):  # in chunks: a few MB at most
        chunk = codes[start:start + _DEPTH_CHUNK]
        steps = ((chunk == ord("[")) | (chunk == ord("{"))).astype(np.int32) \
            - ((chunk == ord("]")) | (chunk == ord("}")))
        running = np.cumsum(steps, dtype=np.int64) + depth
        deepest = max(deepest, int(running.max()))
        depth = int(running[-1])
    return deepest


# Reads a chunk a tree names: its object (CheckpointError if it is missing or not one).
ChunkLoader = Callable[[str], Any]


def loads(data: bytes, where: str, classes: Classes, max_bytes: int,
          load_chunk: ChunkLoader | None = None) -> Any:
    """The state :func:`dumps` saved; CheckpointError naming ``where`` for anything else.
    ``max_bytes`` bounds the data and all it holds (nothing in it is decompressed).
    ``load_chunk``: where the chunks a tree names come from (None: a tree naming one is
    refused; so is a chunk naming another)."""
    # The tree is parsed into Python objects several times its size: its own bound.
    tree_bytes = max(1, max_bytes // TREE_SHARE)
    try:
        files = npz_reader.read_npz(data, max_bytes, {_TREE: tree_bytes})
    except npz_reader.NpzError as exc:
        raise CheckpointError(where, f"not a fleetslam session checkpoint ({exc})") from None
    text = files.pop(_TREE, None)
    if text is None or text.dtype != np.uint8 or text.ndim != 1:
        raise CheckpointError(where, "not a fleetslam session checkpoint (no tree)")
    depth = nesting_depth(text.tobytes())
    if depth > MAX_DEPTH:
        raise CheckpointError(where, f"nested {depth} deep (at most {MAX_DEPTH})")
    try:
        tree = json.loads(text.tobytes().decode())
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
        raise CheckpointError(where, f"not a fleetslam session checkpoint ({exc})") from None
    if not isinstance(tree, dict) or tree.get("format") != FORMAT:
        raise CheckpointError(where, "not a fleetslam session checkpoint")
    if tree.get("version") not in READABLE_VERSIONS:
        raise CheckpointError(where, f"checkpoint format version {tree.get('version')!r}; "
                                     f"this fleetslam reads versions "
                                     f"{', '.join(map(str, READABLE_VERSIONS))}: not restored")
    return _Decoder(files, where, classes, load_chunk).value(tree.get("state"))


class _Decoder:
    """Rebuilds a tree :func:`capture` made; every malformed node is a CheckpointError.
    Recursion is bounded: the tree's depth was checked before it was parsed."""

    def __init__(self, arrays: dict[str, np.ndarray], where: str, classes: Classes,
                 load_chunk: ChunkLoader | None = None) -> None:
        self.arrays = arrays
        self.where = where
        self.classes = classes
        self.load_chunk = load_chunk

    def fail(self, reason: str) -> CheckpointError:
        return CheckpointError(self.where, f"damaged checkpoint ({reason})")

    def pairs(self, v: Any, what: str) -> list[tuple[Any, Any]]:
        if not isinstance(v, list) or not all(isinstance(p, list) and len(p) == 2 for p in v):
            raise self.fail(f"{what} is not a list of pairs")
        out = [(self.value(k), self.value(x)) for k, x in v]
        for k, _ in out:
            if not _hashable(k):
                raise self.fail(f"{what} has a key of type {type(k).__name__}")
        return out

    def value(self, v: Any) -> Any:
        if isinstance(v, list):
            return [self.value(x) for x in v]
        if not isinstance(v, dict):
            return v
        if len(v) == 1 and "__nd__" in v:
            # Each array is named once in the tree: popped, so never shared by two fields.
            array = self.arrays.pop(v["__nd__"], None) if isinstance(v["__nd__"], str) else None
            if array is None:
                raise self.fail(f"array {v['__nd__']!r} missing or named twice")
            return array
        if len(v) == 1 and "__chunk__" in v:
            name = v["__chunk__"]
            if not isinstance(name, str) or not CHUNK_NAME.fullmatch(name):
                raise self.fail("a chunk name that is not one")
            if self.load_chunk is None:
                raise self.fail(f"chunk {name} named where none may be")
            return self.load_chunk(name)
        if len(v) == 1 and "__bytes__" in v:
            text = v["__bytes__"]
            if not isinstance(text, str) or not _HEX.fullmatch(text):
                raise self.fail("bytes that are not hexadecimal")
            return bytes.fromhex(text)
        if len(v) == 1 and "__counter__" in v:
            counter = Counter(dict(self.pairs(v["__counter__"], "a counter")))
            if not all(isinstance(x, (int, float)) for x in counter.values()):
                raise self.fail("a counter that does not count")
            return counter
        if len(v) == 1 and "__dict__" in v:
            return dict(self.pairs(v["__dict__"], "a mapping"))
        if len(v) == 1 and "__tuple__" in v:
            items = v["__tuple__"]
            if not isinstance(items, list):
                raise self.fail("a tuple that is not a list")
            return tuple(self.value(x) for x in items)
        if set(v) == {"__obj__", "attributes"}:
            name, attributes = v["__obj__"], v["attributes"]
            cls = self.classes.get(name) if isinstance(name, str) else None
            if cls is None:
                raise CheckpointError(self.where, f"a {name!r} is not part of a session")
            if not isinstance(attributes, dict):
                raise self.fail(f"the attributes of a {name} are not an object")
            obj = cls.__new__(cls)
            obj.__dict__.update({k: self.value(x) for k, x in attributes.items()})
            return obj
        raise self.fail("unexpected object in the checkpoint")
