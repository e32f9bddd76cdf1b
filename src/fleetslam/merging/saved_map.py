"""The fleet's map as a folder that outlives its run (``<run>/map/``), and its loader.

    map/manifest.json        format and version, the group's anchor and map frame, each
                             robot's camera and keyframe count, and every file's size and
                             SHA-256
    map/constraints.json     the inter-robot constraints (the graph's edges between robots)
    map/robots/<robot>.npz   the robot's keyframes as the merger holds them (features as the
                             wire codes them: wire/merger_keyframes.py's KeyframeSummary),
                             their poses in the map frame, and each keyframe's dense cloud

Written after a merge, for the merged group (the global outputs' robots): written whole
beside its folder, then put in its place, so a map is never half-written nor changed in
place (a later merge of the same store replaces it whole). The place index is not
stored: it is a function of the keyframes' descriptors, rebuilt when the map is loaded.

Loading checks everything before anything is used, as the checkpoint loader does: the
manifest's format and version, every file's size and hash, then each array's dtype and
shape; a damaged map is refused with the file and the reason, never half-loaded, and the
folder is only read.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.io.files import UnreadableFile, read_regular
from fleetslam.merging.global_map import GlobalMap, RobotTrack
from fleetslam.merging.merger import MapMerger
from fleetslam.pipeline.states import FeatureFrame
from fleetslam.validation.names import name_problem
from fleetslam.wire import data_tree
from fleetslam.wire.merger_keyframes import KeyframeSummary

MAP_FORMAT = "fleetslam-map"
# 2: the inter-robot constraints in a file of their own (1 had them in the manifest, which
# outgrew its bound at ~17,000 constraints when a place was mapped 26 days over).
MAP_VERSION = 2
MANIFEST = "manifest.json"
CONSTRAINTS = "constraints.json"
# A manifest is kilobytes; a listed file is a robot's (its keyframes' features and dense
# clouds, ~0.1-1 MB a keyframe) or the constraints (~1 kB each).
MAX_MANIFEST_BYTES = 16 << 20
MAX_FILE_BYTES = 8 << 30
# A loaded map's robots join the run under their names with this before them (a run's own
# robots are r0, r1, ... as the map's were).
LOADED_PREFIX = "map-"
# Two cameras are one when their images are the same size and their pinholes agree within
# this fraction of the focal length (a calibration done again differs by a few pixels).
SAME_CAMERA_TOLERANCE = 0.02
CLASSES = data_tree.classes_of(Camera, KeyframeSummary, FeatureFrame)


class MapError(ValueError):
    """A saved map that cannot be loaded: ``path`` (the file) and ``reason``."""

    def __init__(self, path: Path | str, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path, self.reason = str(path), reason


@dataclass
class SavedRobot:
    name: str
    camera: Camera
    keyframes: list[KeyframeSummary]  # the merger's, in the robot's own map frame
    poses: np.ndarray  # K x 4 x 4 T_map_keyframe in the saved map's frame
    clouds: list[tuple[np.ndarray, np.ndarray]]  # per keyframe: N x 3 float32 (camera), colours


@dataclass
class SavedMap:
    anchor: str  # whose first camera (made level) the map frame is
    map_frame: dict[str, Any]  # how the level frame was found (global_map.py)
    robots: dict[str, SavedRobot]
    constraints: list[dict[str, Any]]  # the inter-robot edges, as the manifest has them
    features: dict[str, Any]  # how its keyframes' features were made (features_of)
    folder: Path | None = None

    @property
    def keyframes(self) -> int:
        return sum(len(r.keyframes) for r in self.robots.values())


def same_camera(a: Camera, b: Camera) -> bool:
    """Whether ``a`` and ``b`` are one camera (``SAME_CAMERA_TOLERANCE``)."""
    if (a.width, a.height) != (b.width, b.height):
        return False
    scale = max(a.fx, a.fy, b.fx, b.fy)
    return all(abs(x - y) <= SAME_CAMERA_TOLERANCE * scale
               for x, y in ((a.fx, b.fx), (a.fy, b.fy), (a.cx, b.cx), (a.cy, b.cy)))


def describe_camera(camera: Camera) -> str:
    return (f"{camera.width}x{camera.height}, fx {camera.fx:g} fy {camera.fy:g} "
            f"cx {camera.cx:g} cy {camera.cy:g}")


@dataclass(frozen=True)
class LoadedMap:
    """A saved map and how a run or a cloud uses it."""

    saved: SavedMap
    # The robots are placed in it and extend it not: its keyframes keep their poses, and no
    # new map/ is written (ORB-SLAM3's localisation mode, for the fleet's map).
    localise_only: bool = False
    # A robot whose camera is none of the map's may search it (a fleet of other cameras);
    # without it such a robot is refused: a wrong camera file or a wrong map, said at once.
    new_cameras: bool = False

    def camera_problem(self, robot: str, camera: Camera) -> str | None:
        """Why ``robot`` with ``camera`` may not search this map, or None."""
        if self.new_cameras or any(same_camera(camera, r.camera)
                                   for r in self.saved.robots.values()):
            return None
        theirs: dict[str, list[str]] = {}
        for name, r in sorted(self.saved.robots.items()):
            theirs.setdefault(describe_camera(r.camera), []).append(name)
        listed = "; ".join(f"{', '.join(names)}: {camera}" for camera, names in theirs.items())
        return (f"robot {robot}'s camera ({describe_camera(camera)}) is none of the map's "
                f"cameras ({listed}): a wrong camera file or a wrong map? If the robot's "
                f"camera is meant to be new to the map, say so with --new-camera (fleetslam "
                f"run's, or the cloud's)")


def map_names(members: list[str], saved: set[str]) -> dict[str, str]:
    """Each robot's name in the map written: a loaded map's robot its name there (map-r0:
    r0), a robot of this run its own, numbered on where the map has it (r0-2), so that names
    stay short however often a map is loaded and extended."""
    out = {m: m[len(LOADED_PREFIX):] for m in members if m in saved}
    taken = set(out.values())
    for m in members:
        if m not in saved:
            name, n = m, 1
            while name in taken:
                n += 1
                name = f"{m}-{n}"
            out[m] = name
            taken.add(name)
    return out


def _constraints(merger: MapMerger, names: dict[str, str]) -> list[dict[str, Any]]:
    out = []
    for c in merger.constraints:
        q, p = c.match.query, c.match.place
        if q.robot in names and p.robot in names:
            info = c.information
            out.append({"query": [names[q.robot], q.keyframe],
                        "place": [names[p.robot], p.keyframe],
                        "T_place_query": np.asarray(c.T_place_query).tolist(),
                        "information": None if info is None else np.asarray(info).tolist(),
                        "trusted": c.trusted, "kept": c.kept})
    return out


def write_map(folder: Path, merger: MapMerger, global_map: GlobalMap) -> dict[str, Any]:
    """The merged group's map into ``folder`` (written beside it, then put in its place:
    there is never a half-written map; an earlier map there is replaced whole); what
    summary.json says of it."""
    if folder.exists() and not (folder / MANIFEST).is_file():
        raise FileExistsError(f"{folder}: exists and is not a map fleetslam wrote; not "
                              f"replaced")
    members = [m for m in global_map.members if m not in merger.localising]
    names = map_names(members, merger.saved)
    staging = folder.with_name(folder.name + ".writing")
    shutil.rmtree(staging, ignore_errors=True)
    (staging / "robots").mkdir(parents=True)
    files, robots = {}, []
    for name in members:
        record = merger.robots[name]
        clouds = global_map.keyframe_clouds.get(name, [])
        tree = {"camera": record.camera,
                "keyframes": [dataclasses.replace(k, robot=names[name])
                              for k in record.keyframes],
                "poses": np.asarray(global_map.keyframe_poses[name], np.float64),
                "cloud_points": [np.asarray(p, np.float32) for p, _ in clouds],
                "cloud_colors": [np.asarray(c, np.uint8) for _, c in clouds]}
        relative = f"robots/{names[name]}.npz"
        files[relative] = _write_listed(staging / relative, data_tree.dumps(tree, CLASSES))
        robots.append({"name": names[name], "keyframes": len(record.keyframes),
                       "file": relative, "camera": record.camera.to_dict()})
    files[CONSTRAINTS] = _write_listed(staging / CONSTRAINTS,
                                       json.dumps(_constraints(merger, names)).encode())
    manifest = {"format": MAP_FORMAT, "version": MAP_VERSION,
                "anchor": names.get(global_map.anchor, global_map.anchor),
                "map_frame": global_map.map_frame, "robots": robots,
                "features": features_of(merger.config), "constraints": CONSTRAINTS,
                "files": files}
    (staging / MANIFEST).write_text(json.dumps(manifest, indent=1))
    _put_in_place(staging, folder)
    total = sum(f["bytes"] for f in files.values())
    keyframes = sum(r["keyframes"] for r in robots)
    return {"folder": folder.name, "format_version": MAP_VERSION,
            "robots": [names[m] for m in members],
            "keyframes": keyframes, "bytes": total,
            "bytes_per_keyframe": total / keyframes if keyframes else None}


def _write_listed(path: Path, data: bytes) -> dict[str, Any]:
    """Write a file of the map; its manifest entry (size and hash, as ``_checked_file``
    checks them), from the bytes in hand."""
    path.write_bytes(data)
    return {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def _put_in_place(staging: Path, folder: Path) -> None:
    """``staging`` becomes ``folder``; an earlier map there goes only once it is replaced."""
    old = folder.with_name(folder.name + ".replaced")
    shutil.rmtree(old, ignore_errors=True)
    if folder.exists():
        os.replace(folder, old)
    os.replace(staging, folder)
    shutil.rmtree(old, ignore_errors=True)


def _manifest(folder: Path) -> dict[str, Any]:
    path = folder / MANIFEST
    try:
        text = read_regular(path, MAX_MANIFEST_BYTES, f"the limit of {MAX_MANIFEST_BYTES}")
        manifest = json.loads(text)
    except UnreadableFile as exc:
        raise MapError(path, "no manifest: not a map folder fleetslam wrote"
                       if exc.reason == "missing" else exc.reason) from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapError(path, f"not a map manifest ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != MAP_FORMAT:
        raise MapError(path, "not a map manifest fleetslam wrote")
    version = manifest.get("version")
    if not isinstance(version, int) or isinstance(version, bool) or version > MAP_VERSION:
        raise MapError(path, f"map format version {version!r}; this fleetslam reads up to "
                             f"{MAP_VERSION} (a newer fleetslam wrote it)")
    constraints = list if version == 1 else str  # version 1: in the manifest
    for key, kind in (("anchor", str), ("robots", list), ("files", dict),
                      ("constraints", constraints), ("map_frame", dict)):
        if not isinstance(manifest.get(key), kind):
            raise MapError(path, f"{key} is not a {kind.__name__}")
    return manifest


def _checked_file(folder: Path, relative: str, listed: Any) -> bytes:
    """A listed file's bytes, once its size and hash match the manifest's."""
    path = folder / relative
    if not isinstance(listed, dict) or not isinstance(listed.get("bytes"), int) \
            or not isinstance(listed.get("sha256"), str):
        raise MapError(folder / MANIFEST, f"{relative}: no size and hash listed")
    if Path(relative).is_absolute() or ".." in Path(relative).parts:
        raise MapError(folder / MANIFEST, f"{relative}: not a path inside the map")
    try:
        data = read_regular(path, min(listed["bytes"], MAX_FILE_BYTES), "its listed size")
    except UnreadableFile as exc:
        raise MapError(path, "missing (the manifest lists it)" if exc.reason == "missing"
                       else exc.reason) from None
    if len(data) != listed["bytes"]:
        raise MapError(path, f"{len(data)} bytes, the manifest says {listed['bytes']} "
                             f"(truncated or changed)")
    if hashlib.sha256(data).hexdigest() != listed["sha256"]:
        raise MapError(path, "its SHA-256 is not the manifest's (changed since it was "
                             "written)")
    return data


def _robot(folder: Path, entry: Any, files: dict[str, Any]) -> SavedRobot:
    manifest_path = folder / MANIFEST
    if not isinstance(entry, dict) or not isinstance(entry.get("name"), str) \
            or name_problem(entry["name"]) or not isinstance(entry.get("file"), str) \
            or not isinstance(entry.get("keyframes"), int):
        raise MapError(manifest_path, f"robot entry {str(entry)[:80]!r} is not one")
    name, relative = entry["name"], entry["file"]
    data = _checked_file(folder, relative, files.get(relative))
    path = folder / relative
    try:
        tree = data_tree.loads(data, str(path), CLASSES, MAX_FILE_BYTES)
    except data_tree.CheckpointError as exc:
        raise MapError(path, exc.reason.replace("session checkpoint", "map file")) from None
    robot = _robot_from_tree(path, name, entry["keyframes"], tree)
    try:
        listed = Camera.from_dict(entry.get("camera"), f"robot {name}'s camera") \
            if isinstance(entry.get("camera"), dict) else None
    except ValueError as exc:
        raise MapError(manifest_path, str(exc)) from None
    if listed is None or listed != robot.camera:
        raise MapError(manifest_path, f"robot {name}'s camera is not the one its file "
                                      f"{relative} holds (changed since it was written)")
    return robot


def _robot_from_tree(path: Path, name: str, count: int, tree: Any) -> SavedRobot:
    if not isinstance(tree, dict) or not isinstance(tree.get("camera"), Camera):
        raise MapError(path, "no camera")
    keyframes, poses = tree.get("keyframes"), tree.get("poses")
    points, colors = tree.get("cloud_points"), tree.get("cloud_colors")
    if not isinstance(keyframes, list) or len(keyframes) != count or not all(
            isinstance(k, KeyframeSummary) and k.robot == name for k in keyframes):
        raise MapError(path, f"not {count} keyframes of robot {name}")
    if not isinstance(poses, np.ndarray) or poses.shape != (count, 4, 4) \
            or poses.dtype != np.float64 or not np.isfinite(poses).all():
        raise MapError(path, f"poses are not {count} finite 4 x 4 transforms")
    if not isinstance(points, list) or not isinstance(colors, list) \
            or len(points) != len(colors) or len(points) not in (0, count):
        raise MapError(path, "dense clouds are not one per keyframe")
    for p, c in zip(points, colors):
        if not isinstance(p, np.ndarray) or not isinstance(c, np.ndarray) \
                or p.dtype != np.float32 or c.dtype != np.uint8 or p.ndim != 2 \
                or p.shape[1:] != (3,) or c.shape != p.shape or not np.isfinite(p).all():
            raise MapError(path, "a dense cloud is not N x 3 finite float32 points with "
                                 "N x 3 uint8 colours")
    return SavedRobot(name, tree["camera"], keyframes, poses, list(zip(points, colors)))


def read_map(folder: Path) -> SavedMap:
    """The map saved in ``folder``, every file checked first; MapError naming the file and
    what is wrong (nothing is loaded then, and the folder is never written)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MapError(folder, "not a folder")
    manifest = _manifest(folder)
    robots = {}
    for entry in manifest["robots"]:
        robot = _robot(folder, entry, manifest["files"])
        robots[robot.name] = robot
    if manifest["anchor"] not in robots:
        raise MapError(folder / MANIFEST, f"anchor {manifest['anchor']!r} is not one of its "
                                          f"robots")
    constraints, where = _constraints_of(folder, manifest)
    for c in constraints:
        problem = _constraint_problem(c, robots)
        if problem is not None:
            raise MapError(where, f"constraint {str(c)[:80]}: {problem}")
    features = manifest.get("features")
    if not isinstance(features, dict):
        raise MapError(folder / MANIFEST, "no features entry (how its ORB features were made)")
    return SavedMap(manifest["anchor"], manifest["map_frame"], robots, constraints, features,
                    folder)


