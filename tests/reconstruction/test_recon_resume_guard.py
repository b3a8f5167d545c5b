"""`tacsplat reconstruct --resume` continues a run only as what it is: on the scene it was trained on (moved or
not), with its own settings, and not without a loss it trained with that has since been removed; --iterations may
raise its step count, and then every record says the new one."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import sys
from pathlib import Path

import pytest
import torch

from tacsplat.cli import main
from tacsplat.reconstruction.config import PAPER_SCHEDULE
from tacsplat.reconstruction.run_dir import load_run
from tacsplat.reconstruction.trainer import Trainer

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import build_sphere_scene, one_error_line  # noqa: E402

FAST = ["--sh-degree", "0", "--lambda-s", "0", "--backend", "cpu", "--init.no-use-sfm", "--quiet"]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """Two scenes of the sphere seen from other cameras, with other touches (A and B)."""
    root = tmp_path_factory.mktemp("scenes")
    return tuple(
        build_sphere_scene(root / name, size=24, train_views=3, test_views=1, seed=seed)
        for name, seed in (("a", 0), ("b", 1))
    )


@pytest.fixture(scope="module")
def trained(scenes, tmp_path_factory):
    """A 3-step run of scene A (a copy: tests move it), copied by each test that changes it."""
    root = tmp_path_factory.mktemp("trained")
    scene = Path(shutil.copytree(scenes[0], root / "scene"))
    assert main(["reconstruct", str(scene), "--out", str(root / "run"), "--iterations", "3", *FAST]) == 0
    return root


def _copy(trained: Path, tmp_path: Path) -> tuple[Path, Path]:
    """(scene, run) copies of :func:`trained`'s: the scene as if moved since the run was trained on it."""
    return (
        Path(shutil.copytree(trained / "scene", tmp_path / "scene")),
        Path(shutil.copytree(trained / "run", tmp_path / "run")),
    )


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _resume(scene: Path, run: Path, *extra: str) -> int:
    return main(["reconstruct", str(scene), "--out", str(run), *FAST, "--resume", *extra])


# --- the scene ---------------------------------------------------------------------------------------------------


def test_resume_on_another_scene_is_refused_naming_both(scenes, trained, tmp_path, capsys):
    _, run = _copy(trained, tmp_path)
    before = _files(run)
    capsys.readouterr()
    assert _resume(scenes[1], run, "--iterations", "6") == 1
    one_error_line(capsys, "--resume", str((trained / "scene").resolve()), str(scenes[1].resolve()))
    assert _files(run) == before


def _trained_then_scene_replaced(scenes, tmp_path) -> tuple[Path, Path]:
    """(scene, run): a run trained on a copy of ``scenes[0]``, whose folder then holds ``scenes[1]`` instead."""
    scene, run = Path(shutil.copytree(scenes[0], tmp_path / "scene")), tmp_path / "run"
    assert main(["reconstruct", str(scene), "--out", str(run), "--iterations", "2", *FAST]) == 0
    shutil.rmtree(scene)
    shutil.copytree(scenes[1], scene)  # the same folder now holds another capture
    return scene, run


def test_a_scene_changed_in_place_is_refused(scenes, tmp_path, capsys):
    scene, run = _trained_then_scene_replaced(scenes, tmp_path)
    before = _files(run)
    capsys.readouterr()
    assert _resume(scene, run, "--iterations", "4") == 1
    one_error_line(capsys, "--resume", str(scene.resolve()), "has changed")
    assert _files(run) == before


def test_a_moved_scene_resumes_and_the_run_records_where_it_is_now(trained, tmp_path):
    moved, run = _copy(trained, tmp_path)
    assert _resume(moved, run, "--iterations", "4") == 0
    assert json.loads((run / "config.json").read_text())["scene"]["path"] == str(moved.resolve())
    assert torch.load(run / "checkpoint.pt", weights_only=False)["scene_path"] == str(moved)


