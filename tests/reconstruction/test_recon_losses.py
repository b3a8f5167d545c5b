"""Losses of tactile-informed 3DGS on hand-made inputs with known values."""

import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction import losses
from tacsplat.reconstruction.losses import (
    TouchNeighbours,
    edge_aware_smoothness,
    photometric_loss,
    proximity_mask,
    transmittance_loss,
    visible_touch_pixels,
)

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import precisions  # noqa: E402

IDENTITY = torch.tensor([[1.0, 0.0, 0.0, 0.0]])


def _one_gaussian(mean, scale, opacity):
    return (
        torch.tensor([mean], dtype=torch.float64),
        IDENTITY.double(),
        torch.full((1, 3), scale, dtype=torch.float64),
        torch.tensor([opacity], dtype=torch.float64),
    )


def test_gaussian_at_touch_point_lowers_transmittance_to_one_minus_opacity():
    means, quats, scales, opac = _one_gaussian([0.1, 0.2, 0.3], 0.002, 0.7)
    points = torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64)
    loss = transmittance_loss(points, means, quats, scales, opac, torch.tensor([[0]]), top_k=4, max_distance=0.01)
    assert loss.item() == pytest.approx(1.0 - 0.7, abs=1e-12)


def test_transmittance_averages_points_and_counts_unreached_points_as_transparent():
    means, quats, scales, opac = _one_gaussian([0.0, 0.0, 0.0], 0.002, 0.6)
    offset = 0.002  # one standard deviation along x: f = exp(-1/2)
    points = torch.tensor([[offset, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    candidates = torch.tensor([[0], [-1]])
    loss = transmittance_loss(points, means, quats, scales, opac, candidates, top_k=4, max_distance=0.01)
    expected = 0.5 * ((1.0 - math.exp(-0.5) * 0.6) + 1.0)
    assert loss.item() == pytest.approx(expected, abs=1e-12)


def test_transmittance_uses_top_k_by_influence_within_the_distance_threshold():
    means = torch.tensor([[0.0, 0, 0], [0.001, 0, 0], [0.003, 0, 0], [0.02, 0, 0]], dtype=torch.float64)
    quats = IDENTITY.double().repeat(4, 1)
    scales = torch.tensor([[0.001] * 3, [0.001] * 3, [0.001] * 3, [0.5] * 3], dtype=torch.float64)
    opac = torch.tensor([0.2, 0.9, 0.9, 0.99], dtype=torch.float64)
    point = torch.zeros(1, 3, dtype=torch.float64)
    # influences f*alpha: 0.2, exp(-0.5)*0.9 = 0.546, exp(-4.5)*0.9 = 0.010; the 4th is out of reach
    loss = transmittance_loss(
        point, means, quats, scales, opac, torch.tensor([[0, 1, 2, 3]]), top_k=2, max_distance=0.01
    )
    expected = 0.5 * ((1 - 0.2) + (1 - math.exp(-0.5) * 0.9))
    assert loss.item() == pytest.approx(expected, abs=1e-12)


def test_minimising_transmittance_raises_opacity_and_pulls_the_mean_onto_the_point():
    means, quats, scales, opac = _one_gaussian([0.001, 0.0, 0.0], 0.002, 0.5)
    means.requires_grad_(True)
    opac.requires_grad_(True)
    loss = transmittance_loss(
        torch.zeros(1, 3, dtype=torch.float64),
        means,
        quats,
        scales,
        opac,
        torch.tensor([[0]]),
        top_k=1,
        max_distance=0.01,
    )
    loss.backward()
    assert opac.grad.item() < 0  # descending raises opacity
    assert means.grad[0, 0].item() > 0  # descending moves the mean towards x = 0


def _touch_cluster(dtype, n=300, points=64, candidates=16, seed=0):
    """Gaussians and touch points in a 2 cm cube: pairs in and out of reach, shared candidates, missing ones,
    a zero quaternion, and Gaussians so thin that the exponent is clamped."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=dtype) * 0.02
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    quats[0] = 0.0
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.002 + 0.0003
    scales[1:20, 2] = 1e-7  # exponent beyond MAX_MAHALANOBIS off their plane
    opacities = torch.rand(n, generator=g, dtype=dtype)
    touch = torch.rand(points, 3, generator=g, dtype=dtype) * 0.02
    ids = torch.randint(0, n, (points, candidates), generator=g)
    ids[:, 12:] = -1
    ids[5] = -1
    ids[7, :4] = torch.arange(1, 5)  # thin ones
    return touch, means, quats, scales, opacities, ids


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_fused_transmittance_matches_the_torch_reference_in_value_and_every_gradient(dtype, tol):
    touch, *params, ids = _touch_cluster(dtype)
    params = [p.requires_grad_(True) for p in params]
    reference = losses.transmittance_loss(touch, *params, ids, top_k=4, max_distance=0.006, fused=False)
    expected = torch.autograd.grad(reference, params)
    fused = losses.transmittance_loss(touch, *params, ids, top_k=4, max_distance=0.006)  # CPU: numba kernels
    got = torch.autograd.grad(2.0 * fused, params)
    assert 0.05 < reference.item() < 1.0
    assert fused.item() == pytest.approx(reference.item(), abs=tol)
    for name, want, have in zip(("means", "quats", "scales", "opacities"), expected, got):
        assert want.abs().max() > 0, name
        torch.testing.assert_close(have, 2.0 * want, rtol=0, atol=tol * float(want.abs().max()), msg=name)


def test_fused_transmittance_stays_finite_for_a_gaussian_with_a_zero_scale():
    """A collapsed axis (floored at MIN_SCALE) puts the point 1e9 standard deviations away: influence exp(-80)
    alpha, gradients finite (the opacity's only)."""
    means, quats, scales, opac = _one_gaussian([0.001, 0.0, 0.0], 0.002, 0.5)
    scales[0, 0] = 0.0
    params = [p.requires_grad_(True) for p in (means, quats, scales, opac)]
    loss = transmittance_loss(
        torch.zeros(1, 3, dtype=torch.float64), *params, torch.tensor([[0]]), top_k=1, max_distance=0.01
    )
    grads = torch.autograd.grad(loss, params)
    assert loss.item() == pytest.approx(1.0, abs=1e-30)
    assert all(torch.isfinite(g).all() for g in grads)
    assert grads[3].item() == pytest.approx(-math.exp(-80.0), rel=1e-12)
    assert all(g.abs().max() == 0 for g in grads[:3])


def test_fused_transmittance_gradient_is_the_float64_finite_difference():
    touch, means, quats, scales, opacities, ids = _touch_cluster(torch.float64, n=40, points=8, candidates=6)
    for param in (means, quats, scales, opacities):
        param.requires_grad_(True)
    torch.autograd.gradcheck(
        lambda m, q, s, o: losses.transmittance_loss(touch, m, q, s, o, ids, top_k=3, max_distance=0.006),
        (means, quats, scales, opacities),
        eps=1e-9,
        atol=1e-6,
    )


def test_touch_neighbours_see_only_touch_gaussians_and_rebuild_on_schedule():
    means = torch.tensor([[0.0, 0, 0], [0.001, 0, 0], [0.002, 0, 0], [0.5, 0, 0]])
    from_touch = torch.tensor([False, True, True, True])
    index = TouchNeighbours(np.zeros((1, 3)), num_candidates=3, max_distance=0.01, rebuild_every=2)
    cand = index.candidates(means, from_touch)
    assert cand.tolist() == [[1, 2, -1]]  # G_c (0) excluded, far G_t (3) out of reach
    index.candidates(means, from_touch)
    assert index.num_builds == 1
    index.candidates(means, from_touch)
    assert index.num_builds == 2
    index.invalidate()
    index.candidates(means, from_touch)
    assert index.num_builds == 3


def test_smoothness_of_constant_depth_is_zero_and_of_a_ramp_is_its_slope():
    h, w = 12, 16
    image = torch.full((h, w, 3), 0.5)  # no edges: e^{-beta * 0} = 1
    assert edge_aware_smoothness(torch.full((h, w), 0.3), image).item() == pytest.approx(0.0, abs=1e-7)
    slope = 0.01
    ramp = slope * torch.arange(w, dtype=torch.float32)[None, :].expand(h, w)
    # 5x5 Sobel normalised to unit response: |dD/dx| = slope, |dD/dy| = 0 everywhere
    assert edge_aware_smoothness(ramp, image).item() == pytest.approx(slope, rel=1e-5)
    assert edge_aware_smoothness(ramp.T.contiguous(), image.transpose(0, 1)).item() == pytest.approx(slope, rel=1e-5)


def test_smoothness_is_damped_where_the_image_has_an_edge_and_masked_near_touches():
    h, w = 12, 16
    slope_d, slope_i, beta = 0.01, 0.05, 10.0
    ramp = slope_d * torch.arange(w, dtype=torch.float32)[None, :].expand(h, w)
    image = (slope_i * torch.arange(w, dtype=torch.float32))[None, :, None].expand(h, w, 3).contiguous()
    expected = slope_d * math.exp(-beta * slope_i)
    assert edge_aware_smoothness(ramp, image, beta=beta).item() == pytest.approx(expected, rel=1e-5)
    flat = torch.full((h, w, 3), 0.5)
    assert edge_aware_smoothness(ramp, flat, proximity=torch.ones(h, w)).item() == 0.0
    half = torch.zeros(h, w)
    half[:, : w // 2] = 1.0  # masked on the left half
    valid_cols = torch.arange(2, w - 2)
    expected_half = slope_d * (valid_cols >= w // 2).float().mean().item()
    assert edge_aware_smoothness(ramp, flat, proximity=half).item() == pytest.approx(expected_half, rel=1e-5)


def test_proximity_mask_is_one_at_a_touch_and_decays_as_a_gaussian_of_distance():
    sigma = 3.0
    seeds = torch.zeros(30, 40, dtype=torch.bool)
    seeds[10, 20] = True
    mask = proximity_mask(seeds, sigma_px=sigma)
    assert mask.shape == (30, 40)
    assert mask[10, 20] == pytest.approx(1.0)
    for k in (1, 2, 5):
        assert mask[10, 20 + k] == pytest.approx(math.exp(-(k**2) / (2 * sigma**2)), rel=1e-4)
        assert mask[10 - k, 20] == pytest.approx(math.exp(-(k**2) / (2 * sigma**2)), rel=1e-4)
    assert mask[13, 24] == pytest.approx(math.exp(-25 / (2 * sigma**2)), rel=1e-4)
    assert not proximity_mask(torch.zeros(30, 40, dtype=torch.bool), sigma).any()


@pytest.mark.parametrize("sigma", [2.5, 40.0])  # (40: a reach of 160 px, past the image's sides)
def test_proximity_mask_matches_the_exact_distance_transform_within_reach(sigma):
    rng = np.random.default_rng(4)
    seeds = torch.from_numpy(rng.random((50, 70)) < 0.004)
    free = np.where(seeds.numpy(), 0, 255).astype(np.uint8)
    exact = np.exp(
        -(cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE).astype(np.float64) ** 2) / (2 * sigma**2)
    )
    np.testing.assert_allclose(proximity_mask(seeds, sigma).numpy(), exact, atol=3.4e-4, rtol=1e-5)


def test_visible_touch_pixels_project_and_drop_hidden_behind_and_outside_points():
    K = torch.tensor([[50.0, 0, 20], [0, 50.0, 15], [0, 0, 1]])
    viewmat = torch.from_numpy(invert_pose(look_at([0, 0, -1.0], [0, 0, 0], up=(0, -1, 0)))).float()  # at z=-1
    points = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [0, 0, -2.0], [5.0, 0, 0]])  # centre, right, behind, outside

    def seen(mask):
        return sorted(map(tuple, torch.nonzero(mask).tolist()))

    assert seen(visible_touch_pixels(points, K, viewmat, 40, 30)) == [(15, 20), (15, 25)]
    depth = torch.full((30, 40), 0.9)  # a rendered surface 0.1 m in front of the touched plane
    depth[:, 23:] = 1.0
    assert seen(visible_touch_pixels(points, K, viewmat, 40, 30, depth, occlusion_tolerance=0.01)) == [(15, 25)]


def test_photometric_loss_is_zero_for_identical_images_and_weights_l1():
    target = torch.rand(8, 9, 3, generator=torch.Generator().manual_seed(0))
    assert photometric_loss(target, target).item() == pytest.approx(0.0, abs=1e-6)
    assert photometric_loss(target + 0.1, target, ssim_weight=0.0).item() == pytest.approx(0.1, rel=1e-5)


def test_backdrop_alpha_loss_is_the_mean_alpha_over_backdrop_pixels():
    from tacsplat.reconstruction.losses import backdrop_alpha_loss

    alpha = torch.tensor([[0.2, 0.9], [0.4, 1.0]])
    mask = torch.tensor([[True, False], [True, False]])
    assert backdrop_alpha_loss(alpha, mask).item() == pytest.approx(0.3)
    assert backdrop_alpha_loss(alpha, torch.zeros(2, 2, dtype=torch.bool)).item() == 0.0


def test_window_inside_keeps_only_windows_wholly_in_the_mask():
    mask = torch.zeros(12, 12, dtype=torch.bool)
    mask[2:10, 3:11] = True
    inside = losses.window_inside(mask)
    assert inside.shape == (8, 8)
    # a window centred at (r, c) of the full image is inside when r-2..r+2 and c-2..c+2 are in the mask
    expected = torch.zeros(8, 8)
    expected[2:6, 3:7] = 1.0  # centres r 4..7, c 5..8
    assert torch.equal(inside, expected)


def test_expected_depth_of_a_half_transparent_plane_is_its_depth_and_smooth():
    alpha = torch.full((16, 16), 0.5)
    alpha[:, 8:] = 0.25  # an opacity edge over a flat surface at 2 m
    depth = 2.0 * alpha  # Eq. 5's accumulated depth
    accumulated = losses.edge_aware_smoothness(depth, weights=torch.ones(2, 12, 12))
    expected = losses.edge_aware_smoothness(losses.expected_depth(depth, alpha), weights=torch.ones(2, 12, 12))
    assert accumulated > 0.01 and float(expected) == pytest.approx(0.0, abs=1e-6)


def test_a_planar_depth_map_gives_a_constant_depth_normal():
    from tacsplat.reconstruction.losses import depth_normals

    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]], dtype=torch.float64)
    normal = torch.tensor([0.2, -0.3, -1.0], dtype=torch.float64)
    normal = normal / normal.norm()  # the plane n.p = c, facing the camera
    v, u = torch.meshgrid(
        torch.arange(24.0, dtype=torch.float64) + 0.5, torch.arange(32.0, dtype=torch.float64) + 0.5, indexing="ij"
    )
    rays = torch.stack([(u - 16) / 40, (v - 12) / 40, torch.ones_like(u)], -1)
    depth = -2.0 / (rays @ normal)  # ray hits the plane n.p = -2 at z = depth
    n = depth_normals(depth, K)
    inner = n[1:-1, 1:-1].reshape(-1, 3)
    torch.testing.assert_close(inner, normal.expand_as(inner), rtol=0, atol=1e-9)
    assert (n[0] == 0).all() and (n[:, -1] == 0).all()


