"""Scene folders on disk: generate a scene (room, trajectories, rendering, sensor noise)
into a folder, check whether a folder already holds a scene of a config, reuse it.

Output per robot is a native TUM RGB-D folder (rgb/, depth/, rgb.txt, depth.txt,
groundtruth.txt) plus camera.json; ``scene.json`` beside the robot folders records the
config and is written last, so only a complete scene has one.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import SyntheticConfig
from fleetslam.datasets.synthetic.render import render
from fleetslam.datasets.synthetic.room import Room
from fleetslam.datasets.synthetic.sensor import DEPTH_SCALE, sensor_depth, sensor_rgb
from fleetslam.datasets.synthetic.trajectories import robot_timestamps, robot_trajectories
from fleetslam.io.trajectory import write_tum_trajectory

FORMAT_NAME = "fleetslam-synthetic"
FORMAT_VERSION = 2  # 2: furnished common view, views that cross at the start


def scene_camera(config: SyntheticConfig) -> Camera:
    return Camera(config.fx, config.fy, config.cx, config.cy, width=config.width,
                  height=config.height, distortion=(), depth_scale=DEPTH_SCALE)


def robot_folder_name(robot: int) -> str:
    return f"robot_{robot}"


def _config_json(config: SyntheticConfig) -> dict:
    # Through JSON so tuples compare equal to the lists read back from scene.json.
    return json.loads(json.dumps(dataclasses.asdict(config)))


def _write_list(path: Path, header: str, times: np.ndarray, folder: str) -> None:
    lines = [f"# {header}", f"# file: '{path.parent.name}' (fleetslam synthetic)",
             "# timestamp filename"]
    lines += [f"{t:.6f} {folder}/{t:.6f}.png" for t in times]
    path.write_text("\n".join(lines) + "\n")


def _frame_rng(config: SyntheticConfig, robot: int, frame: int) -> np.random.Generator:
    return np.random.default_rng([config.seed, 3, robot, frame])


def _write_robot(folder: Path, room: Room, camera: Camera, config: SyntheticConfig, robot: int,
                 poses: np.ndarray, tick: Callable[[], None]) -> None:
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    times = robot_timestamps(config, robot)
    for i, (t, T) in enumerate(zip(times, poses)):
        rgb, depth = render(room, camera, T)
        rng = _frame_rng(config, robot, i)
        raw = sensor_depth(depth, config, rng)
        noisy = sensor_rgb(rgb, rng)
        name = f"{t:.6f}.png"
        if not cv2.imwrite(str(folder / "rgb" / name), cv2.cvtColor(noisy, cv2.COLOR_RGB2BGR)):
            raise OSError(f"{folder / 'rgb' / name}: cannot write image")
        if not cv2.imwrite(str(folder / "depth" / name), raw):
            raise OSError(f"{folder / 'depth' / name}: cannot write image")
        tick()
    _write_list(folder / "rgb.txt", "color images", times, "rgb")
    _write_list(folder / "depth.txt", "depth maps", times, "depth")
    write_tum_trajectory(folder / "groundtruth.txt", times, poses,
                         comment=f"ground truth trajectory\nfile: '{folder.name}' (fleetslam synthetic, "
                                 f"T_world_camera, OpenCV camera axes)")
    (folder / "camera.json").write_text(camera.to_json() + "\n")


def _scene_record(config: SyntheticConfig, room: Room) -> dict:
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "seed": config.seed,
        "config": _config_json(config),
        "robots": [robot_folder_name(r) for r in range(config.n_robots)],
        "frames_per_robot": config.frames_per_robot,
        "world_frame": "z up, floor at z=0, room centred on x=y=0; poses are T_world_camera",
        "room": {"size_m": list(room.size_m), "boxes": [b.to_dict() for b in room.boxes]},
    }


def _looks_like_scene(path: Path) -> bool:
    """Only folders we wrote (or empty ones) may be replaced."""
    if not path.exists():
        return True
    if not path.is_dir():
        return False
    entries = list(path.iterdir())
    return not entries or (path / "scene.json").exists()


def _remove_stale_partials(out_dir: Path) -> None:
    """Temporary folders left by killed runs (their process is gone)."""
    leftovers = [*out_dir.parent.glob(f".{out_dir.name}.partial-*"),
                 *out_dir.parent.glob(f".{out_dir.name}.old-*")]
    for tmp in leftovers:
        try:
            pid = int(tmp.name.rsplit("-", 1)[1])
            os.kill(pid, 0)
        except ProcessLookupError:
            shutil.rmtree(tmp, ignore_errors=True)
        except (ValueError, PermissionError):
            pass


def generate_scene(out_dir: Path, config: SyntheticConfig,
                   progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """Write the scene to ``out_dir`` (replacing a previous scene there); returns the robot
    folders. Everything is written to a temporary sibling folder that is renamed into place
    at the end, so an interrupted run never leaves a folder that looks complete."""
    out_dir = Path(out_dir)
    if not _looks_like_scene(out_dir):
        raise FileExistsError(f"{out_dir}: exists and is not a synthetic scene; not replacing it")
    poses = robot_trajectories(config)
    room = Room.from_config(config)
    camera = scene_camera(config)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_partials(out_dir)
    tmp = out_dir.parent / f".{out_dir.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    total = config.n_robots * config.frames_per_robot
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    try:
        tmp.mkdir()
        for r in range(config.n_robots):
            _write_robot(tmp / robot_folder_name(r), room, camera, config, r, poses[r], tick)
        (tmp / "scene.json").write_text(json.dumps(_scene_record(config, room), indent=2) + "\n")
        if out_dir.exists():
            old = out_dir.parent / f".{out_dir.name}.old-{os.getpid()}"
            out_dir.rename(old)
            tmp.rename(out_dir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return [out_dir / robot_folder_name(r) for r in range(config.n_robots)]


def _count_entries(path: Path) -> int:
    return sum(1 for line in path.read_text().splitlines() if line.strip() and not line.startswith("#"))


def scene_matches(out_dir: Path, config: SyntheticConfig) -> bool:
    """True if ``out_dir`` holds a complete scene generated with exactly this config."""
    out_dir = Path(out_dir)
    try:
        record = json.loads((out_dir / "scene.json").read_text())
        if (record.get("format") != FORMAT_NAME or record.get("format_version") != FORMAT_VERSION
                or record.get("config") != _config_json(config)):
            return False
        for name in record["robots"]:
            folder = out_dir / name
            for f in ("groundtruth.txt", "camera.json"):
                if not (folder / f).is_file():
                    return False
            for f in ("rgb.txt", "depth.txt"):
                if _count_entries(folder / f) != config.frames_per_robot:
                    return False
        return len(record["robots"]) == config.n_robots
    except (OSError, ValueError, KeyError, TypeError):
        return False


def ensure_scene(out_dir: Path, config: SyntheticConfig,
                 progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """The robot folders of the scene in ``out_dir``, generating it unless a complete scene
    with the same config is already there."""
    out_dir = Path(out_dir)
    if scene_matches(out_dir, config):
        total = config.n_robots * config.frames_per_robot
        if progress is not None:
            progress(total, total)
        return [out_dir / robot_folder_name(r) for r in range(config.n_robots)]
    return generate_scene(out_dir, config, progress)
