"""The tracking pipeline as one ordered list of stages, and the rules of its offloading point.

    0 Extract -> 1 Describe -> 2 AssociateDepth -> 3 Match -> 4 EstimatePose
    -> 5 DecideKeyframe

The offloading point k is an index into that list: the robot runs stages[:k], sends the
state at k, and the cloud runs stages[k:]. Running both parts one after the other, with the
state serialised in between, gives the same poses as running the whole list (the central
invariant of partial offloading; tests/test_split.py). The first three stages are the front
end (pipeline/front_end.py), the last three the back-end's tracking (backend/tracking.py);
``fleetslam.backend.back_end.CloudBackEnd`` puts the whole list together.

Every rule about which points exist lives here: which ones the cloud serves, which one
means "the robot tracks by itself", at which ones frames can be inter-coded.
"""

from __future__ import annotations

import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any, Protocol

# The stages' names, in order: the offloading point k is the number of them a robot runs.
STAGE_NAMES = ("extract", "describe", "associate_depth", "match", "estimate_pose",
               "decide_keyframe")
# The front end is stages[:FRONT_END_LENGTH] (Extract, Describe, AssociateDepth).
FRONT_END_LENGTH = 3
# Points at which the cloud tracks: the robot runs at most the front end. (4 and 5 would
# split the tracking map between robot and cloud.)
CLOUD_TRACKS = (0, 1, 2, 3)
# The robot runs every stage (its own map) and sends its poses.
ROBOT_TRACKS = len(STAGE_NAMES)
SUPPORTED_POINTS = (*CLOUD_TRACKS, ROBOT_TRACKS)
# The point the paper chose: features with a depth per keypoint.
PAPER_POINT = 3
# Points whose state carries ORB descriptors, so a frame can be coded against earlier ones
# (wire/inter.py).
INTER_POINTS = (2, 3, 4, 5)


def parse_offload_point(text: str) -> int:
    """A split point: a number, 'paper' (3, the paper's choice), or the name of the first
    stage that runs in the cloud ('match' = 3). ValueError saying what is allowed."""
    allowed = (f"give one of {', '.join(map(str, SUPPORTED_POINTS))}, 'paper', or the first "
               f"cloud stage ({', '.join(n for k, n in enumerate(STAGE_NAMES) if k in SUPPORTED_POINTS)})")
    if text == "paper":
        return PAPER_POINT
    if text.isdigit():
        k = int(text)
    elif text in STAGE_NAMES:
        k = STAGE_NAMES.index(text)
    else:
        raise ValueError(f"offloading point {text!r}: {allowed}")
    if k > ROBOT_TRACKS:
        raise ValueError(f"offloading point {k}: there are {ROBOT_TRACKS} stages; {allowed}")
    check_point(k)
    return k


def check_point(k: int) -> None:
    """ValueError unless ``k`` is a point robot and cloud can split at."""
    if k not in SUPPORTED_POINTS:
        done = f"after {STAGE_NAMES[k - 1]}" if 0 < k <= ROBOT_TRACKS else "?"
        raise ValueError(
            f"offloading point {k} ({done} on the robot) splits the tracking map between "
            f"robot and cloud; use {', '.join(map(str, SUPPORTED_POINTS))}")


class Stage(Protocol):
    name: str
    side: str  # "edge": reads a FrontEndState; "cloud": reads the back-end's state

    def __call__(self, state: Any, context: Any) -> Any: ...


@dataclass
class Sides:
    """What the stages of each side read: a process holds only the sides it runs (a robot
    at point 3 the front end, its cloud session the back-end)."""

    edge: Any = None
    cloud: Any = None

    def part(self, side: str) -> Any:
        part = self.edge if side == "edge" else self.cloud if side == "cloud" else None
        if part is None:
            raise ValueError(f"this process holds no {side} state (stage on the wrong side "
                             f"of the offloading point)")
        return part


@dataclass
class StageTimer:
    """Wall time of every stage, per frame."""

    seconds: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))

    def mean_ms(self) -> dict[str, float]:
        return {name: 1000.0 * sum(v) / len(v) for name, v in self.seconds.items() if v}


def run_stages(stages: list[Stage], state: Any, sides: Sides,
               timer: StageTimer | None = None) -> Any:
    """Run ``stages`` in order; each gets its own side's state."""
    for stage in stages:
        start = time.perf_counter()
        state = stage(state, sides.part(stage.side))
        if timer is not None:
            timer.seconds[stage.name].append(time.perf_counter() - start)
    return state
