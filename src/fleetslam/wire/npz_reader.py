"""Reading an ``.npz`` (a zip of ``.npy`` members, as ``np.savez`` writes it) that nobody
vouches for: every member is checked before a byte of it is allocated, and nothing is ever
decompressed.

``np.savez`` stores its members uncompressed, so a member of any other compression method
is refused before it is read: a stored member's bytes are the file's own, so what is read
is at most the file, and a small file that would inflate to gigabytes (a zip bomb) costs
nothing. Each ``.npy`` header is checked (a plain numeric dtype, a shape whose bytes are
exactly those present) before its array is made. Every problem raises :class:`NpzError`
with the reason; nothing else escapes.
"""

from __future__ import annotations

import io
import struct
import tokenize
import zipfile
from typing import BinaryIO

import numpy as np

# Plain numbers only (bool, ints, floats, complex): no objects, strings or records.
_DTYPE_KINDS = "biufc"
# An .npy header is a short Python dict literal; numpy's own limit for untrusted files.
_MAX_NPY_HEADER = 10_000


class NpzError(ValueError):
    """An .npz that cannot be accepted; the text says why."""


# zipfile documents BadZipFile only; on a damaged directory its parsing can also fail with
# these (seen by bench/fuzz_checkpoint.py; NotImplementedError: "zip file version 6.5").
_ZIP_ERRORS = (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError,
               struct.error, OverflowError, IndexError, KeyError, UnicodeDecodeError,
               NotImplementedError)


def _members(data: bytes) -> list[zipfile.ZipInfo]:
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            return archive.infolist()
    except _ZIP_ERRORS as exc:
        raise NpzError(f"not a zip archive ({exc})") from None


# Bytes a member may take beyond its name and data (local header extras: zip64's 20, a
# data descriptor's 24), and the archive after its directory (zip64 end record and
# locator, 76; the end record, 22).
_MEMBER_SLACK = 64
_TAIL_SLACK = 98


def layout_problem(f: BinaryIO, size: int) -> str | None:
    """Why the open file of ``size`` bytes is not laid out as ``np.savez`` writes an archive
    (None: it is), read from its directory at the end alone: every byte must belong to a
    member, the directory or its end. A file padded or holed past its members (a sparse
    gigabyte behind a real checkpoint) is refused before it is read whole."""
    if not size:
        return "empty file"
    try:
        with zipfile.ZipFile(f) as archive:
            members = archive.infolist()
            directory_at = archive.start_dir
            comment = len(archive.comment)
    except _ZIP_ERRORS as exc:
        return f"not a zip archive ({exc})"
    data = sum(30 + len(i.orig_filename.encode()) + i.compress_size for i in members)
    directory = sum(46 + len(i.orig_filename.encode()) + len(i.extra) + len(i.comment)
                    for i in members)
    unaccounted = directory_at - data
    tail = size - directory_at - directory - comment
    if not 0 <= unaccounted <= _MEMBER_SLACK * len(members) or not 0 <= tail <= _TAIL_SLACK:
        return (f"{size} bytes, of which its {len(members)} members and their directory "
                f"account for {data + directory}: not an archive fleetslam wrote (padded, "
                f"or a hole in it?)")
    return None


def _check_member(info: zipfile.ZipInfo, budget: int) -> str:
    """The member's array name; NpzError unless it can be read as np.savez writes it."""
    if not info.filename.endswith(".npy"):
        raise NpzError(f"member {info.filename!r} is not an .npy array")
    if info.flag_bits & 0x1:
        raise NpzError(f"member {info.filename!r} is encrypted")
    if info.compress_type != zipfile.ZIP_STORED:
        # Never decompressed: np.savez does not compress, so this is no file of ours.
        raise NpzError(f"member {info.filename!r} is compressed (method "
                       f"{info.compress_type}); checkpoints are stored uncompressed")
    if info.file_size != info.compress_size:
        raise NpzError(f"member {info.filename!r} declares {info.file_size} bytes stored "
                       f"in {info.compress_size}")
    if info.file_size > budget:
        raise NpzError(f"member {info.filename!r} of {info.file_size} bytes exceeds what is "
                       f"left of the limit ({budget} bytes)")
    return info.filename[:-len(".npy")]


def _array(raw: bytes, name: str) -> np.ndarray:
    """The array of one .npy member, checked before it is made."""
    fp = io.BytesIO(raw)
    try:
        major, _ = np.lib.format.read_magic(fp)
        read_header = {1: np.lib.format.read_array_header_1_0,
                       2: np.lib.format.read_array_header_2_0}.get(major)
        if read_header is None:
            raise NpzError(f"array {name!r}: .npy version {major} not supported")
        shape, fortran_order, dtype = read_header(fp, max_header_size=_MAX_NPY_HEADER)
    except NpzError:
        raise
    # numpy parses the header as a Python literal (tokenize, ast): their errors too.
    except (ValueError, TypeError, SyntaxError, struct.error, EOFError,
            tokenize.TokenError) as exc:
        raise NpzError(f"array {name!r}: bad .npy header ({exc})") from None
    if dtype.kind not in _DTYPE_KINDS or dtype.fields is not None or dtype.subdtype:
        raise NpzError(f"array {name!r}: dtype {dtype} is not a plain number")
    if not all(isinstance(n, int) and n >= 0 for n in shape):
        raise NpzError(f"array {name!r}: bad shape {shape}")
    count = 1
    for n in shape:
        count *= n  # Python ints: a forged shape cannot overflow
    present = len(raw) - fp.tell()
    if count * dtype.itemsize != present:
        raise NpzError(f"array {name!r}: shape {shape} of {dtype} needs "
                       f"{count * dtype.itemsize} bytes, {present} present")
    flat = np.frombuffer(raw, dtype, count, fp.tell())
    # A copy: writable, and the member's bytes can go.
    return flat.reshape(shape, order="F" if fortran_order else "C").copy()


def read_npz(data: bytes, max_bytes: int, limits: dict[str, int] | None = None
             ) -> dict[str, np.ndarray]:
    """Every array of the archive by name. ``max_bytes`` bounds the file and all its
    members together; ``limits`` bounds single members by name (bytes). NpzError on any
    problem."""
    if len(data) > max_bytes:
        raise NpzError(f"{len(data)} bytes exceeds the limit of {max_bytes}")
    if not data:
        raise NpzError("empty file")
    members = _members(data)
    budget = max_bytes
    names: list[str] = []
    for info in members:  # all checked before any is read
        name = _check_member(info, min(budget, (limits or {}).get(
            info.filename[:-len(".npy")], budget)))
        if name in names:
            raise NpzError(f"member {info.filename!r} appears twice")
        names.append(name)
        budget -= info.file_size
    arrays: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            for info, name in zip(members, names):
                with archive.open(info) as member:
                    # At most the declared size (checked above); the CRC is checked at its end.
                    raw = member.read(info.file_size + 1)
                if len(raw) != info.file_size:
                    raise NpzError(f"member {info.filename!r}: {len(raw)} bytes, declared "
                                   f"{info.file_size}")
                arrays[name] = _array(raw, name)
    except NpzError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, struct.error, OverflowError,
            NotImplementedError, RuntimeError, UnicodeDecodeError) as exc:
        raise NpzError(f"damaged zip archive ({exc})") from None
    return arrays
