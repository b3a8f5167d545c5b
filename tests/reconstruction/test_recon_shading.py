"""Normals and reflections: flat Gaussians, depth-normal consistency on a plane, the environment lookup."""

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction import losses
from tacsplat.reconstruction.gaussians import Gaussians, rgb_to_sh0
from tacsplat.reconstruction.shading import EnvironmentMap, gaussian_normals, render


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
    tilted.params["quats"].data = torch.tensor(Rotation.from_euler("x", 0.6).as_quat(scalar_first=True),
                                               dtype=torch.float32).expand_as(tilted.params["quats"]).clone()
    out_t = render(tilted, viewmat, K, 48, 48, sh_degree=0, backend="cpu", depth_mode="D", normals=True)
    assert losses.normal_consistency_loss(out_t.normal, from_depth, out.alpha * drawn).item() > 0.05
    # the fused CPU pass the trainer uses agrees on both
    fused = [losses.depth_normal_consistency(o.normal, surface, K[0], out.alpha * drawn).item() for o in (out, out_t)]
    assert fused[0] < 2e-3 and fused[1] > 0.05


def test_the_environment_lookup_of_a_mirror_returns_the_maps_value():
    environment = EnvironmentMap(height=16)
    with torch.no_grad():
        environment.log_radiance.copy_(torch.log(torch.rand(3, 16, 32, generator=torch.Generator().manual_seed(0))))
    # the centre of texel (row 5, column 20): u = (20.5 / 32) * 2 - 1 (azimuth), v = (5.5 / 16) * 2 - 1 (elevation)
    azimuth, elevation = ((20.5 / 32) * 2 - 1) * math.pi, -((5.5 / 16) * 2 - 1) * math.pi / 2
    direction = torch.tensor([[math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                               math.sin(elevation)]])
    value = environment.lookup(direction, torch.zeros(1))
    torch.testing.assert_close(value[0], torch.exp(environment.log_radiance[:, 5, 20]), rtol=1e-5, atol=1e-6)
    # full roughness: the coarsest level, the two hemispheres' averages blended at the direction's azimuth
    rough = environment.lookup(direction, torch.ones(1))
    radiance = torch.exp(environment.log_radiance)
    left, right = radiance[:, :, :16].mean(dim=(1, 2)), radiance[:, :, 16:].mean(dim=(1, 2))
    weight = (20.5 / 32) * 2 - 1 + 0.5  # of the right half (texel centres at u = -0.5 and 0.5)
    torch.testing.assert_close(rough[0], weight * right + (1 - weight) * left, rtol=1e-5, atol=1e-6)


def test_the_environment_lookup_has_finite_gradients_at_the_poles_and_for_no_direction():
    """Reflected rays straight up or down (asin's infinite slope once made the trainer's means NaN) and a zero
    direction (no blended normal) give finite gradients; elsewhere the float64 gradient is the numerical one."""
    environment = EnvironmentMap(height=8).double()
    with torch.no_grad():
        environment.log_radiance.copy_(torch.randn(3, 8, 16, generator=torch.Generator().manual_seed(1)))
    awkward = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1e-9, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1e-9],
                            [-1.0, 0.0, 0.0], [-1.0, -1e-12, 0.0], [3.0, 4.0, 0.0]], dtype=torch.float64,
                           requires_grad=True)
    roughness = torch.full((len(awkward),), 0.3, dtype=torch.float64, requires_grad=True)
    environment.lookup(awkward, roughness).sum().backward()
    assert torch.isfinite(awkward.grad).all() and torch.isfinite(roughness.grad).all()
    assert torch.isfinite(environment.log_radiance.grad).all()
    generic = torch.tensor([[0.3, -0.5, 0.4], [-0.2, 0.1, -0.9]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda d: environment.lookup(d, torch.full((2,), 0.3, dtype=torch.float64)),
                                    (generic,))


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
