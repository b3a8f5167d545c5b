"""The render grid gains a normals row when its panels carry normals, and a coverage and depth-error row when\nit is told what training cameras see (and only then)."""

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
    return {"3dgs": panel, "paper": panel}, depth, normal


def test_normals_row_makes_the_grid_taller(tmp_path):
    panels, depth, _ = _panels(False)
    two = Image.open(render_grid(panels, np.ones((16, 16, 3)), depth, tmp_path / "two.png"))
    panels, depth, normal = _panels(True)
    three = Image.open(render_grid(panels, np.ones((16, 16, 3)), depth, tmp_path / "three.png", gt_normal=normal))
    assert three.height > 1.3 * two.height
    pixels = np.asarray(three.convert("RGB")).reshape(-1, 3)
    # (n + 1) / 2 of the normal (0, 0, -1) is (0.5, 0.5, 0): an olive colour present only in the normals row
    assert np.any(np.all(np.abs(pixels.astype(int) - (128, 128, 0)) <= 3, axis=1))


def test_error_row_shows_unseen_surface_in_magenta_and_signed_depth_error(tmp_path):
    panels, depth, normal = _panels(True)
    behind = depth.copy()
    behind[4:12, 4:12] += 0.02  # the whole method surface behind the truth
    panels = {"paper": (panels["paper"][0], behind, normal)}
    seen = np.zeros((16, 16), bool)
    seen[4:8, 4:12] = True  # the top half of the surface seen, the bottom half not
    three = Image.open(render_grid(panels, np.ones((16, 16, 3)), depth, tmp_path / "three.png", gt_normal=normal))
    four = Image.open(
        render_grid(panels, np.ones((16, 16, 3)), depth, tmp_path / "four.png", gt_normal=normal, gt_seen=seen)
    )
    assert four.height > 1.2 * three.height
    pixels = np.asarray(four.convert("RGB")).reshape(-1, 3).astype(int)
    assert np.any(np.all(np.abs(pixels - (230, 0, 204)) <= 3, axis=1))  # magenta: unseen ground truth
    # a depth error beyond the scale's end is the colour map's deepest red (RdBu_r's top, (103, 0, 31))
    assert np.any(np.all(np.abs(pixels - (103, 0, 31)) <= 3, axis=1))