def _constraints_of(folder: Path, manifest: dict[str, Any]) -> tuple[list[Any], Path]:
    """The inter-robot constraints (their file's, or a version-1 manifest's own), and where
    they were read."""
    if isinstance(manifest["constraints"], list):
        return manifest["constraints"], folder / MANIFEST
    relative = manifest["constraints"]
    data = _checked_file(folder, relative, manifest["files"].get(relative))
    try:
        constraints = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapError(folder / relative, f"not a list of constraints ({exc})") from None
    if not isinstance(constraints, list):
        raise MapError(folder / relative, "not a list of constraints")
    return constraints, folder / relative


def _matrix(value: Any, n: int) -> np.ndarray | None:
    try:
        m = np.array(value, np.float64)
    except (TypeError, ValueError, OverflowError):
        return None
    return m if m.shape == (n, n) and np.isfinite(m).all() else None


def _constraint_problem(c: Any, robots: dict[str, SavedRobot]) -> str | None:
    """Why an inter-robot edge of the manifest is not one between its keyframes, or None."""
    if not isinstance(c, dict):
        return "not an object"
    for end in ("query", "place"):
        ref = c.get(end)
        if not isinstance(ref, list) or len(ref) != 2 or ref[0] not in robots \
                or not isinstance(ref[1], int) \
                or not 0 <= ref[1] < len(robots[ref[0]].keyframes):
            return f"its {end} is not a keyframe of the map"
    if _matrix(c.get("T_place_query"), 4) is None:
        return "T_place_query is not a finite 4 x 4"
    if c.get("information") is not None and _matrix(c["information"], 6) is None:
        return "information is not a finite 6 x 6"
    if c.get("kept") not in (True, False, None):
        return "kept is not true, false or null"
    return None


