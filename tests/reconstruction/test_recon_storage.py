"""`tacsplat reconstruct` and `evaluate` on a disk that fills up or is read-only (a real size-limited tmpfs): one
error line naming the file, exit 1, no temporary file left, nothing written before lost, and once there is space
again `--resume` completes the run as if nothing had happened."""

from __future__ import annotations

import csv
import errno
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import tacsplat.files
from tacsplat.cli import main
from tacsplat.reconstruction.ply import save_ply
from tacsplat.reconstruction.run_dir import load_run
from tacsplat.reconstruction.trainer import Trainer

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import build_sphere_scene  # noqa: E402

# 4 steps, a checkpoint and a progress row every 2 (none by run time): each write point is reached once or twice
RUN = [
    "--iterations",
    "4",
    "--checkpoint-every",
    "2",
    "--eval-every-iters",
    "2",
    "--eval-every-seconds",
    "1e9",
    "--sh-degree",
    "0",
    "--lambda-s",
    "0",
    "--backend",
    "cpu",
    "--init.no-use-sfm",
    "--quiet",
]
DISK_FULL = "the disk is full"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return build_sphere_scene(tmp_path_factory.mktemp("scenes") / "sphere", size=24, train_views=3, test_views=1)


@pytest.fixture(scope="module")
def straight(scene, tmp_path_factory):
    """The same run on a disk with room: what every interrupted one must end up writing."""
    run = tmp_path_factory.mktemp("straight") / "run"
    assert main(["reconstruct", str(scene), "--out", str(run), *RUN]) == 0
    return run