@pytest.mark.parametrize("with_proximity", [False, True])
def test_fused_smoothness_matches_the_torch_convolutions_with_its_gradient(with_proximity):
    g = torch.Generator().manual_seed(4)
    depth = torch.rand(37, 45, generator=g, dtype=torch.float64)
    depth[10:25, 10:30] = 0.5  # flat: zero Sobel responses, whose |.| passes no gradient
    depth.requires_grad_(True)
    weights = torch.rand(2, 33, 41, generator=g, dtype=torch.float64)
    proximity = torch.rand(37, 45, generator=g, dtype=torch.float64) if with_proximity else None
    reference = edge_aware_smoothness(depth, proximity=proximity, weights=weights, fused=False)
    (expected,) = torch.autograd.grad(reference, depth)
    fused = edge_aware_smoothness(depth, proximity=proximity, weights=weights)  # CPU: the numba kernels
    (got,) = torch.autograd.grad(fused, depth)
    assert fused.item() == pytest.approx(reference.item(), abs=1e-14)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-12 * float(expected.abs().max()))
    assert expected[15:20, 16:24].abs().max() == 0 and got[15:20, 16:24].abs().max() == 0


def test_fused_depth_normal_consistency_matches_the_torch_reference_with_its_gradients():
    """A wavy depth map with an empty corner (normals unknown there and around it), random rendered normals and
    weights, float64: the fused pass against normal_consistency_loss(depth_normals(...)) through autograd."""
    g = torch.Generator().manual_seed(2)
    K = torch.tensor([[60.0, 0, 26], [0, 60.0, 20], [0, 0, 1]], dtype=torch.float64)
    v, u = torch.meshgrid(
        torch.arange(40.0, dtype=torch.float64), torch.arange(52.0, dtype=torch.float64), indexing="ij"
    )
    depth = (
        1.0 + 0.2 * torch.sin(u / 7) * torch.cos(v / 5) + 0.01 * torch.rand(40, 52, generator=g, dtype=torch.float64)
    )
    depth[:5, :8] = 0.0
    depth.requires_grad_(True)
    rendered = torch.nn.functional.normalize(torch.randn(40, 52, 3, generator=g, dtype=torch.float64), dim=-1)
    rendered.requires_grad_(True)
    weight = torch.rand(40, 52, generator=g, dtype=torch.float64)
    reference = losses.depth_normal_consistency(rendered, depth, K, weight, fused=False)
    expected = torch.autograd.grad(reference, (rendered, depth))
    fused = losses.depth_normal_consistency(rendered, depth, K, weight)
    got = torch.autograd.grad(fused, (rendered, depth))
    assert fused.item() == pytest.approx(reference.item(), abs=1e-12)
    for want, have in zip(expected, got):
        assert want.abs().max() > 0
        torch.testing.assert_close(have, want, rtol=0, atol=1e-12 * float(want.abs().max()))


