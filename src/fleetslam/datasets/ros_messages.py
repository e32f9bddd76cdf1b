"""ROS camera messages to numpy images and a ``Camera``: ``sensor_msgs/Image``,
``sensor_msgs/CompressedImage`` (including image_transport's ``compressedDepth``) and
``sensor_msgs/CameraInfo``, as decoded by rosbags from a bag (ROS 1 or ROS 2) or from CDR
off a live topic. Both generations' field names are read (ROS 1 ``K``/``D``, ROS 2
``k``/``d``).

Every function takes ``where`` (the bag and topic, or the Zenoh key) and raises
``RosMessageError`` naming it and what is wrong. Depth follows REP 118: ``16UC1`` in
millimetres, ``32FC1`` in metres (NaN or 0 = no measurement).
"""

from __future__ import annotations

import math
import struct
from typing import Any

import cv2
import numpy as np

from fleetslam.camera import Camera
from fleetslam.io.coded_image import codec_of, coded_image_problem

# 16-bit depth in millimetres (REP 118): 1000 raw values a metre.
MILLIMETRE_DEPTH_SCALE = 1000.0
# 32FC1 depth in metres is carried in the 16-bit raw images of the wire and the dense map at
# this many values a metre: 0.2 mm steps (well below an RGB-D sensor's noise, and exact for
# any sensor whose quantum is a multiple of 0.2 mm), up to 13.1 m.
METRES_DEPTH_SCALE = 5000.0

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
COLOUR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
# Distortion models OpenCV applies with the coefficients in CameraInfo's order.
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")
# image_transport's compressedDepth prefix: int32 format, float32 depthQuantA, depthQuantB.
_COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")


class RosMessageError(ValueError):
    """A camera message fleetslam cannot use; the text names where it came from."""


def stamp_seconds(msg: Any) -> float:
    """The message header's stamp in seconds."""
    stamp = msg.header.stamp
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def _data(msg: Any) -> np.ndarray:
    data = msg.data
    return data if isinstance(data, np.ndarray) else np.frombuffer(bytes(data), np.uint8)


def _image_pixels(msg: Any, where: str, dtype: np.dtype, channels: int) -> np.ndarray:
    """An Image's rows as an (h, w[, c]) array, honouring ``step`` padding and byte order."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    itemsize = np.dtype(dtype).itemsize
    row = w * channels * itemsize
    data = _data(msg)
    if h <= 0 or w <= 0:
        raise RosMessageError(f"{where}: image of {w} x {h} pixels")
    if step < row or data.size < step * (h - 1) + row:
        raise RosMessageError(f"{where}: {msg.encoding} image {w} x {h} with step {step} needs "
                              f"{step * (h - 1) + row} bytes, the message has {data.size}")
    rows = np.lib.stride_tricks.as_strided(data, (h, row), (step, 1))
    order = ">" if msg.is_bigendian else "<"
    # A copy, always: without padding ascontiguousarray returned a view of the message's
    # buffer, read-only when decoded from a bag, where a frame's images must be its own.
    pixels = rows.copy().view(np.dtype(dtype).newbyteorder(order))
    pixels = pixels.astype(np.dtype(dtype).newbyteorder("="), copy=False)
    return pixels.reshape((h, w, channels) if channels > 1 else (h, w))


def _decode_coded(data: np.ndarray, flags: int, where: str, what: str,
                  size: tuple[int, int] | None) -> np.ndarray | None:
    """cv2.imdecode of a PNG or JPEG once its header says it is worth decoding (within the
    pixel limit, ``size`` (width, height) where the camera is known); RosMessageError
    otherwise. None: OpenCV could not decode it."""
    raw = data.tobytes()
    codec = codec_of(raw)
    if codec is None:
        raise RosMessageError(f"{where}: {what} ({data.size} bytes) is neither PNG nor JPEG")
    problem = coded_image_problem(raw, codec, size)
    if problem:
        raise RosMessageError(f"{where}: {what} not decoded: {problem}")
    return cv2.imdecode(data, flags)


def colour_image(msg: Any, where: str, size: tuple[int, int] | None = None) -> np.ndarray:
    """An Image or CompressedImage to H x W x 3 uint8 RGB; ``size``: the camera's (width,
    height), which a compressed image must have before it is decoded."""
    if hasattr(msg, "format"):
        return _compressed_colour(msg, where, size)
    encoding = str(msg.encoding)
    if encoding in ("rgb8", "bgr8"):
        pixels = _image_pixels(msg, where, np.uint8, 3)
        return pixels if encoding == "rgb8" else pixels[..., ::-1].copy()
    if encoding in ("rgba8", "bgra8"):
        pixels = _image_pixels(msg, where, np.uint8, 4)
        return np.ascontiguousarray(pixels[..., :3] if encoding == "rgba8"
                                    else pixels[..., 2::-1])
    if encoding == "mono8":
        return np.repeat(_image_pixels(msg, where, np.uint8, 1)[..., None], 3, axis=2)
    raise RosMessageError(f"{where}: colour encoding {encoding!r} is not supported "
                          f"(use one of {', '.join(COLOUR_ENCODINGS)})")


def _compressed_colour(msg: Any, where: str, size: tuple[int, int] | None) -> np.ndarray:
    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower():
        raise RosMessageError(f"{where}: a compressedDepth image ({fmt!r}) is depth, not colour")
    image = _decode_coded(_data(msg), cv2.IMREAD_COLOR, where, f"compressed image ({fmt!r})",
                          size)
    if image is None:
        raise RosMessageError(f"{where}: compressed image ({fmt!r}, {_data(msg).size} bytes) "
                              f"does not decode as JPEG or PNG")
    # image_transport names the compressed image's channel order after "compressed"; OpenCV
    # decodes to BGR, which is what cv_bridge stores unless it says rgb8.
    if fmt.replace(" ", "").lower().endswith("compressedrgb8"):
        return np.ascontiguousarray(image)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def image_format(msg: Any) -> str:
    """An Image's encoding or a CompressedImage's format, as the message says it."""
    return str(msg.format) if hasattr(msg, "format") else str(msg.encoding)


def image_role(msg: Any) -> str | None:
    """"colour" or "depth" by the message's encoding or format; None if fleetslam reads
    neither (e.g. yuv422)."""
    if hasattr(msg, "format"):
        return "depth" if "compresseddepth" in str(msg.format).lower() else "colour"
    encoding = str(msg.encoding)
    if encoding in COLOUR_ENCODINGS:
        return "colour"
    return "depth" if encoding in DEPTH_ENCODINGS else None


def depth_image_scale(msg: Any, where: str) -> float:
    """Raw depth values a metre for the wire's 16-bit images of this depth topic."""
    encoding = _depth_encoding(msg, where)
    return MILLIMETRE_DEPTH_SCALE if encoding == "16UC1" else METRES_DEPTH_SCALE


