"""A checkpoint's large arrays that change (the map's landmarks and observations, the place
database) as a log: a base written once and, per checkpoint, a patch of the rows that changed
since the one before. A checkpoint then writes what changed, not the whole map: the rows one
keyframe's tracking and local mapping touched, about the same at every map size. Once the
patches together weigh as much as the base, the next checkpoint starts a new base, so
restoring reads at most about twice the map and the base's cost is spread over the
checkpoints since the last.

Bases and patches are chunks (wire/data_tree.py): immutable, named by their content and a
random token of the log that made them, written before the first checkpoint naming them. The
token keeps two workers' logs apart, so a log deletes only chunks it made itself. A chain a
new base replaced goes once the base after that one is on disk: a reader that opened the
checkpoint before the newest (the merger reads other workers' sessions) still finds its
chain.

Restoring (``restore``) checks every patch before it allocates: lengths bounded by the
checkpoint's byte limit, row indices inside the array and ascending, every new row given,
dtypes and shapes those of the base.
"""

from __future__ import annotations

import copy
import hashlib
import secrets
import threading
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from fleetslam.wire.data_tree import CheckpointError

# A new base once the chain's patches weigh this many times the base (restoring then reads
# at most 1 + REBASE_SHARE bases' bytes; each checkpoint writes about 1 + 1/REBASE_SHARE
# times its patch, amortised).
REBASE_SHARE = 1.0
# And at the latest after this many patches (files a restore reads).
MAX_PATCHES = 64


@dataclass
class ArrayBase:
    """Named arrays as they were when a log (re)started: a chunk."""

    token: str
    number: int
    arrays: dict[str, np.ndarray]


@dataclass
class ArrayPatch:
    """What changed in each named array since the checkpoint before: its new length, the
    rows changed or added (ascending) and their values. A chunk."""

    token: str
    number: int
    lengths: dict[str, int]
    index: dict[str, np.ndarray]
    rows: dict[str, np.ndarray]


@dataclass
class LoggedArrays:
    """In a checkpoint: a base and its patches, oldest first."""

    base: ArrayBase
    patches: list[ArrayPatch]


@dataclass
class Logged:
    """An object whose arrays ``arrays`` holds, in a checkpoint only (a restored session
    holds the object again): ``rest`` is the object without them."""

    rest: Any
    arrays: LoggedArrays


def content_digest(*parts: bytes) -> str:
    """A chunk name's digest of its content (8 bytes of BLAKE2b, hex)."""
    h = hashlib.blake2b(digest_size=8)
    for part in parts:
        h.update(part)
    return h.hexdigest()


def array_parts(a: np.ndarray) -> list[bytes]:
    """An array's kind, shape and bytes, as a digest takes them."""
    return [f"{a.dtype.str}{a.shape}".encode(), np.ascontiguousarray(a).tobytes()]


def chunk_name(value: ArrayBase | ArrayPatch) -> str:
    """A base's or patch's chunk name from its content (a 'b' or 'p', its number, a digest of
    its token and arrays)."""
    parts = [value.token.encode()]
    if type(value) is ArrayBase:
        for name in sorted(value.arrays):
            parts += [name.encode(), *array_parts(value.arrays[name])]
        return f"b{value.number:07d}-" + content_digest(*parts)
    for name in sorted(value.lengths):
        parts += [name.encode(), str(value.lengths[name]).encode(),
                  *array_parts(value.index[name]), *array_parts(value.rows[name])]
    return f"p{value.number:07d}-" + content_digest(*parts)


