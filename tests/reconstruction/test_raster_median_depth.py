"""Median depth ("MD"): the depth at which transmittance first falls below 0.5, on both CPU backends."""

import math

import pytest
import torch

from tacsplat.apps.bench_rasterizer import random_scene
from tacsplat.reconstruction.raster import rasterization


def _layers(opacities, depths, dtype=torch.float64):
    """Wide isotropic Gaussians on the optical axis, one per (opacity, depth): at the image centre each one's
    alpha is its opacity (times exp(-tiny))."""
    n = len(opacities)
    means = torch.tensor([[0.0, 0.0, z] for z in depths], dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=dtype)
    scales = torch.tensor([[0.5 * z] * 3 for z in depths], dtype=dtype)
    K = torch.tensor([[[20.0, 0.0, 8.5], [0.0, 20.0, 8.5], [0.0, 0.0, 1.0]]], dtype=dtype)  # pixel (8, 8) on the axis
    return dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=torch.tensor(opacities, dtype=dtype),
        colors=torch.ones(n, 3, dtype=dtype),
        viewmats=torch.eye(4, dtype=dtype)[None],
        Ks=K,
        width=16,
        height=16,
    )


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize(
    "opacities, depths, expected",
    [
        ([0.3, 0.9], [1.0, 2.0], 2.0),  # T: 1 -> 0.7 -> 0.07, crosses 0.5 at the second
        ([0.6, 0.9], [1.0, 2.0], 1.0),  # T: 1 -> 0.4 at the first
        ([0.4], [1.5], 0.0),  # T never falls below 0.5
        ([0.2, 0.2, 0.5], [1.0, 1.5, 3.0], 3.0),  # 0.8 -> 0.64 -> 0.32
    ],
)
def test_median_depth_is_the_depth_where_transmittance_crosses_one_half(backend, opacities, depths, expected):
    dtype = torch.float32 if backend == "cpu" else torch.float64
    colors, alphas, _ = rasterization(**_layers(opacities, depths, dtype), render_mode="MD", backend=backend)
    centre = colors[0, 7:10, 7:10, 0]  # the pixel on the optical axis and its neighbours
    torch.testing.assert_close(centre, torch.full_like(centre, expected), rtol=0, atol=1e-6)
    # alpha is the same as in the other modes
    _, alphas_rgb, _ = rasterization(**_layers(opacities, depths, dtype), render_mode="RGB", backend=backend)
    torch.testing.assert_close(alphas, alphas_rgb)
    transmittance = math.prod(1 - o for o in opacities)
    assert abs(float(alphas[0, 8, 8, 0]) - (1 - transmittance)) < 1e-3


def test_cpu_and_reference_median_depth_agree_on_a_random_scene():
    args = random_scene(3000, 64, 48, sh_degree=None, seed=3)
    ref, ref_alpha, _ = rasterization(
        **{k: v.double() if torch.is_tensor(v) else v for k, v in args.items()}, render_mode="RGB+MD", backend="torch"
    )
    cpu, cpu_alpha, _ = rasterization(**args, render_mode="RGB+MD", backend="cpu")
    # a pixel whose transmittance sits at 0.5 within float32 rounding may pick the neighbouring Gaussian
    near_half = ((ref_alpha - 0.5).abs() < 1e-4)[..., 0]
    mismatch = ((cpu[..., 3] - ref[..., 3].float()).abs() > 1e-4) & ~near_half
    assert not mismatch.any(), f"{int(mismatch.sum())} pixels differ"
    assert (ref[..., 3] > 0).float().mean() > 0.2  # the scene is not empty
    torch.testing.assert_close(cpu[..., :3], ref[..., :3].float(), rtol=1e-4, atol=1e-4)


def test_median_depth_has_no_gradient_but_rgb_does():
    scene = _layers([0.3, 0.9], [1.0, 2.0], torch.float32)
    scene["means"].requires_grad_(True)
    scene["colors"].requires_grad_(True)
    colors, _, _ = rasterization(**scene, render_mode="RGB+MD", backend="cpu")
    assert colors.requires_grad
    colors[..., :3].sum().backward()
    assert scene["colors"].grad.abs().sum() > 0


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_every_pass_hands_back_the_median_depth_that_md_renders(backend):
    """meta["median_depths"] of an RGB+ED pass is what "MD" renders, so an evaluation renders each view once."""
    args = random_scene(2000, 40, 32, sh_degree=None, seed=5)
    if backend == "torch":
        args = {k: v.double() if torch.is_tensor(v) else v for k, v in args.items()}
    md, _, _ = rasterization(**args, render_mode="MD", backend=backend)
    _, _, meta = rasterization(**args, render_mode="RGB+ED", backend=backend)
    assert (md > 0).float().mean() > 0.2  # the scene is not empty
    torch.testing.assert_close(meta["median_depths"], md, rtol=0, atol=0)
