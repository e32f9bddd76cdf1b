"""The binary wire format: the envelope's checks, feedback and keyframe messages, and the
frame message at every split point, whose decoded state must give the cloud bit-identical
poses and keyframe decisions."""

from __future__ import annotations

import dataclasses
import struct
import sys
import zlib
from dataclasses import replace

import cv2
import numpy as np
import pytest
import zstandard

from conftest import SEVEN_SCENES, require
from fleetslam.camera import Camera
from fleetslam.config import Config, SyntheticConfig, WireConfig
from fleetslam.datasets.synthetic import generate_scene
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.pipeline.split import run_stages
from fleetslam.pipeline.states import (
    CapturedFrame,
    FeatureFrame,
    MatchedFrame,
    PosedFrame,
    TrackedFrame,
)
from fleetslam.wire.binary import DEPTH_CODEC, Reader, Writer, get_image, put_image
from fleetslam.wire.envelope import (
    FLAG_ZSTD,
    FORMAT_VERSION,
    MAX_PAYLOAD_BYTES,
    Header,
    Kind,
    WireError,
    _assemble,
    header_size,
    open_message,
    seal,
)
from fleetslam.wire.frames import (
    MAX_FRAME_KEYPOINTS,
    decode_frame_message,
    decode_state,
    encode_frame_message,
    encode_state,
)
from fleetslam.wire import inter as wire_inter
from fleetslam.wire.inter import (
    InterEncoder,
    InterStats,
    MissingReference,
    ReferenceRing,
    nearest,
    nearest_by_octave,
    reference_of,
)
from fleetslam.wire.messages import (
    Feedback,
    KeyframeUpload,
    decode_feedback,
    decode_keyframe,
    encode_feedback,
    encode_keyframe,
)

N_FRAMES = 30
ROBOT = "robot_7"


# ---------------------------------------------------------------------------------------
# Envelope
# ---------------------------------------------------------------------------------------


def message(payload: bytes = b"payload " * 50, compress: bool = True) -> bytes:
    return seal(Kind.FRAME, ROBOT, 42, 1305031102.175304, 3, payload, compress=compress)


@pytest.mark.parametrize("compress", [True, False])
def test_envelope_round_trip(compress):
    payload = bytes(range(256)) * 3 + b"\0" * 500
    data = message(payload, compress)
    header, out = open_message(data)
    assert out == payload
    assert header == Header(FORMAT_VERSION, Kind.FRAME, ROBOT, 42, 1305031102.175304, 3,
                            header.payload_length, header.checksum, compress, len(payload))
    assert header.size == len(data) == header_size(ROBOT) + header.payload_length
    assert (header.payload_length < len(payload)) == compress


def test_incompressible_payload_is_sent_uncompressed():
    payload = np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8).tobytes()
    header, out = open_message(message(payload, compress=True))
    assert out == payload and not header.compressed and header.payload_length == len(payload)


def test_empty_and_garbage():
    with pytest.raises(WireError, match="empty message"):
        open_message(b"")
    garbage = np.random.default_rng(1).integers(0, 256, 300, dtype=np.uint8).tobytes()
    with pytest.raises(WireError, match="bad magic"):
        open_message(garbage)


def test_truncated_at_every_length():
    data = message()
    for n in [1, 4, 9, 10, 17, header_size(ROBOT) - 1, header_size(ROBOT), len(data) - 1]:
        with pytest.raises(WireError, match="truncated"):
            open_message(data[:n])


def patched(data: bytes, offset: int, new: bytes) -> bytes:
    return data[:offset] + new + data[offset + len(new):]


def test_header_faults_name_their_reason():
    data = message()
    with pytest.raises(WireError, match="bad magic"):
        open_message(patched(data, 0, b"FSLN"))
    with pytest.raises(WireError, match=r"format version 7 not supported \(this build reads 1\)"):
        open_message(patched(data, 4, struct.pack("<H", 7)))
    with pytest.raises(WireError, match="unknown message kind 9"):
        open_message(patched(data, 6, b"\x09"))
    with pytest.raises(WireError, match=r"split point 9 outside 0\.\.6"):
        open_message(patched(data, 7, b"\x09"))
    with pytest.raises(WireError, match="unknown flags"):
        open_message(patched(data, 8, b"\x80"))
    with pytest.raises(WireError, match="trailing bytes: 3"):
        open_message(data + b"abc")


def test_corruption_is_caught_by_the_checksum():
    data = message()
    flipped_payload = patched(data, len(data) - 5, bytes([data[-5] ^ 0x10]))
    with pytest.raises(WireError, match="checksum mismatch"):
        open_message(flipped_payload)
    seq_offset = 10 + len(ROBOT)
    with pytest.raises(WireError, match="checksum mismatch"):
        open_message(patched(data, seq_offset, b"\x43"))


