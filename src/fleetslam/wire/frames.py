"""The frame message: the pipeline state at split point k (states.py) as a binary payload.

Exactness: the cloud's stages (stages[k:]) give bit-identical poses and keyframe decisions
whether the state came in memory or through encode -> decode. Everything a later stage reads
is reproduced bit for bit:

- images: PNG (lossless) by default; depth as the 16-bit sensor values, lossless
  (``camera.depth_scale``; ``binary.DEPTH_CODEC``), turned back into the very float32 metres of
  ``Camera.depth_to_metres``. With ``frame_image_codec = "jpeg"`` colour (k=0) and grey (k=1)
  images are lossy, and the cloud's results differ.
- keypoints at k=1 (Describe reads pt, size, angle, octave): the N x 7 float32 table as is.
- keypoints at k>=2 (later stages read x, y, octave): OpenCV's ORB puts a keypoint of octave o
  at integer coordinates of the level-o image times the level's float32 scale. They are sent
  as those integers (delta-coded within a level, in the keypoints' own order) with one scale
  per level, and rebuilt with the same float32 multiply. The encoder checks every keypoint
  and sends raw float32 x, y for the whole message if one is not exactly so. ``size`` is one
  value per octave (raw column otherwise), ``class_id`` one constant (raw column otherwise).
- depth per keypoint (k>=3): a pixel of the depth image or 0, sent as its uint16 sensor value
  (raw float32 if a value is not one).
- ``uv`` (undistorted coordinates) is not sent: the cloud recomputes it with
  ``camera.undistort_points`` exactly as AssociateDepth does (the encoder checks this and
  sends uv as float64 if it differs).
- descriptors as raw bytes; landmark ids (int32 if in range), their float64 world points for
  the matched rows, float64 poses, inlier bits and flags as they are.
- k=6 (the robot tracked): the result (``TrackedPose``: pose, flags, inlier count,
  reference keyframe and the pose relative to it); no stage runs after it. A keyframe also
  carries what the cloud's map merger needs: its features (coded as at k=3) and every
  keyframe's pose (K x 3 x 4 float64, the rigid last row implied), so a robot that tracks
  itself joins the global map; or, to a cloud that takes them, only the poses changed since a
  table the cloud applied (the base message's seq, K, a bit per keyframe, those poses:
  wire/pose_deltas.py). The robot's TrackedFrame goes in, a TrackedPose comes out.

Quantised or dropped, as no stage after Describe reads them (k>=2 only):
- ``angle``: uint8 steps of 360/256 degrees (1.4 deg);
- ``response``: not sent, decoded as 0;
- NaN world points of unmatched rows come back as the standard NaN.

The payload also carries a digest of the camera (intrinsics, distortion, depth scale, depth
image model), so a cloud that would rebuild uv or depth with another camera rejects the
message instead.

Layout, for zstd: every array is its own column (numbers byte-shuffled, descriptors column
by column, keypoint positions as byte planes, depth as a palette of the few distinct sensor
values plus one index byte per keypoint), and ``encode_frame_message`` gives each column its
own zstd block. Measured (bench/payload.py, frames with 1000 keypoints, k = 3): 35.5 kB on
7-Scenes, 34.9 kB on TUM fr1_rpy, of which ~31 kB are descriptors.
"""

from __future__ import annotations

import struct
import zlib
from typing import Any, Callable, Protocol

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import WireConfig
from fleetslam.pipeline.split import INTER_POINTS
from fleetslam.pipeline.states import (
    CapturedFrame,
    DescribedFrame,
    DetectedFrame,
    FeatureFrame,
    MatchedFrame,
    PosedFrame,
    TrackedFrame,
    TrackedPose,
)
from fleetslam.wire.binary import (
    Reader,
    Writer,
    check_codec,
    depth_codec,
    get_image,
    put_image,
)
from fleetslam.wire.envelope import N_SPLIT_POINTS, Header, Kind, WireError, open_message, seal
from fleetslam.wire.inter import (
    MAX_REFERENCES,
    InterStats,
    MissingReference,
    Reference,
    features_of,
    get_inter_descriptors,
    put_inter_descriptors,
    quantised_angles,
    whole_octaves,
)
from fleetslam.wire.pose_deltas import PoseDelta

State = Any
STATE_TYPES: tuple[type, ...] = (CapturedFrame, DetectedFrame, DescribedFrame, FeatureFrame,
                                 MatchedFrame, PosedFrame, TrackedFrame)
assert len(STATE_TYPES) == N_SPLIT_POINTS

# Keypoint table columns (states.KEYPOINT_COLUMNS).
X, Y, SIZE, ANGLE, RESPONSE, OCTAVE, CLASS_ID = range(7)
MAX_OCTAVES = 32
# A decoded keypoint table is at most 28 MB, whatever a payload claims (ORB: ~1000).
MAX_KEYPOINTS = 1 << 20
# A level's scale is searched this many float32 steps around size[o] / size[0].
_SCALE_SEARCH_ULPS = 4

_KP_RAW, _KP_COMPACT = 0, 1
# What a point-6 message carries after its result: nothing (not a keyframe), a keyframe's
# features with all its keyframes' poses, or with those changed since a table the cloud
# applied (wire/pose_deltas.py; a cloud that predates them rejects 2, and says nothing of
# them in its welcome, so robots send it 1).
POSES_NONE, POSES_WHOLE, POSES_DELTA = 0, 1, 2
_KP_XY_RAW, _KP_SIZE_RAW, _KP_CLASS_RAW = 1, 2, 4
_VALUES_PALETTE, _VALUES_F32 = 0, 1
_DEPTH_IMAGE, _DEPTH_F32 = 0, 1  # 16-bit (an image codec's: PNG, or DEPTH_CODEC), or floats
_UV_RECOMPUTE, _UV_F64 = 0, 1
_IDS_I32, _IDS_I64 = 0, 1
_XYZ_MATCHED, _XYZ_ALL = 0, 1


