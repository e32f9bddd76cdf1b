"""The box every surface of a synthetic scene is made of: the room shell (seen from inside)
and every part of every piece of furniture."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Box:
    """A box rotated by ``yaw`` about the world z axis. ``kind`` picks its texture."""

    center: tuple[float, float, float]
    half: tuple[float, float, float]
    yaw: float = 0.0
    kind: str = "paint"

    def __post_init__(self) -> None:
        # Plain floats, so scene.json and equality do not depend on where numbers came from.
        object.__setattr__(self, "center", tuple(float(v) for v in self.center))
        object.__setattr__(self, "half", tuple(float(v) for v in self.half))
        object.__setattr__(self, "yaw", float(self.yaw))

    @property
    def R(self) -> np.ndarray:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def corners(self) -> np.ndarray:
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        return (signs * np.asarray(self.half)) @ self.R.T + np.asarray(self.center)

    def footprint(self, pad: float = 0.0) -> tuple[float, float, float, float]:
        """Axis-aligned (xmin, xmax, ymin, ymax) of the rotated footprint."""
        c = self.corners()
        return (c[:, 0].min() - pad, c[:, 0].max() + pad, c[:, 1].min() - pad, c[:, 1].max() + pad)

    def distance_to(self, point: np.ndarray) -> float:
        local = self.R.T @ (np.asarray(point, float) - np.asarray(self.center))
        outside = np.maximum(np.abs(local) - np.asarray(self.half), 0.0)
        return float(np.linalg.norm(outside))

    def to_dict(self) -> dict:
        return {"kind": self.kind, "center": list(self.center), "half": list(self.half),
                "yaw": self.yaw}