def test_robot_id_checked_on_both_sides():
    for bad in ["", "a b", "x" * 65, "robot/1", "é"]:
        with pytest.raises(ValueError, match="robot id"):
            seal(Kind.FRAME, bad, 0, 0.0, 0, b"", compress=False)
    seal(Kind.FRAME, "A-z_09" + "x" * 58, 0, 0.0, 0, b"", compress=False)  # 64 characters
    forged = _assemble(FORMAT_VERSION, 1, 0, 0, b"a b", 0, 0.0, 0, b"")
    with pytest.raises(WireError, match="outside"):
        open_message(forged)
    with pytest.raises(WireError, match="robot id not valid UTF-8"):
        open_message(_assemble(FORMAT_VERSION, 1, 0, 0, b"\xff\xfe", 0, 0.0, 0, b""))
    with pytest.raises(WireError, match="robot id length 0"):
        open_message(_assemble(FORMAT_VERSION, 1, 0, 0, b"", 0, 0.0, 0, b""))


def test_decompression_is_bounded():
    bomb = zstandard.ZstdCompressor(level=3).compress(b"\0" * 10_000_000)
    assert len(bomb) < 1000
    with pytest.raises(WireError, match="zstd frame declares 10000000 bytes, header says 100"):
        open_message(_assemble(FORMAT_VERSION, 1, 0, FLAG_ZSTD, b"r", 0, 0.0, 100, bomb))
    with pytest.raises(WireError, match="exceeds the limit"):
        open_message(_assemble(FORMAT_VERSION, 1, 0, FLAG_ZSTD, b"r", 0, 0.0,
                               MAX_PAYLOAD_BYTES + 1, bomb))
    unsized = zstandard.ZstdCompressor(write_content_size=False).compress(b"\0" * 1000)
    with pytest.raises(WireError, match="declares no size"):
        open_message(_assemble(FORMAT_VERSION, 1, 0, FLAG_ZSTD, b"r", 0, 0.0, 1000, unsized))
    with pytest.raises(WireError, match="zstd"):
        open_message(_assemble(FORMAT_VERSION, 1, 0, FLAG_ZSTD, b"r", 0, 0.0, 10, b"notzstd!"))


# ---------------------------------------------------------------------------------------
# Feedback and keyframe messages
# ---------------------------------------------------------------------------------------


def test_feedback_round_trip_is_exact():
    rng = np.random.default_rng(2)
    T = np.eye(4)
    T[:3, :] = rng.normal(size=(3, 4)) * np.array([1e-17, 1.0, 3e5, np.pi])
    fb = Feedback(1234, 1305031102.175304, True, False, 317, T, 12.5)
    header, out = decode_feedback(encode_feedback(ROBOT, 9, fb))
    assert header.kind == Kind.FEEDBACK and header.seq == 9 and header.robot_id == ROBOT
    assert out.T_world_camera.tobytes() == T.tobytes()
    assert dataclasses.astuple(replace(out, T_world_camera=None)) == \
        dataclasses.astuple(replace(fb, T_world_camera=None))
    with pytest.raises(WireError, match="expected a feedback message"):
        decode_feedback(message())


def textured_rgbd(h: int = 96, w: int = 128) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    base = cv2.resize(rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8), (w, h))
    rgb = cv2.GaussianBlur(base, (5, 5), 0)
    depth = (1000 + 10 * np.arange(h)[:, None] + np.arange(w)[None, :]).astype(np.uint16)
    depth[::7, ::5] = 0
    return rgb, depth


@pytest.mark.parametrize("codec", ["png", "jpeg"])
def test_keyframe_round_trip(codec):
    rgb, depth = textured_rgbd()
    kf = KeyframeUpload.from_frame(17, 3.25, rgb, depth, stride=2)
    assert kf.rgb.shape == (48, 64, 3) and kf.depth_raw.shape == (48, 64)
    data = encode_keyframe(ROBOT, 5, kf, WireConfig(keyframe_rgb_codec=codec))
    header, out = decode_keyframe(data)
    assert header.kind == Kind.KEYFRAME and header.timestamp == 3.25
    assert (out.frame_index, out.timestamp, out.stride) == (17, 3.25, 2)
    np.testing.assert_array_equal(out.depth_raw, kf.depth_raw)
    assert out.depth_raw.dtype == np.uint16
    assert out.rgb.shape == kf.rgb.shape
    if codec == "png":
        np.testing.assert_array_equal(out.rgb, kf.rgb)
    else:
        assert np.abs(out.rgb.astype(int) - kf.rgb).mean() < 8


def test_depth_goes_lossless_and_smaller_than_png_and_old_png_uploads_still_read():
    """The depth codec: every 16-bit value back (jumps across the whole range, invalid
    zeros), fewer bytes than the PNG it replaced, a size that lies refused by name, and a
    store's older upload with PNG depth still read."""
    rgb, depth = textured_rgbd()
    depth[5, :] = 65535
    depth[6, ::2] = 0
    w = Writer()
    put_image(w, depth, DEPTH_CODEC)
    image, codec = get_image(Reader(w.getvalue(), "test"), "depth")
    assert codec == DEPTH_CODEC and image.dtype == np.uint16
    assert image.tobytes() == depth.tobytes()
    with pytest.raises(ValueError, match="16-bit depth only"):
        put_image(Writer(), rgb, DEPTH_CODEC)
    lying = bytearray(w.getvalue())
    lying[1:3] = struct.pack("<H", depth.shape[0] + 1)  # one row more than the planes hold
    with pytest.raises(WireError, match="truncated: depth needs 24832 bytes, 24576 left"):
        get_image(Reader(bytes(lying), "test"), "depth")
    kf = KeyframeUpload.from_frame(17, 3.25, rgb, depth, stride=1)
    new = encode_keyframe(ROBOT, 5, kf, WireConfig())
    old = Writer()
    old.pack("qdH", kf.frame_index, kf.timestamp, kf.stride)
    put_image(old, kf.rgb, "jpeg")
    put_image(old, kf.depth_raw, "png")
    old_upload = seal(Kind.KEYFRAME, ROBOT, 5, kf.timestamp, 0, old.getvalue(), compress=True)
    assert len(new) < len(old_upload)
    # Without zstd the planes would go raw: an uncompressed message keeps the PNG.
    plain = encode_keyframe(ROBOT, 5, kf, WireConfig(compress=False))
    assert len(plain) < depth.nbytes
    for data in (new, old_upload, plain):
        assert decode_keyframe(data)[1].depth_raw.tobytes() == depth.tobytes()


