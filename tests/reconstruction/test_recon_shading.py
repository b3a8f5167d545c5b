"""Normals and lit shading: flat Gaussians, depth-normal consistency on a plane, the diffuse light and the lit
shading's gradients."""

import math

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction import losses
from tacsplat.reconstruction.evaluation import equirect_directions, save_light
from tacsplat.reconstruction.gaussians import Gaussians, rgb_to_sh0
from tacsplat.reconstruction.raster.spherical_harmonics import sh_basis
from tacsplat.reconstruction.shading import DiffuseLight, _Channels, _shade, gaussian_normals, render


def test_the_normal_of_a_flat_gaussian_is_its_shortest_axis():
    rotations = Rotation.random(20, random_state=1)
    quats = torch.tensor(rotations.as_quat(scalar_first=True))
    scales = torch.tensor([[1.0, 0.5, 0.01]] * 10 + [[0.02, 1.0, 0.7]] * 10, dtype=torch.float64)
    normals = gaussian_normals(quats, scales).numpy()
    axes = rotations.as_matrix()
    expected = np.concatenate([axes[:10, :, 2], axes[10:, :, 0]])
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", normals, expected)), 1.0, atol=1e-12)


def test_fused_gaussian_normals_match_the_torch_reference_with_their_gradient():
    g = torch.Generator().manual_seed(3)
    quats = torch.randn(200, 4, generator=g, dtype=torch.float64)
    quats[0] = 0.0  # the identity
    scales = torch.rand(200, 3, generator=g, dtype=torch.float64)
    scales[1] = 0.5  # a tie: the first axis, as argmin
    quats.requires_grad_(True)
    weights = torch.randn(200, 3, generator=g, dtype=torch.float64)
    reference = gaussian_normals(quats, scales, fused=False)
    (expected,) = torch.autograd.grad((reference * weights).sum(), quats)
    fused = gaussian_normals(quats, scales)  # CPU tensors: the numba kernels
    (got,) = torch.autograd.grad((fused * weights).sum(), quats)
    torch.testing.assert_close(fused, reference, rtol=0, atol=1e-14)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-12)
    torch.autograd.gradcheck(lambda q: gaussian_normals(q, scales), (quats[2:12].detach().requires_grad_(True),))


def _plane_of_flat_gaussians(normal: np.ndarray, offset: float, n: int = 60) -> Gaussians:
    """A dense grid of flat, opaque Gaussians lying in the plane normal . p = offset."""
    normal = normal / np.linalg.norm(normal)
    u = np.cross(normal, [0.0, 1.0, 0.0] if abs(normal[1]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    grid = np.stack(np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n), indexing="ij"), -1).reshape(-1, 2)
    means = offset * normal + grid[:, :1] * u + grid[:, 1:] * v
    rotation = np.stack([u, v, normal], axis=1)  # columns: the Gaussian's axes; the third is the shortest
    quat = Rotation.from_matrix(rotation).as_quat(scalar_first=True)
    spacing = 2.0 / (n - 1)
    m = len(means)
    params = {
        "means": torch.tensor(means, dtype=torch.float32),
        "quats": torch.tensor(np.tile(quat, (m, 1)), dtype=torch.float32),
        "scales": torch.log(torch.tensor([[spacing, spacing, 1e-4]] * m, dtype=torch.float32)),
        "opacities": torch.full((m,), 4.0),
        "sh0": rgb_to_sh0(torch.full((m, 1, 3), 0.5)),
        "shN": torch.zeros(m, 0, 3),
    }
    return Gaussians(params, torch.zeros(m, dtype=torch.bool), sh_degree=0)