# --- the settings ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "options, words",
    [
        (["--lambda-t", "3"], ["--lambda-t", "0.5 in the run", "3.0 given"]),
        (["--seed", "7"], ["--seed", "0 in the run", "7 given"]),
        (["--lambda-backdrop", "1"], ["--lambda-backdrop", "0.1 in the run", "1.0 given"]),
        (["--densify.max-gaussians", "10"], ["--densify.max-gaussians", "30000 in the run", "10 given"]),
        (
            ["--method", "paper"],
            [
                "--method custom in the run, 3dgs+t given",  # (paper --no-smoothness)
                "--appearance 'sh-lit' in the run, 'sh' given",
            ],
        ),
        (["--config", str(PAPER_SCHEDULE)], ["--touch-top-k 8 in the run, 20 given"]),
    ],
)
def test_resume_refuses_a_setting_that_differs_from_the_runs(trained, tmp_path, capsys, options, words):
    scene, run = _copy(trained, tmp_path)
    before = _files(run)
    capsys.readouterr()
    assert _resume(scene, run, *options) == 2  # a usage error, as --iterations below the step reached is
    one_error_line(capsys, "--resume", str(run), *words, prefix="tacsplat reconstruct: error: --resume: ")
    assert _files(run) == before


def test_resume_below_the_step_reached_is_refused(trained, tmp_path, capsys):
    scene, run = _copy(trained, tmp_path)
    before = _files(run)
    capsys.readouterr()
    assert _resume(scene, run, "--iterations", "2") == 2  # a usage error
    one_error_line(capsys, "--iterations", "step 3", "3 or more", "got 2", prefix="tacsplat reconstruct: error: ")
    assert _files(run) == before


def test_resume_with_more_iterations_continues_and_every_record_says_so(trained, tmp_path):
    scene, run = _copy(trained, tmp_path)
    same = ["--lambda-t", "0.5", "--seed", "0", "--method", "default"]  # the run's own: accepted
    assert _resume(scene, run, "--iterations", "5", *same) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    checkpoint = torch.load(run / "checkpoint.pt", weights_only=False)
    assert json.loads((run / "config.json").read_text())["iterations"] == 5
    assert metrics["iterations"] == metrics["settings"]["iterations"] == 5
    assert checkpoint["step"] == checkpoint["config"]["iterations"] == 5
    with (run / "progress.csv").open() as fh:
        assert [int(r["iteration"]) for r in csv.DictReader(fh)][-1] == 5


def _schedule_spy(monkeypatch, stop_in: int) -> list[tuple[int, int, float]]:
    """(step, training image downscale, the position's learning rate) of each step trained from now on; SIGINT (as
    from Ctrl-C) during step ``stop_in``."""
    seen, real_step = [], Trainer.train_step

    def step(self):
        if self.step == stop_in:
            os.kill(os.getpid(), signal.SIGINT)
        terms = real_step(self)
        seen.append((self.step - 1, self.factor, self.optimizers["means"].param_groups[0]["lr"]))
        return terms

    monkeypatch.setattr(Trainer, "train_step", step)
    return seen


def test_resume_with_more_iterations_never_goes_back_to_coarser_images_or_a_higher_rate(scenes, tmp_path, monkeypatch):
    """Coarse to fine and the position rate's decay are fractions of the steps: a resume that raises --iterations
    goes on with them from where the run stopped to their end at the new count."""
    scene, run = scenes[0], tmp_path / "run"
    seen = _schedule_spy(monkeypatch, stop_in=4)
    coarse = ["--coarse-factors", "4", "2", "--coarse-until", "0.5"]
    assert main(["reconstruct", str(scene), "--out", str(run), "--iterations", "8", *coarse, *FAST]) == 130
    assert [factor for _, factor, _ in seen] == [4, 4, 2, 2, 1]  # stopped at full size, after step 4
    assert _resume(scene, run, "--iterations", "16") == 0
    steps, factors, rates = zip(*seen)
    assert steps == tuple(range(16)) and set(factors[5:]) == {1}
    assert all(later < earlier for earlier, later in zip(rates, rates[1:]))  # lower at every step, the resume's too
    planned = 5 + (15 - 5) * (8 - 5) / (16 - 5)  # step 15 in the 8 steps planned: from 5 at step 5 to 8 at step 16
    assert rates[-1] / rates[0] == pytest.approx(0.01 ** (planned / 8))  # (lr_means_final_factor 0.01)


# --- a loss since removed ----------------------------------------------------------------------------------------


def _with_tactile_normals(trained: Path, tmp_path: Path, weight: float) -> tuple[Path, Path]:
    """(scene, run) copies of :func:`trained`'s, its config.json and checkpoint recording ``lambda_touch_normal``
    ``weight`` as a run from before the tactile-normal loss was removed does (the default's was 0.1)."""
    scene, run = _copy(trained, tmp_path)
    config = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**config, "lambda_touch_normal": weight}, indent=2))
    checkpoint = torch.load(run / "checkpoint.pt", weights_only=False)
    checkpoint["config"]["lambda_touch_normal"] = weight
    torch.save(checkpoint, run / "checkpoint.pt")
    return scene, run


