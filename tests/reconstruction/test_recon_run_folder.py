"""`tacsplat reconstruct` / `evaluate` are safe by construction: a run folder is never overwritten by accident
nor written by two processes, an interrupted run checkpoints and resumes exactly, a scene `inspect` refuses is
refused by every command, and a user mistake is one line on stderr."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import sys
import threading
from pathlib import Path

import pytest
import torch

from tacsplat.cli import main
from tacsplat.datasets.outputs import LOCK_NAME
from tacsplat.reconstruction.run_dir import load_run
from tacsplat.reconstruction.trainer import Trainer

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import build_sphere_scene, one_error_line, pause_training  # noqa: E402

FAST = ["--sh-degree", "0", "--lambda-s", "0", "--backend", "cpu", "--quiet"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return build_sphere_scene(tmp_path_factory.mktemp("scenes") / "sphere", size=24, train_views=3, test_views=1)


def _reconstruct(scene, out, *extra, iterations: int = 3) -> int:
    return main(["reconstruct", str(scene), "--out", str(out), "--iterations", str(iterations), *FAST, *extra])


def _listing(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# --- 1. an earlier run, a run in progress and unrelated files are never overwritten -----------------------------


def test_an_earlier_run_is_kept_unless_overwrite_and_unrelated_files_survive(scene, tmp_path, capsys):
    run = tmp_path / "run"
    assert _reconstruct(scene, run) == 0
    (run / "notes.txt").write_text("my notes")
    before = _listing(run)
    capsys.readouterr()
    assert _reconstruct(scene, run, "--seed", "1") == 1
    one_error_line(capsys, "--out", "already holds a reconstruction run", "--resume", "--overwrite")
    assert _listing(run) == before
    assert _reconstruct(scene, run, "--seed", "1", "--overwrite") == 0
    assert json.loads((run / "config.json").read_text())["seed"] == 1
    assert (run / "notes.txt").read_text() == "my notes"
    assert (run / "checkpoint.pt").read_bytes() != before["checkpoint.pt"]


def test_a_folder_of_unrelated_files_is_refused_and_left_as_it_was(scene, tmp_path, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "img.png").write_bytes(b"\x89PNG not really")
    (photos / "renders").mkdir()
    for extra in ([], ["--overwrite"], ["--resume"]):
        assert _reconstruct(scene, photos, *extra) == 1, extra
        one_error_line(capsys, "--out", str(photos), "img.png")
        assert sorted(p.name for p in photos.iterdir()) == ["img.png", "renders"]  # not even a lock file


def test_two_jobs_never_write_one_run_folder_at_once(scene, tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    in_training, finish = pause_training(monkeypatch)
    first = {}
    job = threading.Thread(target=lambda: first.update(code=_reconstruct(scene, run)))
    job.start()
    try:
        assert in_training.wait(120)
        capsys.readouterr()
        for extra in ([], ["--overwrite"], ["--resume"]):
            assert _reconstruct(scene, run, "--seed", "7", *extra) == 1, extra
            one_error_line(capsys, "--out", "another tacsplat process")
        assert main(["evaluate", str(run)]) == 1
        one_error_line(capsys, "another tacsplat process")
    finally:
        finish.set()
        job.join(120)
    assert first["code"] == 0
    assert json.loads((run / "config.json").read_text())["seed"] == 0
    assert json.loads((run / "metrics.json").read_text())["iterations"] == 3


# --- 3. interruption, checkpoint, exact resume ------------------------------------------------------------------


def _raise_on_sigterm(signum, frame):
    raise RuntimeError("SIGTERM reached the test: the trainer did not handle it")


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_checkpoints_the_step_reached_and_resume_matches_a_straight_run(
    scene, tmp_path, capsys, monkeypatch, signum, code
):
    straight, run = tmp_path / "straight", tmp_path / "run"
    assert _reconstruct(scene, straight, iterations=10) == 0
    real_step = Trainer.train_step

    def signalled_in_step_6(self):
        if self.step == 5:
            os.kill(os.getpid(), signum)  # as from Ctrl-C or `kill`, in the middle of a step
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", signalled_in_step_6)
    monkeypatch.setattr(signal, "SIGTERM", signal.SIGTERM)
    previous = signal.signal(signal.SIGTERM, _raise_on_sigterm)  # what a test process must survive
    try:
        capsys.readouterr()
        assert _reconstruct(scene, run, iterations=10) == code
    finally:
        signal.signal(signal.SIGTERM, previous)
    err = capsys.readouterr().err
    assert f"tacsplat reconstruct {scene} --out {run} --resume" in err, err
    assert "Traceback" not in err
    assert load_run(run).step == 6  # the step in progress finished, then the checkpoint
    assert not (run / "metrics.json").exists()
    monkeypatch.setattr(Trainer, "train_step", real_step)
    assert main(["reconstruct", str(scene), "--out", str(run), "--resume", "--quiet"]) == 0
    resumed, expected = load_run(run), load_run(straight)
    assert resumed.step == 10
    for name in ("means", "scales", "opacities", "sh0"):
        torch.testing.assert_close(resumed.gaussians.params[name], expected.gaussians.params[name], rtol=0, atol=1e-6)
    with (run / "progress.csv").open() as fh:
        assert [int(r["iteration"]) for r in csv.DictReader(fh)] == [0, 10]


def test_a_run_resumed_with_more_iterations_and_stopped_again_resumes_as_if_not_stopped(scene, tmp_path, monkeypatch):
    """A resume that raised --iterations plans the rest of coarse to fine and of the rate's decay anew (from the
    step it resumed at): the checkpoint keeps that plan, so a second stop and resume changes nothing."""
    first, straight, run = tmp_path / "first", tmp_path / "straight", tmp_path / "run"
    real_step = Trainer.train_step

    def stopped_in(step: int):
        def signalled(self):
            if self.step == step:
                os.kill(os.getpid(), signal.SIGINT)  # as from Ctrl-C
            return real_step(self)

        monkeypatch.setattr(Trainer, "train_step", signalled)

    stopped_in(2)
    assert _reconstruct(scene, first, "--coarse-factors", "2", "--coarse-until", "0.5", iterations=8) == 130
    shutil.copytree(first, straight)
    shutil.copytree(first, run)
    stopped_in(7)
    assert main(["reconstruct", str(scene), "--out", str(run), "--resume", "--iterations", "12", "--quiet"]) == 130
    monkeypatch.setattr(Trainer, "train_step", real_step)
    assert main(["reconstruct", str(scene), "--out", str(run), "--resume", "--quiet"]) == 0
    assert main(["reconstruct", str(scene), "--out", str(straight), "--resume", "--iterations", "12", "--quiet"]) == 0
    resumed, expected = load_run(run), load_run(straight)
    assert resumed.step == expected.step == 12
    for name in ("means", "scales", "opacities", "sh0"):
        torch.testing.assert_close(resumed.gaussians.params[name], expected.gaussians.params[name], rtol=0, atol=1e-6)


def test_sigterm_during_the_evaluation_after_training_exits_143_and_resume_evaluates(
    scene, tmp_path, capsys, monkeypatch
):
    """Training has its own handler (stop after the step); the evaluation after it is covered too: a SIGTERM there
    (kill, a scheduler's time limit) exits 143 with the command that continues, which evaluates the trained run."""
    from tacsplat.reconstruction import trainer

    run, real_evaluate = tmp_path / "run", trainer.evaluate_reconstruction

    def signalled(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return real_evaluate(*args, **kwargs)

    monkeypatch.setattr(trainer, "evaluate_reconstruction", signalled)
    previous = signal.signal(signal.SIGTERM, _raise_on_sigterm)  # what a test process must survive
    try:
        assert _reconstruct(scene, run, iterations=4) == 143
    finally:
        signal.signal(signal.SIGTERM, previous)
    err = capsys.readouterr().err
    assert f"interrupted (SIGTERM); continue with:\n  tacsplat reconstruct {scene} --out {run} --resume" in err, err
    assert not (run / "metrics.json").exists()
    monkeypatch.setattr(trainer, "evaluate_reconstruction", real_evaluate)
    assert main(["reconstruct", str(scene), "--out", str(run), "--resume", "--quiet"]) == 0
    assert load_run(run).step == 4 and (run / "metrics.json").is_file()


def _power_cut_then_resume(
    scene, run: Path, iterations: int, checkpoint_every: int, cut_at: int, monkeypatch, between=lambda: None
) -> list[int]:
    """Train ``iterations`` steps (a progress row every 2), killed without a signal (no last checkpoint) when
    step ``cut_at`` starts; call ``between()``, resume; the iterations of progress.csv's rows."""
    from tacsplat.datasets import Scene
    from tacsplat.reconstruction.config import TrainConfig

    config = TrainConfig(
        iterations=iterations,
        sh_degree=0,
        backend="cpu",
        lambda_s=0.0,
        eval_every_iters=2,
        eval_every_seconds=1e9,
        checkpoint_every=checkpoint_every,
    )
    real_step = Trainer.train_step

    def power_cut(self):
        if self.step == cut_at:
            raise SystemError("power cut")
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", power_cut)
    with pytest.raises(SystemError):
        Trainer(Scene.load(scene), run, config).run(show_progress=False)
    monkeypatch.setattr(Trainer, "train_step", real_step)
    between()
    Trainer(Scene.load(scene), run, config).run(resume=True, show_progress=False)
    with (run / "progress.csv").open() as fh:
        return [int(r["iteration"]) for r in csv.DictReader(fh)]


def test_resume_after_a_crash_drops_the_progress_rows_after_the_checkpoint(scene, tmp_path, monkeypatch):
    # cut in step 8: the last checkpoint is step 4's; the rows after it are dropped and written again
    assert _power_cut_then_resume(scene, tmp_path / "run", 10, 4, 7, monkeypatch) == [0, 2, 4, 6, 8, 10]


def test_a_checkpoint_from_before_a_loss_term_existed_resumes(scene, tmp_path, monkeypatch):
    """A checkpoint whose running sums lack a loss term added since (albedo_smoothness) resumes to the end."""
    path = tmp_path / "run" / "checkpoint.pt"

    def as_written_before_the_term():
        checkpoint = torch.load(path, weights_only=False)
        del checkpoint["progress"]["sums"]["albedo_smoothness"]
        torch.save(checkpoint, path)

    assert _power_cut_then_resume(scene, tmp_path / "run", 6, 3, 4, monkeypatch, as_written_before_the_term) == [
        0,
        2,
        4,
        6,
    ]


def test_resume_keeps_an_older_progress_files_values_under_their_own_columns(tmp_path):
    """A progress.csv written before some columns existed (normals, cd_paper, albedo_smoothness: a run from before
    the normals) is cut at the checkpoint and rewritten with today's columns: each value stays under its own
    name, the newer columns empty."""
    from tacsplat.reconstruction.run_dir import PROGRESS_COLUMNS, cut_progress, read_progress

    newer = ("normals", "cd_paper", "albedo_smoothness")
    old_columns = [c for c in PROGRESS_COLUMNS if c not in newer]
    path = tmp_path / "progress.csv"
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(old_columns)
        for step in (0, 2, 4, 6):
            writer.writerow([step] + [f"{step}.{i}" for i in range(1, len(old_columns))])
    cut_progress(path, 4)
    with path.open(newline="") as fh:
        assert next(csv.reader(fh)) == list(PROGRESS_COLUMNS)
    progress = read_progress(path)
    assert list(progress["iteration"]) == [0, 2, 4]
    for i, column in enumerate(old_columns[1:], start=1):
        assert list(progress[column]) == [float(f"{step}.{i}") for step in (0, 2, 4)], column
    assert all(v != v for column in newer for v in progress[column])  # NaN: never written


def test_evaluate_and_export_of_a_run_stopped_before_its_first_checkpoint_say_to_run_it_again(scene, tmp_path, capsys):
    """A run that failed (diverged) or was killed before its first checkpoint holds its config.json only: evaluate,
    export mesh and reconstruct without --overwrite, or with --resume, say there is nothing to resume (a --resume
    keeps the settings it failed with) and print the --overwrite command, which trains it again with the options
    given; a folder whose config.json is not a run's is not a run."""
    import shlex

    run = tmp_path / "run"
    assert _reconstruct(scene, run, "--lr-scales", "1e30") == 1  # diverges at its first step
    one_error_line(capsys, "training diverged")
    assert sorted(p.name for p in run.iterdir() if p.name != LOCK_NAME) == ["config.json", "progress.csv"]
    again = shlex.join(["tacsplat", "reconstruct", str(Path(scene).resolve()), "--out", str(run), "--overwrite"])
    for command in (["evaluate", str(run)], ["export", "mesh", str(run)]):
        assert main(command) == 1
        line = one_error_line(capsys, str(run / "checkpoint.pt"), "before its first checkpoint", "nothing to resume")
        assert line.endswith(f": {again}") and "--resume" not in line, line
    before = _listing(run)
    assert _reconstruct(scene, run, "--resume") == 1  # not trained again from step 0 with the settings that failed
    assert one_error_line(capsys) == line and _listing(run) == before
    assert _reconstruct(scene, run) == 1
    line = one_error_line(capsys, "--out", "no checkpoint to resume", "--overwrite")
    assert "--resume" not in line, line
    assert main([*shlex.split(again)[1:], "--iterations", "3", *FAST]) == 0
    assert json.loads((run / "metrics.json").read_text())["iterations"] == 3
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.json").write_text('{"name": "my project"}')
    assert main(["evaluate", str(other)]) == 1
    one_error_line(capsys, "no checkpoint: not a reconstruction run directory")


def test_a_scene_without_test_views_is_said_to_have_none(tmp_path, capsys):
    """No test views: the warning says so (PSNR, SSIM and CD are not computed), not that ground truth is missing."""
    scene = build_sphere_scene(tmp_path / "scene", size=24, train_views=3, test_views=0)
    assert _reconstruct(scene, tmp_path / "run") == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("WARNING")]
    expected = f"the scene {scene} has no test views: PSNR, SSIM and CD are not computed (null)"
    assert warnings == [f"WARNING tacsplat.reconstruction.evaluation: {expected}"], warnings
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert (metrics["num_test_views"], metrics["psnr"], metrics["ssim"], metrics["cd"]) == (0, None, None, None)


def test_resume_of_no_run_or_of_a_run_without_checkpoint_is_refused(scene, tmp_path, capsys):
    assert _reconstruct(scene, tmp_path / "new", "--resume") == 1
    one_error_line(capsys, "--resume", "holds no run")
    assert not (tmp_path / "new").exists()
    run = tmp_path / "run"
    assert _reconstruct(scene, run, "--lambda-t", "0.25") == 0
    first = (run / "splat.ply").read_bytes()
    for name in ("checkpoint.pt", "splat.ply", "metrics.json"):  # a run killed (or out of disk) before its first
        (run / name).unlink()  # checkpoint: its config.json is all there is
    capsys.readouterr()
    before = _listing(run)
    assert _reconstruct(scene, run, "--resume") == 1  # nothing to resume: --overwrite trains it again
    one_error_line(capsys, str(run / "checkpoint.pt"), "before its first checkpoint", "--overwrite")
    assert _listing(run) == before
    assert _reconstruct(scene, run, "--lambda-t", "0.25", "--overwrite") == 0
    assert (run / "splat.ply").read_bytes() == first


# --- 2. one definition of a valid scene --------------------------------------------------------------------------


def test_every_command_refuses_the_scene_inspect_refuses(scene, tmp_path, capsys):
    copy = Path(shutil.copytree(scene, tmp_path / "scene"))
    assert _reconstruct(copy, tmp_path / "run") == 0
    (copy / "touches.json").unlink()
    capsys.readouterr()
    assert main(["inspect", str(copy), "--json"]) == 1
    problems = json.loads(capsys.readouterr().out)["problems"]
    assert problems == [
        f"{copy / 'journal.jsonl'}: records 4 frames and 4 touches but the index files hold 4 and 0: "
        "a writer stopped between the two; SceneWriter.resume (or resuming the capture) rewrites "
        "the index"
    ]
    assert _reconstruct(copy, tmp_path / "run2") == 1
    assert one_error_line(capsys) == f"error: {problems[0]}"
    assert not (tmp_path / "run2").exists()
    assert main(["evaluate", str(tmp_path / "run")]) == 1
    assert one_error_line(capsys) == f"error: {problems[0]}"


# --- 4. and 6. user mistakes: one line naming the option and what it allows --------------------------------------


def test_an_out_that_is_a_file_inside_a_file_or_unwritable_is_one_error(scene, tmp_path, capsys, monkeypatch):
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    assert _reconstruct(scene, a_file) == 1
    one_error_line(capsys, "--out", "is a file")
    assert _reconstruct(scene, a_file / "run") == 1
    one_error_line(capsys, "--out", "which is a file")
    assert a_file.read_text() == "mine"
    real_access = os.access
    monkeypatch.setattr(
        os, "access", lambda path, mode, **kw: False if "locked" in str(path) else real_access(path, mode)
    )
    assert _reconstruct(scene, tmp_path / "locked") == 1
    one_error_line(capsys, "--out", "is not writable")


@pytest.mark.parametrize(
    "options, words",
    [
        (["--iterations", "-5"], ["--iterations", ">= 1", "-5"]),
        (["--iterations", "0"], ["--iterations", ">= 1"]),
        (["--lambda-t", "-1"], ["--lambda-t", ">= 0"]),
        (["--lambda-s", "nan"], ["--lambda-s", "finite"]),
        (["--lambda-t", "inf"], ["--lambda-t", "finite"]),
        (["--train-views", "0"], ["--train-views", ">= 1"]),
        (["--seed", "-1"], ["--seed", "0 to"]),
        (["--densify.split-scale-divisor", "0"], ["--densify.split-scale-divisor", "> 0"]),
        (["--densify.prune-opacity", "0"], ["--densify.prune-opacity", "between 0 and 0.5"]),
        (["--densify.prune-opacity", "0.5"], ["--densify.prune-opacity", "between 0 and 0.5"]),
        (["--densify.refine-every", "0"], ["--densify.refine-every", ">= 1"]),  # (a modulus: step % 0)
        (["--densify.reset-every", "0"], ["--densify.reset-every", ">= 1"]),
        (["--init.initial-opacity", "0"], ["--init.initial-opacity", "between 0 and 1"]),
        (["--init.touch-initial-opacity", "1"], ["--init.touch-initial-opacity", "between 0 and 1"]),
        (["--init.hull-resolution", "0"], ["--init.hull-resolution", "1 to 256", "got 0"]),
        (["--init.hull-resolution", "1000"], ["--init.hull-resolution", "1 to 256", "about 2 GB", "got 1000"]),
        (["--init.sift-max-features", "0"], ["--init.sift-max-features", ">= 1"]),
        (["--init.min-triangulation-angle-deg", "0"], ["--init.min-triangulation-angle-deg", "> 0"]),
        (["--init.touch-voxel-size", "0"], ["--init.touch-voxel-size", "> 0"]),
        (["--backend", "gsplat", "--device", "cpu"], ["--backend", "CUDA"]),
        (["--resume", "--overwrite"], ["--overwrite", "--resume", "choose one"]),
        (["--downscale", "5"], ["--downscale", "4x4 px", "24x24", "at least 5"]),  # (the scene's 24 px)
        (["--coarse-factors", "8"], ["--coarse-factors", "3x3 px", "at least 5"]),
        (["--downscale", "2", "--coarse-factors", "4"], ["--coarse-factors", "3x3 px"]),
        (["--train-views", "4"], ["--train-views", "has 3 training views", "at most 3", "got 4"]),  # (the scene's 3)
    ],
)
def test_an_option_out_of_range_is_one_error_naming_it(scene, tmp_path, capsys, options, words):
    assert main(["reconstruct", str(scene), "--out", str(tmp_path / "run"), "--quiet", *options]) == 2  # usage error
    one_error_line(capsys, *words, prefix="tacsplat reconstruct: error: ")
    assert not (tmp_path / "run").exists()  # refused before anything is written


@pytest.mark.filterwarnings("ignore:.*does not match any type in Union")  # tyro's, on the value refused
@pytest.mark.filterwarnings("ignore:.*but the default value")  # (ditto)
@pytest.mark.parametrize(
    "text, words",
    [
        ("background: 0.5", ["background:", "3 numbers", "0.5"]),
        ("coarse_factors: 4", ["coarse_factors:", "integers", "4"]),
        ("densify: [1, 2]", ["densify:", "mapping", "densify.x"]),
        ("init: 5", ["init:", "mapping", "init.x"]),
        ("lambda_t: -1", ["lambda_t:", ">= 0", "-1"]),
        ("densify:\n  max_gaussians: -5", ["densify.max_gaussians:", ">= 0", "-5"]),
        ("seed: 1e-3", ["seed:", "integer", "'1e-3'"]),  # (not a whole number)
    ],
)
def test_a_config_file_value_of_the_wrong_kind_is_one_error_naming_the_file_and_key(
    scene, tmp_path, capsys, text, words
):
    """The file's error, as its unknown keys are (exit 1), not a usage error naming an option never typed."""
    settings = tmp_path / "settings.yaml"
    settings.write_text(text + "\n")
    assert _reconstruct(scene, tmp_path / "run", "--config", str(settings)) == 1
    line = one_error_line(capsys, *words, prefix=f"error: {settings}: ")
    assert " --" not in line, line
    assert not (tmp_path / "run").exists()


def test_gsplat_where_torch_sees_no_cuda_is_a_usage_error(scene, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["reconstruct", str(scene), "--out", str(tmp_path / "run"), "--quiet", "--backend", "gsplat"]) == 2
    one_error_line(capsys, "--backend", "gsplat", "CUDA", prefix="tacsplat reconstruct: error: ")
    assert not (tmp_path / "run").exists()


def test_evaluate_of_what_is_not_a_run_is_one_error(tmp_path, capsys):
    assert main(["evaluate", str(tmp_path / "nothing")]) == 1
    one_error_line(capsys, "nothing")
    assert not (tmp_path / "nothing").exists()
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(b"PK\x03\x04 cut short")
    assert main(["evaluate", str(run)]) == 1
    one_error_line(capsys, "checkpoint.pt", "corrupt")


def test_a_run_still_training_before_its_first_checkpoint_is_said_to_be_training_not_stopped(scene, tmp_path, capsys):
    """While its lock is held (its training), a run without a checkpoint is not one to --resume: view and evaluate
    say it is being trained (naming the PID) and to try again after its first checkpoint."""
    pytest.importorskip("viser")
    import subprocess

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"scene": {"path": str(Path(scene).resolve()), "sha256": "0"}}))
    hold = "import sys, time; from tacsplat.datasets.outputs import claim_output_dir as c; l = c(sys.argv[1]); "
    hold += "print('ready', flush=True); sys.stdin.read()"  # (a process that stands in for the training)
    training = subprocess.Popen([sys.executable, "-c", hold, str(run)], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert training.stdout.readline().strip() == b"ready"
        capsys.readouterr()
        for command in (["evaluate", str(run)], ["view", str(run), "--export", str(tmp_path / "view.html")]):
            assert main(command) == 1
            line = one_error_line(capsys, str(training.pid))
            assert "--resume" not in line, line
            if command[0] == "view":
                assert "still being trained" in line and "after its first checkpoint" in line, line
    finally:
        training.stdin.close()
        training.wait(timeout=30)
    assert main(["view", str(run), "--export", str(tmp_path / "view.html")]) == 1
    one_error_line(capsys, "before its first checkpoint", "--overwrite")