@pytest.mark.parametrize("channels", [6, 7])
def test_the_rendered_channels_split_as_slices_and_f_normalize_do_with_their_gradients(channels):
    g = torch.Generator().manual_seed(5)
    out = torch.randn(1, 6, 5, channels, generator=g, dtype=torch.float64)
    out[0, 1, 2, 3:6] = 0.0  # a pixel no Gaussian reaches: the normal's norm clamped at eps
    out[0, 2, 3, 3:6] = torch.tensor([3e-9, -4e-9, 0.0], dtype=torch.float64)  # below eps too
    out.requires_grad_(True)
    weights = [torch.randn(*shape, generator=g, dtype=torch.float64) for shape in ((6, 5, 3), (6, 5, 3), (6, 5))]

    def reference(x):  # what render() did before: slices and F.normalize
        o = x[0]
        depth = o[..., 6] if channels == 7 else None
        return o[..., :3], torch.nn.functional.normalize(o[..., 3:6], dim=-1, eps=1e-8), depth

    split, expected = _Channels.apply(out), reference(out)
    assert (split[2] is None) == (channels == 6)
    for a, b in zip(split, expected):
        assert b is None or torch.equal(a, b)
    for used in ((0, 1, 2), (0, 1)) if channels == 7 else ((0, 1),):  # (7: with and without using the depth)
        (want,) = torch.autograd.grad(sum((reference(out)[i] * weights[i]).sum() for i in used), out)
        (got,) = torch.autograd.grad(sum((_Channels.apply(out)[i] * weights[i]).sum() for i in used), out)
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12 * float(want.abs().max()))
    unclamped = out.detach().clone()
    unclamped[0, 1, 2, 3:6], unclamped[0, 2, 3, 3:6] = 1.0, 0.5  # (gradcheck's steps must not cross the clamp)

    def tensors(x):  # (gradcheck takes no None output)
        return tuple(t for t in _Channels.apply(x) if t is not None)

    assert torch.autograd.gradcheck(tensors, (unclamped.requires_grad_(True),))


def test_depth_normal_consistency_is_zero_for_a_plane_of_flat_gaussians_lying_in_it():
    gaussians = _plane_of_flat_gaussians(np.array([0.1, 0.2, 1.0]), 0.0)
    viewmat = torch.tensor(invert_pose(look_at([0.3, -0.2, 2.5], [0.0, 0.0, 0.0])), dtype=torch.float32)[None]
    K = torch.tensor([[[60.0, 0, 24], [0, 60.0, 24], [0, 0, 1]]])
    out = render(gaussians, viewmat, K, 48, 48, sh_degree=0, backend="cpu", depth_mode="D", normals=True)
    drawn = out.alpha > 0.5
    assert drawn.float().mean() > 0.5
    surface = torch.where(drawn, losses.expected_depth(out.depth, out.alpha), torch.zeros_like(out.alpha))
    from_depth = losses.depth_normals(surface.double(), K[0].double()).float()
    loss = losses.normal_consistency_loss(out.normal, from_depth, out.alpha * drawn)
    assert loss.item() < 2e-3  # (under 4 degrees: overlapping Gaussians' blended depth is not exactly planar)
    # the rendered normal is the plane's, in the camera frame, facing the camera
    plane = viewmat[0, :3, :3] @ torch.tensor([0.1, 0.2, 1.0]) / math.sqrt(1.05)
    plane = plane if plane[2] < 0 else -plane
    inner = out.normal[drawn]
    torch.testing.assert_close(inner, plane.expand_as(inner), rtol=0, atol=1e-4)
    # and a tilted copy of the Gaussians is not consistent with the plane's depth
    tilted = _plane_of_flat_gaussians(np.array([0.1, 0.2, 1.0]), 0.0)
    tilted.params["quats"].data = (
        torch.tensor(Rotation.from_euler("x", 0.6).as_quat(scalar_first=True), dtype=torch.float32)
        .expand_as(tilted.params["quats"])
        .clone()
    )
    out_t = render(tilted, viewmat, K, 48, 48, sh_degree=0, backend="cpu", depth_mode="D", normals=True)
    assert losses.normal_consistency_loss(out_t.normal, from_depth, out.alpha * drawn).item() > 0.05
    # the fused CPU pass the trainer uses agrees on both
    fused = [losses.depth_normal_consistency(o.normal, surface, K[0], out.alpha * drawn).item() for o in (out, out_t)]
    assert fused[0] < 2e-3 and fused[1] > 0.05


def test_sh_colors_of_the_cpu_kernel_match_the_float64_torch_formula_and_its_gradients():
    # render() composites its own channels when normals are on: the SH colours come from the fused numba kernel
    from tacsplat.reconstruction.raster import sh_colors

    g = torch.Generator().manual_seed(4)
    means = torch.randn(300, 3, generator=g, dtype=torch.float64)
    coeffs = 0.3 * torch.randn(300, 16, 3, generator=g, dtype=torch.float64)
    campos = torch.tensor([0.3, -2.0, 4.0], dtype=torch.float64)
    weights = torch.randn(300, 3, generator=g, dtype=torch.float64)
    results = {}
    for backend, dtype in (("torch", torch.float64), ("cpu", torch.float32)):
        m, c = means.to(dtype).clone().requires_grad_(True), coeffs.to(dtype).clone().requires_grad_(True)
        colors = sh_colors(3, m, campos.to(dtype), c, backend=backend)
        (colors * weights.to(dtype)).sum().backward()
        results[backend] = [colors.double(), m.grad.double(), c.grad.double()]
    assert (results["torch"][0] == 0).any() and (results["torch"][0] > 0).any()  # the clamp at 0 is exercised
    for cpu, ref, name in zip(results["cpu"], results["torch"], ("colours", "d/d means", "d/d coefficients")):
        torch.testing.assert_close(cpu, ref, rtol=1e-4, atol=1e-5, msg=name)


