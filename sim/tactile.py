"""Simulated optical tactile sensing: depth maps from ray casting and synthetic tactile RGB images.

Depth (DESIGN.md): the sensor is an orthographic depth camera behind its gel.
Parallel rays start behind the gel and travel along the gel's outward normal
(sensor +z); the first hit on the object's surface at sensor height ``z < 0``
is an indentation ``d = -z``, clamped to the gel thickness; 0 is no contact.
Rays are cast against the object's exact triangle mesh only (trimesh with the
Embree backend, float64 hit positions), never against the hand or the convex
collision hulls.

RGB: a DIGIT/GelSight-like image by a Lambertian model of three coloured
lights (red, green, blue) grazing the gel from azimuths 90, 210 and 330
degrees; each channel is lit by the slope of the indented gel surface.
"""

from __future__ import annotations

import numpy as np

from tacsplat.errors import InvalidInputError

# Unit directions (sensor frame, pointing from the gel towards each light) of the
# red, green and blue lights; rows are channels.
_LIGHT_ELEVATION = np.deg2rad(35.0)
_LIGHT_AZIMUTHS = np.deg2rad([90.0, 210.0, 330.0])
TACTILE_LIGHT_DIRECTIONS = np.stack(
    [
        np.cos(_LIGHT_ELEVATION) * np.cos(_LIGHT_AZIMUTHS),
        np.cos(_LIGHT_ELEVATION) * np.sin(_LIGHT_AZIMUTHS),
        np.full(3, np.sin(_LIGHT_ELEVATION)),
    ],
    axis=1,
)  # [3 channels, 3 xyz]
TACTILE_RGB_GAIN = 180.0  # grey levels per unit of (n . l - n_flat . l)


def default_tactile_background(height: int, width: int) -> np.ndarray:
    """The image of the untouched gel [h, w, 3] uint8: a smooth bluish grey with a soft vignette."""
    v, u = np.meshgrid(np.linspace(-1, 1, height), np.linspace(-1, 1, width), indexing="ij")
    shade = 1.0 - 0.12 * (u**2 + v**2)
    base = np.array([118.0, 128.0, 140.0])
    return np.clip(base * shade[..., None], 0, 255).astype(np.uint8)


def tactile_surface_normals(depth: np.ndarray, pixel_size_m: float) -> np.ndarray:
    """Outward unit normals [h, w, 3] of the indented gel surface ``z = -depth`` (sensor frame)."""
    dd_dy, dd_dx = np.gradient(depth.astype(np.float64), pixel_size_m)
    n = np.stack([dd_dx, dd_dy, np.ones_like(dd_dx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def render_tactile_rgb(depth: np.ndarray, pixel_size_m: float, background: np.ndarray | None = None) -> np.ndarray:
    """Synthetic tactile image [h, w, 3] uint8 of a depth map [h, w] float32 metres.

    ``I_c = background_c + TACTILE_RGB_GAIN * (n . l_c - n_flat . l_c)`` for the
    three light directions ``TACTILE_LIGHT_DIRECTIONS`` (n from the depth
    gradient by central differences), so an untouched gel is the background.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise InvalidInputError(f"render_tactile_rgb: depth must be [h, w], got shape {depth.shape}")
    if not np.all(np.isfinite(depth)):
        raise InvalidInputError("render_tactile_rgb: depth contains NaN or infinite values")
    if not (np.isfinite(pixel_size_m) and pixel_size_m > 0):
        raise InvalidInputError(f"render_tactile_rgb: pixel_size_m must be positive, got {pixel_size_m}")
    h, w = depth.shape
    if background is None:
        background = default_tactile_background(h, w)
    background = np.asarray(background)
    if background.shape != (h, w, 3):
        raise InvalidInputError(f"render_tactile_rgb: background must be [{h}, {w}, 3], got {background.shape}")
    shading = tactile_surface_normals(depth, pixel_size_m) @ TACTILE_LIGHT_DIRECTIONS.T  # [h, w, 3]
    flat = TACTILE_LIGHT_DIRECTIONS[:, 2]  # n_flat = (0, 0, 1)
    image = background.astype(np.float64) + TACTILE_RGB_GAIN * (shading - flat)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)
