"""`tacsplat view` at its edges: a run with no Gaussians and no scene still gets a finite viewpoint, and a scene
recorded relative to where a benchmark ran is found from any folder (or named with every place tried)."""

from __future__ import annotations

import json
import logging
import types
from pathlib import Path

import numpy as np
import torch

from tacsplat.apps import viewer
from tacsplat.datasets import Scene

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