# ---------------------------------------------------------------------------------------
# Frame messages: exactness of every split point
# ---------------------------------------------------------------------------------------


def assert_same_state(original, decoded, k: int, path: str = "state") -> None:
    """Field by field, bit for bit; at k >= 2 the keypoint angle is quantised and the
    response dropped (module docstring of wire/frames.py)."""
    assert type(original) is type(decoded), path
    for field in dataclasses.fields(original):
        a, b = getattr(original, field.name), getattr(decoded, field.name)
        where = f"{path}.{field.name}"
        if dataclasses.is_dataclass(a):
            assert_same_state(a, b, k, where)
        elif isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and a.shape == b.shape, where
            if field.name == "keypoints" and k >= 2:
                exact = [0, 1, 2, 5, 6]
                assert a[:, exact].tobytes() == b[:, exact].tobytes(), where
                err = np.abs((a[:, 3] - b[:, 3] + 180) % 360 - 180)
                assert err.max(initial=0) <= 360 / 512 + 1e-3, where
                assert not b[:, 4].any(), where
            elif field.name == "landmark_xyz":
                np.testing.assert_array_equal(a, b, err_msg=where)  # NaN rows: NaN
                assert a[~np.isnan(a)].tobytes() == b[~np.isnan(b)].tobytes(), where
            else:
                assert a.tobytes() == b.tobytes(), where
        else:
            assert a == b and type(a) is type(b) or (bool(a) == b and isinstance(b, bool)), where


def run_reference(camera: Camera, frames: list[CapturedFrame]) -> tuple[np.ndarray, list[bool]]:
    pipeline = RobotSlam.new(Config(), camera)
    out = [pipeline.track(f) for f in frames]
    return np.array([o.T_world_camera for o in out]), [o.is_keyframe for o in out]


def run_through_wire(camera: Camera, frames: list[CapturedFrame], k: int,
                     config: Config | None = None) -> tuple[np.ndarray, list[bool], list[int]]:
    """Robot stages, then the state at k through encode -> decode, then the cloud stages;
    every decoded state is checked against the one encoded."""
    config = config or Config()
    pipeline = RobotSlam.new(config, camera)
    robot, cloud = pipeline.split(k)
    poses, keyframes, sizes = [], [], []
    for seq, frame in enumerate(frames):
        state = run_stages(robot, frame, pipeline.sides)
        data = encode_frame_message(state, k, ROBOT, seq, camera, config.wire)
        header, decoded = decode_frame_message(data, camera)
        assert (header.split_point, header.seq, header.timestamp) == (k, seq, frame.timestamp)
        # A robot that tracks itself sends its result only (wire/frames.py).
        assert_same_state(state.pose_only() if k == 6 else state, decoded, k)
        sizes.append(len(data))
        out = run_stages(cloud, decoded, pipeline.sides)
        poses.append(out.T_world_camera)
        keyframes.append(out.is_keyframe)
    return np.array(poses), keyframes, sizes


@pytest.fixture(scope="module")
def seven_scenes() -> tuple[Camera, list[CapturedFrame]]:
    seq = RgbdSequence(require(SEVEN_SCENES), last=N_FRAMES - 1)
    frames = [CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m) for f in seq]
    return seq.camera, frames


@pytest.fixture(scope="module")
def seven_scenes_reference(seven_scenes):
    return run_reference(*seven_scenes)


@pytest.mark.realdata
@pytest.mark.parametrize("k", range(7))
def test_every_split_point_through_the_wire_is_exact(seven_scenes, seven_scenes_reference, k):
    camera, frames = seven_scenes
    expected_poses, expected_kf = seven_scenes_reference
    assert np.linalg.norm(expected_poses[-1][:3, 3]) > 0.01 and sum(expected_kf) >= 2
    poses, keyframes, sizes = run_through_wire(camera, frames, k)
    assert poses.tobytes() == expected_poses.tobytes(), f"k={k}"
    assert keyframes == expected_kf
    if k == 3:
        # Compact keypoints: ~32 bytes of descriptor plus ~4.5 of the rest per keypoint.
        pipeline = RobotSlam.new(Config(), camera)
        n = [len(run_stages(pipeline.stages[:3], f, pipeline.sides).keypoints) for f in frames]
        assert all(s < 38 * m + 300 for s, m in zip(sizes, n)), list(zip(sizes, n))