def _unit_sphere_directions(count: int, seed: int) -> torch.Tensor:
    directions = torch.randn(count, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return directions / directions.norm(dim=-1, keepdim=True)


def test_a_diffuse_light_holds_a_directional_lights_irradiance_to_a_few_per_cent():
    """Least squares puts the clamped cosine of a sun (irradiance max(<n, l>, 0) + ambient) into the nine SH
    coefficients: Ramamoorthi & Hanrahan's second-order approximation, within 0.1 at worst and 0.035 on average
    (3 % of the peak of 1.2); and the camera light adds its share only on normals that face the camera."""
    light = DiffuseLight().double()
    normals = _unit_sphere_directions(4000, 0)
    sun = torch.tensor([0.3, -0.4, 0.866], dtype=torch.float64)
    truth = 0.2 + (normals @ sun).clamp_min(0.0)  # [P]
    fit = torch.linalg.lstsq(sh_basis(2, normals), truth[:, None]).solution  # [9, 1]
    with torch.no_grad():
        light.coefficients.copy_(fit.expand(9, 3))
    views = -normals  # every normal faces its camera head-on: the camera light counts fully
    irradiance = light.irradiance(normals, views)  # [P, 3]
    assert (irradiance[:, 0] - truth).abs().max() < 0.1
    assert (irradiance[:, 0] - truth).abs().mean() < 0.035
    with torch.no_grad():
        light.camera.copy_(torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64))
    head_on, grazing = light.irradiance(normals, views), light.irradiance(normals, normals)
    torch.testing.assert_close(head_on[:, 0] - irradiance[:, 0], torch.full_like(truth, 0.5))
    torch.testing.assert_close(grazing, irradiance)  # a normal facing away from the camera gets none of it


@pytest.mark.parametrize("fused", [True, False], ids=["numba", "torch"])
def test_a_new_diffuse_light_shades_nothing_and_the_lit_shading_has_float64_gradients(fused):
    """The light starts as irradiance 1 everywhere (a lit colour starts as its albedo); the lit, saturating
    shading's gradient with respect to the albedo, the normal and the light is the numerical one, a pixel with
    alpha 0 included (the numba kernels and the torch reference)."""
    light = DiffuseLight().double()
    normals = _unit_sphere_directions(50, 1)
    torch.testing.assert_close(light.irradiance(normals, -normals), torch.ones(50, 3, dtype=torch.float64))
    g = torch.Generator().manual_seed(2)
    with torch.no_grad():
        light.coefficients.add_(0.3 * torch.randn(9, 3, generator=g, dtype=torch.float64))
        light.camera.fill_(0.2)
    blended = torch.rand(3, 4, 3, generator=g, dtype=torch.float64)
    blended[0, 0] = 3.0  # a saturated pixel: its colour is clipped at 1
    alpha = torch.full((3, 4), 0.9, dtype=torch.float64)
    alpha[2, 3], blended[2, 3] = 0.0, 0.0  # a pixel no Gaussian reaches: not shaded, black
    normal = torch.nn.functional.normalize(
        torch.randn(3, 4, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, -2.0], dtype=torch.float64),
        dim=-1,
    ).requires_grad_(True)
    viewmat = torch.eye(4, dtype=torch.float64)
    K = torch.tensor([[4.0, 0, 2], [0, 4.0, 1.5], [0, 0, 1]], dtype=torch.float64)
    rgb, albedo = _shade(blended, alpha, normal, viewmat, K, light, fused=fused)
    assert torch.all(rgb <= 0.9 + 1e-12) and rgb[0, 0].max() == 0.9  # clipped at 1, times alpha
    assert torch.all(rgb[2, 3] == 0)
    torch.testing.assert_close(albedo, blended / alpha.clamp_min(1e-6)[..., None])

    def shaded(b, n, coefficients, camera):  # the light's parameters as inputs, for gradcheck
        lit = DiffuseLight().double()
        del lit.coefficients, lit.camera
        lit.coefficients, lit.camera = coefficients, camera
        return _shade(b, alpha, n, viewmat, K, lit, fused=fused)[0]

    inputs = (
        blended.clone().requires_grad_(True),
        normal,
        light.coefficients.detach().clone().requires_grad_(True),
        light.camera.detach().clone().requires_grad_(True),
    )
    assert torch.autograd.gradcheck(shaded, inputs)


