"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, '#' comments."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fleetslam.transforms import T_from_tum, tum_from_T


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,), poses (N, 4, 4) camera-to-world), sorted by time."""
    path = Path(path)
    rows = []
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read trajectory: {exc}") from exc
    for number, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise ValueError(f"{path}:{number}: expected 8 values (t tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            rows.append([float(p) for p in parts])
        except ValueError as exc:
            raise ValueError(f"{path}:{number}: not a number: {exc}") from exc
    if not rows:
        raise ValueError(f"{path}: no poses in trajectory file")
    table = np.array(rows)
    table = table[np.argsort(table[:, 0], kind="stable")]
    return table[:, 0], T_from_tum(table[:, 1:])


def write_tum_trajectory(path: str | Path, times: np.ndarray, poses: np.ndarray, comment: str = "") -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    values = tum_from_T(poses)
    with open(path, "w") as f:
        if comment:
            for line in comment.splitlines():
                f.write(f"# {line}\n")
        f.write("# timestamp tx ty tz qx qy qz qw\n")
        for t, v in zip(times, values):
            f.write(f"{t:.6f} " + " ".join(f"{x:.9f}" for x in v) + "\n")