def _depth_encoding(msg: Any, where: str) -> str:
    if hasattr(msg, "format"):
        fmt = str(msg.format)
        if "compresseddepth" not in fmt.lower():
            raise RosMessageError(f"{where}: compressed depth must be image_transport's "
                                  f"compressedDepth, got format {fmt!r}")
        encoding = fmt.split(";")[0].strip()
    else:
        encoding = str(msg.encoding)
    if encoding == "mono16":
        encoding = "16UC1"
    if encoding not in ("16UC1", "32FC1"):
        raise RosMessageError(f"{where}: depth encoding {encoding!r} is not supported "
                              f"(use one of {', '.join(DEPTH_ENCODINGS)})")
    return encoding


def depth_image(msg: Any, where: str, scale: float, size: tuple[int, int] | None = None
                ) -> np.ndarray:
    """An Image or compressedDepth CompressedImage to H x W uint16 at ``scale`` raw values a
    metre; no measurement (0, NaN, infinite, out of the 16-bit range) is 0. ``size``: as
    colour_image's."""
    encoding = _depth_encoding(msg, where)
    if hasattr(msg, "format"):
        metres_or_mm = _compressed_depth(msg, where, encoding, size)
    elif encoding == "16UC1":
        metres_or_mm = _image_pixels(msg, where, np.uint16, 1)
    else:
        metres_or_mm = _image_pixels(msg, where, np.float32, 1)
    if metres_or_mm.dtype == np.uint16:
        if scale == MILLIMETRE_DEPTH_SCALE:
            return metres_or_mm
        metres = metres_or_mm.astype(np.float64) / MILLIMETRE_DEPTH_SCALE
        metres[metres_or_mm == 0] = np.nan
    else:
        # float32 throughout (half the time of float64, bench/robot_cpu.py's bag camera):
        # a reading of n raw units came as float32(n / scale), within 1e-7 of it, so
        # rounding its product with ``scale`` gives n back either way.
        metres = metres_or_mm
    with np.errstate(invalid="ignore", over="ignore"):
        raw = np.rint(metres * np.asarray(scale, metres.dtype))
        # NaN and infinite compare false: no measurement.
        raw[~((raw > 0) & (raw <= 0xFFFF))] = 0
    return raw.astype(np.uint16)


