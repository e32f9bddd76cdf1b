"""Which live source a ``--source`` spec names: one row per kind of camera, tried in
order; a spec no row claims is a recording (``datasets.recording.open_source``), which
``--live`` plays as a camera (``datasets.replay``)."""

from __future__ import annotations

from collections.abc import Callable

from fleetslam.config import Config
from fleetslam.datasets.live import LiveSource
from fleetslam.datasets.realsense import RealSenseSource, parse_realsense_spec
from fleetslam.datasets.ros2_topics import Ros2TopicSource, is_ros2_spec


def _realsense(spec: str, config: Config) -> LiveSource | None:
    parsed = parse_realsense_spec(spec)
    if parsed is None:
        return None
    serial, bag = parsed
    return RealSenseSource(spec, serial, bag)


def _ros2(spec: str, config: Config) -> LiveSource | None:
    return Ros2TopicSource.from_spec(spec, config) if is_ros2_spec(spec) else None


# Each opener returns None for a spec that is not its kind. A camera's library is imported
# only when that camera is opened, so a robot without its extra runs everything else.
OPENERS: list[tuple[str, Callable[[str, Config], LiveSource | None]]] = [
    ("realsense, realsense:SERIAL, realsense:FILE.db3|.bag", _realsense),
    ("ros2 (topics at [source] ros_endpoint), ros2:ENDPOINT", _ros2),
]


def open_live(spec: str, config: Config) -> LiveSource | None:
    """The live source ``spec`` names, not started; None if it names none."""
    for _, opener in OPENERS:
        source = opener(spec, config)
        if source is not None:
            return source
    return None


def live_specs() -> str:
    """The live specs, for help texts."""
    return "; ".join(forms for forms, _ in OPENERS)
