"""A Gaussian so large that its screen radius is past the int64 range (scale >= ~1e18 here) is drawn by the ``cpu``
backend as by ``torch``: the same image, and the same radii (clamped to 2**30), among normal Gaussians whose radii
are unchanged. (``math.ceil`` of such a radius overflowed to a negative int64 and the cpu backend dropped it.)"""

from __future__ import annotations

import pytest
import torch

from tacsplat.reconstruction.raster import rasterization

WIDTH, HEIGHT = 64, 48
K = torch.tensor([[[60.0, 0.0, 32.0], [0.0, 60.0, 24.0], [0.0, 0.0, 1.0]]])


def _scene(huge_scale: float, huge_mean: tuple[float, float, float]) -> dict[str, torch.Tensor]:
    """Eight normal Gaussians in front of the camera, then the huge one (a low opacity: the others show through)."""
    g = torch.Generator().manual_seed(0)
    n = 8
    means = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.randn(n + 1, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.1 + 0.02
    return {
        "means": torch.cat([means, torch.tensor([huge_mean])]),
        "quats": quats,
        "scales": torch.cat([scales, torch.full((1, 3), huge_scale)]),
        "opacities": torch.cat([torch.rand(n, generator=g) * 0.5 + 0.4, torch.tensor([0.3])]),
        "colors": torch.rand(n + 1, 3, generator=g),
    }


def _render(scene: dict[str, torch.Tensor], backend: str):
    colors, alphas, meta = rasterization(
        scene["means"],
        scene["quats"],
        scene["scales"],
        scene["opacities"],
        scene["colors"],
        torch.eye(4)[None],
        K,
        WIDTH,
        HEIGHT,
        backend=backend,
    )
    return colors, alphas, meta["radii"]


@pytest.mark.parametrize("huge_scale", [1e17, 1e18, 1e20])
@pytest.mark.parametrize(
    "huge_mean",
    [
        (0.0, 0.0, 3.0),  # over the whole image
        # its centre 4e9 px left of the image: kept by its true radius, though its tiles (by the clamped radius)
        # miss the image on both backends
        (-2e8, 0.0, 3.0),
    ],
)
def test_a_huge_gaussian_is_drawn_alike_by_the_cpu_and_torch_backends(huge_scale, huge_mean):
    scene = _scene(huge_scale, huge_mean)
    colors, alphas, radii = _render(scene, "cpu")
    ref_colors, ref_alphas, ref_radii = _render(scene, "torch")
    assert torch.equal(radii, ref_radii)
    assert (radii[0, -1] == 2**30).all()  # drawn, its radius clamped
    torch.testing.assert_close(colors, ref_colors, rtol=0, atol=1e-5)
    torch.testing.assert_close(alphas, ref_alphas, rtol=0, atol=1e-5)
    if huge_mean[0] == 0.0:
        assert alphas.min() > 0.29  # the huge one covers every pixel


def test_the_normal_gaussians_radii_do_not_change_with_a_huge_one_beside_them():
    scene = _scene(1e18, (0.0, 0.0, 3.0))
    alone = {name: value[:-1] for name, value in scene.items()}
    assert torch.equal(_render(scene, "cpu")[2][0, :-1], _render(alone, "cpu")[2][0])


@pytest.mark.parametrize("huge_scale", [1e18, 1e20])
def test_the_huge_gaussian_gets_the_same_gradients_on_both_backends(huge_scale):
    grads = {}
    for backend in ("cpu", "torch"):
        scene = {name: value.requires_grad_() for name, value in _scene(huge_scale, (0.0, 0.0, 3.0)).items()}
        colors, alphas, _ = _render(scene, backend)
        (colors.sum() + alphas.sum()).backward()
        grads[backend] = {name: value.grad for name, value in scene.items()}
    for name in ("means", "scales", "opacities", "colors"):
        assert torch.isfinite(grads["cpu"][name]).all(), name
        torch.testing.assert_close(grads["cpu"][name], grads["torch"][name], rtol=1e-4, atol=1e-3, msg=name)
    assert grads["cpu"]["opacities"][-1] > 1.0  # the huge one is seen by the backward too