class _Coding:
    """How a message codes its descriptors: alone (``refs`` None) or against reference
    frames (wire/inter.py), which then also carry the keypoint angles."""

    def __init__(self, refs: list[Reference] | None = None,
                 stats: InterStats | None = None, octave_window: int | None = None) -> None:
        self.refs = refs
        self.stats = stats
        self.angles: np.ndarray | None = None  # quantised angles left to the descriptors
        # The keypoints' levels (compact table) and how far from its own level a descriptor's
        # reference is searched (the robot's choice; nothing of it is sent).
        self.octaves: np.ndarray | None = None
        self.octave_window = octave_window
        # Point 6: a keyframe's poses against a table the cloud applied (wire/pose_deltas.py).
        self.poses: PoseDelta | None = None


INTRA = _Coding()


def camera_digest(camera: Camera) -> int:
    """CRC-32 of what decoding depends on: intrinsics, distortion, depth scale, depth
    image model."""
    values = (camera.fx, camera.fy, camera.cx, camera.cy, camera.depth_scale,
              *camera.distortion, *camera.depth_intrinsics)
    return zlib.crc32(struct.pack(f"<{len(values)}d", *values))


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal bit for bit (unlike ==, tells -0.0 from 0.0)."""
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and a.tobytes() == b.tobytes()


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


# ---------------------------------------------------------------------------------------
# Depth images and per-keypoint depth
# ---------------------------------------------------------------------------------------


def _put_depth_image(w: Writer, depth_m: np.ndarray, camera: Camera,
                     config: WireConfig) -> None:
    _require(depth_m.ndim == 2 and depth_m.dtype == np.float32,
             f"depth image must be H x W float32, got {depth_m.shape} {depth_m.dtype}")
    raw = camera.metres_to_depth(depth_m)
    if raw is not None:
        w.pack("B", _DEPTH_IMAGE)
        put_image(w, raw, depth_codec(config.compress))
    else:
        w.pack("BHH", _DEPTH_F32, *depth_m.shape)
        w.shuffled(depth_m, "f4")


def _get_depth_image(r: Reader, camera: Camera) -> np.ndarray:
    (mode,) = r.unpack("B", "depth image mode")
    if mode == _DEPTH_IMAGE:
        raw, _ = get_image(r, "depth image", (camera.height, camera.width))
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise WireError(f"depth image is {raw.shape} {raw.dtype}, expected 16-bit grey")
        return camera.depth_to_metres(raw)
    if mode == _DEPTH_F32:
        h, width = r.unpack("HH", "depth image size")
        return r.shuffled("f4", h * width, "depth image").reshape(h, width)
    raise WireError(f"unknown depth image mode {mode}")


def _put_depth_values(w: Writer, depth: np.ndarray, camera: Camera) -> None:
    raw = camera.metres_to_depth(depth)
    if raw is None:
        w.pack("B", _VALUES_F32)
        w.shuffled(depth, "f4")
        return
    # Keypoints sit on a few surfaces and the sensor quantises depth: ~150 distinct values
    # among 1000 keypoints. A sorted palette (delta-coded) and one byte per keypoint.
    palette, index = np.unique(raw, return_inverse=True)
    w.pack("BI", _VALUES_PALETTE, len(palette))
    w.array(np.diff(palette.astype(np.int64), prepend=0), "u2")
    w.array(index, "u1" if len(palette) <= 256 else "u2")


def _get_depth_values(r: Reader, n: int, camera: Camera) -> np.ndarray:
    (mode,) = r.unpack("B", "keypoint depth mode")
    if mode == _VALUES_PALETTE:
        (n_palette,) = r.unpack("I", "depth palette size")
        palette = np.cumsum(r.array("u2", n_palette, "depth palette").astype(np.int64))
        index = r.array("u1" if n_palette <= 256 else "u2", n, "keypoint depth").astype(np.int64)
        if n and (index.max() >= n_palette or palette[-1] > 0xFFFF):
            raise WireError(f"keypoint depth refers past its {n_palette}-value palette")
        return camera.depth_to_metres(palette.astype(np.uint16)[index])
    if mode == _VALUES_F32:
        return r.shuffled("f4", n, "keypoint depth")
    raise WireError(f"unknown keypoint depth mode {mode}")


# ---------------------------------------------------------------------------------------
# Keypoints
# ---------------------------------------------------------------------------------------


def _check_keypoints(kp: np.ndarray) -> None:
    _require(kp.ndim == 2 and kp.shape[1] == 7 and kp.dtype == np.float32,
             f"keypoints must be N x 7 float32, got {kp.shape} {kp.dtype}")
    _require(len(kp) <= MAX_KEYPOINTS, f"{len(kp)} keypoints exceed {MAX_KEYPOINTS}")


def _keypoint_count(r: Reader) -> int:
    (n,) = r.unpack("I", "keypoint count")
    # _check_content refuses more than MAX_FRAME_KEYPOINTS anyway: refusing them here saves
    # reading up to 60 MB of keypoints and descriptors a zstd bomb can declare (~0.3 s).
    if n > MAX_FRAME_KEYPOINTS:
        raise WireError(f"keypoint count {n} exceeds the limit of {MAX_FRAME_KEYPOINTS}")
    return n


def _level_scales(kp: np.ndarray, octave: np.ndarray, n_levels: int,
                  level_size: np.ndarray | None) -> np.ndarray | None:
    """The float32 scale of each level such that every keypoint's x and y is
    float32(integer) * scale exactly, or None. Candidates come from the size per level
    (ORB: patch size times the scale)."""
    if level_size is None or not (octave == 0).any() or not level_size[0] > 0:
        return None
    scales = np.ones(n_levels, np.float32)
    for o in range(n_levels):  # a handful of levels; the keypoints are vectorised
        xy = kp[octave == o][:, :2]
        if not len(xy):
            continue
        guess = np.float32(float(level_size[o]) / float(level_size[0]))
        found = False
        for step in sorted(range(-_SCALE_SEARCH_ULPS, _SCALE_SEARCH_ULPS + 1), key=abs):
            s = guess
            for _ in range(abs(step)):
                s = np.nextafter(s, np.float32(np.inf if step > 0 else -np.inf))
            if not s > 0:
                continue
            with np.errstate(invalid="ignore", over="ignore"):
                i = np.rint(xy / s)
                ok = (i >= 0).all() and (i < 0xFFFF).all()  # level widths are u16
            if ok and _same_bits(i.astype(np.float32) * s, xy):
                scales[o], found = s, True
                break
        if not found:
            return None
    return scales


def _zigzag(d: np.ndarray) -> np.ndarray:
    return (d << 1) ^ (d >> 63)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    return (z >> 1) ^ -(z & 1)


def _put_keypoints(w: Writer, kp: np.ndarray, ctx: _Coding = INTRA) -> None:
    """The compact keypoint table of split points >= 2 (see the module docstring). An
    inter-coded frame sends the angles with its descriptors (``ctx.angles``)."""
    _check_keypoints(kp)
    n = len(kp)
    octave = whole_octaves(kp)
    if octave is None or (n and octave.max() >= MAX_OCTAVES):
        w.pack("IB", n, _KP_RAW)
        w.shuffled(kp, "f4")
        return
    n_levels = int(octave.max()) + 1 if n else 0
    level_size: np.ndarray | None = np.zeros(n_levels, np.float32)
    level_size[octave] = kp[:, SIZE]
    if not _same_bits(level_size[octave], kp[:, SIZE]):
        level_size = None
    class_id = kp[:1, CLASS_ID]
    class_constant = _same_bits(np.broadcast_to(class_id, (n,)), kp[:, CLASS_ID])
    scales = _level_scales(kp, octave, n_levels, level_size)
    flags = ((_KP_XY_RAW if scales is None else 0) | (_KP_SIZE_RAW if level_size is None else 0)
             | (_KP_CLASS_RAW if not class_constant else 0))
    w.pack("IBBB", n, _KP_COMPACT, flags, n_levels)
    w.array(octave, "u1")  # ORB lists keypoints level by level: runs that zstd removes
    if scales is None:
        w.shuffled(kp[:, X], "f4")
        w.shuffled(kp[:, Y], "f4")
    else:
        ix = np.rint(kp[:, X] / scales[octave]).astype(np.int64)
        iy = np.rint(kp[:, Y] / scales[octave]).astype(np.int64)
        width = np.ones(n_levels, np.int64)
        np.maximum.at(width, octave, ix + 1)
        # Position within the level image, delta to the previous keypoint of the same level:
        # FAST finds corners row by row, so these are mostly small and positive.
        order = np.argsort(octave, kind="stable")
        pos = (iy * width[octave] + ix)[order]
        first = np.r_[True, octave[order][1:] != octave[order][:-1]] if n else np.zeros(0, bool)
        delta = pos - np.where(first, 0, np.r_[0, pos[:-1]])
        z = _zigzag(delta)
        n_bytes = max(1, (int(z.max()).bit_length() + 7) // 8) if n else 1
        w.array(scales, "f4")
        w.array(width, "u2")
        w.pack("B", n_bytes)
        w.planes(z, n_bytes)
    if level_size is None:
        w.shuffled(kp[:, SIZE], "f4")
    else:
        w.array(level_size, "f4")
    if class_constant:
        w.array(class_id if n else np.zeros(1, np.float32), "f4")
    else:
        w.shuffled(kp[:, CLASS_ID], "f4")
    if ctx.refs is not None:
        ctx.angles = quantised_angles(kp)
        ctx.octaves = octave
    else:
        w.array(quantised_angles(kp), "u1")


def _get_keypoints(r: Reader, ctx: _Coding = INTRA) -> np.ndarray:
    n = _keypoint_count(r)
    (mode,) = r.unpack("B", "keypoint mode")
    if mode == _KP_RAW:
        return r.shuffled("f4", n * 7, "keypoints").reshape(n, 7)
    if mode != _KP_COMPACT:
        raise WireError(f"unknown keypoint mode {mode}")
    flags, n_levels = r.unpack("BB", "keypoint flags")
    if flags & ~(_KP_XY_RAW | _KP_SIZE_RAW | _KP_CLASS_RAW) or n_levels > MAX_OCTAVES:
        raise WireError(f"bad keypoint flags 0x{flags:02x} or {n_levels} levels")
    octave = r.array("u1", n, "octaves").astype(np.int64)
    if n and octave.max() >= n_levels:
        raise WireError(f"keypoint octave {octave.max()} outside the {n_levels} levels sent")
    kp = np.zeros((n, 7), np.float32)
    kp[:, OCTAVE] = octave
    if flags & _KP_XY_RAW:
        kp[:, X] = r.shuffled("f4", n, "keypoint x")
        kp[:, Y] = r.shuffled("f4", n, "keypoint y")
    else:
        scales = r.array("f4", n_levels, "level scales").astype(np.float32)
        width = r.array("u2", n_levels, "level widths").astype(np.int64)
        (n_bytes,) = r.unpack("B", "position bytes")
        if not 1 <= n_bytes <= 5 or (n and width[octave].min() < 1):
            raise WireError(f"bad keypoint positions ({n_bytes} bytes, widths {width.tolist()})")
        delta = _unzigzag(r.planes(n_bytes, n, "keypoint positions"))
        order = np.argsort(octave, kind="stable")
        first = np.r_[True, octave[order][1:] != octave[order][:-1]] if n else np.zeros(0, bool)
        # Undo the per-level deltas: a running sum, minus what it had reached before the
        # keypoint's level began.
        total = np.cumsum(delta)
        level_start = np.maximum.accumulate(np.where(first, np.arange(n), 0))
        pos = np.empty(n, np.int64)
        pos[order] = total - (total - delta)[level_start]
        ix, iy = pos % width[octave], pos // width[octave]
        kp[:, X] = ix.astype(np.float32) * scales[octave]
        kp[:, Y] = iy.astype(np.float32) * scales[octave]
    if flags & _KP_SIZE_RAW:
        kp[:, SIZE] = r.shuffled("f4", n, "keypoint size")
    else:
        kp[:, SIZE] = r.array("f4", n_levels, "level sizes")[octave]
    if flags & _KP_CLASS_RAW:
        kp[:, CLASS_ID] = r.shuffled("f4", n, "keypoint class id")
    else:
        kp[:, CLASS_ID] = r.array("f4", 1, "keypoint class id")[0]
    if ctx.refs is not None:
        ctx.angles = np.zeros(0, np.uint8)  # (with the descriptors)
    else:
        kp[:, ANGLE] = _angles(r.array("u1", n, "keypoint angle"))
    return kp


def _angles(steps: np.ndarray) -> np.ndarray:
    return steps.astype(np.float32) * np.float32(360 / 256)


def _put_raw_keypoints(w: Writer, kp: np.ndarray) -> None:
    _check_keypoints(kp)
    w.pack("I", len(kp))
    w.shuffled(kp, "f4")


def _get_raw_keypoints(r: Reader) -> np.ndarray:
    n = _keypoint_count(r)
    return r.shuffled("f4", n * 7, "keypoints").reshape(n, 7)


def _put_descriptors(w: Writer, descriptors: np.ndarray, n: int, ctx: _Coding = INTRA) -> None:
    _require(descriptors.shape == (n, 32) and descriptors.dtype == np.uint8,
             f"descriptors must be {n} x 32 uint8, got {descriptors.shape} {descriptors.dtype}")
    if ctx.refs is not None:
        return put_inter_descriptors(w, descriptors, ctx.angles, ctx.refs, ctx.stats,
                                     ctx.octaves, ctx.octave_window)
    # Column by column, each its own zstd block: every byte position has its own bit biases,
    # which zstd exploits only with a table per position (TUM fr1_rpy 4 % smaller, 7-Scenes
    # 1 %; row by row zstd level 3 gains nothing).
    w.columns(descriptors)


def _get_descriptors(r: Reader, kp: np.ndarray, ctx: _Coding = INTRA) -> np.ndarray:
    if ctx.refs is None:
        return r.columns(len(kp), 32, "descriptors")
    descriptors, angles = get_inter_descriptors(r, len(kp), ctx.refs, ctx.angles is not None)
    if angles is not None:
        kp[:, ANGLE] = _angles(angles)
    return descriptors


# ---------------------------------------------------------------------------------------
# States, one encoder and one decoder per split point; later states nest earlier ones
# ---------------------------------------------------------------------------------------


def _put_captured(w: Writer, s: CapturedFrame, camera: Camera, config: WireConfig,
                   ctx: _Coding = INTRA) -> None:
    _require(s.rgb.ndim == 3 and s.rgb.shape[2] == 3 and s.rgb.dtype == np.uint8,
             f"rgb must be H x W x 3 uint8, got {s.rgb.shape} {s.rgb.dtype}")
    put_image(w, s.rgb, config.frame_image_codec, config.jpeg_quality)
    _put_depth_image(w, s.depth_m, camera, config)


def _get_captured(r: Reader, index: int, timestamp: float, camera: Camera,
                   ctx: _Coding = INTRA) -> CapturedFrame:
    rgb, _ = get_image(r, "rgb image", (camera.height, camera.width))
    if rgb.ndim != 3:
        raise WireError(f"rgb image has shape {rgb.shape}")
    return CapturedFrame(index, timestamp, rgb, _get_depth_image(r, camera))


def _put_detected(w: Writer, s: DetectedFrame, camera: Camera, config: WireConfig,
                   ctx: _Coding = INTRA) -> None:
    _require(s.gray.ndim == 2 and s.gray.dtype == np.uint8,
             f"grey image must be H x W uint8, got {s.gray.shape} {s.gray.dtype}")
    put_image(w, s.gray, config.frame_image_codec, config.jpeg_quality)
    _put_depth_image(w, s.depth_m, camera, config)
    _put_raw_keypoints(w, s.keypoints)


def _get_detected(r: Reader, index: int, timestamp: float, camera: Camera,
                   ctx: _Coding = INTRA) -> DetectedFrame:
    gray, _ = get_image(r, "grey image", (camera.height, camera.width))
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise WireError(f"grey image is {gray.shape} {gray.dtype}")
    depth = _get_depth_image(r, camera)
    return DetectedFrame(index, timestamp, gray, depth, _get_raw_keypoints(r))


def _put_described(w: Writer, s: DescribedFrame, camera: Camera, config: WireConfig,
                    ctx: _Coding = INTRA) -> None:
    _put_depth_image(w, s.depth_m, camera, config)
    _put_keypoints(w, s.keypoints, ctx)
    _put_descriptors(w, s.descriptors, len(s.keypoints), ctx)


def _get_described(r: Reader, index: int, timestamp: float, camera: Camera,
                    ctx: _Coding = INTRA) -> DescribedFrame:
    depth = _get_depth_image(r, camera)
    kp = _get_keypoints(r, ctx)
    return DescribedFrame(index, timestamp, depth, kp, _get_descriptors(r, kp, ctx))


def _undistort(kp: np.ndarray, camera: Camera) -> np.ndarray:
    # Exactly AssociateDepth's call, so the result is the same bits.
    return camera.undistort_points(kp[:, :2].astype(np.float64))


def _put_features(w: Writer, f: FeatureFrame, camera: Camera, config: WireConfig,
                   ctx: _Coding = INTRA) -> None:
    n = len(f.keypoints)
    _put_keypoints(w, f.keypoints, ctx)
    _put_descriptors(w, f.descriptors, n, ctx)
    _require(f.depth.shape == (n,) and f.depth.dtype == np.float32,
             f"keypoint depth must be {n} float32, got {f.depth.shape} {f.depth.dtype}")
    _put_depth_values(w, f.depth, camera)
    uv = np.asarray(f.uv)
    _require(uv.shape == (n, 2), f"uv must be {n} x 2, got {uv.shape}")
    if _same_bits(_undistort(f.keypoints, camera), uv):
        w.pack("B", _UV_RECOMPUTE)
    else:
        w.pack("B", _UV_F64)
        w.shuffled(uv, "f8")


def _get_features(r: Reader, index: int, timestamp: float, camera: Camera,
                   ctx: _Coding = INTRA) -> FeatureFrame:
    kp = _get_keypoints(r, ctx)
    n = len(kp)
    descriptors = _get_descriptors(r, kp, ctx)
    depth = _get_depth_values(r, n, camera)
    (uv_mode,) = r.unpack("B", "uv mode")
    if uv_mode == _UV_RECOMPUTE:
        uv = _undistort(kp, camera)
    elif uv_mode == _UV_F64:
        uv = r.shuffled("f8", 2 * n, "uv").reshape(n, 2)
    else:
        raise WireError(f"unknown uv mode {uv_mode}")
    return FeatureFrame(index, timestamp, kp, descriptors, depth, uv)


def _put_pose(w: Writer, T: np.ndarray, what: str) -> None:
    T = np.asarray(T)
    _require(T.shape == (4, 4), f"{what} must be 4 x 4, got {T.shape}")
    w.array(T.astype(np.float64), "f8")


def _get_pose(r: Reader, what: str) -> np.ndarray:
    return r.array("f8", 16, what).reshape(4, 4)


def _put_matched(w: Writer, s: MatchedFrame, camera: Camera, config: WireConfig,
                  ctx: _Coding = INTRA) -> None:
    _put_features(w, s.features, camera, config, ctx)
    n = len(s.features.keypoints)
    ids, xyz = np.asarray(s.landmark_ids), np.asarray(s.landmark_xyz, dtype=np.float64)
    _require(ids.shape == (n,) and xyz.shape == (n, 3),
             f"landmark ids {ids.shape} / points {xyz.shape} do not match {n} keypoints")
    matched = ids >= 0
    # Unmatched rows are -1 / NaN: send which rows match, then only their ids and points.
    ids_mode = _IDS_I32 if (not n or (ids.min() >= -1 and ids.max() < 2**31)) else _IDS_I64
    xyz_mode = _XYZ_MATCHED if np.isnan(xyz[~matched]).all() else _XYZ_ALL
    w.pack("BB", ids_mode, xyz_mode)
    w.bits(matched)
    if ids_mode == _IDS_I32:
        w.shuffled(ids[matched], "i4")
    else:
        w.shuffled(ids, "i8")
    w.shuffled(xyz[matched] if xyz_mode == _XYZ_MATCHED else xyz, "f8")
    _put_pose(w, s.T_world_camera_predicted, "predicted pose")
    w.pack("B", bool(s.repeated))


def _get_matched(r: Reader, index: int, timestamp: float, camera: Camera,
                  ctx: _Coding = INTRA) -> MatchedFrame:
    features = _get_features(r, index, timestamp, camera, ctx)
    n = len(features.keypoints)
    ids_mode, xyz_mode = r.unpack("BB", "landmark modes")
    if ids_mode not in (_IDS_I32, _IDS_I64) or xyz_mode not in (_XYZ_MATCHED, _XYZ_ALL):
        raise WireError(f"unknown landmark modes {ids_mode}, {xyz_mode}")
    matched = r.bits(n, "matched rows")
    m = int(matched.sum())
    if ids_mode == _IDS_I32:
        ids = np.full(n, -1, np.int64)
        ids[matched] = r.shuffled("i4", m, "landmark ids")
    else:
        ids = r.shuffled("i8", n, "landmark ids").astype(np.int64)
    if xyz_mode == _XYZ_MATCHED:
        xyz = np.full((n, 3), np.nan)
        xyz[matched] = r.shuffled("f8", 3 * m, "landmark points").reshape(m, 3)
    else:
        xyz = r.shuffled("f8", 3 * n, "landmark points").reshape(n, 3)
    T_pred = _get_pose(r, "predicted pose")
    return MatchedFrame(features, ids, xyz, T_pred, r.flag("repeated flag"))


def _put_posed(w: Writer, s: PosedFrame, camera: Camera, config: WireConfig,
                ctx: _Coding = INTRA) -> None:
    _put_matched(w, s.matched, camera, config, ctx)
    n = len(s.matched.features.keypoints)
    _require(np.shape(s.inliers) == (n,), f"inliers must have {n} entries")
    _put_pose(w, s.T_world_camera, "pose")
    w.bits(s.inliers)
    w.pack("B", bool(s.tracked))


def _get_posed(r: Reader, index: int, timestamp: float, camera: Camera,
                ctx: _Coding = INTRA) -> PosedFrame:
    matched = _get_matched(r, index, timestamp, camera, ctx)
    T = _get_pose(r, "pose")
    inliers = r.bits(len(matched.features.keypoints), "inliers")
    return PosedFrame(matched, T, inliers, r.flag("tracked flag"))


def _put_tracked(w: Writer, s: TrackedFrame, camera: Camera, config: WireConfig,
                  ctx: _Coding = INTRA) -> None:
    _put_pose(w, s.T_world_camera, "pose")
    _require(0 <= s.n_inliers < 2**32, f"inlier count {s.n_inliers}")
    w.pack("BBI", bool(s.tracked), bool(s.is_keyframe), s.n_inliers)
    # The reference keyframe (-1: none) and, with one, the pose relative to it.
    _require(-1 <= s.reference_keyframe < 2**31, f"reference keyframe {s.reference_keyframe}")
    w.pack("i", int(s.reference_keyframe))
    if s.reference_keyframe >= 0:
        _put_pose(w, s.T_reference_camera, "pose relative to the reference keyframe")
    # A keyframe: its features and its keyframes' poses (all, or those changed since a
    # table the cloud applied), for the cloud's map merger.
    delta = ctx.poses if s.sends_keyframe else None
    w.pack("B", POSES_DELTA if delta is not None else
           POSES_WHOLE if s.sends_keyframe else POSES_NONE)
    if s.sends_keyframe:
        poses = np.asarray(s.keyframe_poses, np.float64)
        _require(poses.ndim == 3 and poses.shape[1:] == (4, 4)
                 and len(poses) == s.reference_keyframe + 1,
                 f"keyframe poses {poses.shape}: keyframe {s.reference_keyframe} is the last")
        if delta is None:
            w.pack("I", len(poses))
            w.shuffled(poses[:, :3, :], "f8")  # rigid: the last row is implied
        else:
            _require(delta.count == len(poses) and 0 <= delta.base_seq < 2**63
                     and len(delta.ids) and delta.ids[-1] == len(poses) - 1,
                     f"a pose delta of {delta.count} keyframes for {len(poses)}, the newest "
                     "not among its rows")
            rows = np.zeros(len(poses), bool)
            rows[delta.ids] = True
            w.pack("qI", delta.base_seq, len(poses))
            w.bits(rows)
            w.shuffled(poses[delta.ids, :3, :], "f8")
        _put_features(w, s.posed.matched.features, camera, config)


def _rigid_pose(r: Reader, what: str) -> np.ndarray:
    """A pose the cloud will record as is: it must be a finite rigid transform."""
    T = _get_pose(r, what)
    if not np.isfinite(T).all():
        raise WireError(f"{what} is not finite")
    if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-9 or \
            np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max() > 1e-6 or \
            np.linalg.det(T[:3, :3]) < 0:
        raise WireError(f"{what} is not a rigid transform")
    return T


def _rigid_poses(T: np.ndarray, what: str) -> np.ndarray:
    """``T`` (K x 4 x 4) if every pose is a finite rigid transform; WireError otherwise."""
    if not np.isfinite(T).all():
        raise WireError(f"{what} are not finite")
    R = T[:, :3, :3]
    if len(T) and (np.abs(T[:, 3] - [0, 0, 0, 1]).max() > 1e-9
                   or np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() > 1e-6
                   or (np.linalg.det(R) < 0).any()):
        raise WireError(f"{what} are not all rigid transforms")
    return T


def _get_keyframe_poses(r: Reader, reference: int) -> np.ndarray:
    """Every keyframe's pose a keyframe message carries: the keyframe (``reference``) last."""
    (n,) = r.unpack("I", "keyframe pose count")
    if n != reference + 1:
        raise WireError(f"{n} keyframe poses, but keyframe {reference} is the newest")
    return _poses_3x4(r, n, "keyframe poses")


