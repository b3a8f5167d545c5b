"""Degenerate inputs of ``rasterization()``: every backend gives finite renders and zero (finite) gradients where
nothing is drawn, agrees with the others on what is drawn, or raises one InvalidInputError naming the argument."""

from __future__ import annotations

import pytest
import torch

from tacsplat.errors import InvalidInputError
from tacsplat.reconstruction.raster import rasterization

BACKENDS = ("torch", "cpu")
WIDTH, HEIGHT = 20, 14


def _gaussians(n: int = 6, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 2.0]),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.rand(n, 3, generator=g) * 0.1 + 0.02,
        "opacities": torch.rand(n, generator=g) * 0.5 + 0.4,
        "colors": torch.rand(n, 1, 3, generator=g),  # SH degree 0
    }


def _render(params: dict, backend: str, render_mode: str = "RGB+D", rasterize_mode: str = "classic"):
    K = torch.tensor([[[18.0, 0.0, WIDTH / 2], [0.0, 18.0, HEIGHT / 2], [0.0, 0.0, 1.0]]])
    return rasterization(
        params["means"],
        params["quats"],
        params["scales"],
        params["opacities"],
        params["colors"],
        torch.eye(4)[None],
        K,
        WIDTH,
        HEIGHT,
        sh_degree=0,
        render_mode=render_mode,
        backend=backend,
        rasterize_mode=rasterize_mode,
    )


def _forward_backward(params: dict, backend: str, rasterize_mode: str = "classic"):
    """(colours, alphas, gradients by name) of a loss that touches every output pixel and channel."""
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    colors, alphas, _ = _render(leaves, backend, rasterize_mode=rasterize_mode)
    (colors.square().sum() + alphas.sum()).backward()
    return colors.detach(), alphas.detach(), {k: v.grad for k, v in leaves.items()}


def _culled(case: str) -> dict:
    params = _gaussians()
    if case == "opacity 0":
        params["opacities"] = torch.zeros_like(params["opacities"])
    elif case == "all behind the camera":
        params["means"] = params["means"] * torch.tensor([1.0, 1.0, -1.0])
    elif case == "all at the camera centre":
        params["means"] = torch.zeros_like(params["means"])
    elif case == "N = 0":
        params = {k: v[:0] for k, v in params.items()}
    return params


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", ["opacity 0", "all behind the camera", "all at the camera centre", "N = 0"])
def test_nothing_drawn_gives_an_empty_image_and_zero_gradients(backend, case):
    colors, alphas, grads = _forward_backward(_culled(case), backend)
    assert colors.shape == (1, HEIGHT, WIDTH, 4) and alphas.shape == (1, HEIGHT, WIDTH, 1)
    assert (colors == 0).all() and (alphas == 0).all()
    for name, grad in grads.items():
        assert grad is not None, f"{name} got no gradient"
        assert torch.isfinite(grad).all() and (grad == 0).all(), name


DEGENERATE = {
    # scales enter through the covariance R diag(s^2) R^T: a sign is irrelevant, zero is a point (made visible
    # by the 0.3 px dilation), and a zero quaternion is the identity rotation
    "zero scales": lambda p: p.update(scales=torch.zeros_like(p["scales"])),
    "negative scales": lambda p: p.update(scales=-p["scales"]),
    "one flat axis": lambda p: p["scales"][:, 2].zero_(),
    "zero quaternions": lambda p: p.update(quats=torch.zeros_like(p["quats"])),
    "tiny quaternions": lambda p: p.update(quats=p["quats"] * 1e-30),
    "huge quaternions": lambda p: p.update(quats=p["quats"] * 1e30),
    "negative opacities": lambda p: p.update(opacities=-p["opacities"]),
    "opacities above one": lambda p: p.update(opacities=p["opacities"] * 1e6),
}


@pytest.mark.parametrize("mode", ["classic", "antialiased"])  # antialiased: sqrt(det ratio), 0 for a point or line
@pytest.mark.parametrize("case", list(DEGENERATE))
def test_degenerate_gaussians_render_finitely_and_the_backends_agree(case, mode):
    params = _gaussians()
    DEGENERATE[case](params)
    results = {backend: _forward_backward(params, backend, mode) for backend in BACKENDS}
    for backend, (colors, alphas, grads) in results.items():
        assert torch.isfinite(colors).all() and torch.isfinite(alphas).all(), backend
        assert all(torch.isfinite(g).all() for g in grads.values()), backend
    (c_ref, a_ref, _), (c_cpu, a_cpu, _) = results["torch"], results["cpu"]
    torch.testing.assert_close(c_cpu, c_ref, atol=2e-4, rtol=1e-3)
    torch.testing.assert_close(a_cpu, a_ref, atol=2e-4, rtol=1e-3)


def test_the_documented_meaning_of_degenerate_scales_and_quaternions():
    params = _gaussians()
    reference, _, _ = _render(params, "torch")
    for change in ("negative scales", "zero quaternions"):
        changed = dict(params)
        DEGENERATE[change](changed)
        if change == "zero quaternions":  # identity rotation: the same as quaternion (1, 0, 0, 0)
            identity = dict(params, quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(6, 4))
            torch.testing.assert_close(_render(changed, "torch")[0], _render(identity, "torch")[0])
        else:
            torch.testing.assert_close(_render(changed, "torch")[0], reference)


@pytest.mark.parametrize("backend", BACKENDS)
def test_degenerate_image_and_camera_arguments_are_one_clear_error(backend):
    p = _gaussians()
    args = (p["means"], p["quats"], p["scales"], p["opacities"], p["colors"])
    K = torch.tensor([[[18.0, 0.0, 10.0], [0.0, 18.0, 7.0], [0.0, 0.0, 1.0]]])
    for width, height in ((0, 14), (20, 0), (-3, 14), (20.5, 14)):
        with pytest.raises(InvalidInputError, match="width and height must be positive ints"):
            rasterization(*args, torch.eye(4)[None], K, width, height, sh_degree=0, backend=backend)
    with pytest.raises(InvalidInputError, match="viewmats must hold at least one camera"):
        rasterization(*args, torch.zeros(0, 4, 4), torch.zeros(0, 3, 3), 20, 14, sh_degree=0, backend=backend)
    flat_K = K.clone()
    flat_K[0, 0, 0] = 0.0
    with pytest.raises(InvalidInputError, match="positive focal lengths"):
        rasterization(*args, torch.eye(4)[None], flat_K, 20, 14, sh_degree=0, backend=backend)