def _one_error_line(err: str, *words: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _leftover_temporaries(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*.tmp*"))


def _iterations(run: Path) -> list[int]:
    with (run / "progress.csv").open() as fh:
        return [int(r["iteration"]) for r in csv.DictReader(fh)]


def _fill(mount: Path, leave: int = 0) -> Path:
    """Take every free byte of the file system at ``mount`` but ``leave`` (a filler file); returns the filler."""
    filler = mount / "filler"
    with open(filler, "wb", buffering=0) as f:
        for chunk in (1 << 20, 1 << 12, 1):
            try:
                while True:
                    f.write(b"\0" * chunk)
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc
    os.truncate(filler, max(filler.stat().st_size - leave, 0))
    return filler


def _run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tacsplat", *args], capture_output=True, text=True, timeout=600)


def test_a_disk_that_fills_up_at_a_checkpoint_keeps_the_last_one_and_resume_completes(scene, straight, tmpfs):
    """The issue's case, as a user meets it: the disk fills while the second checkpoint is written."""
    mount = tmpfs("16m")
    run = mount.path / "run"
    checkpoint = (straight / "checkpoint.pt").stat().st_size
    _fill(mount.path, leave=3 * checkpoint // 2)  # the first checkpoint fits, the second beside it does not
    done = _run_cli("reconstruct", str(scene), "--out", str(run), *RUN)
    assert done.returncode == 1, done.stderr
    _one_error_line(done.stderr, str(run / "checkpoint.pt"), DISK_FULL)
    assert _leftover_temporaries(run) == []
    assert torch.load(run / "checkpoint.pt", weights_only=False)["step"] == 2  # the one before stays
    mount.resize("64m")  # space freed
    done = _run_cli("reconstruct", str(scene), "--out", str(run), *RUN, "--resume")
    assert done.returncode == 0, done.stderr
    assert (run / "splat.ply").read_bytes() == (straight / "splat.ply").read_bytes()
    assert _iterations(run) == _iterations(straight) == [0, 2, 4]
    assert (run / "metrics.json").is_file() and _leftover_temporaries(run) == []


def _fill_when_opened(monkeypatch, mount: Path, name: str, nth: int, run: Path) -> dict:
    """Fill the disk the ``nth`` time a temporary file of ``name`` (a file name, or ``renders`` for any render) is
    opened for writing by tacsplat.files: only the moment is chosen here, the failure that follows is the kernel's
    own. Returns {"before": the run's files then, "filler": the file that fills the disk}."""
    real_open, seen, state = open, [], {}

    def opening(path, *args, **kwargs):
        path = Path(path)
        if name in (path.name.removesuffix(".tmp"), path.parent.name):
            seen.append(path)
            if len(seen) == nth:
                state["before"] = {k: v for k, v in _files(run).items() if not k.endswith(".tmp")}
                state["filler"] = _fill(mount)
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(tacsplat.files, "open", opening, raising=False)  # (atomic_file opens the temporary file)
    return state


# every file the run writes, and the time it is written at which it fails (the second checkpoint, progress.csv's
# row of step 4, ...); config.json and the first progress row come before any checkpoint
WRITE_POINTS = [
    ("config.json", 1),
    ("progress.csv", 1),
    ("checkpoint.pt", 1),
    ("checkpoint.pt", 2),
    ("progress.csv", 3),
    ("splat.touch.npy", 1),
    ("splat.ply", 1),
    ("error_vs_time.png", 1),
    ("renders", 1),
    ("light.png", 1),
    ("metrics.json", 1),
]


@pytest.mark.parametrize("name, nth", WRITE_POINTS)
def test_a_full_disk_at_any_write_is_one_error_and_the_run_completes_after(
    scene, straight, tmpfs, monkeypatch, capsys, name, nth
):
    mount = tmpfs("16m")
    run = mount.path / "run"
    state = _fill_when_opened(monkeypatch, mount.path, name, nth, run)
    capsys.readouterr()
    assert main(["reconstruct", str(scene), "--out", str(run), *RUN]) == 1
    line = _one_error_line(capsys.readouterr().err, DISK_FULL)
    assert str(run / name) in line, line
    assert _leftover_temporaries(run) == []
    after = _files(run)
    assert {k: v for k, v in state["before"].items() if after.get(k) != v} == {}  # nothing written before is lost
    monkeypatch.undo()
    state["filler"].unlink()
    resumable = (run / "checkpoint.pt").is_file()
    assert main(["reconstruct", str(scene), "--out", str(run), *RUN, "--resume" if resumable else "--overwrite"]) == 0
    assert (run / "splat.ply").read_bytes() == (straight / "splat.ply").read_bytes()
    assert _iterations(run) == _iterations(straight)
    assert set(_files(run)) == set(_files(straight)) and _leftover_temporaries(run) == []


@pytest.mark.parametrize("name", ["splat.ply", "metrics.json"])
def test_evaluate_on_a_full_disk_keeps_the_files_it_would_replace(straight, tmpfs, monkeypatch, capsys, name):
    mount = tmpfs("16m")
    run = Path(shutil.copytree(straight, mount.path / "run"))
    if name == "splat.ply":  # (evaluate replaces only a lit run's splat.ply from before the bake: its unlit colours)
        save_ply(load_run(run).gaussians, run / "splat.ply")
    before = _files(run)
    state = _fill_when_opened(monkeypatch, mount.path, name, 1, run)
    assert main(["evaluate", str(run), "--quiet"]) == 1
    _one_error_line(capsys.readouterr().err, str(run / name), DISK_FULL)
    assert _files(run) == before and _leftover_temporaries(run) == []
    state["filler"].unlink()


def test_a_read_only_out_is_one_error_before_any_training(scene, straight, tmpfs, monkeypatch, capsys):
    mount = tmpfs("16m")
    run = Path(shutil.copytree(straight, mount.path / "run"))
    (mount.path / "empty").mkdir()
    mount.read_only()

    def no_training(*args, **kwargs):
        raise AssertionError("training started on a read-only --out")

    monkeypatch.setattr(Trainer, "__init__", no_training)
    for out, extra in ((run, ["--resume"]), (mount.path / "empty", [])):
        assert main(["reconstruct", str(scene), "--out", str(out), *RUN, *extra]) == 1, out
        _one_error_line(capsys.readouterr().err, str(out), "the file system is read-only")
    assert main(["reconstruct", str(scene), "--out", str(mount.path / "new"), *RUN]) == 1
    _one_error_line(capsys.readouterr().err, str(mount.path / "new"), "the file system is read-only")
    assert main(["evaluate", str(run)]) == 1
    _one_error_line(capsys.readouterr().err, str(run), "the file system is read-only")


def test_a_full_temporary_folder_for_sfm_is_one_error_naming_it(scene, tmpfs, monkeypatch, tmp_path, capsys):
    import tempfile

    mount = tmpfs("1m")
    _fill(mount.path)
    monkeypatch.setattr(tempfile, "tempdir", str(mount.path))  # (what TMPDIR sets)
    with_sfm = [option for option in RUN if option != "--init.no-use-sfm"]
    assert main(["reconstruct", str(scene), "--out", str(tmp_path / "run"), *with_sfm]) == 1
    _one_error_line(capsys.readouterr().err, str(mount.path), DISK_FULL, "TMPDIR")