def _poses_3x4(r: Reader, n: int, what: str) -> np.ndarray:
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :] = r.shuffled("f8", 12 * n, what).reshape(n, 3, 4)
    poses[:, 3, 3] = 1.0
    return _rigid_poses(poses, what)


def _get_pose_delta(r: Reader, reference: int) -> PoseDelta:
    """The keyframe poses a keyframe message carries against a table the cloud applied."""
    base_seq, n = r.unpack("qI", "keyframe pose delta")
    if n != reference + 1:
        raise WireError(f"{n} keyframe poses, but keyframe {reference} is the newest")
    if base_seq < 0:
        raise WireError(f"keyframe poses coded against message {base_seq}")
    ids = np.flatnonzero(r.bits(n, "changed keyframe poses"))
    if not len(ids) or ids[-1] != n - 1:
        raise WireError(f"a pose delta without the newest keyframe's ({n - 1}) pose")
    return PoseDelta(int(base_seq), int(n), ids, _poses_3x4(r, len(ids), "changed keyframe poses"))


def _get_tracked(r: Reader, index: int, timestamp: float, camera: Camera,
                  ctx: _Coding = INTRA) -> TrackedPose:
    T = _rigid_pose(r, "pose")
    tracked = r.flag("tracked flag")
    is_keyframe = r.flag("keyframe flag")
    (n_inliers,) = r.unpack("I", "inlier count")
    (reference,) = r.unpack("i", "reference keyframe")
    if reference < -1:
        raise WireError(f"reference keyframe {reference} < -1")
    T_reference = _rigid_pose(r, "pose relative to the reference keyframe") \
        if reference >= 0 else None
    features = poses = delta = None
    (carried,) = r.unpack("B", "keyframe features flag")
    if carried not in (POSES_NONE, POSES_WHOLE, POSES_DELTA):
        raise WireError(f"keyframe features flag {carried}, expected 0, 1 or 2")
    if carried != POSES_NONE:
        if not is_keyframe or reference < 0:
            raise WireError(f"keyframe features on a frame that is no keyframe (keyframe flag "
                            f"{is_keyframe}, reference keyframe {reference})")
        if carried == POSES_WHOLE:
            poses = _get_keyframe_poses(r, reference)
        else:
            delta = _get_pose_delta(r, reference)
        features = _get_features(r, index, timestamp, camera)
    return TrackedPose(index, timestamp, T, tracked, is_keyframe, int(n_inliers), reference,
                       T_reference, features, poses, delta)


