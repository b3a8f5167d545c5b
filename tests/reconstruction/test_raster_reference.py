"""The pure-PyTorch reference rasterizer: closed forms, dense-vs-tiled, gradcheck, validation."""

from __future__ import annotations

import math

import pytest
import torch

from tacsplat.apps.bench_rasterizer import random_scene
from tacsplat.errors import InvalidInputError
from tacsplat.reconstruction.raster import rasterization
from tacsplat.reconstruction.raster.reference import _composite_tile, project_gaussians
from tacsplat.reconstruction.raster.spherical_harmonics import sh_basis


def _single_gaussian(opacity: float, scale: float, z: float, dtype=torch.float64):
    means = torch.tensor([[0.0, 0.0, z]], dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype)
    scales = torch.full((1, 3), scale, dtype=dtype)
    opacities = torch.tensor([opacity], dtype=dtype)
    K = torch.tensor([[[50.0, 0, 20.0], [0, 50.0, 15.0], [0, 0, 1]]], dtype=dtype)
    return means, quats, scales, opacities, torch.eye(4, dtype=dtype)[None], K


@pytest.mark.parametrize("opacity", [0.5, 1.0])
def test_single_isotropic_gaussian_alpha_profile_is_analytic(opacity):
    means, quats, scales, opac, viewmats, K = _single_gaussian(opacity, 0.1, 2.0)
    colors = torch.tensor([[0.2, 0.5, 1.0]], dtype=torch.float64)
    img, alpha, meta = rasterization(means, quats, scales, opac, colors, viewmats, K, 40, 30, backend="torch")
    var = (50.0 * 0.1 / 2.0) ** 2 + 0.3  # EWA covariance plus the 0.3 px dilation
    ys, xs = torch.meshgrid(
        torch.arange(30.0, dtype=torch.float64) + 0.5, torch.arange(40.0, dtype=torch.float64) + 0.5, indexing="ij"
    )
    r2 = (xs - 20.0) ** 2 + (ys - 15.0) ** 2
    expected = torch.clamp(opacity * torch.exp(-0.5 * r2 / var), max=0.99)
    expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
    torch.testing.assert_close(alpha[0, :, :, 0], expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(img[0], expected[..., None] * colors[0], rtol=1e-12, atol=1e-12)
    r = math.ceil(min(3.33, math.sqrt(2 * math.log(255 * opacity))) * math.sqrt(var))
    assert meta["radii"][0, 0].tolist() == [r, r]
    torch.testing.assert_close(meta["means2d"][0, 0], torch.tensor([20.0, 15.0], dtype=torch.float64))


def test_depth_modes_and_background():
    means, quats, scales, opac, viewmats, K = _single_gaussian(0.8, 0.1, 2.0)
    colors = torch.tensor([[0.2, 0.5, 1.0]], dtype=torch.float64)
    bg = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64)
    args = (means, quats, scales, opac, colors, viewmats, K, 40, 30)
    rgb, alpha, _ = rasterization(*args, backgrounds=bg, backend="torch")
    torch.testing.assert_close(rgb[0], alpha[0] * colors[0] + (1 - alpha[0]) * bg[0])
    d, alpha_d, _ = rasterization(*args, render_mode="D", backgrounds=bg, backend="torch")
    torch.testing.assert_close(d, 2.0 * alpha_d)  # accumulated depth = z * alpha
    rgbed, _, _ = rasterization(*args, render_mode="RGB+ED", backgrounds=bg, backend="torch")
    assert rgbed.shape == (1, 30, 40, 4)
    torch.testing.assert_close(rgbed[..., :3], rgb)
    covered = alpha[..., 0] > 0
    torch.testing.assert_close(rgbed[..., 3][covered], torch.full_like(rgbed[..., 3][covered], 2.0))
    assert (rgbed[..., 3][~covered] == 0).all()


