"""`tacsplat view` at its edges: a run with no Gaussians and no scene still gets a finite viewpoint, a scene
recorded relative to where a benchmark ran is found from any folder (or named with every place tried), and a
foreign splat's absurd Gaussians (log-scales of +-80, centres at 1e30 m, saturated opacities and colours) reach the
browser finite, with one warning per file."""

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
from tacsplat.apps.viewer_splat import MAX_CENTRE_EXTENTS, UNIT_RANGE, splat_buffers
from tacsplat.cli import main
from tacsplat.datasets import Scene
from tacsplat.reconstruction.ply import save_ply

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from viewer_client import exported_scene  # noqa: E402
from viewer_test_splats import splat  # noqa: E402

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


def _exported_splat_words(page: Path) -> np.ndarray:
    """The 32-byte words of every Gaussian of the exported page's splat nodes [N, 32] (uint8)."""
    from viser import _messages as m

    splats = [n for n in exported_scene(page.read_text()).values() if n.message is m.GaussianSplatsMessage]
    assert all(np.isfinite(n.props["scale"]) and n.props["scale"] > 0 for n in splats)
    return np.concatenate([n.buffers["buffer"].view(np.uint8).reshape(-1, 32) for n in splats])


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
    words = _exported_splat_words(page)
    assert len(words) == 40
    centers, covariances = words[:, :12].copy().view(np.float32), words[:, 16:28].copy().view(np.float16)
    assert np.isfinite(centers).all() and np.isfinite(covariances).all()


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


@pytest.mark.parametrize("far", [3e38, 1e30])
def test_a_foreign_splat_of_far_centres_is_exported_finite_with_one_warning(tmp_path, capsys, far):
    """Centres at 3e38 m overflow float32 in the splat's unit, and at 1e30 m they would leave viser nothing to sort
    the object by: left out, and named with the clamped ones in the file's one warning."""
    pytest.importorskip("viser", reason="tacsplat view needs viser")
    log_scales = np.full((40, 3), math.log(3e-3))
    log_scales[2] = 80.0
    gaussians = splat(log_scales)
    gaussians.params["means"].data[[1, 4]] = torch.tensor([far, -far, far])  # a camera and a touch Gaussian
    save_ply(gaussians, tmp_path / "run" / "splat.ply")
    page = tmp_path / "view.html"
    assert main(["view", str(tmp_path / "run"), "--export", str(page)]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("WARNING")]
    assert len(warnings) == 1, warnings
    assert f"{tmp_path / 'run' / 'splat.ply'}: 1 of 40 Gaussians are too large" in warnings[0], warnings
    assert f"2 of 40 Gaussians lie too far from the rest to draw (over {MAX_CENTRE_EXTENTS:.0f} times" in warnings[0]
    words = _exported_splat_words(page)
    assert len(words) == 38
    centers = words[:, :12].copy().view(np.float32)
    assert np.isfinite(centers).all() and np.abs(centers).max() < 1e5


def test_a_run_with_far_centres_is_framed_by_the_rest(tmp_path):
    """A tenth of the Gaussians at 3e38 m (past the sphere's 95th percentile) neither size the object's sphere nor
    push the first viewpoint past float32, as the browser holds it."""
    gaussians = splat(np.full((40, 3), math.log(3e-3)))
    gaussians.params["means"].data[:4] = 3e38
    run = viewer.RunData(tmp_path, "far", gaussians, {}, None)
    centre, radius = viewer.object_sphere(run)
    assert np.abs(centre).max() < 0.1 and 0 < radius < 0.5
    position, look_at = viewer.initial_viewpoint(centre, radius)
    assert np.isfinite(position.astype(np.float32)).all() and np.isfinite(look_at.astype(np.float32)).all()


@pytest.fixture
def server():
    viser = pytest.importorskip("viser", reason="tacsplat view needs viser")
    with viewer._viser_quiet():
        srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    with viewer._viser_quiet():
        srv.stop()


def test_a_files_warning_is_given_once_however_often_it_is_shown(tmp_path, server, caplog):
    """A report's two foreign splats, each with a huge Gaussian: shown side by side, then one in both slots, then
    back again, each file is warned about once."""
    log_scales = np.full((20, 3), math.log(3e-3))
    log_scales[0] = 80.0
    runs = tmp_path / "report" / "runs" / "teapot" / "minimal"
    for method in ("3dgs", "paper"):
        save_ply(splat(log_scales), runs / f"{method}-s0" / "splat.ply")
    with caplog.at_level(logging.WARNING, logger="tacsplat.apps.viewer_splat"):
        view = viewer.build_view(server, viewer.load_content(tmp_path / "report"))
        view.controls["left run"].value = "teapot/minimal/paper-s0"
        view.controls["left run"].value = "teapot/minimal/3dgs-s0"
    named = sorted(record.getMessage().split(": ")[0] for record in caplog.records)
    assert named == [str(runs / f"{method}-s0" / "splat.ply") for method in ("3dgs", "paper")], named