_ENCODERS: tuple[Callable[[Writer, Any, Camera, WireConfig, _Coding], None], ...] = (
    _put_captured, _put_detected, _put_described, _put_features, _put_matched, _put_posed,
    _put_tracked)
_DECODERS: tuple[Callable[[Reader, int, float, Camera, _Coding], Any], ...] = (
    _get_captured, _get_detected, _get_described, _get_features, _get_matched, _get_posed,
    _get_tracked)


def state_index_time(state: State) -> tuple[int, float]:
    """(frame index, timestamp) of a state of any split point."""
    if isinstance(state, PosedFrame):
        state = state.matched
    if isinstance(state, MatchedFrame):
        state = state.features
    return int(state.index), float(state.timestamp)


# ---------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------


References = list[tuple[int, Reference]]


def _write_state(state: State, split_point: int, camera: Camera, config: WireConfig,
                 references: References | None = None, stats: InterStats | None = None,
                 pose_delta: PoseDelta | None = None) -> tuple[Writer, bool]:
    """The payload's columns, and whether it is inter-coded: against ``references`` (seq and
    frame, at most MAX_REFERENCES) when given and the state carries descriptors. A point-6
    keyframe's poses go as ``pose_delta`` when given (else whole)."""
    if not 0 <= split_point < N_SPLIT_POINTS:
        raise ValueError(f"split point {split_point} outside 0..{N_SPLIT_POINTS - 1}")
    expected = STATE_TYPES[split_point]
    if not isinstance(state, expected):
        raise TypeError(f"split point {split_point} sends a {expected.__name__}, "
                        f"got {type(state).__name__}")
    check_codec(config.frame_image_codec)
    index, timestamp = state_index_time(state)
    w = Writer()
    w.pack("Iqd", camera_digest(camera), index, timestamp)
    ctx = INTRA
    if references and features_of(state) is not None:
        _require(len(references) <= MAX_REFERENCES,
                 f"{len(references)} references (at most {MAX_REFERENCES})")
        seqs = [int(seq) for seq, _ in references]
        _require(len(set(seqs)) == len(seqs), f"references {seqs} repeat a frame")
        w.pack("B", len(seqs))
        w.array(np.array(seqs, np.uint64), "u8")
        ctx = _Coding([ref for _, ref in references], stats, config.inter_octaves)
    elif stats is not None and (features := features_of(state)) is not None:
        stats.descriptors += len(features[1])
    inter = ctx is not INTRA
    if pose_delta is not None:  # point 6, which has no descriptors to code (INTER_POINTS)
        ctx = _Coding()
        ctx.poses = pose_delta
    _ENCODERS[split_point](w, state, camera, config, ctx)
    return w, inter