def test_a_run_of_the_removed_tactile_normal_loss_loads_and_evaluates_as_it_did(trained, tmp_path):
    """The loss shaped the Gaussians, not how they render: the run reads as today's config and evaluates to the
    numbers it had."""
    _, run = _with_tactile_normals(trained, tmp_path, 0.1)
    before, loaded = json.loads((run / "metrics.json").read_text()), load_run(run)
    assert loaded.config == load_run(trained / "run").config and loaded.step == 3
    assert main(["evaluate", str(run)]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    for key in ("cd", "psnr", "num_gaussians"):
        assert metrics[key] == pytest.approx(before[key], rel=1e-6), key


def test_resume_of_a_run_that_trained_with_the_tactile_normal_loss_is_refused_naming_it(trained, tmp_path, capsys):
    scene, run = _with_tactile_normals(trained, tmp_path, 0.1)
    before = _files(run)
    capsys.readouterr()
    assert _resume(scene, run, "--iterations", "6") == 1
    one_error_line(
        capsys,
        f"{run / 'config.json'}: lambda_touch_normal: this run trained with the tactile-normal loss, removed (no "
        "gain on held-out meshes: docs/experiments.md); reconstruct the scene again",
    )
    assert _files(run) == before


def test_a_run_with_the_tactile_normal_loss_off_resumes(trained, tmp_path):
    scene, run = _with_tactile_normals(trained, tmp_path, 0.0)
    assert _resume(scene, run, "--iterations", "5") == 0
    assert load_run(run).step == 5 and "lambda_touch_normal" not in json.loads((run / "config.json").read_text())


def test_an_explicit_method_other_than_the_runs_is_refused(scenes, tmp_path, capsys):
    """--method default on a run of another method sets nothing the run lacks (default's overrides are empty), yet
    asks for another method: refused as any other setting, while the run's own method resumes."""
    scene, run = Path(shutil.copytree(scenes[0], tmp_path / "scene")), tmp_path / "run"
    assert main(["reconstruct", str(scene), "--out", str(run), "--iterations", "2", "--method", "3dgs+t", *FAST]) == 0
    before = _files(run)
    capsys.readouterr()
    assert _resume(scene, run, "--method", "default", "--iterations", "3") == 2
    one_error_line(
        capsys, "--method 3dgs+t in the run, default given", prefix="tacsplat reconstruct: error: --resume: "
    )
    assert _files(run) == before
    assert _resume(scene, run, "--method", "3dgs+t", "--iterations", "3") == 0


# --- evaluate and export mesh: the run's own scene, from any folder ----------------------------------------------


def test_a_run_of_a_relative_scene_path_evaluates_from_any_folder(scenes, tmp_path, monkeypatch):
    """The checkpoint records the scene's resolved path (a run from before that, its path as typed, takes
    config.json's), so evaluate and export mesh find it from another folder, and never take another scene of
    the same relative name there."""
    monkeypatch.chdir(tmp_path)
    shutil.copytree(scenes[0], tmp_path / "scene")
    assert main(["reconstruct", "scene", "--out", "run", "--iterations", "2", *FAST]) == 0
    run, scene = tmp_path / "run", (tmp_path / "scene").resolve()
    assert torch.load(run / "checkpoint.pt", weights_only=False)["scene_path"] == str(scene)
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(scenes[1], elsewhere / "scene")  # another scene under the same relative name
    monkeypatch.chdir(elsewhere)
    assert main(["evaluate", str(run)]) == 0
    assert json.loads((run / "metrics.json").read_text())["scene"] == str(scene)
    checkpoint = torch.load(run / "checkpoint.pt", weights_only=False)
    torch.save({**checkpoint, "scene_path": "scene"}, run / "checkpoint.pt")  # as a run from before recorded it
    assert load_run(run).scene_path == scene
    assert main(["export", "mesh", str(run), "--views", "8"]) == 0


def test_evaluate_and_export_refuse_the_runs_scene_changed_since(scenes, tmp_path, capsys):
    scene, run = _trained_then_scene_replaced(scenes, tmp_path)
    before = _files(run)
    capsys.readouterr()
    assert main(["evaluate", str(run)]) == 1
    one_error_line(capsys, str(scene.resolve()), "has changed")
    assert main(["export", "mesh", str(run)]) == 1
    one_error_line(capsys, str(scene.resolve()), "has changed")
    assert _files(run) == before