def _compressed_depth(msg: Any, where: str, encoding: str, size: tuple[int, int] | None
                      ) -> np.ndarray:
    data = _data(msg)
    if data.size <= _COMPRESSED_DEPTH_HEADER.size:
        raise RosMessageError(f"{where}: compressedDepth message of {data.size} bytes")
    _, quant_a, quant_b = _COMPRESSED_DEPTH_HEADER.unpack(data[:_COMPRESSED_DEPTH_HEADER.size]
                                                          .tobytes())
    png = _decode_coded(data[_COMPRESSED_DEPTH_HEADER.size:], cv2.IMREAD_UNCHANGED, where,
                        "compressedDepth payload", size)
    if png is None or png.dtype != np.uint16 or png.ndim != 2:
        raise RosMessageError(f"{where}: compressedDepth payload is not a 16-bit PNG")
    if encoding == "16UC1":
        return png
    # 32FC1 is stored as quantised inverse depth: depth = A / (value - B), 0 = none.
    with np.errstate(divide="ignore", invalid="ignore"):
        metres = quant_a / (png.astype(np.float32) - quant_b)
    metres[png == 0] = np.nan
    return metres.astype(np.float32)


def camera_from_info(msg: Any, where: str, depth_scale: float,
                     depth_info: Any = None, depth_where: str = "") -> Camera:
    """The colour camera of a CameraInfo; with the depth topic's CameraInfo, the pinhole the
    depth image is registered to where it differs from the colour camera's model (TUM
    freiburg1/2's OpenNI registration, see camera.py)."""
    fx, fy, cx, cy, width, height, distortion = _intrinsics(msg, where)
    depth_intrinsics: tuple[float, ...] = ()
    if depth_info is not None:
        dfx, dfy, dcx, dcy, dwidth, dheight, ddistortion = _intrinsics(depth_info, depth_where)
        if (dwidth, dheight) != (width, height):
            raise RosMessageError(
                f"{depth_where}: depth camera {dwidth} x {dheight} is not registered to the "
                f"colour camera {width} x {height} ({where}); fleetslam needs depth aligned "
                f"to colour (e.g. a driver's aligned_depth_to_color topic)")
        # Distortions of different lengths (plumb_bob 5, rational_polynomial 8) differ;
        # np.allclose would raise on their shapes instead.
        same = np.allclose((dfx, dfy, dcx, dcy), (fx, fy, cx, cy)) and \
            len(ddistortion) == len(distortion) and np.allclose(ddistortion, distortion)
        if not same:
            if any(abs(d) > 0 for d in ddistortion):
                raise RosMessageError(
                    f"{depth_where}: depth camera with its own distortion differs from the "
                    f"colour camera ({where}): fleetslam needs depth registered to colour, "
                    f"or to an undistorted pinhole")
            depth_intrinsics = (dfx, dfy, dcx, dcy)
    camera = Camera(fx, fy, cx, cy, width, height, distortion, depth_scale=depth_scale,
                    invalid_depth=(0,), depth_intrinsics=depth_intrinsics)
    try:  # what the cloud checks a hello's camera for, so a run refuses what a cloud would
        return Camera.from_dict(camera.to_dict(), f"{where}: CameraInfo")
    except ValueError as exc:
        raise RosMessageError(str(exc)) from None


def _intrinsics(msg: Any, where: str) -> tuple[float, float, float, float, int, int,
                                               tuple[float, ...]]:
    K = [float(v) for v in (msg.k if hasattr(msg, "k") else msg.K)]
    D = [float(v) for v in (msg.d if hasattr(msg, "d") else msg.D)]
    width, height = int(msg.width), int(msg.height)
    if len(K) != 9 or not all(math.isfinite(v) for v in K + D):
        raise RosMessageError(f"{where}: CameraInfo K must be 9 finite numbers, got {K}")
    fx, fy, cx, cy = K[0], K[4], K[2], K[5]
    if not (fx > 0 and fy > 0 and cx > 0 and cy > 0 and width > 0 and height > 0):
        raise RosMessageError(f"{where}: CameraInfo is not calibrated (fx {fx}, fy {fy}, "
                              f"cx {cx}, cy {cy}, {width} x {height}): a camera driver "
                              f"publishes zeros before calibration; give --camera camera.json")
    model = str(msg.distortion_model)
    if any(abs(d) > 0 for d in D) and model not in DISTORTION_MODELS:
        raise RosMessageError(f"{where}: distortion model {model!r} is not supported "
                              f"(use one of {', '.join(DISTORTION_MODELS)})")
    distortion = tuple(D) if any(abs(d) > 0 for d in D) else ()
    return fx, fy, cx, cy, width, height, distortion