def encode_state(state: State, split_point: int, camera: Camera, config: WireConfig,
                 references: References | None = None) -> bytes:
    """The payload of state ``split_point`` (the input of stage ``split_point``); inter-coded
    against ``references`` if given (decode it with ``inter=True``)."""
    return _write_state(state, split_point, camera, config, references)[0].getvalue()


# Content limits a decoded frame must meet before any stage reads it (a message that decodes
# cleanly can still be hostile: NaN keypoints, images of another size, uv far from its
# keypoint). More keypoints than this is no ORB frame of a camera.
MAX_FRAME_KEYPOINTS = 20_000
# uv sent explicitly must be where undistorting its keypoint puts it, within this (pixels).
UV_TOLERANCE_PX = 1.0
# Depth per keypoint above this (metres) is no measurement of an RGB-D camera.
MAX_KEYPOINT_DEPTH_M = 100.0


def _check_image(image: np.ndarray, camera: Camera, what: str) -> None:
    if image.shape[:2] != (camera.height, camera.width):
        raise WireError(f"{what} is {image.shape[1]} x {image.shape[0]}, the camera's is "
                        f"{camera.width} x {camera.height}")


def _check_keypoint_content(kp: np.ndarray, camera: Camera) -> None:
    if len(kp) > MAX_FRAME_KEYPOINTS:
        raise WireError(f"{len(kp)} keypoints (at most {MAX_FRAME_KEYPOINTS} in a frame)")
    if not np.isfinite(kp).all():
        raise WireError("keypoints hold NaN or infinite values")
    x, y = kp[:, 0], kp[:, 1]
    if ((x < 0) | (y < 0) | (x >= camera.width) | (y >= camera.height)).any():
        raise WireError(f"keypoints outside the {camera.width} x {camera.height} image")
    octave = kp[:, 5]
    if ((octave < 0) | (octave > 31) | (octave != np.round(octave))).any():
        raise WireError("keypoint octaves are not pyramid levels 0-31")