def test_synthetic_scene_through_the_wire_is_exact(tmp_path):
    config = SyntheticConfig(n_robots=1, frames_per_robot=8)
    folder = generate_scene(tmp_path / "scene", config)[0]
    seq = RgbdSequence(folder)
    frames = [CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m) for f in seq]
    expected_poses, expected_kf = run_reference(seq.camera, frames)
    for k in (0, 3, 5):
        poses, keyframes, _ = run_through_wire(seq.camera, frames, k)
        assert poses.tobytes() == expected_poses.tobytes(), f"k={k}"
        assert keyframes == expected_kf


@pytest.mark.realdata
def test_jpeg_frames_decode_and_are_smaller(seven_scenes):
    camera, frames = seven_scenes
    pipeline = RobotSlam.new(Config(), camera)
    detected = run_stages(pipeline.stages[:1], frames[0], pipeline.sides)
    jpeg = WireConfig(frame_image_codec="jpeg")
    for k, state in ((0, frames[0]), (1, detected)):
        png_data = encode_frame_message(state, k, ROBOT, 0, camera, WireConfig())
        jpeg_data = encode_frame_message(state, k, ROBOT, 0, camera, jpeg)
        _, decoded = decode_frame_message(jpeg_data, camera)
        image = decoded.rgb if k == 0 else decoded.gray
        original = state.rgb if k == 0 else state.gray
        assert image.shape == original.shape and image.dtype == np.uint8
        assert np.abs(image.astype(int) - original).mean() < 5
        np.testing.assert_array_equal(decoded.depth_m, state.depth_m)  # depth stays exact
        # Only the image changes codec (the depth PNG stays): ~100 kB less either way.
        assert len(jpeg_data) < len(png_data) - 50_000, (k, len(jpeg_data), len(png_data))


# ---------------------------------------------------------------------------------------
# Frame messages: fallbacks and faults, on a small synthetic feature frame
# ---------------------------------------------------------------------------------------


DISTORTED = Camera(517.3, 516.5, 318.6, 255.3, distortion=(0.26, -0.95, -0.005, 0.003, 1.16))


def orb_features(camera: Camera = DISTORTED) -> FeatureFrame:
    """ORB on a textured image, depth from a plane: a FeatureFrame as AssociateDepth makes."""
    rgb, _ = textured_rgbd(480, 640)
    orb = cv2.ORB_create(nfeatures=500)
    kps, desc = orb.detectAndCompute(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), None)
    kp = np.array([(k.pt[0], k.pt[1], k.size, k.angle, k.response, k.octave, k.class_id)
                   for k in kps], np.float32)
    raw = (2000 + 3 * (np.arange(len(kp)) % 50)).astype(np.uint16)
    raw[::4] = 0
    depth = raw.astype(np.float32) / np.float32(camera.depth_scale)
    uv = camera.undistort_points(kp[:, :2].astype(np.float64))
    return FeatureFrame(3, 0.5, kp, desc, depth, uv)


def features_round_trip(f: FeatureFrame, camera: Camera = DISTORTED) -> tuple[FeatureFrame, int]:
    payload = encode_state(f, 3, camera, WireConfig())
    out = decode_state(payload, 3, camera)
    assert_same_state(f, out, 3)
    return out, len(payload)


def test_orb_keypoints_are_sent_compactly():
    f = orb_features()
    assert len(f.keypoints) > 300 and len(np.unique(f.keypoints[:, 5])) >= 4
    _, size = features_round_trip(f)
    # Per keypoint: descriptor 32, position 3 (raw x, y: 8), octave, angle, depth 1 each.
    assert size < len(f.keypoints) * (32 + 3 + 1 + 1 + 1) + 400


def test_fallbacks_keep_decoding_exact():
    f = orb_features()
    _, compact = features_round_trip(f)
    odd = f.keypoints.copy()
    odd[5, 0] += 0.1  # not on the level grid: x, y go raw
    odd[7, 2] = 12.0  # size not the level's
    odd[9, 6] = 3  # class id not constant
    _, raw_xy = features_round_trip(replace(f, keypoints=odd, uv=DISTORTED.undistort_points(
        odd[:, :2].astype(np.float64))))
    assert raw_xy > compact
    depth = f.depth.copy()
    depth[3] = 1.2345678  # no sensor value gives this float32
    features_round_trip(replace(f, depth=depth))
    features_round_trip(replace(f, uv=f.uv + 1e-9))  # uv not recomputable: sent
    features_round_trip(replace(f, keypoints=f.keypoints[:0], descriptors=f.descriptors[:0],
                                depth=f.depth[:0], uv=f.uv[:0]))


def test_frame_payload_faults():
    f = orb_features()
    payload = encode_state(f, 3, DISTORTED, WireConfig())
    other = replace(DISTORTED, fx=DISTORTED.fx + 1e-6)
    with pytest.raises(WireError, match="camera differs"):
        decode_state(payload, 3, other)
    with pytest.raises(WireError, match="truncated"):
        decode_state(payload[:-10], 3, DISTORTED)
    with pytest.raises(WireError, match="unexpected bytes"):
        decode_state(payload + b"\0", 3, DISTORTED)
    for n in range(0, len(payload), 97):
        with pytest.raises(WireError):
            decode_state(payload[:n], 3, DISTORTED)
    with pytest.raises(TypeError, match="FeatureFrame"):
        encode_state(f, 2, DISTORTED, WireConfig())
    with pytest.raises(WireError, match="expected a frame message"):
        decode_frame_message(encode_feedback(ROBOT, 0, Feedback(0, 0.0, True, True, 0, np.eye(4),
                                                                1.0)), DISTORTED)



