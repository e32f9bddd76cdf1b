"""The envelope every robot <-> cloud message travels in: a fixed little-endian header, then
the payload (optionally zstd-compressed), checked by a CRC-32.

    offset  size  field
    0       4     magic b"FSLM"
    4       2     format version (u16)
    6       1     kind (u8, Kind)
    7       1     split point (u8, 0..N_SPLIT_POINTS-1)
    8       1     flags (u8; bit 0: payload is zstd-compressed)
    9       1     robot id length L (u8, 1..64)
    10      L     robot id, UTF-8, characters [A-Za-z0-9_-]
    10+L    8     sequence number (u64)
    18+L    8     timestamp, seconds (f64, finite)
    26+L    4     raw payload length: bytes after decompression (u32, <= MAX_PAYLOAD_BYTES)
    30+L    4     payload length: bytes on the wire (u32)
    34+L    4     CRC-32 of every byte before this field, then of the payload
    38+L    ...   payload

The payload is one zstd frame, cut into blocks where the sender's columns change (each block
has its own entropy tables; see ``seal``). The raw length is declared so a receiver allocates
at most that much: a small message that would decompress to gigabytes is rejected before it
is decompressed. Every problem found while
opening a message raises :class:`WireError` with the reason; nothing else escapes.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum

import zstandard

from fleetslam.pipeline.split import STAGE_NAMES
from fleetslam.validation.names import MAX_NAME_LENGTH as MAX_ROBOT_ID_LENGTH
from fleetslam.validation.names import NAME

MAGIC = b"FSLM"
FORMAT_VERSION = 1
# Split points 0..6: the pipeline has six stages (pipeline/split.py), so seven states.
N_SPLIT_POINTS = len(STAGE_NAMES) + 1
# No payload is larger than this once decompressed (a full-resolution frame is ~1.5 MB).
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024

FLAG_ZSTD = 0x01
_KNOWN_FLAGS = FLAG_ZSTD

_PREFIX = struct.Struct("<4sHBBBB")  # magic, version, kind, split, flags, robot id length
_TAIL = struct.Struct("<QdII")  # seq, timestamp, raw length, payload length
_CRC = struct.Struct("<I")


class Kind(IntEnum):
    FRAME = 1
    FEEDBACK = 2
    KEYFRAME = 3
    # A frame whose descriptors are coded against earlier frames (wire/inter.py). A kind of
    # its own: a build that predates it refuses it ("unknown message kind 4"), and an intra
    # frame stays byte for byte what it was.
    FRAME_INTER = 4


class WireError(ValueError):
    """A message that cannot be accepted; the text says why."""


@dataclass(frozen=True)
class Header:
    version: int
    kind: Kind
    robot_id: str
    seq: int
    timestamp: float
    split_point: int
    payload_length: int  # bytes on the wire (compressed if ``compressed``)
    checksum: int
    compressed: bool
    raw_length: int = 0  # payload bytes after decompression

    @property
    def size(self) -> int:
        """Bytes of the whole message."""
        return header_size(self.robot_id) + self.payload_length


def header_size(robot_id: str) -> int:
    return _PREFIX.size + len(robot_id.encode()) + _TAIL.size + _CRC.size


def check_robot_id(robot_id: str) -> None:
    """Raise ValueError unless ``robot_id`` is 1..64 characters of [A-Za-z0-9_-]."""
    if not isinstance(robot_id, str) or not NAME.fullmatch(robot_id):
        raise ValueError(f"robot id {robot_id!r} must be 1..{MAX_ROBOT_ID_LENGTH} characters "
                         "of [A-Za-z0-9_-]")


def _assemble(version: int, kind: int, split_point: int, flags: int, robot_id: bytes, seq: int,
              timestamp: float, raw_length: int, wire_payload: bytes) -> bytes:
    """Header + payload with its CRC; no validation (seal validates; tests forge with it)."""
    head = (_PREFIX.pack(MAGIC, version, kind, split_point, flags, len(robot_id)) + robot_id
            + _TAIL.pack(seq, timestamp, raw_length, len(wire_payload)))
    crc = zlib.crc32(wire_payload, zlib.crc32(head))
    return b"".join((head, _CRC.pack(crc), wire_payload))


def seal(kind: Kind, robot_id: str, seq: int, timestamp: float, split_point: int,
         payload: bytes | Sequence[bytes], *, compress: bool, level: int = 3) -> bytes:
    """One message around ``payload``. With ``compress``, the payload is zstd-compressed
    unless that does not make it smaller (images already compressed): the header's flag says
    which was sent. A payload given as a sequence of sections is the same bytes joined, but
    each section gets its own zstd block, so its own entropy tables."""
    check_robot_id(robot_id)
    kind = Kind(kind)
    if not 0 <= split_point < N_SPLIT_POINTS:
        raise ValueError(f"split point {split_point} outside 0..{N_SPLIT_POINTS - 1}")
    if not 0 <= seq < 2**64:
        raise ValueError(f"sequence number {seq} outside 0..2^64-1")
    if not math.isfinite(timestamp):
        raise ValueError(f"timestamp {timestamp} is not finite")
    sections = [payload] if isinstance(payload, (bytes, bytearray, memoryview)) else payload
    sections = [bytes(s) for s in sections]
    raw = b"".join(sections)
    if len(raw) > MAX_PAYLOAD_BYTES:
        raise ValueError(f"payload of {len(raw)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    flags, wire_payload = 0, raw
    if compress:
        packed = _compress(sections, len(raw), level)
        if len(packed) < len(raw):
            flags, wire_payload = FLAG_ZSTD, packed
    return _assemble(FORMAT_VERSION, int(kind), split_point, flags, robot_id.encode(), seq,
                     float(timestamp), len(raw), wire_payload)


def _compress(sections: list[bytes], total: int, level: int) -> bytes:
    # The content size goes into the zstd frame: open_message checks it against the declared
    # raw length before decompressing anything.
    cobj = zstandard.ZstdCompressor(level=level, write_content_size=True).compressobj(size=total)
    out = []
    for i, section in enumerate(sections):
        out.append(cobj.compress(section))
        if i < len(sections) - 1:
            out.append(cobj.flush(zstandard.COMPRESSOBJ_FLUSH_BLOCK))
    out.append(cobj.flush(zstandard.COMPRESSOBJ_FLUSH_FINISH))
    return b"".join(out)


def open_message(data: bytes) -> tuple[Header, bytes]:
    """Check every field of a message and return its header and raw (decompressed) payload.
    Raises WireError with the reason on any problem."""
    data = bytes(data)
    if not data:
        raise WireError("empty message")
    if len(data) < _PREFIX.size:
        raise WireError(f"truncated: {len(data)} bytes, the header alone needs at least "
                        f"{_PREFIX.size}")
    magic, version, kind, split_point, flags, id_length = _PREFIX.unpack_from(data)
    if magic != MAGIC:
        raise WireError(f"bad magic {magic!r} (expected {MAGIC!r})")
    if version != FORMAT_VERSION:
        raise WireError(f"format version {version} not supported (this build reads "
                        f"{FORMAT_VERSION})")
    if kind not in Kind._value2member_map_:
        raise WireError(f"unknown message kind {kind}")
    if split_point >= N_SPLIT_POINTS:
        raise WireError(f"split point {split_point} outside 0..{N_SPLIT_POINTS - 1}")
    if flags & ~_KNOWN_FLAGS:
        raise WireError(f"unknown flags 0x{flags:02x}")
    if not 1 <= id_length <= MAX_ROBOT_ID_LENGTH:
        raise WireError(f"robot id length {id_length} outside 1..{MAX_ROBOT_ID_LENGTH}")
    head_length = _PREFIX.size + id_length + _TAIL.size + _CRC.size
    if len(data) < head_length:
        raise WireError(f"truncated: {len(data)} bytes, the header needs {head_length}")
    id_bytes = data[_PREFIX.size:_PREFIX.size + id_length]
    try:
        robot_id = id_bytes.decode("utf-8")
    except UnicodeDecodeError:
        raise WireError("robot id not valid UTF-8") from None
    if not NAME.fullmatch(robot_id):
        raise WireError(f"robot id {robot_id!r} has characters outside [A-Za-z0-9_-]")
    seq, timestamp, raw_length, payload_length = _TAIL.unpack_from(data, _PREFIX.size + id_length)
    (checksum,) = _CRC.unpack_from(data, head_length - _CRC.size)
    present = len(data) - head_length
    if present < payload_length:
        raise WireError(f"truncated: header says {payload_length} payload bytes, {present} "
                        "present")
    if present > payload_length:
        raise WireError(f"trailing bytes: {present - payload_length} after the "
                        f"{payload_length}-byte payload")
    payload = data[head_length:]
    computed = zlib.crc32(payload, zlib.crc32(data[:head_length - _CRC.size]))
    if computed != checksum:
        raise WireError(f"checksum mismatch (header 0x{checksum:08x}, computed 0x{computed:08x})")
    if not math.isfinite(timestamp):
        raise WireError(f"timestamp {timestamp} is not finite")
    if raw_length > MAX_PAYLOAD_BYTES:
        raise WireError(f"declared payload size {raw_length} bytes exceeds the limit of "
                        f"{MAX_PAYLOAD_BYTES}")
    compressed = bool(flags & FLAG_ZSTD)
    if compressed:
        payload = _decompress(payload, raw_length)
    elif raw_length != payload_length:
        raise WireError(f"uncompressed payload of {payload_length} bytes but header declares "
                        f"{raw_length}")
    header = Header(version, Kind(kind), robot_id, seq, timestamp, split_point, payload_length,
                    checksum, compressed, raw_length)
    return header, payload


def _decompress(payload: bytes, raw_length: int) -> bytes:
    try:
        declared = zstandard.frame_content_size(payload)
    except zstandard.ZstdError as exc:
        raise WireError(f"zstd: not a zstd frame ({exc})") from None
    # The frame's own size field decides how much zstd allocates: check it first.
    if declared != raw_length:
        what = "no size" if declared < 0 else f"{declared} bytes"
        raise WireError(f"zstd frame declares {what}, header says {raw_length}")
    try:
        out = zstandard.ZstdDecompressor().decompress(payload, max_output_size=raw_length,
                                                      allow_extra_data=False)
    except zstandard.ZstdError as exc:
        raise WireError(f"zstd: {exc}") from None
    if len(out) != raw_length:
        raise WireError(f"zstd: {len(out)} bytes decompressed, header says {raw_length}")
    return out
