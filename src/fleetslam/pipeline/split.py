"""The tracking pipeline as one ordered list of stages, and its split at an offloading point.

``split(k)`` gives the robot's part (stages[:k]) and the cloud's part (stages[k:]). Running
the two parts one after the other, with the state at the split serialised in between, gives
the same poses as running the whole list: the central invariant of partial offloading.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.pipeline.session import Session
from fleetslam.pipeline.stages import Stage, default_stages
from fleetslam.pipeline.states import CapturedFrame, TrackedFrame


@dataclass
class StageTimer:
    """Wall time of every stage, per frame."""

    seconds: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))

    def mean_ms(self) -> dict[str, float]:
        return {name: 1000.0 * sum(v) / len(v) for name, v in self.seconds.items() if v}


def run_stages(stages: list[Stage], state: Any, session: Session,
               timer: StageTimer | None = None) -> Any:
    """Run ``stages`` in order; each gets its own side of ``session``."""
    for stage in stages:
        start = time.perf_counter()
        state = stage(state, session.part(stage.side))
        if timer is not None:
            timer.seconds[stage.name].append(time.perf_counter() - start)
    return state


class TrackingPipeline:
    """One robot's tracking: a session and the ordered stages that update it."""

    def __init__(self, config: Config, camera: Camera) -> None:
        self.stages: list[Stage] = default_stages()
        self.session = Session.full(config, camera)
        self.timer = StageTimer()

    @property
    def stage_names(self) -> list[str]:
        return [s.name for s in self.stages]

    def split(self, k: int) -> tuple[list[Stage], list[Stage]]:
        """(robot stages, cloud stages) for offloading point ``k`` in 0..len(stages)."""
        if not 0 <= k <= len(self.stages):
            raise ValueError(f"offloading point {k} outside 0..{len(self.stages)}")
        return self.stages[:k], self.stages[k:]

    def track(self, frame: CapturedFrame) -> TrackedFrame:
        return run_stages(self.stages, frame, self.session, self.timer)
