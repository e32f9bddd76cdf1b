"""What a PNG or JPEG holds, read from its own header before it is decoded: a small message
can claim a huge image (a 1.2 MB PNG of 20000 x 20000 pixels decodes to 1.2 GB), and a
valid one can make the decoder work for seconds. Every coded image fleetslam reads (the
wire's keyframe uploads and frames, a bag's or a live ROS 2 topic's compressed images) is
checked here first.
"""

from __future__ import annotations

import struct

# Larger images are refused before decoding (a 4K frame has 8.3 Mpixels).
MAX_IMAGE_PIXELS = 1 << 24
# JPEG start-of-frame markers (baseline, progressive, ...): they carry the image size.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
# Markers (and fill bytes) walked before the size is found: a real JPEG has a handful (APPn,
# DQT, COM); a payload of millions of 4-byte segments would keep this Python loop busy for
# seconds (bench/fuzz_wire.py).
_JPEG_MAX_MARKERS = 1024
# Scans (SOS markers) a JPEG may have: libjpeg's progressive scripts use at most 10. Every
# scan is a pass over the whole image, so thousands of tiny scans take libjpeg seconds at
# MAX_IMAGE_PIXELS (a 36 kB message: 28 s). Entropy-coded data stuffs 0xFF as FF 00, so
# counting FF DA overcounts at most (a thumbnail in an APP segment).
MAX_JPEG_SCANS = 64
# PNG chunks allowed per kB of image: OpenCV's libpng writes 8 kB IDAT chunks, but libpng
# spends microseconds on every chunk however small, so 14 MB of 15-byte iTXt chunks (a 150 kB
# message once zstd-compressed) took it 2.4 s (bench/fuzz_wire.py).
_PNG_CHUNKS_PER_KB = 1
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def codec_of(data: bytes) -> str | None:
    """"png" or "jpeg" by the data's first bytes, else None."""
    if data[:8] == PNG_MAGIC:
        return "png"
    return "jpeg" if data[:2] == b"\xff\xd8" else None


def coded_size(data: bytes, codec: str) -> tuple[int, int] | None:
    """(width, height) from the image's own header, without decoding it."""
    if codec == "png":
        if len(data) < 24 or data[:8] != PNG_MAGIC or data[12:16] != b"IHDR":
            return None
        return struct.unpack(">II", data[16:24])
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    for _ in range(_JPEG_MAX_MARKERS):
        if i + 9 > len(data) or data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in _JPEG_SOF:
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        i += 2 + length
    return None


def png_chunks_bounded(data: bytes) -> bool:
    """At most 16 chunks plus _PNG_CHUNKS_PER_KB per kB (a walk of at most that many steps)."""
    i = 8
    for _ in range(16 + _PNG_CHUNKS_PER_KB * len(data) // 1024):
        if i + 8 > len(data):
            return True
        (length,) = struct.unpack_from(">I", data, i)
        i += 12 + length
    return i + 8 > len(data)


def coded_image_problem(data: bytes, codec: str,
                        expected: tuple[int, int] | None = None) -> str | None:
    """Why the ``codec`` image ``data`` must not be decoded (its header unreadable, more
    than MAX_IMAGE_PIXELS, not ``expected`` (width, height), too many JPEG scans or PNG
    chunks), or None."""
    size = coded_size(data, codec)
    if size is None:
        return f"no {codec} header with the image's size"
    width, height = size
    if width * height > MAX_IMAGE_PIXELS:
        return f"{width} x {height} pixels exceed the limit of {MAX_IMAGE_PIXELS}"
    if expected is not None and (width, height) != tuple(expected):
        return f"{width} x {height} pixels, the camera's images are {expected[0]} x {expected[1]}"
    return coded_work_problem(data, codec)


def coded_work_problem(data: bytes, codec: str) -> str | None:
    """Why an image whose size was checked would still cost its decoder too much (too many
    JPEG scans or PNG chunks), or None."""
    if codec == "jpeg" and data.count(b"\xff\xda") > MAX_JPEG_SCANS:
        return f"more than {MAX_JPEG_SCANS} JPEG scans"
    if codec == "png" and not png_chunks_bounded(data):
        return f"more than {_PNG_CHUNKS_PER_KB} PNG chunk per kB"
    return None