def test_corrupted_payloads_raise_only_wire_errors():
    # The envelope's CRC stops random corruption; this is what a hostile sender could try.
    payload = encode_state(orb_features(), 3, DISTORTED, WireConfig())
    rng = np.random.default_rng(4)
    for _ in range(300):
        data = bytearray(payload)
        for pos in rng.integers(0, len(data), 3):
            data[pos] = rng.integers(0, 256)
        try:
            decode_state(bytes(data), 3, DISTORTED)
        except WireError:
            pass
    huge = bytearray(payload)
    huge[20:24] = struct.pack("<I", 0xFFFFFFFF)  # keypoint count, after the frame header
    with pytest.raises(WireError, match="keypoint count"):
        decode_state(bytes(huge), 3, DISTORTED)


# ---------------------------------------------------------------------------------------
# Found by bench/fuzz_wire.py: each took the decoder far longer than the message is worth
# (the replay command is bench/fuzz_wire.py --replay FAMILY:SEED:INDEX)
# ---------------------------------------------------------------------------------------


def image_field(data: bytes, codec: int, h: int, w: int, channels: int = 3) -> Reader:
    """A payload holding one image as put_image writes it (codec 0 PNG, 1 JPEG)."""
    return Reader(struct.pack("<BHHBBI", codec, h, w, channels, 1, len(data)) + data, "test")


def small_jpeg(progressive: bool = False) -> bytes:
    rgb, _ = textured_rgbd(48, 64)
    ok, buf = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)])
    return buf.tobytes()


def python_lines_run(fn) -> int:
    """How many Python lines ``fn()`` runs (through sys.settrace)."""
    count = 0

    def tracer(frame, event, arg):
        nonlocal count
        count += event == "line"
        return tracer

    previous = sys.gettrace()
    sys.settrace(tracer)
    try:
        fn()
    finally:
        sys.settrace(previous)
    return count


def test_jpeg_size_probe_is_bounded():
    # image_bomb:0:117: millions of 4-byte segments before the size kept the probe's Python
    # loop busy for 2.6 s.
    jpeg = small_jpeg()
    assert get_image(image_field(jpeg, 1, 48, 64), "image")[0].shape == (48, 64, 3)
    sof = jpeg.index(b"\xff\xc0")
    for filler in (b"\xff\xfe\x00\x02", b"\xff"):
        bomb = jpeg[:sof] + filler * 2_000_000 + jpeg[sof:]

        def refuse() -> None:
            with pytest.raises(WireError, match="not a 64x48 jpeg image"):
                get_image(image_field(bomb, 1, 48, 64), "image")

        # The probe's work in Python lines run, which no machine's load changes: a walk of
        # every segment was ~10^7.
        assert python_lines_run(refuse) < 50_000


def test_jpeg_scans_are_bounded():
    # image_bomb:0:157: a 36 kB frame message, a progressive 4096 x 4096 JPEG with its scans
    # repeated: libjpeg took 28 s.
    jpeg = small_jpeg(progressive=True)
    assert get_image(image_field(jpeg, 1, 48, 64), "image")[0].shape == (48, 64, 3)
    first, end = jpeg.index(b"\xff\xda"), jpeg.rindex(b"\xff\xd9")
    bomb = jpeg[:first] + jpeg[first:end] * 7 + jpeg[end:]
    with pytest.raises(WireError, match="more than 64 JPEG scans"):
        get_image(image_field(bomb, 1, 48, 64), "image")


def test_png_chunks_are_bounded():
    # image_bomb:1:1221: 930k tiny iTXt chunks (150 kB with zstd) took libpng 2.4 s.
    rgb, _ = textured_rgbd(48, 64)
    png = cv2.imencode(".png", rgb)[1].tobytes()
    assert get_image(image_field(png, 0, 48, 64), "image")[0].shape == (48, 64, 3)
    chunk = struct.pack(">I", 3) + b"iTXtk\0v" + struct.pack(">I", zlib.crc32(b"iTXtk\0v"))
    bomb = png[:33] + chunk * 100_000 + png[33:]  # after the signature and IHDR
    with pytest.raises(WireError, match="PNG chunk per kB"):
        get_image(image_field(bomb, 0, 48, 64), "image")


