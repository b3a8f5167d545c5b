"""metrics.json's ``mechanisms`` and ``method`` say what the run used: a mechanism that starts at a step the run
never reached (smoothness_start_iter, depth_normal_start_iter, lit_start_iter at or past its iterations) is off, and
a --resume that raises --iterations past its start records it on."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import pytest

from tacsplat.cli import main
from tacsplat.reconstruction.methods import START_STEPS, mechanisms, method_config, method_of

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import build_sphere_scene  # noqa: E402

FAST = ["--sh-degree", "0", "--backend", "cpu", "--init.no-use-sfm", "--quiet"]


def test_a_mechanism_starting_at_or_past_the_last_step_is_off_and_the_method_follows():
    """A run's (``touched`` given) are those it reached; a config's as set up (no ``touched``) are all it switches
    on, whatever its iterations: what --resume, which may raise them, and a batch's changed settings compare."""
    paper = dataclasses.replace(method_config("paper"), iterations=30, smoothness_start_iter=20000)  # the schedule's
    assert mechanisms(paper, touched=True)["smoothness"] is False and method_of(paper, touched=True) == "3dgs+t"
    assert mechanisms(paper)["smoothness"] is True and method_of(paper) == "paper"
    short = dataclasses.replace(method_config("default"), iterations=20)  # depth-normal from 700, lit from 300
    on = mechanisms(short, touched=True)
    assert (on["depth_normal"], on["sh_lit"]) == (False, False) and method_of(short, touched=True) == "custom"
    assert all(mechanisms(short).values()) and method_of(short) == "default"
    for name, start in START_STEPS.items():  # the start step itself is the last one trained: on; one later: off
        config = method_config("default")
        assert mechanisms(dataclasses.replace(config, **{start: config.iterations - 1}), touched=True)[name], name
        assert not mechanisms(dataclasses.replace(config, **{start: config.iterations}), touched=True)[name], name


@pytest.mark.timeout(300)
def test_metrics_record_the_mechanisms_the_run_reached_and_a_resume_past_their_start_updates_them(tmp_path, capsys):
    scene = build_sphere_scene(tmp_path / "scene", size=24, train_views=3, test_views=1)
    run = tmp_path / "run"
    starts = ["--lit-start-iter", "2", "--depth-normal-start-iter", "4", "--smoothness-start-iter", "6"]
    assert main(["reconstruct", str(scene), "--out", str(run), "--iterations", "4", *starts, *FAST]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    off = {"smoothness": False, "depth_normal": False}  # from steps 6 and 4 of steps 0-3: never reached
    assert metrics["mechanisms"] == {**dict.fromkeys(metrics["mechanisms"], True), **off}
    assert metrics["method"] == "custom" and json.loads(capsys.readouterr().out)["method"] == "custom"
    # the run's own method asked for again resumes (it is the method it was set up as), and records all of them
    resume = ["reconstruct", str(scene), "--out", str(run), "--resume", "--method", "default", "--iterations", "8"]
    assert main([*resume, "--quiet"]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["iterations"] == 8 and all(metrics["mechanisms"].values()) and metrics["method"] == "default"


@pytest.mark.timeout(300)
def test_a_run_stopped_before_its_planned_steps_records_what_it_reached_and_leaves_the_callers_rng(tmp_path):
    import torch

    from tacsplat.reconstruction import TrainConfig, reconstruct
    from tacsplat.reconstruction.evaluation import evaluate_run

    scene = build_sphere_scene(tmp_path / "scene", size=24, train_views=3, test_views=1)
    config = TrainConfig(iterations=4, lit_start_iter=2, depth_normal_start_iter=4, smoothness_start_iter=3)
    config = dataclasses.replace(config, sh_degree=0, backend="cpu")
    config.init.use_sfm = False
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    reconstruct(scene, tmp_path / "run", config, show_progress=False)
    assert torch.equal(torch.rand(3), expected)  # the script's own stream goes on as if no run had been made
    checkpoint = tmp_path / "run" / "checkpoint.pt"
    state = torch.load(checkpoint, weights_only=False)
    state["config"]["iterations"] = 10  # planned 10, stopped at step 4 (as Ctrl-C leaves a run)
    torch.save(state, checkpoint)
    on = evaluate_run(tmp_path / "run")["mechanisms"]
    assert (on["sh_lit"], on["smoothness"], on["depth_normal"]) == (True, True, False)