@pytest.mark.parametrize("lit", [True, False], ids=["lit", "unlit"])
def test_fused_shading_matches_the_torch_reference_with_its_gradients(lit):
    """The numba shading (:mod:`.fused_shading`) against the torch reference in float64: values and the gradients
    of every input (blended albedo, alpha, normals, light), with a pixel no Gaussian reaches, one under the alpha
    floor and a saturated one; unlit (before ``lit_start_iter``) the albedo clipped at 1."""
    g = torch.Generator().manual_seed(5)
    h, w = 9, 11
    alpha = torch.rand(h, w, generator=g, dtype=torch.float64)
    alpha[:, 0] = 0.0  # nothing drawn
    alpha[1, 1] = 1e-7  # drawn, under the floor the colours are divided by
    blended = torch.rand(h, w, 3, generator=g, dtype=torch.float64) * alpha[..., None]
    blended[2, 2] = 3.0 * alpha[2, 2]  # saturates
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = torch.tensor(Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix())
    K = torch.tensor([[9.0, 0, 5.5], [0, 9.0, 4.5], [0, 0, 1]], dtype=torch.float64)
    normal = torch.nn.functional.normalize(
        torch.randn(h, w, 3, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0, -1.5], dtype=torch.float64),
        dim=-1,
    )
    light = DiffuseLight().double()
    with torch.no_grad():
        light.coefficients.add_(0.5 * torch.randn(9, 3, generator=g, dtype=torch.float64))
        light.camera.normal_(0.0, 0.3, generator=g)
    inputs = [blended.requires_grad_(True), alpha.requires_grad_(True)]
    inputs += [normal.requires_grad_(True), light.coefficients, light.camera] if lit else []  # (unlit: no normals)
    weights = torch.randn(2, h, w, 3, generator=g, dtype=torch.float64)
    results = []
    for fused in (True, False):
        rgb, albedo = _shade(blended, alpha, normal, viewmat, K, light if lit else None, fused=fused)
        loss = (rgb * weights[0]).sum() + (albedo * weights[1]).sum()
        results.append((rgb, albedo, *torch.autograd.grad(loss, inputs)))
    assert results[1][0][2, 2].max() == alpha[2, 2]  # the reference clips the saturated pixel
    for got, expected in zip(*results):
        torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)


def test_fused_shading_in_float32_follows_torch_at_the_alpha_floor_and_survives_nan():
    """Training runs in float32: alpha exactly at float32(1e-6) passes its gradient as torch's clamp_min in float32
    does; a NaN normal gives a NaN pixel and leaves the others finite."""
    g = torch.Generator().manual_seed(6)
    h, w = 5, 6
    alpha = torch.rand(h, w, generator=g)
    alpha[1, 2] = 1e-6  # the floor itself, in float32
    blended = (torch.rand(h, w, 3, generator=g) * alpha[..., None]).requires_grad_(True)
    alpha.requires_grad_(True)
    normal = torch.nn.functional.normalize(torch.randn(h, w, 3, generator=g) - torch.tensor([0.0, 0.0, 2.0]), dim=-1)
    K = torch.tensor([[6.0, 0, 3.0], [0, 6.0, 2.5], [0, 0, 1]])
    light = DiffuseLight()
    weights = torch.randn(2, h, w, 3, generator=g)
    grads = []
    for fused in (True, False):
        rgb, albedo = _shade(blended, alpha, normal, torch.eye(4), K, light, fused=fused)
        grads.append(torch.autograd.grad((rgb * weights[0]).sum() + (albedo * weights[1]).sum(), alpha)[0])
    assert grads[1][1, 2] != 0
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-3 * grads[1].abs().max().item())
    normal[3, 3] = float("nan")
    rgb, _ = _shade(blended.detach(), alpha.detach(), normal, torch.eye(4), K, light)
    assert torch.isnan(rgb[3, 3]).all() and torch.isfinite(rgb[torch.arange(h) != 3]).all()


