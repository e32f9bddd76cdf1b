"""An edge of the global pose graph between two robots' keyframes: the match that found it
(features, or the graph's own proximity: proximity.py), its dense refinement, and GNC's
verdict."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fleetslam.merging.dense_constraint import DenseRefinement
from fleetslam.merging.inter_robot import PlaceMatch


@dataclass
class Constraint:
    """An inter-robot match as a graph edge."""

    match: PlaceMatch
    trusted: bool  # one of the consistent set that joined two components
    kept: bool | None = None  # GNC's verdict at the last optimisation (trusted: True)
    dense: DenseRefinement | None = None  # None: not tried yet (no depth at hand)
    proximity: bool = False  # found by where the graph put the keyframes, not by features

    @property
    def T_place_query(self) -> np.ndarray:
        """The edge's measurement: the dense refinement's where it was accepted."""
        if self.dense is not None and self.dense.T_place_query is not None:
            return self.dense.T_place_query
        return self.match.T_place_query

    @property
    def information(self) -> np.ndarray | None:
        return None if self.dense is None else self.dense.information
