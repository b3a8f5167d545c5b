"""Initialisation from a scene's sparse points (an import's COLMAP points3D) instead of triangulating its own."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tacsplat.datasets import Scene, SceneWriter
from tacsplat.reconstruction import trainer as trainer_module
from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.gaussians import rgb_to_sh0
from tacsplat.reconstruction.initialization import InitConfig, SfmResult
from tacsplat.reconstruction.trainer import Trainer
from tacsplat.reconstruction.views import scene_at

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import RADIUS, build_sphere_scene  # noqa: E402

COUNT = 150


def _scene_with_points(path: Path, count: int = COUNT) -> tuple[Path, np.ndarray, np.ndarray]:
    """The synthetic sphere scene with ``count`` coloured sparse points on the sphere."""
    build_sphere_scene(path, size=16, train_views=3, test_views=1, touches=False)
    rng = np.random.default_rng(1)
    points = rng.normal(size=(count, 3))
    points *= RADIUS / np.linalg.norm(points, axis=1, keepdims=True)
    colors = rng.integers(0, 256, (count, 3), dtype=np.uint8)
    if count:
        with SceneWriter.resume(path) as writer:
            writer.set_sparse_points(points, colors)
    return path, points, colors


class _Triangulation:
    """Stands in for ``sfm_points``: counts its calls and finds ``count`` points."""

    def __init__(self, count: int):
        self.calls, self.count = 0, count

    def __call__(self, images, Ks, poses, config, seed):
        self.calls += 1
        return SfmResult(np.random.default_rng(2).uniform(-0.05, 0.05, (self.count, 3)), np.full((self.count, 3), 0.5))


def _config(**init) -> TrainConfig:
    return TrainConfig(backend="cpu", use_touch=False, sh_degree=0, init=InitConfig(num_random_points=300, **init))


@pytest.mark.parametrize("downscale", [1, 2])
def test_a_scene_with_enough_sparse_points_starts_from_them_without_triangulating(
    tmp_path, monkeypatch, caplog, downscale
):
    path, points, colors = _scene_with_points(tmp_path / "scene")
    triangulation = _Triangulation(500)
    monkeypatch.setattr(trainer_module, "sfm_points", triangulation)
    trainer = Trainer(scene_at(Scene.load(path), downscale), tmp_path / "run", _config())
    with caplog.at_level("INFO", logger="tacsplat.reconstruction.trainer"):
        trainer.initialize()
    assert triangulation.calls == 0
    assert f"initialisation: {COUNT} sparse points from the scene (points3D.ply)" in caplog.text
    gaussians = trainer.gaussians
    assert len(gaussians) == COUNT and not gaussians.from_touch.any()
    np.testing.assert_allclose(gaussians.means.detach().numpy(), points, atol=1e-6)
    expected = rgb_to_sh0(torch.as_tensor(colors / 255.0, dtype=torch.float32)[:, None])
    torch.testing.assert_close(gaussians.params["sh0"].detach(), expected)


def test_too_few_sparse_points_triangulate_as_before(tmp_path, monkeypatch, caplog):
    path, _, _ = _scene_with_points(tmp_path / "scene")
    triangulation = _Triangulation(120)
    monkeypatch.setattr(trainer_module, "sfm_points", triangulation)
    trainer = Trainer(Scene.load(path), tmp_path / "run", _config(min_sfm_points=COUNT + 1))
    with caplog.at_level("INFO", logger="tacsplat.reconstruction.trainer"):
        trainer.initialize()
    assert triangulation.calls == 1
    assert f"the scene's {COUNT} sparse points (points3D.ply) are fewer than {COUNT + 1}: triangulating" in caplog.text
    assert f"initialisation: 120 SfM points (< {COUNT + 1}): 300 random points" in caplog.text


@pytest.mark.parametrize(
    "count, use_sfm, calls, line",
    [
        (0, True, 1, "initialisation: 120 SfM points"),
        (COUNT, False, 0, "initialisation: 0 SfM points (< 100): 300 random points"),
    ],
)
def test_a_scene_without_sparse_points_or_without_sfm_initialises_as_before(
    tmp_path, monkeypatch, caplog, count, use_sfm, calls, line
):
    path, _, _ = _scene_with_points(tmp_path / "scene", count)
    triangulation = _Triangulation(120)
    monkeypatch.setattr(trainer_module, "sfm_points", triangulation)
    trainer = Trainer(Scene.load(path), tmp_path / "run", _config(use_sfm=use_sfm))
    with caplog.at_level("INFO", logger="tacsplat.reconstruction.trainer"):
        trainer.initialize()
    assert triangulation.calls == calls
    assert line in caplog.text and "sparse points" not in caplog.text


@pytest.mark.parametrize("train_views, calls", [(2, 1), (3, 0)])
def test_sparse_points_are_used_only_when_training_uses_every_train_view(
    tmp_path, monkeypatch, caplog, train_views, calls
):
    # (the scene's points come from every image, held-out ones included: a few-view run triangulates its own)
    path, _, _ = _scene_with_points(tmp_path / "scene")
    triangulation = _Triangulation(120)
    monkeypatch.setattr(trainer_module, "sfm_points", triangulation)
    config = _config()
    config.train_views = train_views
    trainer = Trainer(Scene.load(path), tmp_path / "run", config)
    with caplog.at_level("INFO", logger="tacsplat.reconstruction.trainer"):
        trainer.initialize()
    assert triangulation.calls == calls
    subset = (
        "the scene's sparse points (points3D.ply) come from all its images: training on 2 of its 3 train views "
        "(--train-views), triangulating from those"
    )
    assert (subset in caplog.text) == (calls == 1)
    assert ("initialisation: 120 SfM points" in caplog.text) == (calls == 1)
    assert (f"initialisation: {COUNT} sparse points from the scene" in caplog.text) == (calls == 0)
