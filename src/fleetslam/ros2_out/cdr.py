"""The ROS 2 messages fleetslam publishes, serialised as ROS 2 does: classic CDR, little
endian, after the 4-byte encapsulation header (00 01 00 00). Written by hand so a robot's
base install needs no rosbags; tests/test_ros2_out.py checks every message byte for byte
against rosbags' serialiser and each type hash against rosbags' REP-2016 hashes.

Alignment is counted from the byte after the encapsulation header, as CDR does: a value of
n bytes starts at a multiple of n (8 at most). Times are integer nanoseconds since the epoch
(``stamp_ns``); poses are 4 x 4 homogeneous transforms.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

import numpy as np

from fleetslam.transforms import T_from_tum, tum_from_T

ENCAPSULATION = b"\x00\x01\x00\x00"  # CDR little endian, no options

# REP-2016 type hashes (Iron and later; rmw_zenoh puts them in keys and tokens), of the
# definitions in ROS 2 Jazzy's common_interfaces.
TYPE_HASHES = {
    "geometry_msgs/msg/PoseStamped":
        "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "tf2_msgs/msg/TFMessage":
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "nav_msgs/msg/Path":
        "RIHS01_1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
    "diagnostic_msgs/msg/DiagnosticArray":
        "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
}
# What Humble's rmw_zenoh puts where the hash goes (it has no type hashes).
HUMBLE_TYPE_HASH = "TypeHashNotSupported"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
PATH = "nav_msgs/msg/Path"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

# diagnostic_msgs/DiagnosticStatus levels.
OK, WARN, ERROR, STALE = 0, 1, 2, 3

_NS = 1_000_000_000


class CdrWriter:
    """Appends CDR values to a buffer that starts with the encapsulation header."""

    def __init__(self) -> None:
        self.buf = bytearray(ENCAPSULATION)

    def align(self, n: int) -> None:
        pad = -(len(self.buf) - len(ENCAPSULATION)) % n
        self.buf += b"\x00" * pad

    def pack(self, fmt: str, *values: float | int) -> None:
        """Values of one size (``fmt`` one struct letter repeated), aligned to it."""
        s = struct.Struct("<" + fmt)
        self.align(s.size // len(fmt))
        self.buf += s.pack(*values)

    def uint32(self, value: int) -> None:
        self.pack("I", value)

    def string(self, text: str) -> None:
        data = text.encode() + b"\x00"
        self.uint32(len(data))
        self.buf += data

    def time(self, stamp_ns: int) -> None:
        """builtin_interfaces/Time: int32 sec, uint32 nanosec."""
        sec, nanosec = divmod(int(stamp_ns), _NS)
        self.pack("iI", sec, nanosec)

    def header(self, stamp_ns: int, frame_id: str) -> None:
        self.time(stamp_ns)
        self.string(frame_id)

    def pose(self, values: Sequence[float]) -> None:
        """geometry_msgs/Pose (or Transform: the same seven float64) from TUM order
        tx ty tz qx qy qz qw."""
        self.pack("ddddddd", *values)

    def bytes(self) -> bytes:
        return bytes(self.buf)


def stamp_ns(seconds: float) -> int:
    """A capture time in seconds (a frame's timestamp) as integer nanoseconds, rounded."""
    return int(round(float(seconds) * 1e9))


def _tum(T: np.ndarray) -> list[list[float]]:
    return tum_from_T(np.asarray(T, np.float64).reshape(-1, 4, 4)).tolist()


def pose_stamped(stamp: int, frame_id: str, T: np.ndarray) -> bytes:
    """geometry_msgs/PoseStamped: the pose ``T`` (child to ``frame_id``) at ``stamp`` ns."""
    w = CdrWriter()
    w.header(stamp, frame_id)
    w.pose(_tum(T)[0])
    return w.bytes()


def tf_message(transforms: Sequence[tuple[int, str, str, np.ndarray]]) -> bytes:
    """tf2_msgs/TFMessage of (stamp ns, parent frame, child frame, T_parent_child)."""
    w = CdrWriter()
    w.uint32(len(transforms))
    for stamp, parent, child, T in transforms:
        w.header(stamp, parent)
        w.string(child)
        w.pose(_tum(T)[0])
    return w.bytes()


def path(stamp: int, frame_id: str, stamps: Sequence[int], poses: np.ndarray) -> bytes:
    """nav_msgs/Path: each pose at its stamp, all in ``frame_id``."""
    w = CdrWriter()
    w.header(stamp, frame_id)
    w.uint32(len(stamps))
    for t, values in zip(stamps, _tum(poses) if len(stamps) else []):
        w.header(int(t), frame_id)
        w.pose(values)
    return w.bytes()


def diagnostic_array(stamp: int, statuses: Sequence[tuple[int, str, str, str,
                                                          Sequence[tuple[str, str]]]]) -> bytes:
    """diagnostic_msgs/DiagnosticArray of (level, name, message, hardware_id, key-values)."""
    w = CdrWriter()
    w.header(stamp, "")
    w.uint32(len(statuses))
    for level, name, message, hardware_id, values in statuses:
        w.buf += struct.pack("<B", level)  # a byte: no alignment
        w.string(name)
        w.string(message)
        w.string(hardware_id)
        w.uint32(len(values))
        for key, value in values:
            w.string(key)
            w.string(value)
    return w.bytes()


# -- reading (the robot's own /tf and /tf_static) --------------------------------------------

# A TFMessage holds a few transforms; one claiming more than this is not one a robot sends.
MAX_TRANSFORMS = 10_000
# A frame id longer than this is not one.
MAX_NAME_BYTES = 1024


class CdrError(ValueError):
    """A message that is not the CDR it should be; the text says where and why."""


class CdrReader:
    """Reads CDR values with bounds checked before anything is taken (little or big
    endian, as the encapsulation header says)."""

    def __init__(self, data: bytes, where: str) -> None:
        self.where = where
        if len(data) < len(ENCAPSULATION) or data[0] != 0 or data[1] not in (0, 1):
            raise CdrError(f"{where}: not classic CDR (encapsulation "
                           f"{bytes(data[:4]).hex(' ') or 'missing'})")
        self.order = "<" if data[1] == 1 else ">"
        self.data = memoryview(data)[len(ENCAPSULATION):]
        self.pos = 0

    def _take(self, n: int, align: int) -> memoryview:
        self.pos += -self.pos % align
        if self.pos + n > len(self.data):
            raise CdrError(f"{self.where}: ends at byte {len(self.data)}, a value needs "
                           f"{self.pos + n}")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str) -> tuple:
        s = struct.Struct(self.order + fmt)
        return s.unpack(self._take(s.size, s.size // len(fmt)))

    def count(self, limit: int, what: str) -> int:
        (n,) = self.unpack("I")
        if n > limit:
            raise CdrError(f"{self.where}: {n} {what} (at most {limit})")
        return n

    def string(self) -> str:
        n = self.count(MAX_NAME_BYTES, "bytes of a string")
        raw = bytes(self._take(n, 1))
        if n == 0 or raw[-1] != 0:
            raise CdrError(f"{self.where}: a string without its terminating NUL")
        try:
            return raw[:-1].decode()
        except UnicodeDecodeError:
            raise CdrError(f"{self.where}: a string that is not UTF-8") from None


def read_tf_message(data: bytes, where: str) -> list[tuple[int, str, str, np.ndarray]]:
    """A tf2_msgs/TFMessage's (stamp ns, parent, child, T_parent_child); CdrError naming
    ``where`` if it is not one, or holds a transform that is not rigid and finite."""
    r = CdrReader(data, where)
    out = []
    for _ in range(r.count(MAX_TRANSFORMS, "transforms")):
        sec, nanosec = r.unpack("iI")
        parent, child = r.string(), r.string()
        values = np.array(r.unpack("ddddddd"))
        q = values[3:]
        if not np.isfinite(values).all() or abs(np.linalg.norm(q) - 1.0) > 1e-3:
            raise CdrError(f"{where}: transform {parent} -> {child} is not finite with a unit "
                           f"quaternion ({values.tolist()})")
        if not parent.strip("/") or not child.strip("/") or parent == child:
            raise CdrError(f"{where}: transform {parent!r} -> {child!r} does not name two "
                           f"frames")
        out.append((sec * _NS + nanosec, parent.lstrip("/"), child.lstrip("/"),
                    T_from_tum(values[None])[0]))
    return out
