"""Camera poses on the upper hemisphere around the object: train and held-out test views."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tacsplat.errors import ConfigError
from tacsplat.geometry import look_at


@dataclass(frozen=True)
class ViewConfig:
    """Hemisphere views looking at the object's centre (the world origin)."""

    radius_factor: float = 3.5  # camera distance = this x the object's bounding-sphere radius
    min_elevation_deg: float = 10.0
    max_elevation_deg: float = 75.0


def unit_vectors(z, azimuth) -> np.ndarray:
    """Unit vectors [..., 3] of heights ``z`` [...] and azimuths ``azimuth`` [...] radians about the z axis."""
    r = np.sqrt(1.0 - z**2)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=-1)


def fibonacci_directions(count: int, lo: float, hi: float, offset: float = 0.5) -> np.ndarray:
    """``count`` unit vectors spread evenly (Fibonacci spiral) over the band of elevations [lo, hi] radians."""
    i = np.arange(count) + offset
    z = np.sin(lo) + (np.sin(hi) - np.sin(lo)) * i / count  # equal-area in elevation
    return unit_vectors(z, i * np.pi * (3.0 - np.sqrt(5.0)))


def hemisphere_views(
    num_train: int, num_test: int, object_radius: float, seed: int = 0, config: ViewConfig = ViewConfig()
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``(train, test)`` OpenCV camera-to-world poses [4, 4] looking at the origin, image-up towards +z.

    Train views are drawn at random (seeded) over the band of elevations; test
    views cover it evenly on a Fibonacci spiral, so they are held out from training.
    """
    if num_train < 0 or num_test < 0:
        raise ConfigError("views", f"view counts must be non-negative, got {num_train} train, {num_test} test")
    if not (0 <= config.min_elevation_deg < config.max_elevation_deg < 90):
        raise ConfigError("views.elevation", "need 0 <= min_elevation_deg < max_elevation_deg < 90")
    lo, hi = np.deg2rad(config.min_elevation_deg), np.deg2rad(config.max_elevation_deg)
    distance = config.radius_factor * object_radius
    rng = np.random.default_rng(seed)
    train = unit_vectors(rng.uniform(np.sin(lo), np.sin(hi), num_train), rng.uniform(0, 2 * np.pi, num_train))
    test = fibonacci_directions(num_test, lo, hi)
    to_pose = lambda d: look_at(distance * d, np.zeros(3), up=(0.0, 0.0, 1.0))  # noqa: E731
    return [to_pose(d) for d in train], [to_pose(d) for d in test]
