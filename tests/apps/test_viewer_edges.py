"""`tacsplat view` at its edges: a run with no Gaussians and no scene still gets a finite viewpoint, a scene
recorded relative to where a benchmark ran is found from any folder (or named with every place tried), and a
foreign splat's absurd Gaussians (log-scales of +-80, saturated opacities and colours) reach the browser finite."""

from __future__ import annotations

import json
import logging
import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from tacsplat.apps import viewer
from tacsplat.apps.viewer_splat import UNIT_RANGE, splat_buffers
from tacsplat.cli import main
from tacsplat.datasets import Scene
from tacsplat.reconstruction.gaussians import Gaussians
from tacsplat.reconstruction.ply import save_ply

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from viewer_client import exported_scene  # noqa: E402

RECORDED = "pb1/scenes/teapot/minimal-s0"  # as `bench paper --out pb1` records it, relative to where it ran


def test_a_run_without_gaussians_or_scene_is_looked_at_from_a_finite_viewpoint(tmp_path):
    run = viewer.RunData(tmp_path, "empty", types.SimpleNamespace(means=torch.zeros(0, 3)), {}, None)
    centre, radius = viewer.object_sphere(run)
    assert np.array_equal(centre, np.zeros(3)) and radius == 1.0
    position, look_at = viewer.initial_viewpoint(centre, radius)
    assert np.isfinite(position).all() and np.isfinite(look_at).all()


def bench_run(tmp_path: Path) -> Path:
    """``BENCH/pb1/runs/teapot/minimal/3dgs-s0`` and the scene it recorded, ``BENCH/pb1/scenes/...``."""
    (tmp_path / "bench" / RECORDED).mkdir(parents=True)
    (tmp_path / "bench" / RECORDED / "transforms.json").touch()
    run = tmp_path / "bench" / "pb1" / "runs" / "teapot" / "minimal" / "3dgs-s0"
    run.mkdir(parents=True)
    return run


def test_a_scene_recorded_relative_to_the_benchmarks_folder_is_found_from_anywhere(tmp_path, monkeypatch):
    """metrics.json holds the scene's path as the bench was given it (relative); config.json's absolute one is
    what the viewer follows."""
    run = bench_run(tmp_path)
    (run / "splat.ply").touch()
    (run / "metrics.json").write_text(json.dumps({"scene": RECORDED}))
    scene = tmp_path / "bench" / RECORDED
    (run / "config.json").write_text(json.dumps({"scene": {"path": str(scene), "sha256": "0"}}))
    monkeypatch.setattr(Scene, "load", staticmethod(lambda path: path))  # (the folder stands in for its scene)
    monkeypatch.setattr("tacsplat.reconstruction.ply.load_ply", lambda path: None)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert viewer.read_run(run, "run").scene == scene


def test_a_scene_found_nowhere_is_named_with_every_place_tried(tmp_path, monkeypatch, caplog):
    run = bench_run(tmp_path)
    monkeypatch.chdir(tmp_path)
    with caplog.at_level(logging.WARNING, logger=viewer.log.name):
        assert viewer.find_scene("gone/scenes/x", run) is None
    message = caplog.records[-1].getMessage()
    assert str(tmp_path / "gone/scenes/x") in message and str(run / "gone/scenes/x") in message, message
    assert "showing the splat alone" in message, message


def splat(log_scales: np.ndarray, seed: int = 0) -> Gaussians:
    """Gaussians around a 10 cm object with the given log-scales [N, 3]; every 4th one is a touch Gaussian."""
    rng = np.random.default_rng(seed)
    n = len(log_scales)
    return Gaussians(
        {
            "means": torch.tensor(rng.normal(0, 0.05, (n, 3)), dtype=torch.float32),
            "quats": torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
            "scales": torch.tensor(log_scales, dtype=torch.float32),
            "opacities": torch.tensor(rng.choice([-1e4, 0.0, 1e4], n), dtype=torch.float32),
            "sh0": torch.tensor(rng.choice([-1e4, 0.0, 1e4], (n, 1, 3)), dtype=torch.float32),
            "shN": torch.zeros(n, 0, 3),
        },
        torch.arange(n) % 4 == 0,
        0,
    )


def test_a_foreign_splat_of_huge_and_tiny_gaussians_is_exported_finite_with_one_warning(tmp_path, capsys):
    """Log-scales of +80 (a covariance of 1e69 m^2) are drawn clamped and named in one warning; -80 ones are
    dots. What viser sends, float32 centres and float16 covariances, is finite throughout."""
    pytest.importorskip("viser", reason="tacsplat view needs viser")
    log_scales = np.full((40, 3), math.log(3e-3))
    log_scales[[1, 2, 5], 0] = 80.0  # camera Gaussians, huge along one axis
    log_scales[4] = 80.0  # a touch Gaussian, huge along each
    log_scales[[6, 7, 8]] = -80.0  # (8 is a touch Gaussian)
    save_ply(splat(log_scales), tmp_path / "run" / "splat.ply")
    page = tmp_path / "view.html"
    assert main(["view", str(tmp_path / "run"), "--export", str(page)]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("WARNING")]
    assert len(warnings) == 1 and f"{tmp_path / 'run' / 'splat.ply'}: 4 of 40 Gaussians" in warnings[0], warnings
    from viser import _messages as m

    splats = [n for n in exported_scene(page.read_text()).values() if n.message is m.GaussianSplatsMessage]
    words = np.concatenate([n.buffers["buffer"].view(np.uint8).reshape(-1, 32) for n in splats])
    assert len(words) == 40
    centers, covariances = words[:, :12].copy().view(np.float32), words[:, 16:28].copy().view(np.float16)
    assert np.isfinite(centers).all() and np.isfinite(covariances).all()
    assert all(np.isfinite(n.props["scale"]) and n.props["scale"] > 0 for n in splats)


@pytest.mark.parametrize("log_scale", [-80.0, 80.0])
def test_a_splat_of_degenerate_gaussians_is_drawn_in_a_unit_of_the_objects_size(log_scale):
    """Every Gaussian 1e-35 m (or 5e34 m): the unit follows the object (centres within ~1e4 units), not them."""
    gaussians = splat(np.full((30, 3), log_scale))
    b = splat_buffers(gaussians)
    means = gaussians.means.detach().double()
    extent = float((means - means.median(dim=0).values).norm(dim=1).median())
    assert 0.999 * UNIT_RANGE[0] * extent <= b.unit <= 1.001 * UNIT_RANGE[1] * extent  # (exp(log(x)) rounds)
    assert np.abs(b.centers).max() < 1e5
    for buffer in (b.centers, b.covariances.astype(np.float16), b.rgbs, b.opacities):
        assert np.isfinite(buffer).all()
    assert b.clamped == (30 if log_scale > 0 else 0)
    assert ((0 <= b.rgbs) & (b.rgbs <= 1)).all() and ((0 <= b.opacities) & (b.opacities <= 1)).all()
