"""Which recorded frames a source plays, in what order, at what times: the ``SPEC:a-b,c-d``
frame ranges shared by sequence folders and bags."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_RANGES = re.compile(r"^(?P<path>.+?):(?P<ranges>\d+-\d+(?:,\d+-\d+)*)$")
# Frame interval of a re-timed recording with a single frame (none to measure): 30 Hz.
SINGLE_FRAME_INTERVAL_S = 1 / 30


def parse_robot_spec(spec: str) -> tuple[Path, list[tuple[int, int]] | None]:
    """``PATH``, ``PATH:first-last`` (inclusive) or ``PATH:a-b,c-d,...`` (ranges played in
    turn; ``c > d`` plays backwards) to (path, ranges or None for all frames)."""
    match = _RANGES.match(spec)
    if not match:
        if not Path(spec).exists():
            for cut in (i for i, c in enumerate(spec) if c == ":"):
                head, tail = spec[:cut], spec[cut + 1:]
                if head and Path(head).exists():
                    # SEQ:0:99, SEQ:5, SEQ:a-b: a recording, then something that is no range.
                    raise ValueError(
                        f"robot '{spec}': '{tail}' after {head} is not a frame range: give "
                        f"FIRST-LAST (SEQ:0-99) or ranges played in turn (SEQ:0-99,98-0)")
        return Path(spec), None
    ranges = [tuple(int(v) for v in r.split("-")) for r in match["ranges"].split(",")]
    if len(ranges) == 1 and ranges[0][1] < ranges[0][0]:
        raise ValueError(f"robot '{spec}': frame range {ranges[0][0]}-{ranges[0][1]} is empty "
                         f"(to play backwards, follow a forward range: DIR:0-99,98-0)")
    return Path(match["path"]), ranges  # type: ignore[return-value]


@dataclass(frozen=True)
class PlayOrder:
    """The played frames: recording index of each, its recorded stamp and the stamp it is
    played at."""

    order: np.ndarray  # (N,) int, index into the recording's frames
    recorded_timestamps: np.ndarray  # (N,) the frames' own stamps (ground truth is there)
    timestamps: np.ndarray  # (N,) increasing: recorded, or re-timed if they were not
    retimed: bool
    repeated: int = 0  # frames left out: their stamp repeats the frame's before them


def play_order(recorded: np.ndarray, segments: list[tuple[int, int]] | None, where: str
               ) -> PlayOrder:
    """The frames of ``segments`` (inclusive ranges played one after the other; ``a > b``
    plays backwards; None: all) of a recording whose frames have the stamps ``recorded``
    (in recording order, not decreasing). A frame whose stamp repeats the one's before it is
    left out (one frame published twice; a session's stamps must increase, and the cloud
    refuses the repeat). Played stamps that do not increase (a backward range) are re-timed
    at the recording's median frame interval, so time still runs forward."""
    total = len(recorded)
    segments = segments or [(0, total - 1)]
    parts = []
    for a, b in segments:
        if not (0 <= a < total and 0 <= b < total):
            raise ValueError(f"{where}: frame range {a}-{b} outside 0-{total - 1}")
        parts.append(np.arange(a, b + 1) if a <= b else np.arange(a, b - 1, -1))
    order = np.concatenate(parts)
    repeats = np.r_[False, np.diff(recorded) <= 0]
    kept = order[~repeats[order]]
    if not len(kept):
        raise ValueError(f"{where}: every frame of {segments_text(segments)} repeats the stamp "
                         f"of the frame before it: nothing to play")
    stamps = recorded[kept]
    retimed = bool(np.any(np.diff(stamps) <= 0))
    timestamps = stamps.copy()
    if retimed:
        distinct = np.diff(recorded)[~repeats[1:]]
        dt = float(np.median(distinct)) if len(distinct) else SINGLE_FRAME_INTERVAL_S
        timestamps = recorded[kept[0]] + dt * np.arange(len(kept))
    return PlayOrder(kept, stamps, timestamps, retimed, len(order) - len(kept))


def repeated_text(repeated: int) -> str:
    """What a source says of the frames ``play_order`` left out (empty: none)."""
    if not repeated:
        return ""
    return (f"{repeated} frame{'s' if repeated > 1 else ''} left out: the stamp repeats "
            f"the frame's before")


def segments_text(segments: list[tuple[int, int]]) -> str:
    return "frames " + ",".join(f"{a}-{b}" for a, b in segments)