def test_images_are_checked_against_the_camera_before_decoding(monkeypatch):
    # The JPEG and PNG bombs above claimed 16 Mpixels; the camera says what size to expect.
    camera = Camera(525.0, 525.0, 319.5, 239.5)
    frame = CapturedFrame(0, 0.5, np.zeros((600, 800, 3), np.uint8),
                          np.zeros((600, 800), np.float32))
    data = encode_frame_message(frame, 0, ROBOT, 0, camera, WireConfig())
    kf = KeyframeUpload.from_frame(1, 0.5, frame.rgb, np.zeros((600, 800), np.uint16), 2)
    upload = encode_keyframe(ROBOT, 1, kf, WireConfig())
    decoded = []
    monkeypatch.setattr(cv2, "imdecode", lambda *args: decoded.append(args))
    with pytest.raises(WireError, match="rgb image is 800 x 600, expected 640 x 480"):
        decode_frame_message(data, camera)
    with pytest.raises(WireError, match="keyframe colour is 400 x 300, expected 320 x 240"):
        decode_keyframe(upload, camera)
    assert not decoded


def test_keypoint_count_is_refused_before_the_keypoints_are_read():
    # zstd_bomb:0:82: 2^20 keypoints of zeros in a 64 MB payload (a few kB with zstd) were
    # read, with their 32 MB of descriptors, before the content check refused them (0.25 s).
    payload = bytearray(encode_state(orb_features(), 3, DISTORTED, WireConfig()))
    payload[20:24] = struct.pack("<I", MAX_FRAME_KEYPOINTS + 1)
    with pytest.raises(WireError, match=f"keypoint count {MAX_FRAME_KEYPOINTS + 1} exceeds"):
        decode_state(bytes(payload), 3, DISTORTED)


def test_a_robots_own_pose_must_be_a_finite_rigid_transform():
    camera = Camera(525.0, 525.0, 319.5, 239.5)
    features = FeatureFrame(3, 0.1, np.zeros((0, 7), np.float32), np.zeros((0, 32), np.uint8),
                            np.zeros(0, np.float32), np.zeros((0, 2)))
    matched = MatchedFrame(features, np.zeros(0, np.int64), np.zeros((0, 3)), np.eye(4), False)
    good = TrackedFrame(PosedFrame(matched, np.eye(4), np.zeros(0, bool), True), True, 2,
                        np.eye(4))
    data = encode_frame_message(good, 6, ROBOT, 0, camera, WireConfig())
    _, decoded = decode_frame_message(data, camera)
    assert (decoded.index, decoded.is_keyframe, decoded.reference_keyframe) == (3, True, 2)
    assert decoded.T_world_camera.tobytes() == np.eye(4).tobytes()
    assert len(data) < 400  # the result alone, whatever the features were
    for bad, reason in ((np.full((4, 4), np.nan), "not finite"),
                        (np.diag([2.0, 1.0, 1.0, 1.0]), "not a rigid transform")):
        wrong = TrackedFrame(PosedFrame(matched, bad, np.zeros(0, bool), True), True, -1)
        with pytest.raises(WireError, match=reason):
            decode_frame_message(encode_frame_message(wrong, 6, ROBOT, 0, camera, WireConfig()),
                                 camera)


@pytest.mark.parametrize("h, w, what", [(1, 1, "rgb image is 1 x 1"),
                                        (2, 640, "rgb image is 640 x 2"),
                                        (480, 320, "rgb image is 320 x 480")])
def test_images_of_another_size_than_the_camera_are_refused(h, w, what):
    camera = Camera(525.0, 525.0, 319.5, 239.5)
    frame = CapturedFrame(0, 0.5, np.zeros((h, w, 3), np.uint8), np.zeros((h, w), np.float32))
    data = encode_frame_message(frame, 0, ROBOT, 0, camera, WireConfig())
    with pytest.raises(WireError, match=what):
        decode_frame_message(data, camera)


def test_depth_of_another_size_than_the_colour_image_is_refused():
    camera = Camera(525.0, 525.0, 319.5, 239.5)
    frame = CapturedFrame(0, 0.5, np.zeros((480, 640, 3), np.uint8),
                          np.zeros((240, 320), np.float32))
    with pytest.raises(WireError, match="depth image is 320 x 240"):
        decode_frame_message(encode_frame_message(frame, 0, ROBOT, 0, camera, WireConfig()),
                             camera)


# ---------------------------------------------------------------------------------------
# Inter-frame coding (wire/inter.py): exact over real sequences, with frames lost
# ---------------------------------------------------------------------------------------


def run_inter_through_wire(camera: Camera, frames: list[CapturedFrame], k: int, loss: float,
                           ack_lag: int = 1, config: Config | None = None
                           ) -> tuple[np.ndarray, list[bool], list[int], InterEncoder]:
    """As run_through_wire, with the robot's InterEncoder and the cloud's ReferenceRing:
    a frame is lost with probability ``loss``; the cloud's feedback for a frame reaches the
    robot ``ack_lag`` frames after it was sent. Lost frames are not tracked by the cloud,
    so the poses compare with an in-memory run that skips them too."""
    config = config or Config()
    pipeline = RobotSlam.new(config, camera)
    robot, cloud = pipeline.split(k)
    encoder = InterEncoder(config.wire, config.wire.reference_frames)
    ring = ReferenceRing(config.wire.reference_frames)
    rng = np.random.default_rng(11)
    poses, keyframes, sizes, in_flight = [], [], [], []
    for seq, frame in enumerate(frames):
        while in_flight and in_flight[0] <= seq - ack_lag:
            encoder.acked(in_flight.pop(0))
        state = run_stages(robot, frame, pipeline.sides)
        refs = encoder.choose(seq)
        stats = InterStats()
        data = encode_frame_message(state, k, ROBOT, seq, camera, config.wire, refs, stats)
        encoder.sent(seq, reference_of(state), len(refs))
        encoder.record(stats)
        sizes.append(len(data))
        assert open_message(data)[0].kind == (Kind.FRAME_INTER if refs else Kind.FRAME)
        if seq and rng.random() < loss:
            continue
        header, decoded = decode_frame_message(data, camera, ring)
        assert_same_state(state, decoded, k)
        ring.put(seq, reference_of(decoded))
        mine, theirs = reference_of(state), ring.get(seq)
        assert mine.descriptors.tobytes() == theirs.descriptors.tobytes()
        assert mine.angles.tobytes() == theirs.angles.tobytes()
        in_flight.append(seq)
        out = run_stages(cloud, decoded, pipeline.sides)
        poses.append(out.T_world_camera)
        keyframes.append(out.is_keyframe)
    return np.array(poses), keyframes, sizes, encoder


