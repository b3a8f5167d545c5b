"""SSIM: the evaluation metric on the valid region (against pytorch-msssim), the training loss's padded map, and
the fused CPU D-SSIM of the loss against that map in float64."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from pytorch_msssim import ssim as msssim_ssim

from tacsplat.errors import InvalidInputError
from tacsplat.reconstruction.fused_ssim import d_ssim
from tacsplat.reconstruction.metrics import ssim, ssim_map


def _structured(h: int, w: int, seed: int) -> torch.Tensor:
    """A render-like image [H, W, 3] float64: a shaded disc with a highlight on a vertical-gradient backdrop."""
    rng = np.random.default_rng(seed)
    v, u = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    image = (0.3 + 0.5 * v)[..., None] * np.array([0.9, 0.95, 1.0])
    cy, cx, r = rng.uniform(0.35, 0.65), rng.uniform(0.35, 0.65), rng.uniform(0.2, 0.3)
    d2 = (v - cy) ** 2 + (u - cx) ** 2
    shade = np.sqrt(np.clip(1 - d2 / r**2, 0, 1))[..., None] * rng.uniform(0.2, 1.0, 3)
    image = np.where((d2 < r**2)[..., None], shade, image)
    image += 0.6 * np.exp(-((v - cy + r / 3) ** 2 + (u - cx - r / 3) ** 2) / (2 * (r / 6) ** 2))[..., None]
    return torch.from_numpy(np.clip(image, 0, 1))


def _degraded(image: torch.Tensor, seed: int) -> torch.Tensor:
    """Blurred, shifted by a pixel and noisy, like the render of a partly trained splat."""
    g = torch.Generator().manual_seed(seed)
    x = image.permute(2, 0, 1)[None]
    x = F.avg_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1)
    x = torch.roll(x, shifts=(1, -1), dims=(2, 3))
    x = x + 0.05 * torch.randn(x.shape, generator=g, dtype=x.dtype)
    return x[0].permute(1, 2, 0).clamp(0, 1)


def _msssim(a: torch.Tensor, b: torch.Tensor) -> float:
    """pytorch-msssim's SSIM (11x11 Gaussian window, sigma 1.5, valid convolution) of [B?, H, W, C] images."""
    if a.ndim == 3:
        a, b = a[None], b[None]
    return float(msssim_ssim(a.permute(0, 3, 1, 2), b.permute(0, 3, 1, 2), data_range=1.0, size_average=True))