def test_the_flattening_loss_is_the_mean_shortest_axis_over_the_scene_scale():
    from tacsplat.reconstruction.losses import flatten_loss

    scales = torch.tensor([[1.0, 0.2, 3.0], [0.5, 0.5, 0.1]])
    assert flatten_loss(scales, 2.0).item() == pytest.approx((0.2 + 0.1) / 2 / 2.0)


def test_the_influence_from_the_whitening_matches_eq1_with_the_precision_matrix_and_stays_finite_far_away():
    from tacsplat.reconstruction.gaussians import whitening
    from tacsplat.reconstruction.losses import MAX_MAHALANOBIS, gaussian_influence

    g = torch.Generator().manual_seed(2)
    quats = torch.randn(40, 4, generator=g, dtype=torch.float64)
    scales = 0.01 + 0.05 * torch.rand(40, 3, generator=g, dtype=torch.float64)
    means = 0.05 * torch.randn(40, 3, generator=g, dtype=torch.float64)
    points = 0.05 * torch.randn(5, 3, generator=g, dtype=torch.float64)
    d = points[:, None, :] - means[None]  # [5, 40, 3]
    maha = torch.einsum("pki,kij,pkj->pk", d, precisions(quats, scales), d)
    influence = gaussian_influence(d, whitening(quats, scales)[None].expand(5, -1, -1, -1))
    assert (maha > MAX_MAHALANOBIS).any() and (maha < 10).any()  # both sides of the floor
    torch.testing.assert_close(influence, torch.exp(-0.5 * maha.clamp(max=MAX_MAHALANOBIS)), rtol=1e-12, atol=1e-300)
    far = means.clone().requires_grad_(True)  # 1e3 scales away: the exponent is floored, no subnormal, no NaN
    out = gaussian_influence(torch.full((1, 3), 100.0, dtype=torch.float64) - far[None], whitening(quats, scales)[None])
    out.sum().backward()
    assert torch.isfinite(far.grad).all() and (out > 0).all() and (out <= math.exp(-80)).all()