def _changed_rows(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Rows of ``new`` that differ bit for bit from ``old`` or are past its end."""
    common = min(len(old), len(new))
    added = np.arange(common, len(new), dtype=np.int64)
    if common == 0:
        return added
    # Compared as the widest unsigned integers a row divides into: bit for bit (a NaN equals
    # itself, a restore gives the very bytes), one column at a time (``any(axis=1)`` over a
    # few columns is several times slower).
    row_bytes = new.itemsize * (new[:1].size or 1)
    width = next(w for w in (8, 4, 2, 1) if row_bytes % w == 0)
    a = np.ascontiguousarray(old[:common]).view(f"u{width}").reshape(common, -1)
    b = np.ascontiguousarray(new[:common]).view(f"u{width}").reshape(common, -1)
    differs = a[:, 0] != b[:, 0]
    for column in range(1, a.shape[1]):
        differs |= a[:, column] != b[:, column]
    changed = np.flatnonzero(differs)
    return np.concatenate([changed, added]) if len(added) else changed


class ArrayLog:
    """The log of one object's named arrays, kept by the session that checkpoints it (the
    session's thread calls ``logged``; the checkpoint writer's, ``written``)."""

    def __init__(self, names: Iterable[str]) -> None:
        self.names = tuple(names)
        self.token = secrets.token_hex(4)
        self._number = 0
        self._head: dict[str, np.ndarray] = {}  # the arrays as the chain's end has them
        self._chain: LoggedArrays | None = None
        self._base_bytes = 0
        self._patch_bytes = 0
        self._named: dict[int, tuple[Any, str]] = {}  # id -> (base or patch, its name)
        # Chunks of chains the newest base replaced (``_retiring_for``, not on disk yet), and
        # of those an older base replaced that is on disk: deleted with the next base's write.
        self._retired: list[str] = []
        self._retiring_for: str | None = None
        self._grace: list[str] = []
        # Names of the chain's chunks on disk: their arrays are let go at the next call of
        # ``logged`` (a written chunk is named, never captured again).
        self._on_disk: set[str] = set()
        self._lock = threading.Lock()

    def name_of(self, value: Any) -> str | None:
        """The chunk name of a base or patch of this log's current chain, None otherwise."""
        known = self._named.get(id(value))
        return known[1] if known is not None and known[0] is value else None

    def logged(self, obj: Any) -> Logged:
        """``obj`` as a checkpoint keeps it: its other attributes, and its arrays as the
        chain with a patch of what changed since the last call."""
        self._let_go_of_written()
        arrays = {name: getattr(obj, name) for name in self.names}
        rest = copy.copy(obj)
        for name in self.names:
            delattr(rest, name)
        patch = self._patch(arrays)
        if patch is None or self._patch_bytes + _nbytes(patch) > REBASE_SHARE * self._base_bytes \
                or len(self._chain.patches) >= MAX_PATCHES:
            self._rebase(arrays)
        elif patch.lengths:  # something changed
            self._chain = LoggedArrays(self._chain.base, self._chain.patches + [patch])
            self._patch_bytes += _nbytes(patch)
            self._name(patch)
        self._head = {name: a.copy() for name, a in arrays.items()}
        return Logged(rest, self._chain)

    def _patch(self, arrays: dict[str, np.ndarray]) -> ArrayPatch | None:
        """The rows changed since the chain's end; None if there is no chain or an array
        changed its kind (a new base then)."""
        if self._chain is None:
            return None
        lengths, index, rows = {}, {}, {}
        for name, new in arrays.items():
            old = self._head[name]
            if new.dtype != old.dtype or new.shape[1:] != old.shape[1:]:
                return None
            changed = _changed_rows(old, new)
            if len(changed) or len(new) != len(old):
                lengths[name], index[name], rows[name] = len(new), changed, new[changed]
        self._number += 1
        return ArrayPatch(self.token, self._number, lengths, index, rows)

    def _rebase(self, arrays: dict[str, np.ndarray]) -> None:
        self._number += 1
        base = ArrayBase(self.token, self._number, {n: a.copy() for n, a in arrays.items()})
        with self._lock:
            if self._chain is not None:
                self._retired += [self._named[id(v)][1] for v in
                                  [self._chain.base, *self._chain.patches]]
            self._retiring_for = self._name(base)
        self._named = {id(base): self._named[id(base)]}
        self._chain = LoggedArrays(base, [])
        self._base_bytes, self._patch_bytes = _nbytes(base), 0

    def _let_go_of_written(self) -> None:
        """The arrays of the chain's chunks on disk are dropped (the chain keeps only their
        names): what the log holds is the head and what is not written yet."""
        with self._lock:
            on_disk, self._on_disk = self._on_disk, set()
        if self._chain is None or not on_disk:
            return
        for value in [self._chain.base, *self._chain.patches]:
            if self.name_of(value) in on_disk:
                if type(value) is ArrayBase:
                    value.arrays = {}
                else:
                    value.index, value.rows = {}, {}

    def _name(self, value: ArrayBase | ArrayPatch) -> str:
        name = chunk_name(value)
        self._named[id(value)] = (value, name)
        return name

    def written(self, names: Iterable[str]) -> list[str]:
        """Chunks ``names`` are on disk with a checkpoint naming them: if the newest base is
        among them, the chunks of the chains replaced by the base before it (to delete: no
        checkpoint but ones two bases old names them); else none."""
        names = set(names)
        with self._lock:
            self._on_disk |= names
            if self._retiring_for is None or self._retiring_for not in names:
                return []
            gone, self._grace = self._grace, self._retired
            self._retired, self._retiring_for = [], None
            return gone


