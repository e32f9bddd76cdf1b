"""Sensor models: Kinect-like raw depth (noise that grows with depth, nothing near depth
edges or in random holes, nothing closer than MIN_SENSOR_DEPTH_M; TUM scale) and colour
with Gaussian pixel noise, applied to noise-free renderings."""

from __future__ import annotations

import cv2
import numpy as np

from fleetslam.config import SyntheticConfig

DEPTH_SCALE = 5000.0  # TUM: raw value per metre
# Kinect-like sensors return nothing closer than this.
MIN_SENSOR_DEPTH_M = 0.4
RGB_NOISE_SIGMA = 2.0


def _depth_edges(depth_m: np.ndarray) -> np.ndarray:
    """Pixels next to a depth discontinuity (where real sensors return nothing)."""
    kernel = np.ones((3, 3), np.uint8)
    spread = cv2.dilate(depth_m, kernel) - cv2.erode(depth_m, kernel)
    return spread > 0.02 + 0.03 * depth_m


def _dropout_mask(rng: np.random.Generator, shape: tuple[int, int], fraction: float) -> np.ndarray:
    """Random holes as small blobs covering about ``fraction`` of the image."""
    mask = np.zeros(shape, np.uint8)
    if fraction <= 0:
        return mask.astype(bool)
    radii_choices = np.arange(1, 5)
    mean_area = float(np.mean(np.pi * radii_choices**2))
    n = int(rng.poisson(fraction * shape[0] * shape[1] / mean_area))
    us = rng.integers(0, shape[1], n)
    vs = rng.integers(0, shape[0], n)
    radii = rng.choice(radii_choices, n)
    for u, v, r in zip(us, vs, radii):
        cv2.circle(mask, (int(u), int(v)), int(r), 1, -1)
    return mask.astype(bool)


def sensor_depth(depth_m: np.ndarray, config: SyntheticConfig, rng: np.random.Generator) -> np.ndarray:
    """Kinect-like raw depth (uint16, TUM scale 5000, 0 = none) from a noise-free depth."""
    z = depth_m.astype(np.float64)
    holes = _dropout_mask(rng, z.shape, config.depth_dropout) | _depth_edges(depth_m)
    sigma = config.depth_noise_a + config.depth_noise_b * (z - MIN_SENSOR_DEPTH_M) ** 2
    noisy = z + rng.standard_normal(z.shape) * sigma
    valid = ((z >= MIN_SENSOR_DEPTH_M) & (z <= config.max_depth_m) & ~holes
             & (noisy >= MIN_SENSOR_DEPTH_M) & (noisy <= config.max_depth_m))
    raw = np.clip(np.rint(noisy * DEPTH_SCALE), 1, 65535).astype(np.uint16)
    raw[~valid] = 0
    return raw


def sensor_rgb(rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Colour image with small Gaussian pixel noise."""
    noise = rng.standard_normal(rgb.shape, dtype=np.float32) * np.float32(RGB_NOISE_SIGMA)
    return np.clip(rgb.astype(np.float32) + noise + 0.5, 0, 255).astype(np.uint8)
