"""Training on the silhouette's box (``crop_margin``): a window of a view is that view's pixels, and a step on it
has the whole view's losses, less the bare backdrop's nothing."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders

from recon_synthetic import build_sphere_scene, sphere_gaussians  # noqa: E402

from tacsplat.datasets import Scene  # noqa: E402
from tacsplat.reconstruction.config import TrainConfig  # noqa: E402
from tacsplat.reconstruction.initialization import InitConfig  # noqa: E402
from tacsplat.reconstruction.raster import rasterization  # noqa: E402
from tacsplat.reconstruction.trainer import Trainer  # noqa: E402
from tacsplat.reconstruction.views import camera_tensors  # noqa: E402


def _config(**overrides) -> TrainConfig:
    init = InitConfig(use_sfm=False, num_random_points=3000)  # (small: hardly any of them renders off the sphere)
    return TrainConfig(iterations=10, backend="cpu", sh_degree=0, init=init, **overrides)


def test_a_window_with_its_shifted_intrinsics_renders_the_same_pixels_as_the_whole_view(tmp_path):
    scene = Scene.load(build_sphere_scene(tmp_path / "sphere", size=48, touches=False))
    frame = scene.frames[0]
    means, quats, scales, opacities, colors = (t.float() for t in sphere_gaussians(600))
    viewmat, K = camera_tensors([frame])
    x0, y0, w, h = 7, 12, 29, 21
    window = K.clone()
    window[0, 0, 2] -= x0
    window[0, 1, 2] -= y0
    whole, whole_alpha, _ = rasterization(means, quats, scales, opacities, colors, viewmat, K, 48, 48, backend="cpu")
    part, part_alpha, _ = rasterization(means, quats, scales, opacities, colors, viewmat, window, w, h, backend="cpu")
    assert part.shape == (1, h, w, 3)
    np.testing.assert_allclose(part[0].numpy(), whole[0, y0 : y0 + h, x0 : x0 + w].numpy(), atol=1e-5)
    np.testing.assert_allclose(part_alpha[0].numpy(), whole_alpha[0, y0 : y0 + h, x0 : x0 + w].numpy(), atol=1e-5)


def test_each_view_trains_on_its_silhouettes_box_widened_by_the_margin_and_kept_in_the_image(tmp_path):
    scene = Scene.load(build_sphere_scene(tmp_path / "sphere", size=48, touches=False))
    trainer = Trainer(scene, tmp_path / "run", _config(crop_margin=0.1))
    margin = 5  # ceil(0.1 x 48)
    for (x0, y0, w, h), silhouette in zip(trainer.windows, trainer.silhouettes):
        rows, cols = np.flatnonzero(silhouette.any(axis=1)), np.flatnonzero(silhouette.any(axis=0))
        assert (x0, y0) == (max(cols[0] - margin, 0), max(rows[0] - margin, 0))
        assert (x0 + w, y0 + h) == (min(cols[-1] + margin + 1, 48), min(rows[-1] + margin + 1, 48))
        assert w * h < 48 * 48  # (the sphere leaves a border of backdrop to skip)
    whole = Trainer(scene, tmp_path / "whole", _config())
    assert whole.windows == [(0, 0, 48, 48)] * len(whole.windows)
    trainer.silhouettes[0] = None  # a view without a known backdrop trains whole
    assert trainer._window(0) == (0, 0, 48, 48)
    trainer.silhouettes[0] = np.zeros((48, 48), bool)
    trainer.silhouettes[0][47, 47] = True  # a box at the corner is widened inside the image
    trainer.config.crop_margin = 0.0
    assert trainer._window(0) == (40, 40, 8, 8)


def test_a_step_on_the_window_has_the_whole_views_losses_and_densification_gradients(tmp_path):
    scene = Scene.load(build_sphere_scene(tmp_path / "sphere", size=48, touches=False))
    steps = {}
    for name, crop in (("whole", None), ("window", 0.1)):
        # (L1 only: D-SSIM's 11-pixel windows reach past the window's edge, whose ring of pixels a crop leaves out)
        trainer = Trainer(scene, tmp_path / name, _config(crop_margin=0.1, ssim_weight=0.0))
        for image, background, (x0, y0, w, h) in zip(trainer.images, trainer.backgrounds, trainer.windows):
            # the sphere's images have faint tails on the backdrop: made bare backdrop outside the window
            inside = torch.zeros(image.shape[:2], dtype=torch.bool)
            inside[y0 : y0 + h, x0 : x0 + w] = True
            image[~inside] = background[~inside]
        trainer.config.crop_margin = crop
        trainer.set_windows()
        trainer.config.depth_normal_start_iter = 0
        trainer.initialize()
        terms = trainer.train_step()
        steps[name] = ({k: float(v) for k, v in terms.items()}, trainer.densify_state.grad2d.clone())
    (whole, whole_grad), (window, window_grad) = steps["whole"], steps["window"]
    assert whole["photometric"] > 0 and whole["smoothness"] > 0 and whole["backdrop"] > 0
    for term in ("photometric", "backdrop", "smoothness", "normals", "albedo_smoothness"):
        assert window[term] == pytest.approx(whole[term], rel=1e-4), term
    # each Gaussian's 2D-mean gradient, in the whole view's NDC
    np.testing.assert_allclose(window_grad.numpy(), whole_grad.numpy(), rtol=1e-3, atol=1e-6 * whole_grad.max().item())


def test_crop_margin_out_of_range_is_refused_naming_the_setting():
    assert TrainConfig(crop_margin=-0.1).problem()[0] == "crop_margin"
    assert TrainConfig(crop_margin=2.0).problem()[0] == "crop_margin"
    assert TrainConfig(crop_margin=None).problem() is None and TrainConfig(crop_margin=0.0).problem() is None
