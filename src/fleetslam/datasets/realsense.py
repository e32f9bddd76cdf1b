"""An Intel RealSense as a live source, through pyrealsense2 (the ``realsense`` extra,
imported only when a RealSense is asked for): the first device, one by serial number, or a
RealSense recording played back in real time, so it behaves like the camera: ``.db3`` (the
ROS 2 bag librealsense 2.57+ records) or a ROS 1 ``.bag`` of older versions (pyrealsense2
2.59 still opens those with its ROS 1 reader, calling the format deprecated; its
``context.convert_bag_to_db3`` converts one).

Depth is aligned to colour (``rs.align``): both images share the colour camera's pixel grid
and intrinsics. The camera model comes from the device: fx, fy, ppx, ppy of the colour
stream; its lens model mapped to OpenCV's k1, k2, p1, p2, k3 (``opencv_distortion``); the
depth scale (metres per unit) as ``Camera.depth_scale`` = units per metre.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.camera import Camera
from fleetslam.datasets.live import NewestFrame, SlotCounts, take_numbered
from fleetslam.datasets.source import Frame

EXTRA = "needs the realsense extra: pip install 'fleetslam[realsense]'"
# Colour and depth a live device is asked for (a recording plays what it holds).
STREAM_SIZE = (640, 480)
STREAM_FPS = 30
# The camera thread's wait for a frameset, between looks at whether a recording ended.
POLL_MS = 200
# Normalised image extent sampled to fit OpenCV coefficients to a RealSense lens model.
FIT_GRID = 21


def import_pyrealsense2(what: str) -> Any:
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise ValueError(f"{what}: {EXTRA} ({exc})") from None
    return rs


def opencv_distortion(model: str, coeffs: list[float], camera: Camera
                      ) -> tuple[tuple[float, ...], float]:
    """(OpenCV k1, k2, p1, p2, k3; the fit's worst error in pixels) for a RealSense lens model.

    ``brown_conrady`` is OpenCV's model: copied. ``inverse_brown_conrady`` (the polynomial
    maps distorted to undistorted points) and ``modified_brown_conrady`` (the tangential
    terms act on the radially scaled point) are not: OpenCV's coefficients are fitted by
    least squares to point pairs of the RealSense model over the image. All-zero coefficients
    are no distortion; other models (fisheye) are refused."""
    c = [float(v) for v in coeffs[:5]] + [0.0] * (5 - len(coeffs[:5]))
    if not any(c) or model == "none":
        return (), 0.0
    if model == "brown_conrady":
        return tuple(c), 0.0
    if model not in ("inverse_brown_conrady", "modified_brown_conrady"):
        raise ValueError(f"RealSense lens model {model} is not one fleetslam maps "
                         f"(brown_conrady, inverse_brown_conrady, modified_brown_conrady)")
    k1, k2, p1, p2, k3 = c
    u, v = np.meshgrid(np.linspace(0, camera.width - 1, FIT_GRID),
                       np.linspace(0, camera.height - 1, FIT_GRID))
    x, y = (u.ravel() - camera.cx) / camera.fx, (v.ravel() - camera.cy) / camera.fy
    r2 = x * x + y * y
    f = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    if model == "inverse_brown_conrady":
        # x, y are distorted points; librealsense's deprojection undistorts them so.
        xd, yd = x, y
        x = xd * f + 2 * p1 * xd * yd + p2 * (r2 + 2 * xd * xd)
        y = yd * f + 2 * p2 * xd * yd + p1 * (r2 + 2 * yd * yd)
    else:  # modified: librealsense's projection scales first, then adds the tangential terms
        xs, ys = x * f, y * f
        xd = xs + 2 * p1 * xs * ys + p2 * (r2 + 2 * xs * xs)
        yd = ys + 2 * p2 * xs * ys + p1 * (r2 + 2 * ys * ys)
    # OpenCV: xd = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2), same for
    # y: linear in (k1, k2, p1, p2, k3).
    r2 = x * x + y * y
    ax = np.stack([x * r2, x * r2 ** 2, 2 * x * y, r2 + 2 * x * x, x * r2 ** 3], 1)
    ay = np.stack([y * r2, y * r2 ** 2, r2 + 2 * y * y, 2 * x * y, y * r2 ** 3], 1)
    a = np.vstack([ax, ay])
    b = np.concatenate([xd - x, yd - y])
    fit = np.linalg.lstsq(a, b, rcond=None)[0]
    residual = (a @ fit - b).reshape(2, -1) * np.array([[camera.fx], [camera.fy]])
    return tuple(float(v) for v in fit), float(np.abs(residual).max())


RECORDING_SUFFIXES = (".db3", ".bag")


def parse_realsense_spec(spec: str) -> tuple[str | None, Path | None] | None:
    """``realsense`` (first device), ``realsense:SERIAL`` or ``realsense:FILE.db3|.bag`` to
    (serial, recording); None for a spec that is no RealSense."""
    if spec != "realsense" and not spec.startswith("realsense:"):
        return None
    rest = spec.partition(":")[2]
    if not rest:
        return None, None
    if rest.lower().endswith(RECORDING_SUFFIXES):
        path = Path(rest)
        if not path.is_file():
            raise ValueError(f"--source {spec}: no such RealSense recording")
        return None, path
    return rest, None


class RealSenseSource(SlotCounts):
    """``LiveSource`` over a RealSense device or a RealSense .bag played in real time."""

    def __init__(self, spec: str, serial: str | None = None, bag: Path | None = None) -> None:
        self.spec = spec
        self.serial = serial
        self.bag = bag
        self.description = (f"RealSense recording {bag} (played in real time)" if bag
                            else f"RealSense #{serial}" if serial else "RealSense (first device)")
        self.camera = Camera(1.0, 1.0, 0.0, 0.0)  # replaced by the device's in start()
        self.camera_source = "not started"
        self._rs = import_pyrealsense2(f"--source {spec}")
        self._slot = NewestFrame()
        self._stop = threading.Event()
        self._pipeline: Any = None
        self._thread: threading.Thread | None = None

    def start(self, timeout: float) -> None:
        rs = self._rs
        config = rs.config()
        if self.bag is not None:
            config.enable_device_from_file(str(self.bag), repeat_playback=False)
        else:
            if self.serial:
                config.enable_device(self.serial)
            config.enable_stream(rs.stream.depth, *STREAM_SIZE, rs.format.z16, STREAM_FPS)
            config.enable_stream(rs.stream.color, *STREAM_SIZE, rs.format.rgb8, STREAM_FPS)
        pipeline = rs.pipeline()
        try:
            profile = pipeline.start(config)  # a recording it cannot read fails here too
        except RuntimeError as exc:
            raise ValueError(f"{self.description}: cannot start: {exc}") from None
        self._pipeline = pipeline
        device = profile.get_device()
        if self.bag is not None:
            # Real time: frames come at the recording's pace whether or not they are taken.
            device.as_playback().set_real_time(True)
        try:
            depth_units = device.first_depth_sensor().get_depth_scale()  # metres per unit
            colour = profile.get_stream(rs.stream.color).as_video_stream_profile()
        except RuntimeError as exc:
            self.close()
            raise ValueError(f"{self.description}: no depth and colour streams ({exc})") from None
        self.camera, self.camera_source = self._camera(colour.get_intrinsics(), depth_units,
                                                       device)
        self._thread = threading.Thread(target=self._run, args=(timeout,),
                                        name="realsense-camera", daemon=True)
        self._thread.start()

    def _camera(self, intr: Any, depth_units: float, device: Any) -> tuple[Camera, str]:
        if not depth_units > 0:
            raise ValueError(f"{self.description}: depth scale {depth_units} metres per unit")
        pinhole = Camera(float(intr.fx), float(intr.fy), float(intr.ppx), float(intr.ppy),
                         int(intr.width), int(intr.height), depth_scale=1.0 / depth_units)
        model = str(intr.model).rpartition(".")[2]
        distortion, error_px = opencv_distortion(model, list(intr.coeffs), pinhole)
        name = device.get_info(self._rs.camera_info.name) \
            if device.supports(self._rs.camera_info.name) else "RealSense"
        source = (f"{name} colour intrinsics, {model}"
                  + (f" (OpenCV fit, worst {error_px:.3f} px)" if error_px else "")
                  + f", depth scale {depth_units:g} m per unit")
        return Camera(pinhole.fx, pinhole.fy, pinhole.cx, pinhole.cy, pinhole.width,
                      pinhole.height, distortion, pinhole.depth_scale), source

    def take(self, timeout: float) -> Frame | None:
        return take_numbered(self._slot, timeout)

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(5.0)
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:  # already stopped (the end of a recording)
                pass
            self._pipeline = None
        self._slot.close()

    def _run(self, timeout: float) -> None:
        """The camera thread: align each frameset, convert it, put it in the slot."""
        rs = self._rs
        align = rs.align(rs.stream.color)
        ended = self._playback_ended()
        last = time.monotonic()
        try:
            while not self._stop.is_set():
                # Short waits: the end of a recording shows between them, not after a timeout.
                ok, frames = self._pipeline.try_wait_for_frames(POLL_MS)
                if not ok:
                    if ended():
                        break
                    if time.monotonic() - last > timeout:
                        raise TimeoutError(f"{self.description}: no frames in {timeout:.1f} s")
                    continue
                last = time.monotonic()
                frame = self._frame(align.process(frames))
                if frame is not None:
                    self._slot.put(frame)
        except Exception as exc:  # the camera's error reaches the robot through take()
            self._slot.close(exc if isinstance(exc, (TimeoutError, ValueError))
                             else ValueError(f"{self.description}: {exc}"))
            return
        self._slot.close()

    def _playback_ended(self) -> Callable[[], bool]:
        if self.bag is None:
            return lambda: False
        playback = self._pipeline.get_active_profile().get_device().as_playback()
        return lambda: playback.current_status() == self._rs.playback_status.stopped

    def _frame(self, frames: Any) -> Frame | None:
        colour, depth = frames.get_color_frame(), frames.get_depth_frame()
        if not colour or not depth:
            return None  # a frameset missing one stream (start-up): not an RGB-D frame
        rgb = np.asanyarray(colour.get_data())
        fmt = colour.get_profile().format()
        if fmt == self._rs.format.bgr8:
            rgb = rgb[:, :, ::-1]
        elif fmt != self._rs.format.rgb8:
            raise ValueError(f"{self.description}: colour format {fmt}, expected rgb8 or bgr8")
        raw = np.array(depth.get_data(), dtype=np.uint16, copy=True)
        return Frame(0, colour.get_timestamp() / 1000.0, np.ascontiguousarray(rgb).copy(), raw,
                     self.camera.depth_to_metres(raw))
