"""Synthetic tactile RGB images (tacsplat.sim.tactile.render_tactile_rgb)."""

import numpy as np
import pytest

from tacsplat.errors import InvalidInputError
from tacsplat.geometry import tactile_pixel_grid
from tacsplat.sim.tactile import (
    TACTILE_LIGHT_DIRECTIONS,
    TACTILE_RGB_GAIN,
    default_tactile_background,
    render_tactile_rgb,
    tactile_surface_normals,
)

PIX = 1.5e-4


def sphere_dent(h=64, w=80, radius=0.006, press=0.0008):
    x, y = tactile_pixel_grid(h, w, PIX)
    z_surface = np.sqrt(np.maximum(radius**2 - x**2 - y**2, 0.0)) - radius + press  # sphere bottom at -press
    return np.clip(z_surface, 0.0, None).astype(np.float32)


def test_untouched_gel_is_the_background():
    bg = default_tactile_background(48, 64)
    assert np.array_equal(render_tactile_rgb(np.zeros((48, 64), np.float32), PIX), bg)
    custom = np.full((48, 64, 3), 100, np.uint8)
    assert np.array_equal(render_tactile_rgb(np.zeros((48, 64), np.float32), PIX, custom), custom)


def test_dent_walls_are_lit_by_the_light_they_face():
    depth = sphere_dent()
    img = render_tactile_rgb(depth, PIX).astype(int)
    bg = default_tactile_background(*depth.shape).astype(int)
    # red light at azimuth +90 deg (towards +y = increasing rows): the dent wall at smaller
    # rows faces +y and is brighter in red; the wall at larger rows is darker.
    r0, c0 = depth.shape[0] // 2, depth.shape[1] // 2
    assert img[r0 - 10, c0, 0] > bg[r0 - 10, c0, 0] + 20
    assert img[r0 + 10, c0, 0] < bg[r0 + 10, c0, 0] - 20


def test_normals_can_be_recovered_from_the_colors():
    depth = sphere_dent()
    bg = default_tactile_background(*depth.shape)
    img = render_tactile_rgb(depth, PIX, bg).astype(np.float64)
    shading = (img - bg) / TACTILE_RGB_GAIN + TACTILE_LIGHT_DIRECTIONS[:, 2]
    n = np.linalg.solve(TACTILE_LIGHT_DIRECTIONS, shading.reshape(-1, 3).T).T.reshape(depth.shape + (3,))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    truth = tactile_surface_normals(depth, PIX)
    assert np.degrees(np.arccos(np.clip((n * truth).sum(-1), -1, 1))).max() < 2.0


def test_bad_inputs_are_rejected():
    with pytest.raises(InvalidInputError, match="depth"):
        render_tactile_rgb(np.zeros((3, 4, 1)), PIX)
    with pytest.raises(InvalidInputError, match="NaN"):
        render_tactile_rgb(np.full((3, 4), np.nan), PIX)
    with pytest.raises(InvalidInputError, match="pixel_size_m"):
        render_tactile_rgb(np.zeros((3, 4)), 0.0)
    with pytest.raises(InvalidInputError, match="background"):
        render_tactile_rgb(np.zeros((3, 4)), PIX, np.zeros((4, 3, 3), np.uint8))
