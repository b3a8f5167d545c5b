"""The render grid gains a normals row when its panels carry normals (and only then)."""

import numpy as np
from PIL import Image

from tacsplat.apps.report import render_grid


def _panels(with_normals: bool):
    depth = np.zeros((16, 16), np.float32)
    depth[4:12, 4:12] = 0.3
    normal = np.zeros((16, 16, 3), np.float32)
    normal[4:12, 4:12] = (0.0, 0.0, -1.0)  # facing the camera
    rgb = np.full((16, 16, 3), 0.5)
    panel = (rgb, depth, normal) if with_normals else (rgb, depth)
    return {"3dgs": panel, "full": panel}, depth, normal


def test_normals_row_makes_the_grid_taller(tmp_path):
    panels, depth, _ = _panels(False)
    two = Image.open(render_grid(panels, np.ones((16, 16, 3)), depth, tmp_path / "two.png"))
    panels, depth, normal = _panels(True)
    three = Image.open(render_grid(panels, np.ones((16, 16, 3)), depth, tmp_path / "three.png", gt_normal=normal))
    assert three.height > 1.3 * two.height
    pixels = np.asarray(three.convert("RGB")).reshape(-1, 3)
    # (n + 1) / 2 of the normal (0, 0, -1) is (0.5, 0.5, 0): an olive colour present only in the normals row
    assert np.any(np.all(np.abs(pixels.astype(int) - (128, 128, 0)) <= 3, axis=1))
