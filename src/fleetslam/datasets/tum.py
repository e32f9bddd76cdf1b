"""TUM RGB-D sequences in the native layout (rgb/, depth/, rgb.txt, depth.txt, groundtruth.txt).

The same reader serves 7-Scenes folders that carry TUM index files, and the synthetic
scenes (which are written in this layout with a ``camera.json``).

Camera choice, first match wins: the ``camera`` argument; ``camera.json`` in the folder;
7-Scenes ``camera-intrinsics.txt`` (depth in millimetres, 65535 also invalid); the
freiburg1/2/3 camera named by the folder (``freiburg1`` or ``fr1`` ...); the ROS default.
"""

from __future__ import annotations

import functools
import logging
import re
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from fleetslam.camera import TUM_CAMERAS, Camera
from fleetslam.datasets.ranges import play_order, repeated_text
from fleetslam.datasets.source import Frame
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.transforms import interpolate_poses

log = logging.getLogger(__name__)

# TUM's associate.py pairs stamps closer than this (seconds).
MAX_ASSOCIATION_DIFF_S = 0.02
# Ground truth is interpolated only across gaps shorter than this (mocap drop-outs).
MAX_GT_GAP_S = 0.2


def read_file_list(path: Path) -> list[tuple[float, str]]:
    """A TUM list file: ``timestamp filename`` lines, '#' comments."""
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    entries = []
    for number, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 2:
            raise ValueError(f"{path}:{number}: expected 'timestamp filename', got '{line}'")
        try:
            stamp = float(parts[0])
        except ValueError:
            raise ValueError(f"{path}:{number}: timestamp '{parts[0]}' is not a number") from None
        entries.append((stamp, parts[1]))
    return entries


def associate(rgb_times: np.ndarray, depth_times: np.ndarray, max_diff: float = MAX_ASSOCIATION_DIFF_S
              ) -> list[tuple[int, int]]:
    """Pair rgb and depth stamps as TUM's associate.py does: all pairs closer than
    ``max_diff``, taken greedily from the closest, each stamp used once. Returns index pairs
    sorted by rgb time."""
    order = np.argsort(depth_times)
    sorted_depth = depth_times[order]
    candidates: list[tuple[float, int, int]] = []
    lo = np.searchsorted(sorted_depth, rgb_times - max_diff, side="left")
    hi = np.searchsorted(sorted_depth, rgb_times + max_diff, side="right")
    for i, (a, b) in enumerate(zip(lo, hi)):
        for j in range(a, b):
            candidates.append((abs(rgb_times[i] - sorted_depth[j]), i, int(order[j])))
    candidates.sort()
    used_rgb: set[int] = set()
    used_depth: set[int] = set()
    pairs = []
    for _, i, j in candidates:
        if i not in used_rgb and j not in used_depth:
            used_rgb.add(i)
            used_depth.add(j)
            pairs.append((i, j))
    pairs.sort(key=lambda p: rgb_times[p[0]])
    return pairs


def _seven_scenes_camera(path: Path) -> Camera:
    try:
        K = np.loadtxt(path)
        if K.shape != (3, 3):
            raise ValueError(f"expected a 3x3 matrix, got shape {K.shape}")
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not a camera matrix: {exc}") from exc
    return Camera(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                  depth_scale=1000.0, invalid_depth=(0, 65535))


def detect_camera(folder: Path) -> tuple[Camera, str]:
    """The camera of a sequence folder and a word on where it came from."""
    if (folder / "camera.json").exists():
        return Camera.from_json(folder / "camera.json"), "camera.json"
    if (folder / "camera-intrinsics.txt").exists():
        return _seven_scenes_camera(folder / "camera-intrinsics.txt"), "7-Scenes camera-intrinsics.txt"
    name = folder.resolve().name.lower()
    for number in ("1", "2", "3"):
        if re.search(rf"(freiburg{number}|(^|[^a-z])fr{number}([^0-9]|$))", name):
            return TUM_CAMERAS[f"freiburg{number}"], f"TUM freiburg{number} (from folder name)"
    return TUM_CAMERAS["default"], "ROS default (folder names no freiburg camera)"