def _check_content(state: State, camera: Camera) -> None:
    """Sizes against the camera, finite values, plausible counts: what the stages assume."""
    if isinstance(state, TrackedPose):
        state = state.features  # a keyframe's (point 6), else nothing to check
    if isinstance(state, PosedFrame):
        state = state.matched
    if isinstance(state, MatchedFrame):
        state = state.features
    if isinstance(state, CapturedFrame):
        _check_image(state.rgb, camera, "rgb image")
    if isinstance(state, DetectedFrame):
        _check_image(state.gray, camera, "grey image")
    if isinstance(state, (CapturedFrame, DetectedFrame, DescribedFrame)):
        _check_image(state.depth_m, camera, "depth image")
        if not np.isfinite(state.depth_m).all():
            raise WireError("depth image holds NaN or infinite values")
    if isinstance(state, (DetectedFrame, DescribedFrame, FeatureFrame)):
        _check_keypoint_content(state.keypoints, camera)
    if isinstance(state, FeatureFrame):
        depth = state.depth
        if not np.isfinite(depth).all() or (depth < 0).any() \
                or (depth > MAX_KEYPOINT_DEPTH_M).any():
            raise WireError(f"keypoint depths outside 0-{MAX_KEYPOINT_DEPTH_M:g} m")
        if len(state.uv) and np.abs(state.uv - _undistort(state.keypoints, camera)).max() \
                > UV_TOLERANCE_PX:
            raise WireError("uv disagrees with the keypoints it belongs to")


