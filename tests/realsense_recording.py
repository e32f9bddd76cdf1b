"""RealSense recordings made from recorded RGB-D frames, for pyrealsense2's playback device:
- ``.db3`` (librealsense 2.57+), written by pyrealsense2 itself: a software device with a
  depth and a colour sensor (the frames' intrinsics, depth units) recorded by librealsense's
  own recorder;
- ``.bag``, the ROS 1 format of older librealsense versions, written with rosbags' ROS 1
  writer in librealsense's file layout version 3: static device, sensor and stream
  descriptions at the earliest bag time, then one sensor_msgs/Image per frame and stream."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np


def write_realsense_recording(path: Path, frames: list, camera) -> None:
    """``frames``: fleetslam Frames of one size; ``camera``: their Camera (fx, fy, cx, cy,
    k1 k2 p1 p2 k3 as Brown-Conrady, depth_scale as depth units)."""
    import pyrealsense2 as rs

    height, width = frames[0].depth_raw.shape
    device = rs.software_device()
    depth_sensor, colour_sensor = device.add_sensor("Depth"), device.add_sensor("Color")

    def stream(kind, fmt, bpp: int, uid: int):
        intr = rs.intrinsics()
        intr.width, intr.height = width, height
        intr.fx, intr.fy, intr.ppx, intr.ppy = camera.fx, camera.fy, camera.cx, camera.cy
        intr.model = rs.distortion.brown_conrady
        intr.coeffs = list(camera.distortion) or [0.0] * 5
        s = rs.video_stream()
        s.type, s.index, s.uid, s.width, s.height = kind, 0, uid, width, height
        s.fps, s.bpp, s.fmt, s.intrinsics = 30, bpp, fmt, intr
        return s

    depth_profile = depth_sensor.add_video_stream(stream(rs.stream.depth, rs.format.z16, 2, 0))
    colour_profile = colour_sensor.add_video_stream(stream(rs.stream.color, rs.format.rgb8, 3, 1))
    depth_sensor.add_read_only_option(rs.option.depth_units, 1.0 / camera.depth_scale)
    device.create_matcher(rs.matchers.default)
    recorder = rs.recorder(str(path), device)
    depth_sensor.open(depth_profile)
    colour_sensor.open(colour_profile)
    queue = rs.frame_queue(len(frames) * 2 + 2)
    depth_sensor.start(queue)
    colour_sensor.start(queue)
    # The recorder stamps each message with the time it arrives, and real-time playback
    # follows those stamps: frames are fed at their recorded pace.
    start = time.monotonic()
    for n, frame in enumerate(frames):
        time.sleep(max(0.0, start + frame.timestamp - frames[0].timestamp - time.monotonic()))
        for sensor, profile, pixels, bpp in ((depth_sensor, depth_profile, frame.depth_raw, 2),
                                             (colour_sensor, colour_profile, frame.rgb, 3)):
            out = rs.software_video_frame()
            out.pixels = np.ascontiguousarray(pixels)
            out.stride, out.bpp = width * bpp, bpp
            out.timestamp = frame.timestamp * 1000.0  # milliseconds
            out.domain = rs.timestamp_domain.hardware_clock
            out.frame_number = n
            out.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(out)
    for sensor in (depth_sensor, colour_sensor):
        sensor.stop()
        sensor.close()
    del recorder  # the recorder writes the file out as it goes away


# librealsense's ROS 1 layout (file version 3): topics under /device_0/sensor_<i>/<Stream>_0.
STREAMS = ((0, "Stereo Module", "Depth_0", "mono16", 2), (1, "RGB Camera", "Color_0", "rgb8", 3))
STATIC_NS = 1  # rosbag's earliest valid time: librealsense reads static descriptions there


def write_realsense_ros1_bag(path: Path, frames: list, camera) -> None:
    """``frames`` and ``camera`` as for ``write_realsense_recording``; bag time follows the
    frames' timestamps (real-time playback paces by it)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg("uint32 fps\nstring encoding\nbool is_recommended\n",
                                      "realsense_msgs/msg/StreamInfo"))
    t = store.types
    height, width = frames[0].depth_raw.shape

    def stamp(seconds: float):
        whole = int(seconds)
        return t["builtin_interfaces/msg/Time"](sec=whole,
                                                nanosec=int(round((seconds - whole) * 1e9)))

    def header(seq: int, seconds: float):
        return t["std_msgs/msg/Header"](seq=seq, stamp=stamp(seconds), frame_id="0")

    with Writer(path) as writer:
        connections: dict = {}

        def put(topic: str, message, time_ns: int = STATIC_NS) -> None:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, message.__msgtype__,
                                                           typestore=store)
            writer.write(connections[topic], time_ns,
                         store.serialize_ros1(message, message.__msgtype__))

        key_value = t["diagnostic_msgs/msg/KeyValue"]
        put("/file_version", t["std_msgs/msg/UInt32"](data=3))
        put("/device_0/info", key_value(key="Name", value="fleetslam test recording"))
        for sensor, name, stream, encoding, _ in STREAMS:
            prefix = f"/device_0/sensor_{sensor}/{stream}"
            put(f"/device_0/sensor_{sensor}/info", key_value(key="Name", value=name))
            put(f"{prefix}/info", t["realsense_msgs/msg/StreamInfo"](
                fps=30, encoding=encoding, is_recommended=True))
            put(f"{prefix}/info/camera_info", t["sensor_msgs/msg/CameraInfo"](
                header=header(0, 0.0), height=height, width=width,
                distortion_model="Brown Conrady",
                D=np.array(list(camera.distortion) or [0.0] * 5, float),
                K=camera.K.ravel(), R=np.eye(3).ravel(), P=np.zeros(12), binning_x=0,
                binning_y=0, roi=t["sensor_msgs/msg/RegionOfInterest"](
                    x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))
            put(f"{prefix}/tf/0", t["geometry_msgs/msg/Transform"](  # both in one frame
                translation=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                rotation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
        put("/device_0/sensor_0/option/Depth_Units/value",
            t["std_msgs/msg/Float32"](data=1.0 / camera.depth_scale))
        put("/device_0/sensor_0/option/Depth_Units/description",
            t["std_msgs/msg/String"](data="metres per depth unit"))
        first = frames[0].timestamp
        for n, frame in enumerate(frames):
            time_ns = int(round((frame.timestamp - first + 0.1) * 1e9))
            for (sensor, _, stream, encoding, bpp), pixels in zip(STREAMS, (frame.depth_raw,
                                                                             frame.rgb)):
                data = np.frombuffer(np.ascontiguousarray(pixels).tobytes(), np.uint8)
                put(f"/device_0/sensor_{sensor}/{stream}/image/data", t["sensor_msgs/msg/Image"](
                    header=header(n, frame.timestamp), height=height, width=width,
                    encoding=encoding, is_bigendian=0, step=width * bpp, data=data), time_ns)
