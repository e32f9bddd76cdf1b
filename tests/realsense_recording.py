"""A RealSense recording made from recorded RGB-D frames by pyrealsense2 itself: a software
device with a depth and a colour sensor (the frames' intrinsics, depth units) recorded by
librealsense's own recorder into the .db3 it plays back (librealsense 2.57+). Test data,
written by the library that reads it: no hand-made file layout."""

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