def _padded_reference(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The Inria 3DGS training SSIM (utils/loss_utils.py ``_ssim``: 2D Gaussian window, zero padding of 5
    around each moment), per pixel [1, H, W, C]."""
    x, y = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    channels = x.shape[1]
    coords = torch.arange(11, dtype=x.dtype) - 5
    g = torch.exp(-(coords**2) / (2 * 1.5**2))
    g = g / g.sum()
    window = (g[:, None] @ g[None, :]).expand(channels, 1, 11, 11).contiguous()

    def blur(t):
        return F.conv2d(t, window, padding=5, groups=channels)

    mu1, mu2 = blur(x), blur(y)
    s1, s2, s12 = blur(x * x) - mu1**2, blur(y * y) - mu2**2, blur(x * y) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1**2 + mu2**2 + c1) * (s1 + s2 + c2))
    return m.permute(0, 2, 3, 1)


TOL = 2e-5  # pytorch-msssim builds its window in float32
CASES = [(11, 11, 3), (17, 23, 3), (40, 31, 1), (64, 64, 3)]


@pytest.mark.parametrize("h, w, c", CASES)
def test_ssim_is_pytorch_msssims_valid_region_ssim_on_random_images(h, w, c):
    g = torch.Generator().manual_seed(h * w + c)
    a = torch.rand(h, w, c, generator=g, dtype=torch.float64)
    related = (0.7 * a + 0.3 * torch.rand(h, w, c, generator=g, dtype=torch.float64)).clamp(0, 1)
    unrelated = torch.rand(h, w, c, generator=g, dtype=torch.float64)
    for b in (related, unrelated):
        assert ssim(a, b) == pytest.approx(_msssim(a, b), abs=TOL)
    assert ssim(a.float(), related.float()) == pytest.approx(_msssim(a, related), abs=TOL)  # float32 renders


@pytest.mark.parametrize("h, w", [(24, 24), (48, 36), (64, 64)])
def test_ssim_is_pytorch_msssims_valid_region_ssim_on_structured_images(h, w):
    target = _structured(h, w, seed=h + w)
    render = _degraded(target, seed=h)
    assert ssim(render, target) == pytest.approx(_msssim(render, target), abs=TOL)
    batch = torch.stack([render, target.flip(0)]), torch.stack([target, target])
    assert ssim(*batch) == pytest.approx(_msssim(*batch), abs=TOL)


def test_the_reported_ssim_differs_from_the_zero_padded_mean():
    """The zero-padded map scores border windows half made of padding, which both images share: its mean
    is not the metric the NeRF/3DGS tables report."""
    target = _structured(64, 64, seed=3)
    render = _degraded(target, seed=4)
    padded = float(ssim_map(render, target).mean())
    assert ssim(render, target) == pytest.approx(_msssim(render, target), abs=TOL)
    assert abs(padded - ssim(render, target)) > 1e-3


def test_the_training_loss_keeps_the_zero_padded_map():
    g = torch.Generator().manual_seed(5)
    a = torch.rand(20, 26, 3, generator=g, dtype=torch.float64)
    b = (a + 0.2 * torch.randn(20, 26, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    m = ssim_map(a, b)
    assert m.shape == (1, 20, 26, 3)
    torch.testing.assert_close(m, _padded_reference(a, b), rtol=0, atol=1e-12)


def test_images_smaller_than_the_window_are_refused_naming_the_size():
    a = torch.rand(10, 30, 3)
    with pytest.raises(InvalidInputError, match="10x30.*11x11"):
        ssim(a, a)


@pytest.mark.parametrize("shape", [(20, 26, 3), (2, 13, 40, 1), (64, 48, 3)])
def test_fused_d_ssim_is_one_minus_the_padded_map_mean_with_its_gradient(shape):
    """The numba kernels (hand-written backward) against autograd through ssim_map, both in float64."""
    g = torch.Generator().manual_seed(sum(shape))
    target = torch.rand(shape, generator=g, dtype=torch.float64)
    render = (target + 0.3 * torch.randn(shape, generator=g, dtype=torch.float64)).clamp(0, 1).requires_grad_(True)
    reference = 1.0 - ssim_map(render, target).mean()
    (expected,) = torch.autograd.grad(reference, render)
    fused = d_ssim(render, target)
    (got,) = torch.autograd.grad(3.0 * fused, render)  # an upstream gradient other than 1 scales it
    assert fused.item() == pytest.approx(reference.item(), abs=1e-12)
    torch.testing.assert_close(got, 3.0 * expected, rtol=1e-9, atol=1e-15)
    assert got.abs().max() > 0
    # float32 (what training uses) stays within float32 rounding of the float64 result
    render32 = render.detach().float().requires_grad_(True)
    fused32 = d_ssim(render32, target.float())
    (got32,) = torch.autograd.grad(fused32, render32)
    assert fused32.item() == pytest.approx(reference.item(), abs=1e-6)
    assert float((got32.double() - expected).abs().max() / expected.abs().max()) < 1e-5


def test_fused_d_ssim_is_zero_for_identical_images_and_ignores_the_targets_gradient():
    image = _structured(32, 32, seed=1).float()
    render = image.clone().requires_grad_(True)
    loss = d_ssim(render, image)
    loss.backward()
    assert loss.item() == pytest.approx(0.0, abs=1e-6)
    assert render.grad.abs().max() < 1e-5  # a maximum: the gradient vanishes
    a, b = torch.rand(16, 16, 3, requires_grad=True), torch.rand(16, 16, 3, requires_grad=True)
    both = d_ssim(a, b)  # a target that needs gradients takes the autograd reference
    both.backward()
    assert b.grad is not None and a.grad is not None