class ReferenceSource(Protocol):
    """Where an inter-coded frame's references are looked up (wire/inter.ReferenceRing, or
    a dict of seq -> Reference)."""

    def get(self, seq: int) -> Reference | None: ...




def _read_references(r: Reader, split_point: int, seq: int,
                     references: ReferenceSource | None) -> _Coding:
    if split_point not in INTER_POINTS:
        raise WireError(f"an inter-coded frame at split point {split_point}, which carries no "
                        "descriptors")
    (count,) = r.unpack("B", "reference count")
    if not 1 <= count <= MAX_REFERENCES:
        raise WireError(f"{count} reference frames (1..{MAX_REFERENCES})")
    seqs = [int(s) for s in r.array("u8", count, "reference seqs")]
    if len(set(seqs)) != count or max(seqs) >= seq:
        raise WireError(f"reference seqs {seqs} repeat or are not before the frame's {seq}")
    if references is None:
        raise MissingReference(seq, seqs)
    refs = [references.get(s) for s in seqs]
    missing = [s for s, ref in zip(seqs, refs) if ref is None]
    if missing:
        raise MissingReference(seq, missing)
    return _Coding([ref for ref in refs if ref is not None])


def decode_state(payload: bytes, split_point: int, camera: Camera,
                 references: ReferenceSource | None = None, *, inter: bool = False,
                 seq: int = 2**64 - 1) -> State:
    """The state :func:`encode_state` encoded. Raises WireError on any inconsistency, and on
    content the stages cannot take (sizes, values, counts: :func:`_check_content`). An
    inter-coded payload (``inter``) of frame ``seq`` needs its reference frames in
    ``references``: MissingReference (a WireError) names those absent."""
    if not 0 <= split_point < N_SPLIT_POINTS:
        raise WireError(f"split point {split_point} outside 0..{N_SPLIT_POINTS - 1}")
    r = Reader(payload, f"frame payload (split point {split_point})")
    digest, index, timestamp = r.unpack("Iqd", "frame header")
    if digest != camera_digest(camera):
        raise WireError("the sender's camera differs from this one (intrinsics, distortion or "
                        "depth scale): keypoints and depth would be rebuilt wrongly")
    ctx = _read_references(r, split_point, seq, references) if inter else _Coding()
    state = _DECODERS[split_point](r, index, timestamp, camera, ctx)
    r.finish()
    _check_content(state, camera)
    return state


