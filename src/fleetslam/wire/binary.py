"""Building blocks of the message payloads: a writer and a bounds-checked reader of
little-endian fields and arrays, byte-shuffled numeric columns, and PNG/JPEG images.

Every read is checked against the bytes present before anything is allocated, so a
payload that lies about its sizes raises WireError instead of exhausting memory.
"""

from __future__ import annotations

import struct

import cv2
import numpy as np

from fleetslam.config import IMAGE_CODECS  # re-exported: the wire's image codecs
from fleetslam.io.coded_image import MAX_IMAGE_PIXELS, coded_size, coded_work_problem
from fleetslam.wire.envelope import WireError

# PNG images: zlib's run-length strategy. On the real 640x480 frames it is both smaller and
# no slower than the default strategy at level 1: depth 107 vs 120 kB (8 vs 11 ms), grey
# 154 vs 175 kB, colour 458 vs 482 kB (7-Scenes); higher levels cost 1.5-3x the time.
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY,
              cv2.IMWRITE_PNG_STRATEGY_RLE]
# Smallest zstd block a payload is cut into (Writer.sections).
SECTION_MIN_BYTES = 256


def little(dtype: str | np.dtype) -> np.dtype:
    return np.dtype(dtype).newbyteorder("<")


class Writer:
    """Collects a payload as columns. Each column can become its own zstd block (see
    :meth:`sections`): zstd fits one entropy table per block, and one table over descriptor
    bytes, coordinates and flags together fits none of them."""

    def __init__(self) -> None:
        self._parts: list[bytes] = []

    def pack(self, fmt: str, *values: object) -> None:
        self._parts.append(struct.pack("<" + fmt, *values))

    def array(self, values: np.ndarray, dtype: str) -> None:
        self._parts.append(np.ascontiguousarray(values, dtype=little(dtype)).tobytes())

    def shuffled(self, values: np.ndarray, dtype: str) -> None:
        """Byte i of every element together, one column per byte: exponents and high bytes
        are alike, low bytes are noise, and each gets its own table."""
        a = np.ascontiguousarray(values, dtype=little(dtype)).reshape(-1)
        for plane in a.view(np.uint8).reshape(-1, a.itemsize).T:
            self._parts.append(plane.tobytes())

    def columns(self, table: np.ndarray) -> None:
        """An N x M uint8 table column by column (descriptor byte j of every keypoint)."""
        for column in np.asarray(table, dtype=np.uint8).T:
            self._parts.append(column.tobytes())

    def planes(self, values: np.ndarray, n_bytes: int) -> None:
        """Non-negative integers as ``n_bytes`` byte planes, low byte first."""
        v = np.asarray(values, dtype=np.uint64)
        for b in range(n_bytes):
            plane = (v >> np.uint64(8 * b)) & np.uint64(255)
            self._parts.append(plane.astype(np.uint8).tobytes())

    def bits(self, flags: np.ndarray) -> None:
        self._parts.append(np.packbits(np.asarray(flags, dtype=bool)).tobytes())

    def blob(self, data: bytes) -> None:
        self.pack("I", len(data))
        self._parts.append(data)

    def getvalue(self) -> bytes:
        return b"".join(self._parts)

    def sections(self, min_bytes: int = SECTION_MIN_BYTES) -> list[bytes]:
        """The payload cut at column boundaries into pieces of at least ``min_bytes`` (a
        block's own table costs some bytes: tiny columns ride with their neighbours)."""
        out: list[bytes] = []
        pending: list[bytes] = []
        size = 0
        for part in self._parts:
            pending.append(part)
            size += len(part)
            if size >= min_bytes:
                out.append(b"".join(pending))
                pending, size = [], 0
        if pending:
            if out and size < min_bytes:
                out[-1] += b"".join(pending)
            else:
                out.append(b"".join(pending))
        return out