@pytest.fixture(scope="module")
def lossy_frames(seven_scenes):
    """The frames the cloud gets when 20 % are lost (same seed as run_inter_through_wire)."""
    camera, frames = seven_scenes
    rng = np.random.default_rng(11)
    kept = [f for i, f in enumerate(frames) if not (i and rng.random() < 0.2)]
    return kept


@pytest.mark.realdata
@pytest.mark.parametrize("k", [2, 3, 5])
@pytest.mark.parametrize("loss", [0.0, 0.2])
def test_inter_coded_frames_are_exact(seven_scenes, seven_scenes_reference, lossy_frames,
                                      k, loss):
    camera, frames = seven_scenes
    poses, keyframes, sizes, encoder = run_inter_through_wire(camera, frames, k, loss,
                                                              ack_lag=2)
    if loss:
        expected_poses, expected_kf = run_reference(camera, lossy_frames)
        assert len(poses) == len(lossy_frames) < len(frames)
    else:
        expected_poses, expected_kf = seven_scenes_reference
    assert poses.tobytes() == expected_poses.tobytes(), f"k={k} loss={loss}"
    assert keyframes == expected_kf
    counts = encoder.counts
    assert counts.inter_frames >= len(frames) - 4 and counts.intra_frames >= 1
    assert counts.inter_descriptors > 0.8 * counts.descriptors
    if k == 3:
        intra = run_through_wire(camera, frames[:3], 3)[2]
        assert np.mean(sizes[3:]) < 0.75 * np.mean(intra), (sizes, intra)


def test_intra_frames_come_every_n_and_when_no_reference_is_acknowledged():
    f = orb_features()
    refs = reference_of(f)
    encoder = InterEncoder(WireConfig(intra_every=4, inter_references=2), cloud_ring=3)
    kinds = []
    for seq in range(10):
        chosen = encoder.choose(seq)
        kinds.append(len(chosen))
        encoder.sent(seq, refs, len(chosen))
        if seq != 9:  # frame 9 is lost: never acknowledged
            encoder.acked(seq)
    assert kinds == [0, 1, 2, 2, 0, 2, 2, 2, 0, 2]  # intra at 0, 4, 8
    assert encoder.choose(10) == [(8, refs), (7, refs)]  # newest first, 9 never acked
    encoder.refused(next_seq=10)  # the cloud lacked one: no earlier ack counts
    assert encoder.choose(10) == [] and encoder.choose(12) == []
    encoder.sent(10, refs, 0)
    encoder.acked(10)
    assert encoder.choose(11) == encoder.choose(13) == [(10, refs)]
    assert encoder.choose(14) == []  # 10 may have left the cloud's ring of 3
    off = InterEncoder(WireConfig(inter_frame=False), cloud_ring=8)
    off.sent(0, refs, 0)
    off.acked(0)
    assert off.choose(1) == []
    old_cloud = InterEncoder(WireConfig(), cloud_ring=0)  # its welcome named no ring
    old_cloud.sent(0, refs, 0)
    old_cloud.acked(0)
    assert old_cloud.choose(1) == []


