"""Initial guesses for map merging. This version: ground truth plus a known perturbation
(labelled so in every output); a later version finds the guess from the robots' own data."""

from __future__ import annotations

import numpy as np

from fleetslam.transforms import make_T, random_perturbation, transform_points


def perturbed_guess(T_target_source: np.ndarray, source_points: np.ndarray,
                    rng: np.random.Generator, rotation_deg: float, translation_m: float
                    ) -> np.ndarray:
    """The true ``T_target_source`` spoiled by a rotation of ``rotation_deg`` about a random
    axis through the source map's centroid and a shift of ``translation_m``. About the
    centroid, because about a far-away origin the same angle would also shift the map by
    metres, hiding the stated translation."""
    noise = random_perturbation(rng, rotation_deg, translation_m)
    centre = transform_points(T_target_source, source_points).mean(axis=0)
    return make_T(np.eye(3), centre) @ noise @ make_T(np.eye(3), -centre) @ T_target_source
