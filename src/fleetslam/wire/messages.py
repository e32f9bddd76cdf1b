"""The two messages besides frames: the cloud's feedback on a frame, and a robot's keyframe
upload for the dense map.

Feedback (Kind.FEEDBACK, cloud -> robot): a fixed 158-byte payload, pose as float64, never
compressed (it would not shrink). Its envelope's split point is 0.

Keyframe upload (Kind.KEYFRAME, robot -> cloud): the RGB-D of one keyframe, decimated by
``stride``; colour as ``WireConfig.keyframe_rgb_codec`` ("jpeg": lossy, it only colours map
points; "png": lossless), depth as the sensor values, lossless (``binary.DEPTH_CODEC``:
left-neighbour differences in byte planes; stores from before it hold 16-bit PNGs).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import WireConfig
from fleetslam.wire.binary import DEPTH_CODEC, Reader, Writer, depth_codec, get_image, put_image
from fleetslam.wire.envelope import Header, Kind, WireError, open_message, seal


def _open(data: bytes, kind: Kind) -> tuple[Header, bytes]:
    header, payload = open_message(data)
    if header.kind != kind:
        raise WireError(f"expected a {kind.name.lower()} message, got {header.kind.name}")
    return header, payload


def _check_timestamp(header: Header, timestamp: float) -> None:
    if timestamp != header.timestamp:
        raise WireError(f"payload timestamp {timestamp} differs from the header's "
                        f"{header.timestamp}")


@dataclass
class Feedback:
    """What the cloud tells a robot about one frame."""

    frame_index: int
    timestamp: float
    tracked: bool
    is_keyframe: bool
    n_inliers: int
    T_world_camera: np.ndarray  # 4 x 4 float64
    cloud_ms: float  # cloud time spent on the frame


def encode_feedback(robot_id: str, seq: int, fb: Feedback) -> bytes:
    T = np.asarray(fb.T_world_camera, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"feedback pose must be 4 x 4, got {T.shape}")
    if not 0 <= fb.n_inliers < 2**32:
        raise ValueError(f"n_inliers {fb.n_inliers} outside 0..2^32-1")
    w = Writer()
    w.pack("qdBBId", fb.frame_index, fb.timestamp, bool(fb.tracked), bool(fb.is_keyframe),
           fb.n_inliers, fb.cloud_ms)
    w.array(T, "f8")
    return seal(Kind.FEEDBACK, robot_id, seq, fb.timestamp, 0, w.getvalue(), compress=False)


def decode_feedback(data: bytes) -> tuple[Header, Feedback]:
    header, payload = _open(data, Kind.FEEDBACK)
    r = Reader(payload, "feedback payload")
    index, timestamp, tracked, is_kf, n_inliers, cloud_ms = r.unpack("qdBBId", "feedback")
    if tracked > 1 or is_kf > 1:
        raise WireError(f"feedback flags {tracked}, {is_kf} are not 0 or 1")
    T = r.array("f8", 16, "feedback pose").reshape(4, 4)
    r.finish()
    _check_timestamp(header, timestamp)
    return header, Feedback(index, timestamp, bool(tracked), bool(is_kf), n_inliers, T, cloud_ms)


@dataclass
class KeyframeUpload:
    """The decimated RGB-D of one keyframe."""

    frame_index: int
    timestamp: float
    stride: int  # every stride-th pixel of every stride-th row of the full frame
    rgb: np.ndarray  # h x w x 3 uint8
    depth_raw: np.ndarray  # h x w uint16 sensor values

    @staticmethod
    def from_frame(index: int, timestamp: float, rgb: np.ndarray, depth_raw: np.ndarray,
                   stride: int) -> "KeyframeUpload":
        if stride < 1:
            raise ValueError(f"stride {stride} must be >= 1")
        return KeyframeUpload(index, timestamp, stride,
                              np.ascontiguousarray(rgb[::stride, ::stride]),
                              np.ascontiguousarray(depth_raw[::stride, ::stride]))


def encode_keyframe(robot_id: str, seq: int, kf: KeyframeUpload, config: WireConfig) -> bytes:
    if kf.rgb.shape[:2] != kf.depth_raw.shape or kf.depth_raw.dtype != np.uint16:
        raise ValueError(f"keyframe rgb {kf.rgb.shape} and depth {kf.depth_raw.shape} "
                         f"{kf.depth_raw.dtype} must be h x w x 3 and h x w uint16")
    if not 1 <= kf.stride <= 0xFFFF:
        raise ValueError(f"stride {kf.stride} outside 1..65535")
    w = Writer()
    w.pack("qdH", kf.frame_index, kf.timestamp, kf.stride)
    put_image(w, kf.rgb, config.keyframe_rgb_codec, config.jpeg_quality)
    put_image(w, kf.depth_raw, depth_codec(config.compress))
    return seal(Kind.KEYFRAME, robot_id, seq, kf.timestamp, 0, w.getvalue(),
                compress=config.compress, level=config.zstd_level)


def decode_keyframe(data: bytes, camera: Camera | None = None) -> tuple[Header, KeyframeUpload]:
    """With ``camera`` (the sender's), images of another size than the camera's decimated by
    the stride are refused before they are decoded (a small message can claim a huge one)."""
    header, payload = _open(data, Kind.KEYFRAME)
    r = Reader(payload, "keyframe payload")
    index, timestamp, stride = r.unpack("qdH", "keyframe header")
    if stride < 1:
        raise WireError("keyframe stride 0")
    size = None if camera is None else (-(-camera.height // stride), -(-camera.width // stride))
    rgb, _ = get_image(r, "keyframe colour", size)
    depth, codec = get_image(r, "keyframe depth", size)
    r.finish()
    # (Stores written before the depth codec hold 16-bit PNGs: both are read.)
    if rgb.ndim != 3 or depth.ndim != 2 or depth.dtype != np.uint16 \
            or codec not in ("png", DEPTH_CODEC):
        raise WireError(f"keyframe colour {rgb.shape} / depth {depth.shape} {depth.dtype} "
                        f"({codec}) are not h x w x 3 and a 16-bit depth image")
    if rgb.shape[:2] != depth.shape:
        raise WireError(f"keyframe colour {rgb.shape[:2]} and depth {depth.shape} differ in size")
    _check_timestamp(header, timestamp)
    return header, KeyframeUpload(index, timestamp, stride, rgb, depth)