def test_the_octave_search_looks_only_near_a_keypoint_s_level_and_decodes_exactly(monkeypatch):
    """The robot's reference search by pyramid level: rows within the window only, the
    lowest among equals with faiss and with OpenCV alike, the whole search once the window
    spans every level; the cloud decodes what it chose bit for bit."""
    f = orb_features()
    rng = np.random.default_rng(5)
    noisy = f.descriptors ^ (rng.random(f.descriptors.shape) < 0.08).astype(np.uint8) * \
        rng.integers(1, 256, f.descriptors.shape, dtype=np.uint8)
    ref = replace(f, descriptors=np.ascontiguousarray(noisy))
    octaves = f.keypoints[:, 5].astype(np.int64)
    assert len(np.unique(octaves)) > 2
    # Every other reference row said to be 3 levels up: its own query may not reach it.
    ref_octaves = octaves + 3 * (np.arange(len(octaves)) % 2)
    rows, dist = nearest_by_octave(f.descriptors, octaves, noisy, ref_octaves, 1)
    assert (np.abs(ref_octaves[rows] - octaves)[dist < 256] <= 1).all()
    full_rows, full_dist = nearest(f.descriptors, noisy)
    assert (dist >= full_dist).all()
    assert (dist[::2] == full_dist[::2]).all() and (dist[1::2] > full_dist[1::2]).all()
    wide = nearest_by_octave(f.descriptors, octaves, noisy, ref_octaves, 100)
    assert wide[0].tolist() == full_rows.tolist() and wide[1].tolist() == full_dist.tolist()
    # Against every distance worked out in numpy, on 300 rows with ties (rows repeated at
    # other places, among them levels out of order) and levels the other side lacks.
    query, q_oct = f.descriptors[:300], octaves[:300]
    rows_300 = np.concatenate([noisy[:300], noisy[:40]])
    r_oct = np.concatenate([ref_octaves[:300], ref_octaves[:40] + 1])
    r_oct[r_oct == 0] = 9
    for window in (0, 1, 2):
        bits = np.unpackbits(query[:, None, :] ^ rows_300[None, :, :], axis=2).sum(axis=2)
        bits = np.where(np.abs(q_oct[:, None] - r_oct[None, :]) <= window, bits, 256)
        want_rows = np.where(bits.min(axis=1) < 256, bits.argmin(axis=1), 0)
        got = nearest_by_octave(query, q_oct, rows_300, r_oct, window)
        assert got[0].tolist() == want_rows.tolist(), window
        assert got[1].tolist() == bits.min(axis=1).tolist(), window
    monkeypatch.setattr(wire_inter, "_faiss", lambda: None)  # a robot without faiss
    opencv = nearest_by_octave(f.descriptors, octaves, noisy, ref_octaves, 1)
    assert opencv[0].tolist() == rows.tolist() and opencv[1].tolist() == dist.tolist()
    monkeypatch.undo()
    for window in (0, 1, 7):
        config = WireConfig(inter_octaves=window)
        data = encode_frame_message(f, 3, ROBOT, 2, DISTORTED, config, [(1, reference_of(ref))])
        _, decoded = decode_frame_message(data, DISTORTED, {1: reference_of(ref)})
        assert decoded.descriptors.tobytes() == f.descriptors.tobytes(), window


def test_inter_frames_refuse_a_missing_reference_and_old_builds_refuse_them(monkeypatch):
    f = orb_features()
    ref = reference_of(f)
    data = encode_frame_message(f, 3, ROBOT, 7, DISTORTED, WireConfig(), [(6, ref), (4, ref)])
    header, decoded = decode_frame_message(data, DISTORTED, {6: ref, 4: ref})
    assert header.kind == Kind.FRAME_INTER
    assert_same_state(f, decoded, 3)
    assert len(data) < 0.3 * len(encode_frame_message(f, 3, ROBOT, 7, DISTORTED, WireConfig()))
    with pytest.raises(MissingReference, match=r"seq 7 refers to frame\(s\) seq 4 that") as exc:
        decode_frame_message(data, DISTORTED, {6: ref})
    assert (exc.value.seq, exc.value.missing) == (7, [4])
    with pytest.raises(MissingReference):
        decode_frame_message(data, DISTORTED)  # a decoder with no ring at all
    # Its reference seqs must come before it, and be distinct.
    with pytest.raises(WireError, match="not before the frame's 6"):
        decode_frame_message(encode_frame_message(f, 3, ROBOT, 6, DISTORTED, WireConfig(),
                                                  [(6, ref)]), DISTORTED, {6: ref})
    # A build from before inter-frame coding does not know the kind: it says so.
    monkeypatch.delitem(Kind._value2member_map_, int(Kind.FRAME_INTER))
    with pytest.raises(WireError, match="unknown message kind 4"):
        open_message(data)
    monkeypatch.undo()
    # An inter payload under the intra kind is refused, with a reason.
    _, payload = open_message(data)
    with pytest.raises(WireError):
        decode_state(payload, 3, DISTORTED)
    # Inter-coding only applies where descriptors are: other points stay intra.
    frame = CapturedFrame(0, 0.5, np.zeros((480, 640, 3), np.uint8),
                          np.zeros((480, 640), np.float32))
    camera = Camera(525.0, 525.0, 319.5, 239.5)
    data = encode_frame_message(frame, 0, ROBOT, 1, camera, WireConfig(), [(0, ref)])
    assert open_message(data)[0].kind == Kind.FRAME


def test_inter_frame_faults_raise_only_wire_errors():
    f = orb_features()
    ref = reference_of(f)
    shifted = replace(f, descriptors=np.roll(f.descriptors, 1, axis=1))
    payload = encode_state(shifted, 3, DISTORTED, WireConfig(), [(2, ref)])
    refs = {2: ref}
    assert_same_state(shifted, decode_state(payload, 3, DISTORTED, refs, inter=True, seq=3), 3)
    rng = np.random.default_rng(5)
    for _ in range(300):
        data = bytearray(payload)
        for pos in rng.integers(0, len(data), 3):
            data[pos] = rng.integers(0, 256)
        try:
            decode_state(bytes(data), 3, DISTORTED, refs, inter=True, seq=3)
        except WireError:
            pass
    for n in range(0, len(payload), 97):
        with pytest.raises(WireError):
            decode_state(payload[:n], 3, DISTORTED, refs, inter=True, seq=3)
