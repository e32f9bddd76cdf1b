"""What the planner weighs: each stage's time and the bytes each split point sends, measured
on real frames (or the paper's own numbers), saved as JSON and reused.

The robot's slower CPU is either measured (stage times taken on the robot, e.g. under a CPU
limit, in ``robot_stage_ms``) or scaled from this host's by the planner's speed ratio. A
robot measures its own side with the base install (``RobotSideProfile``,
planner/robot_profiling.py); ``Profile.with_robot_side`` puts it into a profile measured
where the cloud runs (the cloud's stage times, the later points' bytes, the keyframe rate).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

PROFILE_VERSION = 1

# What crosses the link at each split point k (the robot ran stages[:k]).
SENDS = (
    "RGB-D frame",
    "keypoints, grey image, depth image",
    "keypoints, descriptors, depth image",
    "features with a depth per keypoint",
    "features, their map matches",
    "features, matches, pose",
    "its pose and flags (the robot tracks); a keyframe's features and keyframe poses",
)

# The paper's Table "Time using of each part" (s per frame) and its stated total.
PAPER_STAGE_S = (0.0154, 0.0124, 0.0062, 0.0236, 0.0022, 0.011)
PAPER_TOTAL_S = 0.0702
# The paper's Table "Data to be offloaded": MB per 10 frames at each point.
PAPER_MB_PER_10 = (6.3, 6.3, 3.8, 2.9, 3.7, 4.0, 4.2)
PAPER_SENDS = (
    "RGB + depth images",
    "RGB + depth images (keypoints found)",
    "features + depth image",
    "features + depth value per keypoint",
    "+ rotation matrix (pose)",
    "+ undistort",
    "+ keyframe",
)


@dataclass
class Profile:
    source: str
    label: str  # "measured" or "paper"
    frames: int
    stages: list[str]
    stage_ms: list[float]  # median per frame, on this host
    stage_ms_p95: list[float]
    frame_bytes: list[float]  # mean bytes of the frame message at points 0..len(stages)
    keyframe_bytes: float  # mean bytes of one keyframe upload
    keyframe_fraction: float  # keyframes per frame
    sends: list[str] = field(default_factory=lambda: list(SENDS))
    keypoints_mean: float | None = None
    # Stage times measured on the robot itself; None (all, or a stage's): scaled from the
    # host's.
    robot_stage_ms: list[float | None] | None = None
    # The paper's eta divides by its stated total, not the sum of its stages.
    stated_total_ms: float | None = None
    host: str = ""
    version: int = PROFILE_VERSION

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(asdict(self), indent=2))

    @staticmethod
    def load(path: Path) -> "Profile":
        data = _read(path)
        if data.get("kind") == RobotSideProfile.kind:
            raise ValueError(f"{path}: the robot's side of a profile only (no cloud stage "
                             f"times): plan with it as --robot-profile, beside a whole "
                             f"profile measured where the cloud runs (--profile)")
        try:
            profile = Profile(**data)
        except TypeError as exc:
            raise ValueError(f"{path}: not a profile: {exc}") from exc
        return _lengths_checked(path, profile)

    def with_robot_side(self, robot: "RobotSideProfile") -> "Profile":
        """This profile (measured where the cloud runs) with the robot's own measurement:
        its stage times for the stages it measured (the later ones scaled from this host's
        by the planner, as before), its frame messages at the points it measured and its
        keyframe upload's bytes."""
        n = len(robot.stages)
        if robot.stages != self.stages[:n]:
            raise ValueError(f"the robot's profile measured stages {', '.join(robot.stages)}; "
                             f"the cloud's profile begins {', '.join(self.stages[:n])}: "
                             f"measure both with the same fleetslam")
        return replace(
            self, label=f"{self.label}, robot side measured on {robot.host or 'the robot'}",
            robot_stage_ms=[*robot.stage_ms, *[None] * (len(self.stages) - n)],
            frame_bytes=[*robot.frame_bytes, *self.frame_bytes[n + 1:]],
            keyframe_bytes=robot.keyframe_bytes, keypoints_mean=robot.keypoints_mean,
            source=f"{self.source} (cloud); {robot.source} (robot)")


@dataclass
class RobotSideProfile:
    """What a robot measures of itself with the base install: its stages (the front end)
    and the bytes it sends at the points up to them; how often keyframes come and what the
    cloud's stages cost are not in it (they need the back-end)."""

    kind: ClassVar[str] = "robot-side"
    source: str
    frames: int
    stages: list[str]
    stage_ms: list[float]  # median per frame, on the robot
    stage_ms_p95: list[float]
    frame_bytes: list[float]  # mean bytes of the frame message at points 0..len(stages)
    keyframe_bytes: float  # mean bytes of a keyframe upload (any frame's: the same coding)
    keypoints_mean: float
    host: str = ""
    version: int = PROFILE_VERSION

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"kind": self.kind, **asdict(self)}, indent=2))

    @staticmethod
    def load(path: Path) -> "RobotSideProfile":
        data = _read(path)
        if data.pop("kind", None) != RobotSideProfile.kind:
            raise ValueError(f"{path}: not the robot's side of a profile (fleetslam plan "
                             f"--robot-side writes one)")
        try:
            profile = RobotSideProfile(**data)
        except TypeError as exc:
            raise ValueError(f"{path}: not the robot's side of a profile: {exc}") from exc
        return _lengths_checked(path, profile)


def _lengths_checked(path: Path, profile: Any) -> Any:
    """``profile`` (read from ``path``) if it has a time per stage and a payload per point."""
    n = len(profile.stages)
    if len(profile.stage_ms) != n or len(profile.frame_bytes) != n + 1:
        raise ValueError(f"{path}: {n} stages need {n} stage times and {n + 1} payloads")
    return profile


def _read(path: Path) -> dict[str, Any]:
    """A profile file's JSON object of this version, or ValueError saying why not."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a readable profile: {exc}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: not a profile (not a JSON object)")
    if data.get("version") != PROFILE_VERSION:
        raise ValueError(f"{path}: profile version {data.get('version')!r}, this "
                         f"fleetslam reads {PROFILE_VERSION}")
    return data


def paper_profile() -> Profile:
    """The paper's own stage times and payloads (keyframes are inside its point-1 payload)."""
    return Profile(
        source="paper (Tables 'Time using of each part', 'Data to be offloaded')",
        label="paper", frames=10,
        stages=["extractor", "descriptor", "compute stereo", "feature match", "pnp", "others"],
        stage_ms=[1000 * s for s in PAPER_STAGE_S], stage_ms_p95=[1000 * s for s in PAPER_STAGE_S],
        frame_bytes=[mb * 1e6 / 10 for mb in PAPER_MB_PER_10], keyframe_bytes=0.0,
        keyframe_fraction=0.0, sends=list(PAPER_SENDS), stated_total_ms=1000 * PAPER_TOTAL_S)
