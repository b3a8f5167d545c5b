"""Where a run trains and renders: ``--device auto`` with the cpu backend trains on the CPU even where torch sees
CUDA; a run trained with gsplat on CUDA evaluates on a machine without CUDA (with the CPU rasterizer, said in one
line) unless ``--backend gsplat`` is asked for; ``--resume --device KIND`` of a run that recorded ``auto`` goes on
where KIND is the device its checkpoint trained on."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest
import torch

from tacsplat.cli import main
from tacsplat.reconstruction.config import TrainConfig

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import build_sphere_scene, one_error_line  # noqa: E402

FAST = ["--sh-degree", "0", "--lambda-s", "0", "--backend", "cpu", "--init.no-use-sfm", "--quiet"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A 2-step run with --device auto (the default) on the CPU, copied by each test that changes it."""
    root = tmp_path_factory.mktemp("trained")
    scene = build_sphere_scene(root / "scene", size=24, train_views=3, test_views=1)
    assert main(["reconstruct", str(scene), "--out", str(root / "run"), "--iterations", "2", *FAST]) == 0
    return root


def _as_if_on_cuda(run: Path, backend: str | None) -> None:
    """Make ``run`` look trained on CUDA: its checkpoint's device and, with ``backend``, that backend and --device
    cuda in its records (config.json and the checkpoint's config)."""
    config = json.loads((run / "config.json").read_text())
    checkpoint = torch.load(run / "checkpoint.pt", weights_only=False)
    checkpoint["device"] = "cuda"
    if backend is not None:
        for record in (config, checkpoint["config"]):
            record["backend"], record["device"] = backend, "cuda"
    (run / "config.json").write_text(json.dumps(config, indent=2))
    torch.save(checkpoint, run / "checkpoint.pt")


def test_auto_is_the_cpu_for_the_cpu_backend_where_torch_sees_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert TrainConfig(backend="cpu").torch_device() == torch.device("cpu")  # (its rasterizer runs on the CPU)
    assert TrainConfig(backend="auto").torch_device() == torch.device("cuda")
    assert TrainConfig(backend="torch").torch_device() == torch.device("cuda")
    assert TrainConfig(backend="cpu", device="cpu").torch_device() == torch.device("cpu")


def test_a_gsplat_run_from_cuda_evaluates_here_with_the_cpu_rasterizer(trained, tmp_path, capsys):
    run = Path(shutil.copytree(trained / "run", tmp_path / "run"))
    _as_if_on_cuda(run, "gsplat")
    (run / "metrics.json").unlink()
    capsys.readouterr()
    assert main(["evaluate", str(run)]) == 0
    err = capsys.readouterr().err
    assert err.count("trained with gsplat on CUDA; rendering with the CPU rasterizer here") == 1, err
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["psnr"] > 0 and metrics["settings"]["backend"] == "gsplat"  # (the settings it trained with)


def test_a_gsplat_run_from_cuda_exports_its_mesh_here_with_the_cpu_rasterizer(trained, tmp_path, capsys):
    run = Path(shutil.copytree(trained / "run", tmp_path / "run"))
    _as_if_on_cuda(run, "gsplat")
    capsys.readouterr()
    assert main(["export", "mesh", str(run), "--out", str(tmp_path / "mesh.ply")]) == 0
    assert "trained with gsplat on CUDA; rendering with the CPU rasterizer here" in capsys.readouterr().err
    assert (tmp_path / "mesh.ply").is_file()


def test_an_explicit_gsplat_backend_without_cuda_stays_an_error(trained, tmp_path, capsys):
    run = Path(shutil.copytree(trained / "run", tmp_path / "run"))
    _as_if_on_cuda(run, "gsplat")
    capsys.readouterr()
    assert main(["evaluate", str(run), "--backend", "gsplat"]) == 1
    assert "backend='gsplat' needs CUDA and the gsplat package" in capsys.readouterr().err


def test_resume_names_the_device_the_run_trained_on(trained, tmp_path, capsys):
    scene, run = trained / "scene", Path(shutil.copytree(trained / "run", tmp_path / "run"))
    assert json.loads((run / "config.json").read_text())["device"] == "auto"
    args = ["reconstruct", str(scene), "--out", str(run), *FAST, "--resume", "--iterations", "3"]
    assert main([*args, "--device", "cpu"]) == 0  # the device its checkpoint trained on
    assert json.loads((run / "metrics.json").read_text())["iterations"] == 3


def test_resume_naming_another_device_than_the_checkpoints_is_refused(trained, tmp_path, capsys):
    scene, run = trained / "scene", Path(shutil.copytree(trained / "run", tmp_path / "run"))
    _as_if_on_cuda(run, None)  # (config.json still says auto)
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    capsys.readouterr()
    args = ["reconstruct", str(scene), "--out", str(run), *FAST, "--resume", "--iterations", "3"]
    assert main([*args, "--device", "cpu"]) == 2  # (a usage error: the existing refusal)
    one_error_line(capsys, "--resume", "other settings", "--device 'auto' in the run, 'cpu' given", prefix="")
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