def test_tiled_reference_equals_dense_compositing():
    scene = random_scene(80, 37, 29, sh_degree=None, dtype=torch.float64, seed=3)
    img, alpha, meta = rasterization(**scene, backend="torch", tile_size=8)
    # Dense: every pixel against every visible Gaussian in depth order, no tiles at all.
    visible = (meta["radii"][0] > 0).all(-1)
    order = torch.argsort(torch.where(visible, meta["depths"][0], torch.inf), stable=True)[: int(visible.sum())]
    ys, xs = torch.meshgrid(torch.arange(29.0), torch.arange(37.0), indexing="ij")
    color, trans, _ = _composite_tile(
        xs.reshape(-1).double() + 0.5,
        ys.reshape(-1).double() + 0.5,
        meta["means2d"][0, order],
        meta["conics"][0, order],
        scene["colors"][order],
        meta["opacities"][0, order],
        meta["depths"][0, order],
    )
    torch.testing.assert_close(img[0].reshape(-1, 3), color, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(alpha[0].reshape(-1), 1 - trans, rtol=1e-12, atol=1e-12)
    img16, _, _ = rasterization(**scene, backend="torch", tile_size=16)
    torch.testing.assert_close(img16, img, rtol=1e-12, atol=1e-12)


def test_projection_matches_pinhole_and_culls():
    means = torch.tensor([[0.3, -0.2, 2.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.005], [0.0, 0.0, 50.0]])
    n = len(means)
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    scales = torch.full((n, 3), 0.05)
    K = torch.tensor([[[100.0, 0, 32.0], [0, 90.0, 24.0], [0, 0, 1]]])
    proj = project_gaussians(
        means, quats, scales, torch.full((n,), 0.9), torch.eye(4)[None], K, 64, 48, near_plane=0.01, far_plane=20.0
    )
    torch.testing.assert_close(proj.means2d[0, 0], torch.tensor([32 + 100 * 0.15, 24 - 90 * 0.1]))
    assert proj.radii[0, 0].min() > 0
    assert (proj.radii[0, 1:] == 0).all()  # behind, before the near plane, beyond the far plane


def test_sh_degree_zero_and_basis_orthonormal():
    # Monte-Carlo orthonormality of the degree-3 basis on the sphere.
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(200000, 3, generator=g, dtype=torch.float64), dim=-1)
    basis = sh_basis(3, dirs)
    gram = basis.T @ basis * (4 * math.pi / len(dirs))
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)
    # gsplat convention: colour = SH value + 0.5, so a DC coefficient of 0 renders grey 0.5.
    means, quats, scales, opac, viewmats, K = _single_gaussian(1.0, 0.1, 2.0)
    sh = torch.zeros(1, 1, 3, dtype=torch.float64)
    img, alpha, _ = rasterization(means, quats, scales, opac, sh, viewmats, K, 40, 30, sh_degree=0, backend="torch")
    torch.testing.assert_close(img[0], 0.5 * alpha[0].expand(-1, -1, 3))


def test_gradcheck_float64_tiny_scene():
    scene = random_scene(4, 10, 8, sh_degree=1, radius_px=(2.0, 5.0), dtype=torch.float64, seed=1)
    scene["opacities"] = torch.tensor([0.3, 0.5, 0.6, 0.4], dtype=torch.float64)
    names = ("means", "quats", "scales", "opacities", "colors")
    bg = torch.tensor([[0.2, 0.1, 0.4]], dtype=torch.float64)

    g = torch.Generator().manual_seed(0)
    weights = torch.randn(3, 8, 10, 5, generator=g, dtype=torch.float64)  # 3 random projections of the outputs

    def render(*params):
        kwargs = dict(scene, **dict(zip(names, params)))
        img, alpha, _ = rasterization(**kwargs, backgrounds=bg, render_mode="RGB+ED", backend="torch")
        out = torch.cat([img, alpha], dim=-1)[0]  # [8, 10, 5]
        return (weights * out).sum(dim=(1, 2, 3))

    inputs = tuple(scene[k].clone().requires_grad_(True) for k in names)
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_means2d_grad_is_retained():
    scene = random_scene(30, 24, 20, seed=2)
    scene["means"].requires_grad_(True)
    img, _, meta = rasterization(**scene, backend="torch")
    meta["means2d"].retain_grad()
    img.sum().backward()
    grad = meta["means2d"].grad
    assert grad.shape == (1, 30, 2) and grad.abs().sum() > 0


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("means", "nan", "means contains NaN"),
        ("scales", "inf", "scales contains infinite"),
        ("quats", "shape", r"quats must have shape \[5, 4\]"),
        ("colors", "shape", "colors must have shape"),
        ("viewmats", "nan", "viewmats contains NaN"),
    ],
)
def test_bad_inputs_raise_one_clear_error(field, value, match):
    scene = random_scene(5, 8, 8, seed=0)
    tensor = scene[field].clone()
    if value == "nan":
        tensor.view(-1)[0] = float("nan")
    elif value == "inf":
        tensor.view(-1)[0] = float("inf")
    else:
        tensor = tensor[..., :2]
    scene[field] = tensor
    with pytest.raises(InvalidInputError, match=match):
        rasterization(**scene, backend="torch")


def test_bad_options_raise():
    scene = random_scene(5, 8, 8, seed=0)
    with pytest.raises(InvalidInputError, match="render_mode"):
        rasterization(**scene, render_mode="RGBD", backend="torch")
    with pytest.raises(InvalidInputError, match="backend"):
        rasterization(**scene, backend="vulkan")
    with pytest.raises(InvalidInputError, match="sh_degree=3 needs 16"):
        rasterization(**dict(scene, colors=scene["colors"][:, :9]), backend="torch")
    with pytest.raises(InvalidInputError, match="width and height"):
        rasterization(**dict(scene, width=0), backend="torch")
    if not torch.cuda.is_available():
        with pytest.raises(InvalidInputError, match="needs CUDA and the gsplat package"):
            rasterization(**scene, backend="gsplat")
    with pytest.raises(InvalidInputError, match="float32"):
        rasterization(**{k: (v.double() if torch.is_tensor(v) else v) for k, v in scene.items()}, backend="cpu")
    with pytest.raises(InvalidInputError, match="positive focal lengths"):
        rasterization(**dict(scene, Ks=scene["Ks"] * torch.tensor([0.0, 1.0, 1.0])[:, None]), backend="torch")
    with pytest.raises(InvalidInputError, match="packed=False"):
        rasterization(**scene, packed=True, backend="torch")