def ground_truth_at_stamps(path: Path, stamps: np.ndarray) -> np.ndarray:
    """Poses of a TUM-format ground-truth file at ``stamps`` (N, 4, 4), interpolated between
    its poses; NaN where it does not cover a stamp (outside it, or across a gap longer than
    MAX_GT_GAP_S). ValueError naming the file if it is not one."""
    times, poses = read_tum_trajectory(path)
    out = np.full((len(stamps), 4, 4), np.nan)
    inside = (stamps >= times[0]) & (stamps <= times[-1])
    if len(times) == 1:
        out[stamps == times[0]] = poses[0]
        return out
    idx = np.clip(np.searchsorted(times, stamps), 1, len(times) - 1)
    gap = times[idx] - times[idx - 1]
    ok = inside & (gap <= MAX_GT_GAP_S)
    if ok.any():
        out[ok] = interpolate_poses(times, poses, stamps[ok])
    return out


class RgbdSequence:
    """Random access to the associated RGB-D frames of one folder, optionally a frame range."""

    def __init__(self, folder: str | Path, camera: Camera | None = None,
                 first: int = 0, last: int | None = None,
                 segments: list[tuple[int, int]] | None = None) -> None:
        """``segments``: inclusive frame ranges played one after the other; a range whose
        first frame is after its last plays backwards (the camera retraces its path). The
        played frames are then re-timed at the recording's median frame interval, so time
        still runs forward."""
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise ValueError(f"{self.folder}: no such sequence folder")
        if camera is None:
            camera, self.camera_source = detect_camera(self.folder)
        else:
            self.camera_source = "given"
        self.camera = camera
        rgb = read_file_list(self.folder / "rgb.txt")
        depth = read_file_list(self.folder / "depth.txt")
        if not rgb:
            raise ValueError(f"{self.folder / 'rgb.txt'}: lists no images")
        if not depth:
            raise ValueError(f"{self.folder / 'depth.txt'}: lists no images")
        rgb_t = np.array([t for t, _ in rgb])
        depth_t = np.array([t for t, _ in depth])
        pairs = associate(rgb_t, depth_t)
        if not pairs:
            raise ValueError(
                f"{self.folder}: no rgb/depth pair closer than {MAX_ASSOCIATION_DIFF_S * 1000:.0f} ms "
                f"(rgb.txt {rgb_t[0]:.3f}..{rgb_t[-1]:.3f}, depth.txt {depth_t[0]:.3f}..{depth_t[-1]:.3f})")
        recorded = np.array([rgb_t[i] for i, _ in pairs])
        played = play_order(recorded, segments or [(first, len(pairs) - 1 if last is None
                                                    else last)], str(self.folder))
        pairs = [pairs[i] for i in played.order]
        self.first = int(played.order[0])
        self.recorded_timestamps = played.recorded_timestamps
        self.timestamps = played.timestamps
        self.retimed = played.retimed
        if played.repeated:
            log.warning("%s: %s", self.folder / "rgb.txt", repeated_text(played.repeated))
        self.rgb_paths = [self.folder / rgb[i][1] for i, _ in pairs]
        self.depth_paths = [self.folder / depth[j][1] for _, j in pairs]
        for path in self.rgb_paths + self.depth_paths:
            if not path.is_file():
                raise ValueError(f"{path}: listed in the sequence index but missing")

    @functools.cached_property
    def gt_poses(self) -> np.ndarray | None:
        """Ground-truth camera-to-world pose per frame (NaN where GT does not cover it), for
        evaluation: read from groundtruth.txt on first use, which the running system never
        makes."""
        path = self.folder / "groundtruth.txt"
        if not path.exists():
            return None
        # Ground truth at each played frame's own time.
        return ground_truth_at_stamps(path, self.recorded_timestamps)

    @property
    def has_ground_truth(self) -> bool:
        return self.gt_poses is not None and bool(np.isfinite(self.gt_poses[:, 0, 0]).any())

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i: int) -> Frame:
        if not 0 <= i < len(self):
            raise IndexError(i)
        bgr = cv2.imread(str(self.rgb_paths[i]), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{self.rgb_paths[i]}: cannot decode colour image")
        raw = cv2.imread(str(self.depth_paths[i]), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ValueError(f"{self.depth_paths[i]}: cannot decode depth image")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise ValueError(f"{self.depth_paths[i]}: depth must be 16-bit single-channel, "
                             f"got {raw.dtype} with shape {raw.shape}")
        if raw.shape != bgr.shape[:2]:
            raise ValueError(f"{self.depth_paths[i]}: depth {raw.shape} and colour "
                             f"{bgr.shape[:2]} differ in size")
        cam = self.camera
        if (cam.width, cam.height) != (raw.shape[1], raw.shape[0]):
            self.camera = cam = replace(cam, width=raw.shape[1], height=raw.shape[0])
        return Frame(i, float(self.timestamps[i]), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), raw,
                     cam.depth_to_metres(raw))

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]
