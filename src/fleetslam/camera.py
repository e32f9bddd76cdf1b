"""Pinhole camera with optional radial-tangential distortion, depth scale, back-projection.

The depth image may follow a pixel grid of its own: a sensor that registers depth to the
colour camera with a model other than the calibrated one (TUM freiburg1/2: OpenNI's factory
pinhole 525 / 525 / 319.5 / 239.5, no distortion, while the colour images keep their lens
distortion) gives depth pixel (u, v) the ray of that model, not of colour pixel (u, v).
``depth_intrinsics`` names that pinhole; empty, depth pixel (u, v) is colour pixel (u, v).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np


def _finite(value: int | float) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer too large for a float (JSON allows 10**400)
        return False


def mounting_problem(values: tuple[float, ...]) -> str | None:
    """Why ``values`` is not a mounting (empty, or x y z qx qy qz qw with a unit-able
    quaternion), or None."""
    if not values:
        return None
    if len(values) != 7 or not all(_finite(v) for v in values):
        return f"must be empty or 7 finite numbers x y z qx qy qz qw, got {list(values)}"
    if not 0.5 < math.sqrt(sum(v * v for v in values[3:])) < 2.0:
        return f"quaternion {list(values[3:])} is not a rotation (its norm is far from 1)"
    return None


# How far outside the image (in image widths / heights) a principal point may lie.
PRINCIPAL_POINT_REACH = 4


@dataclass(frozen=True)
class Camera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 640
    height: int = 480
    # OpenCV order k1, k2, p1, p2, k3; empty = no distortion.
    distortion: tuple[float, ...] = field(default_factory=tuple)
    # Raw depth value per metre (TUM 5000, 7-Scenes 1000).
    depth_scale: float = 5000.0
    # Raw depth values that mean "no measurement" besides 0 (7-Scenes uses 65535).
    invalid_depth: tuple[int, ...] = (0,)
    # (fx, fy, cx, cy) of the undistorted pinhole the depth image is registered to, sharing
    # the colour camera's centre; empty = the colour camera's own (distorted) pixel grid.
    # A class-level default: a checkpoint written before this field restores with it empty.
    depth_intrinsics: tuple[float, ...] = ()
    # The camera's mounting: its optical frame in the robot's base_link as x y z qx qy qz qw
    # (REP 103/105; ``[camera] base_link``); empty = not given. With it the fleet's map is
    # the anchor's base_link at its first frame (mapping/map_frame.py: T_base_camera).
    base_link: tuple[float, ...] = ()

    def mounted(self, base_link: tuple[float, ...] | None, where: str = "[camera] base_link"
                ) -> "Camera":
        """This camera with the mounting ``base_link`` (None: as it is); ValueError naming
        ``where`` if it is not one."""
        if base_link is None:
            return self
        problem = mounting_problem(tuple(base_link))
        if problem:
            raise ValueError(f"{where} {problem}")
        return replace(self, base_link=tuple(float(v) for v in base_link))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.distortion)

    def depth_to_metres(self, raw: np.ndarray) -> np.ndarray:
        """Raw 16-bit depth image to float32 metres, invalid values as 0."""
        depth = raw.astype(np.float32) / np.float32(self.depth_scale)
        for bad in self.invalid_depth:
            depth[raw == bad] = 0.0
        return depth

    def metres_to_depth(self, depth_m: np.ndarray) -> np.ndarray | None:
        """The raw 16-bit values that depth_to_metres turns back into exactly ``depth_m``
        (bit for bit; 0 = no measurement), or None if some value is not such a reading."""
        if depth_m.dtype != np.float32:
            return None
        with np.errstate(invalid="ignore", over="ignore"):
            scaled = np.nan_to_num(depth_m.astype(np.float64) * self.depth_scale, nan=0.0,
                                   posinf=0.0, neginf=0.0)
            raw = np.rint(np.clip(scaled, 0, 0xFFFF)).astype(np.uint16)
        back = self.depth_to_metres(raw)
        if not np.array_equal(back.view(np.uint32), np.ascontiguousarray(depth_m).view(np.uint32)):
            return None
        return raw

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixel coordinates (N, 2) to ideal pinhole pixel coordinates."""
        if not self.has_distortion or len(uv) == 0:
            return np.asarray(uv, dtype=np.float64)
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        out = cv2.undistortPoints(pts, self.K, self.dist_coeffs, P=self.K)
        return out.reshape(-1, 2)

    def depth_pixels(self, keypoints_uv: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Where the depth of each keypoint is in the depth image: its detected (distorted)
        position ``keypoints_uv``, or, with ``depth_intrinsics``, its ideal position ``uv``
        re-projected by that pinhole."""
        if not self.depth_intrinsics:
            return np.asarray(keypoints_uv, dtype=np.float64)
        fx, fy, cx, cy = self.depth_intrinsics
        return np.stack([(uv[:, 0] - self.cx) / self.fx * fx + cx,
                         (uv[:, 1] - self.cy) / self.fy * fy + cy], axis=1)

    def distort_points(self, uv: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixel coordinates (N, 2) to distorted ones (as detected)."""
        if not self.has_distortion or len(uv) == 0:
            return np.asarray(uv, dtype=np.float64)
        rays = np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy,
                         np.ones(len(uv))], axis=1)
        out, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), self.K, self.dist_coeffs)
        return out.reshape(-1, 2)

    def backproject(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Ideal pixel coordinates (N, 2) and depths (N,) to camera-frame points (N, 3)."""
        x = (uv[:, 0] - self.cx) / self.fx * z
        y = (uv[:, 1] - self.cy) / self.fy * z
        return np.stack([x, y, z], axis=1)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) to ideal pixel coordinates (N, 2)."""
        z = points[:, 2]
        return np.stack(
            [self.fx * points[:, 0] / z + self.cx, self.fy * points[:, 1] / z + self.cy], axis=1
        )

    def backproject_image(
        self, depth_m: np.ndarray, stride: int = 1, max_depth_m: float = np.inf,
        decimated_by: int = 1,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Depth image to camera-frame points; returns (points (N, 3), pixel indices (N, 2) as v, u).

        ``decimated_by``: the image is ``full[::n, ::n]`` of this camera's full image (a
        keyframe upload), so pixel (v, u) of it is pixel (n v, n u) of the camera."""
        v, u = np.mgrid[0 : depth_m.shape[0] : stride, 0 : depth_m.shape[1] : stride]
        z = depth_m[v, u]
        ok = (z > 0) & (z <= max_depth_m)
        u, v, z = u[ok], v[ok], z[ok].astype(np.float64)
        uv = np.stack([u, v], axis=1).astype(np.float64) * decimated_by
        if not self.depth_intrinsics:
            points = self.backproject(self.undistort_points(uv), z)
            return points, np.stack([v, u], axis=1)
        # The depth pixel's ray is the depth pinhole's; its colour is where that ray meets
        # the (distorted) colour image, on the same decimated grid.
        fx, fy, cx, cy = self.depth_intrinsics
        points = np.stack([(uv[:, 0] - cx) / fx * z, (uv[:, 1] - cy) / fy * z, z], axis=1)
        colour_uv = self.distort_points(self.project(points)) / decimated_by
        cu, cv = np.rint(colour_uv[:, 0]).astype(np.int64), np.rint(colour_uv[:, 1]).astype(np.int64)
        inside = (cu >= 0) & (cu < depth_m.shape[1]) & (cv >= 0) & (cv < depth_m.shape[0])
        return points[inside], np.stack([cv[inside], cu[inside]], axis=1)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2)

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(values: dict, where: str = "camera") -> "Camera":
        """A camera from plain values (JSON, a hello), every field checked: a camera that
        would make every frame fail later is refused here, naming the field."""
        try:
            values = dict(values)
            values["distortion"] = tuple(float(v) for v in values.get("distortion", ()))
            values["invalid_depth"] = tuple(int(v) for v in values.get("invalid_depth", (0,)))
            values["depth_intrinsics"] = tuple(float(v)
                                               for v in values.get("depth_intrinsics", ()))
            values["base_link"] = tuple(float(v) for v in values.get("base_link", ()))
            camera = Camera(**values)
        except (ValueError, TypeError, OverflowError) as exc:  # float(10**400), int(inf)
            raise ValueError(f"{where}: not a valid camera: {exc}") from exc
        for name in ("fx", "fy", "cx", "cy", "depth_scale"):
            value = getattr(camera, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not _finite(value) or (name != "cx" and name != "cy"
                                                     and value <= 0):
                raise ValueError(f"{where}: {name} must be a finite number"
                                 f"{'' if name in ('cx', 'cy') else ' > 0'}, got {value!r}")
        for name in ("width", "height"):
            value = getattr(camera, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 < value <= 16384:
                raise ValueError(f"{where}: {name} must be a whole number of pixels in "
                                 f"1-16384, got {value!r}")
        # The principal point lies in or near the image: one far outside it (1e308) is
        # finite but makes every projection overflow.
        for name, size in (("cx", camera.width), ("cy", camera.height)):
            if abs(getattr(camera, name)) > PRINCIPAL_POINT_REACH * size:
                raise ValueError(f"{where}: {name} must be within {PRINCIPAL_POINT_REACH} "
                                 f"image sizes of the image, got {getattr(camera, name)!r}")
        if len(camera.distortion) not in (0, 4, 5, 8) or \
                not all(math.isfinite(v) for v in camera.distortion):
            raise ValueError(f"{where}: distortion must be 0, 4, 5 or 8 finite coefficients")
        if camera.depth_intrinsics and (
                len(camera.depth_intrinsics) != 4
                or not all(math.isfinite(v) for v in camera.depth_intrinsics)
                or min(camera.depth_intrinsics[:2]) <= 0):
            raise ValueError(f"{where}: depth_intrinsics must be empty or 4 finite numbers "
                             f"fx, fy, cx, cy with fx, fy > 0")
        problem = mounting_problem(camera.base_link)
        if problem:
            raise ValueError(f"{where}: base_link {problem}")
        return camera

    @staticmethod
    def from_json(path: Path) -> "Camera":
        try:
            values = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: not a valid camera file: {exc}") from exc
        return Camera.from_dict(values, str(path))


# TUM RGB-D colour cameras (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats).
# The freiburg1/2 depth images were registered to the colour camera by the OpenNI driver
# with the Kinect's factory model, the pinhole TUM gives for turning depth images into
# points (ROS default, below); their colour images keep the calibrated lens distortion.
KINECT_FACTORY_PINHOLE = (525.0, 525.0, 319.5, 239.5)
TUM_CAMERAS: dict[str, Camera] = {
    "freiburg1": Camera(
        517.306408, 516.469215, 318.643040, 255.313989,
        distortion=(0.262383, -0.953104, -0.005358, 0.002628, 1.163314),
        depth_intrinsics=KINECT_FACTORY_PINHOLE,
    ),
    "freiburg2": Camera(
        520.908620, 521.007327, 325.141442, 249.701764,
        distortion=(0.231222, -0.784899, -0.003257, -0.000105, 0.917205),
        depth_intrinsics=KINECT_FACTORY_PINHOLE,
    ),
    "freiburg3": Camera(535.4, 539.2, 320.1, 247.6),
    # ROS default, used when the folder names no freiburg camera.
    "default": Camera(*KINECT_FACTORY_PINHOLE),
}