def _nbytes(value: ArrayBase | ArrayPatch) -> int:
    if type(value) is ArrayBase:
        return sum(a.nbytes for a in value.arrays.values())
    return sum(a.nbytes for a in value.rows.values()) + \
        sum(a.nbytes for a in value.index.values())


def restore(logged: LoggedArrays, where: str, max_bytes: int) -> dict[str, np.ndarray]:
    """The arrays a chain holds, its patches applied in order; CheckpointError naming
    ``where`` if it is not a chain of this kind, or would take over ``max_bytes``."""
    def fail(why: str) -> CheckpointError:
        return CheckpointError(where, f"damaged checkpoint (logged arrays: {why})")

    base, patches = getattr(logged, "base", None), getattr(logged, "patches", None)
    if type(base) is not ArrayBase or not isinstance(patches, list) \
            or not all(type(p) is ArrayPatch for p in patches):
        raise fail("not a base and its patches")
    if not isinstance(base.arrays, dict) or not all(
            isinstance(k, str) and isinstance(a, np.ndarray) and a.ndim >= 1 and
            not a.dtype.hasobject for k, a in base.arrays.items()):
        raise fail("a base that is not named arrays")
    # Patched in place: copied first only where the reader gave read-only arrays.
    arrays = {k: a if a.flags.writeable else a.copy() for k, a in base.arrays.items()}
    for number, patch in enumerate(patches, 1):
        parts = (patch.lengths, patch.index, patch.rows)
        if not all(isinstance(p, dict) for p in parts) \
                or not set(patch.lengths) == set(patch.index) == set(patch.rows) <= set(arrays):
            raise fail(f"patch {number} names other arrays than its base")
        for name, length in patch.lengths.items():
            old, index, rows = arrays[name], patch.index[name], patch.rows[name]
            row_bytes = old.itemsize * int(np.prod(old.shape[1:], dtype=np.int64))
            if not isinstance(length, int) or isinstance(length, bool) or length < 0 \
                    or length * max(row_bytes, 1) > max_bytes:
                raise fail(f"patch {number}: {name} of a length that is not one")
            if not isinstance(index, np.ndarray) or index.ndim != 1 \
                    or index.dtype.kind not in "iu" or not isinstance(rows, np.ndarray) \
                    or rows.dtype != old.dtype or rows.shape != (len(index), *old.shape[1:]):
                raise fail(f"patch {number}: {name}'s rows are not rows of it")
            if len(index) and (index[0] < 0 or index[-1] >= length
                               or (np.diff(index) <= 0).any()):
                raise fail(f"patch {number}: {name}'s row numbers are not ascending inside "
                           f"its length {length}")
            if int((index >= len(old)).sum()) != max(0, length - len(old)):
                raise fail(f"patch {number}: {name} grows by rows it does not give")
            if length != len(old):
                grown = np.empty((length, *old.shape[1:]), old.dtype)
                common = min(length, len(old))
                grown[:common] = old[:common]
                arrays[name] = old = grown
            old[index] = rows
    return arrays
