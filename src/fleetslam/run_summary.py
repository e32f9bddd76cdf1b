"""The schema of ``summary.json``, one type for whoever ran the run: the in-process run
(system.py) and the cloud (each robot's session as it ends, the merge) fill the same
``RobotSummary`` and ``RunSummary``; ``to_dict`` is what the file holds.

Evaluation (evaluation/fleet.py) adds each robot's scores to the written dictionaries after
the run, and a deployed run adds each robot's own report and the deployment (outputs.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fleetslam.config import Config, config_to_dict

SUMMARY_VERSION = 3


def robot_files(name: str) -> dict[str, str]:
    """A robot's entries in the summary naming its files (relative to the run folder)."""
    return {"trajectory": f"{name}/trajectory.tum", "map": f"{name}/map.ply"}


@dataclass(frozen=True)
class CloudCounts:
    """What the cloud measured of a robot it tracked over the link: where the robot split
    its pipeline, the cloud's ms per frame, the latency per frame (arrival to feedback), the
    transport's counts; from a live source (``live_camera``) what it was and the frames the
    robot took and skipped, and keyframes mapped without images."""

    offload_at: int
    cloud_ms: tuple[float, ...]
    latency_ms: tuple[float, ...]
    transport: dict[str, int]
    live_camera: dict[str, Any] | None = None
    keyframes_without_images: int = 0

    def to_dict(self) -> dict[str, Any]:
        cloud, latency = self.cloud_ms, self.latency_ms
        return {
            "offload_at": self.offload_at,
            "cloud_ms_mean": float(np.mean(cloud)) if cloud else None,
            "cloud_ms_median": float(np.median(cloud)) if cloud else None,
            "cloud_ms_p95": float(np.percentile(cloud, 95)) if cloud else None,
            "cloud_s_total": float(np.sum(cloud)) / 1000.0,
            "latency_ms_median": float(np.median(latency)) if latency else None,
            "latency_ms_p95": float(np.percentile(latency, 95)) if latency else None,
            "transport": self.transport,
            **({"live_camera": self.live_camera} if self.live_camera is not None else {}),
            **({"keyframes_without_images": self.keyframes_without_images}
               if self.live_camera is not None or self.keyframes_without_images else {}),
        }


@dataclass(frozen=True)
class RobotSummary:
    """A robot's entry: its tracking's counts and times, wherever it was tracked.
    ``camera``: where its camera's parameters came from (a recording's, in one process);
    ``cloud``: what the cloud measured (a robot tracked over the link)."""

    name: str
    source: str
    frames: int
    keyframes: int
    lost_frames: int
    loss_events: int
    repeated_frames: int
    map_resets: int
    map_points: int
    loop_closing: dict[str, Any] | None
    stage_ms: dict[str, float]
    tracking_fps: float | None
    camera: str | None = None
    cloud: CloudCounts | None = None

    def to_dict(self) -> dict[str, Any]:
        entry: dict[str, Any] = {
            "name": self.name, "source": self.source, "frames": self.frames,
            "keyframes": self.keyframes, "lost_frames": self.lost_frames,
            "loss_events": self.loss_events, "repeated_frames": self.repeated_frames,
            "map_resets": self.map_resets, "map_points": self.map_points,
            "loop_closing": self.loop_closing, "stage_ms": self.stage_ms,
            "tracking_fps": self.tracking_fps}
        if self.cloud is None:
            # Scored after the run, where the sequence has ground truth.
            entry.update(camera=self.camera, ate=None)
        else:
            entry.update(self.cloud.to_dict())
        return {**entry, **robot_files(self.name)}


@dataclass(frozen=True)
class RunSummary:
    """A run: one entry per robot (a finished cloud session's as it wrote it), the merge
    (None: not merged, an interrupted run), the settings, the wall time."""

    robots: list[RobotSummary | dict[str, Any]]
    merge: dict[str, Any] | None
    config: Config
    wall_time_s: float

    def to_dict(self) -> dict[str, Any]:
        return {"version": SUMMARY_VERSION, "wall_time_s": self.wall_time_s,
                "robots": [r.to_dict() if isinstance(r, RobotSummary) else r
                           for r in self.robots],
                "merge": self.merge, "config": config_to_dict(self.config)}
