"""The trainer is device-agnostic: every tensor a step reads lives on the config's device, created once.

On this CPU-only machine the CUDA run's code path is exercised with the torch reference backend
(standing in for gsplat) and ``device="cpu"``; a tensor created inside a step without the config's
device (which on CUDA would be a host tensor, copied every step) fails the factory check below.
"""

import sys
from pathlib import Path

import pytest
import torch
from torch.overrides import TorchFunctionMode

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders

from recon_synthetic import build_sphere_scene  # noqa: E402

from tacsplat.datasets import Scene  # noqa: E402
from tacsplat.errors import ConfigError  # noqa: E402
from tacsplat.reconstruction.config import TrainConfig  # noqa: E402
from tacsplat.reconstruction.densification import DensifyStrategy  # noqa: E402
from tacsplat.reconstruction.initialization import InitConfig  # noqa: E402
from tacsplat.reconstruction.trainer import Trainer  # noqa: E402

FACTORIES = {
    torch.zeros,
    torch.ones,
    torch.empty,
    torch.full,
    torch.arange,
    torch.tensor,
    torch.as_tensor,
    torch.randn,
    torch.rand,
    torch.randint,
    torch.randperm,
    torch.eye,
    torch.linspace,
}


class HostTensorsCreated(TorchFunctionMode):
    """Records factory calls that create a tensor without saying where (host memory by default)."""

    def __init__(self):
        super().__init__()
        self.calls = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in FACTORIES and kwargs.get("device") is None:
            self.calls.append(func.__name__)
        if func is torch.from_numpy:
            self.calls.append("from_numpy")
        return func(*args, **kwargs)


def _config(**overrides) -> TrainConfig:
    settings = dict(
        iterations=8,
        eval_every_iters=100,
        eval_every_seconds=1e9,
        checkpoint_every=100,
        backend="torch",
        device="cpu",
        touch_rebuild_every=3,
        touch_points_per_step=16,
        init=InitConfig(use_sfm=False, num_random_points=200),
        densify=DensifyStrategy(start_iter=2, refine_every=3, reset_every=100, stop_iter=100),
    )
    return TrainConfig(**{**settings, **overrides})


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    return Scene.load(build_sphere_scene(tmp_path_factory.mktemp("scene") / "sphere", size=24))


def _tensors_of(trainer: Trainer) -> dict[str, torch.Tensor]:
    found = {
        "viewmats": trainer.viewmats,
        "Ks": trainer.Ks,
        "window Ks": trainer.window_Ks,
        "touch points": trainer.touch_tensor,
        "densify.grad2d": trainer.densify_state.grad2d,
        "densify.count": trainer.densify_state.count,
        "from_touch": trainer.gaussians.from_touch,
        "candidates": trainer.neighbours._candidates,
    }
    found.update({f"image {i}": t for i, t in enumerate(trainer.images)})
    found.update({f"background {i}": t for i, t in enumerate(trainer.backgrounds)})
    found.update({f"backdrop mask {i}": t for i, t in enumerate(trainer.backdrop_masks) if t is not None})
    found.update({f"edge weights {i}": t for i, t in trainer._edge_weights.items()})
    found.update({f"gaussians.{k}": v for k, v in trainer.gaussians.params.items()})
    for name, optimizer in trainer.optimizers.items():
        for state in optimizer.state.values():
            found.update({f"adam {name}.{k}": v for k, v in state.items() if torch.is_tensor(v) and v.dim()})
    return found


def test_a_training_step_creates_no_tensor_outside_the_config_device(sphere, tmp_path):
    trainer = Trainer(sphere, tmp_path / "run", _config())
    trainer.initialize()
    for _ in range(3):  # the first steps build caches (edge weights, neighbour candidates) once
        trainer.train_step()
    with HostTensorsCreated() as mode:
        for _ in range(4):  # a densification step (6) and a neighbour rebuild (6) are among them
            trainer.train_step()
    assert mode.calls == [], f"tensors created per step without the config's device: {sorted(set(mode.calls))}"
    wrong = {k: str(v.device) for k, v in _tensors_of(trainer).items() if v is not None and v.device != trainer.device}
    assert not wrong, f"not on {trainer.device}: {wrong}"


def test_the_whole_trainer_runs_device_agnostic_with_the_reference_backend(sphere, tmp_path):
    trainer = Trainer(sphere, tmp_path / "run", _config(eval_every_iters=4))
    gaussians = trainer.run(show_progress=False)
    assert trainer.step == 8 and len(gaussians) > 0 and gaussians.means.device == trainer.device
    assert (tmp_path / "run" / "splat.ply").is_file()


def test_cuda_asked_for_without_cuda_fails_at_once_with_one_clear_message(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ConfigError, match="device: cuda was asked for but torch .* sees no CUDA device"):
        TrainConfig(device="cuda").torch_device()
    assert TrainConfig(device="auto").torch_device() == torch.device("cpu")
    with pytest.raises(ConfigError, match="backend"):
        TrainConfig(device="cuda", backend="cpu").validate()


def test_reconstruct_device_cuda_fails_before_reading_or_writing(monkeypatch, tmp_path, capsys):
    from tacsplat.cli import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["reconstruct", str(tmp_path / "no-scene"), "--out", str(tmp_path / "run"), "--device", "cuda"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error: device: cuda was asked for" in err
    assert not (tmp_path / "run").exists()


def test_bench_gpu_without_cuda_skips_with_a_clear_message(monkeypatch, tmp_path, capsys):
    from tacsplat.cli import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["bench", "gpu", "--out", str(tmp_path / "gpu")]) == 0
    assert "bench gpu: skipped" in capsys.readouterr().out and not (tmp_path / "gpu").exists()