def features_of(config: Config) -> dict[str, Any]:
    """What makes two keyframes' ORB features comparable: the pyramid they were found on
    and the place recognition that indexes them."""
    orb = config.orb
    return {"orb_n_levels": orb.n_levels, "orb_scale_factor": orb.scale_factor,
            "place_recognition": config.place_recognition.method}


def load_into(merger: MapMerger, saved: SavedMap) -> list[RobotTrack]:
    """The saved map as the merger's first group, in the map's frame, each robot renamed
    ``map-<name>``; the tracks the global map needs of them (their keyframes as frames, with
    the saved clouds). Its edges come with it, as its graph held them. MapError if its
    features were made otherwise than this run's robots' are (they could never match)."""
    ours = features_of(merger.config)
    if saved.features != ours:
        differ = ", ".join(f"{k} {saved.features.get(k)!r} (this run: {v!r})"
                           for k, v in ours.items() if saved.features.get(k) != v)
        raise MapError((saved.folder or Path("map")) / MANIFEST,
                       f"its features were made with {differ}: this run's robots' could "
                       f"never match them; run with the map's settings")
    names = {name: LOADED_PREFIX + name for name in saved.robots}
    taken = [n for n in names.values() if n in merger.robots]
    if taken:
        raise ValueError(f"robots {', '.join(taken)} are in the run already: a loaded map's "
                         f"robots are named {LOADED_PREFIX}<name>")
    keyframes: dict[str, list[KeyframeSummary]] = {}
    tracks = []
    for name in sorted(saved.robots, key=lambda n: (n != saved.anchor, n)):
        robot, new = saved.robots[name], names[name]
        kfs = [dataclasses.replace(k, robot=new, T_map_keyframe=pose.copy())
               for k, pose in zip(robot.keyframes, robot.poses)]
        merger.add_saved_robot(new, robot.camera, kfs, robot.poses, names[saved.anchor])
        keyframes[name] = kfs
        count = len(kfs)
        tracks.append(RobotTrack(
            new, robot.camera, np.array([k.timestamp for k in kfs]), robot.poses.copy(),
            np.arange(count), [np.eye(4)] * count, lambda _: None,
            keyframe_clouds={k.frame_index: cloud for k, cloud in zip(kfs, robot.clouds)}
            if robot.clouds else None))
    for c in saved.constraints:
        (q_robot, q), (p_robot, p) = c["query"], c["place"]
        information = c.get("information")
        merger.add_saved_constraint(keyframes[q_robot][q], keyframes[p_robot][p],
                                    np.array(c["T_place_query"], np.float64),
                                    None if information is None
                                    else np.array(information, np.float64), c.get("kept"))
    return tracks