def test_equirect_directions_are_unit_with_the_zenith_on_top_and_azimuth_from_minus_180_degrees():
    directions = equirect_directions(8)  # [8, 16, 3]
    torch.testing.assert_close(directions.norm(dim=-1), torch.ones(8, 16, dtype=torch.float64))
    assert (directions[0, :, 2] > 0.98).all() and (directions[-1, :, 2] < -0.98).all()  # zenith row, nadir row
    azimuth = torch.atan2(directions[4, :, 1], directions[4, :, 0])
    torch.testing.assert_close(azimuth[0], torch.tensor(-math.pi + math.pi / 16, dtype=torch.float64))
    assert (azimuth.diff() > 0).all()


def test_the_light_picture_has_the_zenith_at_the_top(tmp_path):
    """light.png, equirectangular: a light from above (the z band of its SH) brightens the top rows."""
    light = DiffuseLight()
    with torch.no_grad():
        light.coefficients[2] = 1.5  # band 1, z: more irradiance on normals pointing up
    save_light(light, tmp_path / "light.png")
    image = cv2.imread(str(tmp_path / "light.png"), cv2.IMREAD_GRAYSCALE).astype(float)
    assert image.shape == (128, 256)
    assert image[:8].mean() > image[-8:].mean() + 20
    assert np.ptp(image[:, 100]) > 20 and np.ptp(image[60]) < 2  # varies with elevation, not along the equator


@pytest.mark.parametrize("fused", [True, False], ids=["numba", "torch"])
def test_albedo_smoothness_is_zero_on_a_uniform_albedo_and_counts_only_pairs_inside(fused):
    albedo = torch.full((6, 8, 3), 0.4)
    inside = torch.zeros(6, 8, dtype=torch.bool)
    inside[1:5, 2:7] = True
    assert losses.albedo_smoothness_loss(albedo, inside, fused=fused).item() == 0.0
    albedo[:, :, 0] = torch.arange(8.0)[None, :] * 0.1  # a ramp across: 0.1 per pixel step in one channel
    albedo[0, 0] = 9.0  # outside the silhouette: ignored
    pairs_across, pairs_down = 4 * 4, 3 * 5
    expected = 0.1 * pairs_across / (pairs_across + pairs_down)
    assert abs(losses.albedo_smoothness_loss(albedo, inside, fused=fused).item() - expected) < 1e-6
    assert losses.albedo_smoothness_loss(albedo, torch.zeros_like(inside), fused=fused).item() == 0.0


@pytest.mark.parametrize("weighted", [True, False], ids=["pair-weights", "unweighted"])
def test_fused_albedo_smoothness_matches_the_torch_reference_with_its_gradient(weighted):
    g = torch.Generator().manual_seed(4)
    albedo = torch.rand(10, 13, 3, generator=g, dtype=torch.float64)
    albedo[4, 5] = albedo[4, 6]  # equal neighbours: |0| passes gradient 0, as torch's abs
    albedo.requires_grad_(True)
    inside = torch.rand(10, 13, generator=g) > 0.3
    inside[4, 5] = inside[4, 6] = True  # ... and a pair that counts
    weights = (
        losses.image_pair_weights(torch.rand(10, 13, 3, generator=g, dtype=torch.float64), 3.0) if weighted else None
    )
    results = []
    for fused in (True, False):
        loss = losses.albedo_smoothness_loss(albedo, inside, weights, fused=fused)
        results.append((loss, *torch.autograd.grad(loss, albedo)))
    for got, expected in zip(*results):
        torch.testing.assert_close(got, expected, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("fused", [True, False], ids=["numba", "torch"])
def test_edge_weighted_albedo_smoothness_leaves_a_textures_edge_and_flattens_shading(fused):
    """With the image's pair weights, an albedo step where the image steps too (a texture's edge) costs almost
    nothing, while the same step under a smooth image (shading painted into the albedo) costs what it does
    unweighted."""
    image = torch.full((8, 10, 3), 0.3)
    image[:, 5:] = 0.9  # a texture's edge between columns 4 and 5
    albedo = image.clone()
    inside = torch.ones(8, 10, dtype=torch.bool)
    unweighted = losses.albedo_smoothness_loss(albedo, inside, fused=fused).item()
    edge = losses.albedo_smoothness_loss(albedo, inside, losses.image_pair_weights(image, 10.0), fused=fused).item()
    shading = torch.linspace(0.3, 0.5, 10)[None, :, None].expand(8, 10, 3)  # a smooth image: weights near 1
    painted = losses.albedo_smoothness_loss(
        albedo, inside, losses.image_pair_weights(shading, 10.0), fused=fused
    ).item()
    assert unweighted > 0.1 and edge < 0.01 * unweighted and painted > 0.75 * unweighted
