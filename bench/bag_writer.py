"""Write ROS 1 and ROS 2 bags with rosbags' own writers: a TUM sequence folder as the
camera topics a ROS driver records, and hand-made messages for the tests' bad bags.

Used by bench/bag_read.py and tests/test_bag.py (loaded by path, as test_fuzz_smoke loads
fuzz_wire). Frames are read and written one at a time, so writing a bag holds one frame.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from fleetslam.camera import Camera
from fleetslam.datasets.source import RecordedSource

FLAVOURS = ("ros1", "mcap", "sqlite3")
RGB_TOPIC = "/camera/rgb/image_color"
RGB_JPEG_TOPIC = "/camera/rgb/image_color/compressed"
DEPTH_TOPIC = "/camera/depth/image"
RGB_INFO_TOPIC = "/camera/rgb/camera_info"
DEPTH_INFO_TOPIC = "/camera/depth/camera_info"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
# Bag (receive) time trails the header stamp a little, as in a recording.
RECEIVE_DELAY_NS = 3_000_000


def typestore_for(flavour: str) -> Any:
    return get_typestore(Stores.ROS1_NOETIC if flavour == "ros1" else Stores.ROS2_HUMBLE)


def stamp_ns(text: str) -> int:
    """A TUM stamp ('1305031230.325685') to integer nanoseconds, without float rounding."""
    sec, _, frac = text.partition(".")
    return int(sec) * 1_000_000_000 + int((frac + "000000000")[:9])


def header(ts: Any, ns: int, frame_id: str) -> Any:
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    time = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    fields = ts.fielddefs["std_msgs/msg/Header"][1]
    if fields[0][0] == "seq":  # ROS 1
        return Header(seq=0, stamp=time, frame_id=frame_id)
    return Header(stamp=time, frame_id=frame_id)


def image(ts: Any, ns: int, encoding: str, pixels: np.ndarray, frame_id: str = "camera") -> Any:
    pixels = np.ascontiguousarray(pixels)
    h, w = pixels.shape[:2]
    return ts.types[IMAGE](header=header(ts, ns, frame_id), height=h, width=w,
                           encoding=encoding, is_bigendian=0, step=pixels.nbytes // h,
                           data=pixels.reshape(-1).view(np.uint8))


def compressed(ts: Any, ns: int, fmt: str, payload: bytes, frame_id: str = "camera") -> Any:
    return ts.types[COMPRESSED](header=header(ts, ns, frame_id), format=fmt,
                                data=np.frombuffer(payload, np.uint8))


def camera_info(ts: Any, ns: int, fx: float, fy: float, cx: float, cy: float, width: int,
                height: int, distortion: tuple[float, ...] = (), frame_id: str = "camera"
                ) -> Any:
    K = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], np.float64)
    R = np.eye(3).reshape(-1)
    P = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], np.float64)
    D = np.array(distortion, np.float64)
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                        width=0, do_rectify=False)
    ros1 = ts.fielddefs[CAMERA_INFO][1][4][0] == "D"
    matrices = dict(D=D, K=K, R=R, P=P) if ros1 else dict(d=D, k=K, r=R, p=P)
    return ts.types[CAMERA_INFO](header=header(ts, ns, frame_id), height=height, width=width,
                                 distortion_model="plumb_bob", binning_x=0, binning_y=0,
                                 roi=roi, **matrices)


def write_bag(path: Path, flavour: str, messages: Iterable[tuple[str, str, int, Any]]) -> Path:
    """``messages``: (topic, type, bag time ns, message of ``typestore_for(flavour)``) in
    bag time order. ros1 writes ``path`` (a .bag), mcap and sqlite3 a bag folder."""
    ts = typestore_for(flavour)
    if flavour == "ros1":
        writer: Any = Writer1(path)
        serialize = ts.serialize_ros1
    else:
        plugin = StoragePlugin.MCAP if flavour == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
        serialize = ts.serialize_cdr
    connections: dict[str, Any] = {}
    with writer:
        for topic, msgtype, ns, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(connections[topic], ns, serialize(msg, msgtype))
    return path


def tum_messages(folder: Path, flavour: str, camera: Camera, colour: str = "rgb8",
                 jpeg_quality: int = 95) -> Iterator[tuple[str, str, int, Any]]:
    """A TUM folder's images as a Kinect driver's topics: colour ``rgb8`` Image or ``jpeg``
    CompressedImage, depth 32FC1 metres (``raw / depth_scale`` as float32, as TUM's own bags
    carry it; 0 = no measurement), one CameraInfo per topic per frame (colour: ``camera``'s
    calibration; depth: its registered pinhole, no distortion). Header stamps are the TUM
    stamps; bag times trail them by RECEIVE_DELAY_NS, in order."""
    ts = typestore_for(flavour)
    lines = {name: [ln.split() for ln in (folder / f"{name}.txt").read_text().splitlines()
                    if ln.strip() and not ln.startswith("#")] for name in ("rgb", "depth")}
    depth_pinhole = camera.depth_intrinsics or (camera.fx, camera.fy, camera.cx, camera.cy)
    # Every image of the folder, in stamp order, each with its camera_info.
    items = [(stamp_ns(t), "rgb", f) for t, f in lines["rgb"]] + \
        [(stamp_ns(t), "depth", f) for t, f in lines["depth"]]
    for ns, kind, name in sorted(items):
        bag_ns = ns + RECEIVE_DELAY_NS
        if kind == "rgb":
            bgr = cv2.imread(str(folder / name), cv2.IMREAD_COLOR)
            if colour == "jpeg":
                ok, payload = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
                yield RGB_JPEG_TOPIC, COMPRESSED, bag_ns, compressed(
                    ts, ns, "bgr8; jpeg compressed bgr8", payload.tobytes(), "rgb")
            else:
                yield RGB_TOPIC, IMAGE, bag_ns, image(ts, ns, colour, cv2.cvtColor(
                    bgr, cv2.COLOR_BGR2RGB) if colour == "rgb8" else bgr, "rgb")
            yield RGB_INFO_TOPIC, CAMERA_INFO, bag_ns, camera_info(
                ts, ns, camera.fx, camera.fy, camera.cx, camera.cy, bgr.shape[1], bgr.shape[0],
                camera.distortion, "rgb")
        else:
            raw = cv2.imread(str(folder / name), cv2.IMREAD_UNCHANGED)
            yield DEPTH_TOPIC, IMAGE, bag_ns, image(ts, ns, "32FC1", camera.depth_to_metres(raw),
                                                    "depth")
            yield DEPTH_INFO_TOPIC, CAMERA_INFO, bag_ns, camera_info(
                ts, ns, *depth_pinhole, raw.shape[1], raw.shape[0], (), "depth")


def recording_messages(recording: RecordedSource, flavour: str, frames: int | None = None,
                       depth: str = "16UC1") -> Iterator[tuple[str, str, int, Any]]:
    """Any recording's first ``frames`` frames (all: None) as a camera driver's raw topics:
    rgb8 colour, depth ``16UC1`` millimetres (as RealSense's and most ROS 2 drivers publish
    it) or ``32FC1`` metres, a CameraInfo per image (as :func:`tum_messages`). For a
    recording kept as compressed files (7-Scenes' JPEG and PNG), the bytes a driver would
    have delivered. Frames are decoded one at a time."""
    if depth not in ("16UC1", "32FC1"):
        raise ValueError(f"depth encoding {depth!r}: 16UC1 or 32FC1")
    ts = typestore_for(flavour)
    camera = recording.camera
    depth_pinhole = camera.depth_intrinsics or (camera.fx, camera.fy, camera.cx, camera.cy)
    for i in range(len(recording) if frames is None else min(frames, len(recording))):
        frame = recording[i]
        ns = int(round(frame.timestamp * 1e9))
        bag_ns = ns + RECEIVE_DELAY_NS
        h, w = frame.depth_m.shape
        yield RGB_TOPIC, IMAGE, bag_ns, image(ts, ns, "rgb8", frame.rgb, "rgb")
        yield RGB_INFO_TOPIC, CAMERA_INFO, bag_ns, camera_info(
            ts, ns, camera.fx, camera.fy, camera.cx, camera.cy, frame.rgb.shape[1],
            frame.rgb.shape[0], camera.distortion, "rgb")
        pixels = frame.depth_m if depth == "32FC1" else \
            np.rint(frame.depth_m * 1000.0).astype(np.uint16)  # 0 stays 0: no measurement
        yield DEPTH_TOPIC, IMAGE, bag_ns, image(ts, ns, depth, pixels, "depth")
        yield DEPTH_INFO_TOPIC, CAMERA_INFO, bag_ns, camera_info(
            ts, ns, *depth_pinhole, w, h, (), "depth")


def write_tum_bag(folder: Path, out: Path, flavour: str, camera: Camera,
                  colour: str = "rgb8") -> Path:
    """``folder`` written as a bag at ``out`` (see tum_messages)."""
    return write_bag(out, flavour, tum_messages(folder, flavour, camera, colour))

