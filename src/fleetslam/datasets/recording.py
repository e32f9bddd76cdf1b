"""A robot's recording by its spec: ``PATH``, ``PATH:FIRST-LAST`` or ``PATH:a-b,c-d``, where
PATH is a sequence folder (TUM / 7-Scenes layout) or a ROS bag (a ``.bag`` file, a ROS 2 bag
folder with ``metadata.yaml``, a lone ``.mcap`` or ``.db3`` file).

(Not ``open.py``: the module's name would shadow the builtin in ``from ... import``.)
"""

from __future__ import annotations

from pathlib import Path

from fleetslam.camera import Camera
from fleetslam.config import SourceConfig
from fleetslam.datasets.bag import BagSequence, is_bag
from fleetslam.datasets.ranges import parse_robot_spec
from fleetslam.datasets.source import RecordedSource
from fleetslam.datasets.tum import RgbdSequence


def spec_path(spec: str) -> Path:
    """The recording a spec names, without its frame ranges."""
    return parse_robot_spec(spec)[0]


def absolute_spec(spec: str) -> str:
    """``spec`` with its recording's path made absolute (frame ranges kept), so a run's
    summary names a source that ``fleetslam report`` finds from any directory; a spec that
    names no existing path (a live camera) is returned as given."""
    path, ranges = parse_robot_spec(spec)
    if path.is_absolute() or not path.exists():
        return spec
    # Ranges hold no ':', so the last ':' of a spec with ranges starts them.
    return str(path.resolve()) + (":" + spec.rpartition(":")[2] if ranges else "")


def spec_is_bag(spec: str) -> bool:
    return is_bag(spec_path(spec))


def open_source(spec: str, camera: Camera | None = None,
                source_config: SourceConfig | None = None) -> RecordedSource:
    """The recording ``spec`` names, played over its frame ranges; ``camera`` overrides the
    recording's own; ``source_config`` chooses a bag's topics and pairing tolerance."""
    path, ranges = parse_robot_spec(spec)
    if is_bag(path):
        return BagSequence(path, camera, ranges, source_config)
    return RgbdSequence(path, camera=camera, segments=ranges)