class Reader:
    def __init__(self, data: bytes, what: str) -> None:
        self._data = memoryview(data)
        self._pos = 0
        self._what = what

    @property
    def remaining(self) -> int:
        return len(self._data) - self._pos

    def take(self, n: int, what: str) -> memoryview:
        if n < 0 or n > self.remaining:
            raise WireError(f"{self._what} truncated: {what} needs {n} bytes, "
                            f"{self.remaining} left")
        out = self._data[self._pos:self._pos + n]
        self._pos += n
        return out

    def unpack(self, fmt: str, what: str) -> tuple:
        s = struct.Struct("<" + fmt)
        return s.unpack(self.take(s.size, what))

    def array(self, dtype: str, count: int, what: str) -> np.ndarray:
        dt = little(dtype)
        raw = self.take(count * dt.itemsize, what)
        # A writable array in native order (stages may modify what they are given).
        return np.frombuffer(raw, dtype=dt).astype(dt.newbyteorder("="))

    def shuffled(self, dtype: str, count: int, what: str) -> np.ndarray:
        dt = little(dtype)
        raw = np.frombuffer(self.take(count * dt.itemsize, what), dtype=np.uint8)
        joined = np.ascontiguousarray(raw.reshape(dt.itemsize, count).T)
        return joined.view(dt).reshape(count).astype(dt.newbyteorder("="))

    def columns(self, rows: int, n_columns: int, what: str) -> np.ndarray:
        raw = np.frombuffer(self.take(rows * n_columns, what), dtype=np.uint8)
        return np.ascontiguousarray(raw.reshape(n_columns, rows).T)

    def planes(self, n_bytes: int, count: int, what: str) -> np.ndarray:
        raw = np.frombuffer(self.take(n_bytes * count, what), dtype=np.uint8)
        out = np.zeros(count, np.int64)
        for b in range(n_bytes):
            out |= raw[b * count:(b + 1) * count].astype(np.int64) << (8 * b)
        return out

    def bits(self, count: int, what: str) -> np.ndarray:
        raw = np.frombuffer(self.take((count + 7) // 8, what), dtype=np.uint8)
        return np.unpackbits(raw, count=count).astype(bool)

    def flag(self, what: str) -> bool:
        (value,) = self.unpack("B", what)
        if value > 1:
            raise WireError(f"{self._what}: {what} is {value}, expected 0 or 1")
        return bool(value)

    def blob(self, what: str) -> bytes:
        (n,) = self.unpack("I", f"{what} length")
        return bytes(self.take(n, what))

    def finish(self) -> None:
        if self.remaining:
            raise WireError(f"{self._what}: {self.remaining} unexpected bytes after the end")


# ---------------------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------------------

_CODEC_IDS = {"png": 0, "jpeg": 1, "delta": 2}
# 16-bit depth, lossless: each pixel minus its left neighbour (mod 2^16, zigzagged so small
# steps either way are small numbers), as a high and a low byte plane that the envelope's
# zstd compresses. Keyframe depth at the map's stride, each section zstd'd as the envelope
# does: 7-Scenes 34.6 -> 28.9 kB, TUM fr1_rpy 38.1 -> 31.9 kB against PNG (level 1, RLE),
# in ~1 ms; decoding is one cumulative sum.
DEPTH_CODEC = "delta"
_CODEC_NAMES = {v: k for k, v in _CODEC_IDS.items()}


def check_codec(codec: str) -> None:
    if codec not in IMAGE_CODECS:
        raise ValueError(f"image codec {codec!r} is not one of {', '.join(IMAGE_CODECS)}")


def depth_codec(compress: bool) -> str:
    """How 16-bit depth goes: DEPTH_CODEC's planes shrink only under the envelope's zstd,
    so an uncompressed message (wire.compress false) keeps the PNG, compressed itself."""
    return DEPTH_CODEC if compress else "png"


def _delta_code(depth: np.ndarray) -> np.ndarray:
    step = np.diff(depth, axis=1, prepend=np.zeros((len(depth), 1), np.uint16)).view(np.int16)
    return ((step.astype(np.int32) << 1) ^ (step.astype(np.int32) >> 15)).astype(np.uint16)


def _delta_decode(code: np.ndarray) -> np.ndarray:
    step = (code >> 1).astype(np.uint16) ^ (-(code & 1).astype(np.int32)).astype(np.uint16)
    return np.cumsum(step, axis=1, dtype=np.uint16)


def _encode(image: np.ndarray, codec: str, jpeg_quality: int) -> bytes:
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)  # OpenCV codecs think in BGR
    if codec == "png":
        ok, buf = cv2.imencode(".png", image, PNG_PARAMS)
    else:
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise ValueError(f"OpenCV could not encode a {image.shape} {image.dtype} image as {codec}")
    return buf.tobytes()


def put_image(w: Writer, image: np.ndarray, codec: str, jpeg_quality: int = 90) -> None:
    """An H x W x 3 RGB or H x W grey uint8 image (PNG also takes uint16 grey), with its
    size and channel count so the reader can check the image before decoding it."""
    if codec != DEPTH_CODEC:
        check_codec(codec)
    image = np.ascontiguousarray(image)
    channels = 1 if image.ndim == 2 else image.shape[2]
    if image.ndim not in (2, 3) or channels not in (1, 3):
        raise ValueError(f"image of shape {image.shape}: expected H x W or H x W x 3")
    if codec == DEPTH_CODEC and (image.dtype != np.uint16 or channels != 1):
        raise ValueError(f"{image.dtype} image of {channels} channels cannot be sent as "
                         f"{codec} (16-bit depth only)")
    if image.dtype != np.uint8 and not (image.dtype == np.uint16 and codec != "jpeg"
                                        and channels == 1):
        raise ValueError(f"{image.dtype} image cannot be sent as {codec}")
    h, width = image.shape[:2]
    if h > 0xFFFF or width > 0xFFFF:
        raise ValueError(f"image of {width}x{h} pixels is too large for the wire")
    w.pack("BHHBB", _CODEC_IDS[codec], h, width, channels, image.dtype.itemsize)
    if codec == DEPTH_CODEC:
        w.shuffled(_delta_code(image), "u2")
    else:
        w.blob(_encode(image, codec, jpeg_quality))


def get_image(r: Reader, what: str, size: tuple[int, int] | None = None
              ) -> tuple[np.ndarray, str]:
    """The image put by :func:`put_image` and its codec; checks size, channels and type.
    With ``size`` (height, width), an image of another size is refused before decoding:
    decoding is the expensive part, and a small message can claim a huge image."""
    codec_id, h, width, channels, itemsize = r.unpack("BHHBB", f"{what} header")
    if codec_id not in _CODEC_NAMES:
        raise WireError(f"{what}: unknown image codec {codec_id}")
    codec = _CODEC_NAMES[codec_id]
    if channels not in (1, 3) or itemsize not in (1, 2) or (itemsize == 2 and (
            codec == "jpeg" or channels != 1)) or (codec == DEPTH_CODEC and itemsize != 2):
        raise WireError(f"{what}: {channels} channels of {itemsize} bytes not supported "
                        f"as {codec}")
    if h * width > MAX_IMAGE_PIXELS:
        raise WireError(f"{what}: {width}x{h} pixels exceed the limit of {MAX_IMAGE_PIXELS}")
    if size is not None and (h, width) != tuple(size):
        raise WireError(f"{what} is {width} x {h}, expected {size[1]} x {size[0]}")
    if codec == DEPTH_CODEC:  # the planes' length is checked before anything is allocated
        return _delta_decode(r.shuffled("u2", h * width, what).reshape(h, width)), codec
    data = r.blob(what)
    if coded_size(data, codec) != (width, h):
        raise WireError(f"{what}: not a {width}x{h} {codec} image")
    # The header's size was just checked (within MAX_IMAGE_PIXELS above): the work only.
    problem = coded_work_problem(data, codec)
    if problem:
        raise WireError(f"{what}: {problem}")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    dtype = np.uint8 if itemsize == 1 else np.uint16
    expected = (h, width) if channels == 1 else (h, width, 3)
    if image is None or image.shape != expected or image.dtype != dtype:
        got = "nothing" if image is None else f"{image.shape} {image.dtype}"
        raise WireError(f"{what}: {codec} decoded to {got}, expected {expected} "
                        f"{np.dtype(dtype)}")
    if channels == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return image, codec
