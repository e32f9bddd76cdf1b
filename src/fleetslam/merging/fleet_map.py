"""The fleet's map as one object: robots and their keyframes in, groups of joined robots
and their keyframes' global poses out, and the global outputs built from them.

    fleet = FleetMap(config)
    fleet.add_robot("r1", camera)
    fleet.add_keyframe(summary, keyframe_poses)   # each new keyframe, as robots track
    global_map = fleet.build_outputs(tracks, out_dir)   # global/*.tum, .ply, .bt
    summary = fleet.summary(global_map)

The merger (merger.py) holds the robots' keyframes, finds places they share
(place_search.py, inter_robot.py) and solves the global pose graph; the global map
(global_map.py) places every robot's keyframe clouds with the solved poses and refines them
by FS-HICP. The in-process run and the cloud's merger service make these same calls.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.merging.global_map import GlobalMap, RobotTrack, build_global_map, merge_summary
from fleetslam.merging.graph_solver import GraphSolver
from fleetslam.merging.merger import MapMerger, Searcher
from fleetslam.merging.saved_map import LoadedMap, load_into, write_map
from fleetslam.wire.merger_keyframes import KeyframeSummary


class FleetMap:
    """``search``: where places are searched (None: in line; the cloud passes a process)."""

    def __init__(self, config: Config, search: Searcher | None = None,
                 solver: GraphSolver | None = None) -> None:
        self.config = config
        self.merger = MapMerger(config, search, solver)
        self.loaded: LoadedMap | None = None  # the saved map this fleet started from

    def add_robot(self, name: str, camera: Camera, localising: bool = False) -> None:
        """``localising``: the robot is placed in the loaded map, never moves nor extends it."""
        self.merger.add_robot(name, camera, localising)

    def add_keyframe(self, summary: KeyframeSummary, poses: np.ndarray
                     ) -> list[dict[str, Any]]:
        """A robot's new keyframe and its robot's current keyframe poses (K x 4 x 4); the
        joins it caused (searched in line; a search process answers later)."""
        return self.merger.add_keyframe(summary, poses)

    def groups(self) -> dict[str, list[str]]:
        """The groups of joined robots, by the robot whose map frame each is in."""
        return self.merger.components()

    def solve_global_poses(self) -> dict[str, np.ndarray]:
        """Every robot's keyframe poses in its group's frame (solves the pose graph when
        keyframes or constraints changed since the last solve)."""
        return self.merger.solve_keyframe_poses()

    def solve_T_global_map(self, robot: str) -> np.ndarray:
        """Where the robot's map frame lies in its group's frame (solves as above)."""
        return self.merger.solve_T_global_map(robot)

    def build_outputs(self, tracks: list[RobotTrack], out_dir: Path) -> GlobalMap:
        """The largest group's global trajectories, point cloud, octree and grid, written
        under ``out_dir`` (global_map.py)."""
        return build_global_map(self.merger, tracks, self.config, out_dir)

    def load(self, loaded: LoadedMap) -> list[RobotTrack]:
        """A saved map as the fleet's first group, in its own frame: robots added after it
        search it as they search each other, and a group they join keeps the map's frame;
        localising only, its keyframes keep their poses (the robots are placed in it, the
        map does not move). The tracks the global outputs need of its robots."""
        self.merger.hold_saved = loaded.localise_only
        self.loaded = loaded
        return load_into(self.merger, loaded.saved)

    def save(self, folder: Path, global_map: GlobalMap) -> dict[str, Any] | None:
        """The merged group's map as a folder that outlives the run (saved_map.py), without
        the robots that localised only; what summary.json says of it. None when it would be
        the loaded map again (every robot localised only)."""
        if self.loaded is not None and (self.loaded.localise_only or not any(
                m not in self.merger.saved and m not in self.merger.localising
                for m in global_map.members)):
            return None
        return write_map(folder, self.merger, global_map)

    def summary(self, global_map: GlobalMap | None) -> dict[str, Any]:
        """The merge as summary.json has it."""
        return merge_summary(self.merger, global_map)