def encode_frame_message(state: State, split_point: int, robot_id: str, seq: int,
                         camera: Camera, config: WireConfig,
                         references: References | None = None,
                         stats: InterStats | None = None,
                         pose_delta: PoseDelta | None = None) -> bytes:
    """The whole frame message (envelope + payload); its timestamp is the frame's. With
    ``references`` (seq, frame) that the cloud holds, a state that carries descriptors is
    inter-coded (Kind.FRAME_INTER, wire/inter.py); ``stats`` counts its descriptors. A
    point-6 keyframe's poses go as ``pose_delta`` (wire/pose_deltas.py) when given."""
    writer, inter = _write_state(state, split_point, camera, config, references, stats,
                                 pose_delta)
    _, timestamp = state_index_time(state)
    return seal(Kind.FRAME_INTER if inter else Kind.FRAME, robot_id, seq, timestamp,
                split_point, writer.sections(), compress=config.compress,
                level=config.zstd_level)


def decode_frame_message(data: bytes, camera: Camera,
                         references: ReferenceSource | None = None) -> tuple[Header, State]:
    """A frame message's header and state. An inter-coded one needs its reference frames in
    ``references`` (the cloud's ReferenceRing): MissingReference says which are absent."""
    header, payload = open_message(data)
    if header.kind not in (Kind.FRAME, Kind.FRAME_INTER):
        raise WireError(f"expected a frame message, got {header.kind.name}")
    state = decode_state(payload, header.split_point, camera, references,
                         inter=header.kind == Kind.FRAME_INTER, seq=header.seq)
    _, timestamp = state_index_time(state)
    if timestamp != header.timestamp:
        raise WireError(f"payload timestamp {timestamp} differs from the header's "
                        f"{header.timestamp}")
    return header, state
