"""Training below full resolution: a scene downscaled by 2 is the same scene, seen with half the pixels."""

import sys
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders

from recon_synthetic import build_sphere_scene, sphere_gaussians  # noqa: E402

from tacsplat.datasets import Scene  # noqa: E402
from tacsplat.reconstruction.config import TrainConfig  # noqa: E402
from tacsplat.reconstruction.initialization import InitConfig  # noqa: E402
from tacsplat.reconstruction.raster import rasterization  # noqa: E402
from tacsplat.reconstruction.trainer import reconstruct  # noqa: E402
from tacsplat.reconstruction.views import ScaledScene, camera_tensors  # noqa: E402


def _alpha(gaussians, frame) -> np.ndarray:
    means, quats, scales, opacities, colors = (t.float() for t in gaussians)
    viewmat, K = camera_tensors([frame])
    _, alpha, _ = rasterization(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmat,
        K,
        frame.intrinsics.width,
        frame.intrinsics.height,
        eps2d=1e-4,
        backend="cpu",
    )  # (no pixel-size dilation)
    return alpha[0, ..., 0].numpy()


def test_a_scene_downscaled_by_two_renders_the_outline_of_the_full_scene_scaled_down(tmp_path):
    scene = Scene.load(build_sphere_scene(tmp_path / "sphere", size=48))
    half = ScaledScene(scene, 2)
    frame, small = scene.frames[0], half.frames[0]
    assert (small.intrinsics.width, small.intrinsics.height) == (24, 24)
    np.testing.assert_allclose(small.intrinsics.K[:2], scene.frames[0].intrinsics.K[:2] / 2)
    # images: area averages of the full-size ones
    expected = cv2.resize(scene.load_image(frame), (24, 24), interpolation=cv2.INTER_AREA)
    np.testing.assert_allclose(half.load_image(small), expected)
    # the same Gaussians seen through both cameras: the small silhouette is the big one scaled down
    gaussians = sphere_gaussians(800)
    big = cv2.resize(_alpha(gaussians, frame), (24, 24), interpolation=cv2.INTER_AREA) > 0.5
    little = _alpha(gaussians, small) > 0.5
    assert (big & little).sum() / (big | little).sum() > 0.9  # (a one-pixel ring of 24-px edge pixels differs)
    centre = [np.argwhere(mask).mean(axis=0) for mask in (big, little)]
    np.testing.assert_allclose(centre[0], centre[1], atol=0.1)  # same place, to a tenth of a pixel
    # ground-truth depth at the new size lies on the same surface
    depth = half.gt_depth(half.split("test")[0])
    assert depth.shape == (24, 24) and (depth > 0).any()


def test_reconstruct_trains_and_evaluates_at_the_downscaled_size(tmp_path):
    scene = build_sphere_scene(tmp_path / "sphere", size=48)
    config = TrainConfig(
        iterations=4,
        downscale=2,
        backend="cpu",
        sh_degree=0,
        eval_every_iters=100,
        eval_every_seconds=1e9,
        init=InitConfig(use_sfm=False, num_random_points=200),
    )
    metrics = reconstruct(scene, tmp_path / "run", config, show_progress=False)
    render = cv2.imread(str(next((tmp_path / "run" / "renders").glob("*.png"))))
    assert render.shape[:2] == (48, 72)  # 2x3 panels of 24 px
    assert np.isfinite(metrics["psnr"]) and metrics["settings"]["downscale"] == 2
    assert torch.isfinite(torch.tensor(metrics["cd"]))


def test_coarse_to_fine_trains_each_share_of_the_first_steps_at_its_size_then_at_full_size(tmp_path):
    from tacsplat.reconstruction.trainer import Trainer

    scene = Scene.load(build_sphere_scene(tmp_path / "sphere", size=48))
    config = TrainConfig(
        iterations=8,
        coarse_factors=(4, 2),
        coarse_until=0.5,
        backend="cpu",
        sh_degree=0,
        init=InitConfig(use_sfm=False, num_random_points=200),
    )
    trainer = Trainer(scene, tmp_path / "run", config)
    assert [trainer.factor_at(step) for step in range(8)] == [4, 4, 2, 2, 1, 1, 1, 1]
    assert trainer.images[0].shape == (48, 48, 3)  # initialisation sees the full size
    trainer.initialize()
    for step, size in enumerate([12, 12, 24, 24, 48]):
        trainer.set_resolution(trainer.factor_at(step))
        assert trainer.images[0].shape[:2] == (size, size) and trainer.train_frames[0].intrinsics.width == size
        np.testing.assert_allclose(trainer.Ks[0, :2].numpy(), scene.frames[0].intrinsics.K[:2] * size / 48, rtol=1e-6)
        terms = trainer.train_step()
        assert torch.isfinite(terms["loss"])


def test_coarse_factors_out_of_order_or_range_are_refused_naming_the_setting():
    for bad in [(2, 4), (1,), (128,)]:
        problem = TrainConfig(coarse_factors=bad).problem()
        assert problem is not None and problem[0] == "coarse_factors", bad
    assert TrainConfig(coarse_until=1.5).problem()[0] == "coarse_until"


def test_a_coarse_to_fine_config_round_trips_through_its_json():
    import json

    config = TrainConfig(coarse_factors=(4, 2), coarse_until=0.75)
    assert TrainConfig.from_json(json.loads(json.dumps(config.to_json()))) == config


def test_images_smaller_than_the_ssim_window_train_and_evaluate_without_ssim(tmp_path, caplog):
    from tacsplat.reconstruction.evaluation import evaluate_run

    scene = build_sphere_scene(tmp_path / "sphere", size=8, train_views=3, test_views=1)
    config = TrainConfig(iterations=2, backend="cpu", sh_degree=0, init=InitConfig(use_sfm=False, num_random_points=50))
    metrics = reconstruct(scene, tmp_path / "run", config, show_progress=False)
    assert metrics["ssim"] is None and np.isfinite(metrics["psnr"])
    assert "smaller than the 11x11 window" in caplog.text
    assert evaluate_run(tmp_path / "run")["ssim"] is None
