"""Numerical edges of the rasterizer and the fused losses: thin Gaussians in the touch loss, argument checks of
``rasterization()``, huge Gaussians in the float32 torch projection, non-finite inputs of the fused kernels, and
training that diverges to them."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from tacsplat.cli import main
from tacsplat.errors import InvalidInputError
from tacsplat.reconstruction import losses
from tacsplat.reconstruction.fused_normals import gaussian_normals_cpu
from tacsplat.reconstruction.raster import rasterization
from tacsplat.reconstruction.raster.reference import TRANSMITTANCE_THRESHOLD
from tacsplat.reconstruction.trainer import Trainer

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import build_sphere_scene, one_error_line  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities", "colors")

# --------------------------------------------------------------------------- touch loss of thin Gaussians


def _thin_touch_scene(thin_log_scale: float):
    """Float32 Gaussians in a 1 cm cube, ten with their third log-scale at ``thin_log_scale``; touch point 0 lies
    in the plane of Gaussian 0 (identity rotation, z its thin axis: offset exactly 0 along it)."""
    g = torch.Generator().manual_seed(0)
    n, p = 40, 16
    means = torch.rand(n, 3, generator=g) * 0.01
    quats = torch.randn(n, 4, generator=g)
    quats[0] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    log_scales = torch.log(torch.rand(n, 3, generator=g) * 0.003 + 0.001)
    log_scales[:10, 2] = thin_log_scale
    logits = torch.randn(n, generator=g)
    points = torch.rand(p, 3, generator=g) * 0.01
    points[0] = means[0] + torch.tensor([0.0005, -0.0003, 0.0])
    candidates = torch.randint(0, n, (p, 8), generator=g)
    candidates[0, 0] = 0
    return points, (means, quats, log_scales, logits), candidates


def _touch_loss_and_gradients(thin_log_scale: float, dtype: torch.dtype, fused: bool):
    """L_T and its gradients by (means, quats, log-scales, opacity logits)."""
    points, params, candidates = _thin_touch_scene(thin_log_scale)
    means, quats, log_scales, logits = (t.to(dtype).requires_grad_(True) for t in params)
    loss = losses.transmittance_loss(
        points.to(dtype),
        means,
        quats,
        torch.exp(log_scales),
        torch.sigmoid(logits),
        candidates,
        top_k=4,
        max_distance=0.05,
        fused=fused,
    )
    return loss.detach(), torch.autograd.grad(loss, (means, quats, log_scales, logits))


@pytest.mark.parametrize("thin_log_scale", [-50.0, -110.0])  # 1/s^2 overflows float32; exp underflows to 0
def test_touch_loss_of_gaussians_thinner_than_the_scale_floor_is_finite_and_alike_fused_and_reference(
    thin_log_scale,
):
    """Scales are floored at MIN_SCALE in both paths: float32 fused and reference give the float64 reference's
    value and gradients (no NaN), a Gaussian seen in its plane keeps its influence, and a floored scale gets no
    gradient."""
    want_loss, want = _touch_loss_and_gradients(thin_log_scale, torch.float64, fused=False)
    assert 0.0 < want_loss.item() < 1.0
    assert want[2][0, 0] != 0 and want[2][0, 2] == 0  # in-plane axis: a gradient; the floored one: none
    for fused in (True, False):
        loss, grads = _touch_loss_and_gradients(thin_log_scale, torch.float32, fused)
        assert loss.item() == pytest.approx(want_loss.item(), abs=1e-6), fused
        for name, have, expected in zip(("means", "quats", "log_scales", "logits"), grads, want):
            assert torch.isfinite(have).all(), (fused, name)
            tol = 1e-4 * float(expected.abs().max())
            torch.testing.assert_close(have.double(), expected, rtol=0, atol=tol, msg=f"fused={fused} {name}")
        assert grads[2][:10, 2].abs().max() == 0


def test_the_influence_of_a_gaussian_seen_in_its_plane_ignores_its_floored_thickness():
    """One flat Gaussian (z scale 0) and a point in its plane: f alpha = exp(-(x^2/sx^2 + y^2/sy^2)/2) alpha."""
    means = torch.tensor([[0.01, 0.02, 0.03]])
    scales = torch.tensor([[0.002, 0.001, 0.0]])
    point = means + torch.tensor([[0.001, 0.0005, 0.0]])
    expected = 1.0 - 0.6 * math.exp(-0.5 * ((0.001 / 0.002) ** 2 + (0.0005 / 0.001) ** 2))
    for fused in (True, False):
        loss = losses.transmittance_loss(
            point,
            means,
            torch.tensor([[1.0, 0, 0, 0]]),
            scales,
            torch.tensor([0.6]),
            torch.tensor([[0]]),
            1,
            0.01,
            fused,
        )
        assert loss.item() == pytest.approx(expected, rel=1e-5), fused


# --------------------------------------------------------------------------- rasterization() arguments


def _scene(dtype=torch.float32, n: int = 6):
    g = torch.Generator().manual_seed(0)
    return dict(
        means=(torch.randn(n, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 2.0])).to(dtype),
        quats=torch.randn(n, 4, generator=g).to(dtype),
        scales=(torch.rand(n, 3, generator=g) * 0.1 + 0.02).to(dtype),
        opacities=(torch.rand(n, generator=g) * 0.5 + 0.4).to(dtype),
        colors=torch.rand(n, 1, 3, generator=g).to(dtype),
        viewmats=torch.eye(4, dtype=dtype)[None],
        Ks=torch.tensor([[[18.0, 0.0, 10.0], [0.0, 18.0, 7.0], [0.0, 0.0, 1.0]]], dtype=dtype),
        width=20,
        height=14,
        sh_degree=0,
    )


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_a_nan_infinite_or_negative_eps2d_and_a_nan_radius_clip_are_one_clear_error(backend):
    """They would cull every Gaussian (NaN, inf) or some (negative) without a word."""
    for eps2d in (float("nan"), float("inf"), -0.1):
        with pytest.raises(InvalidInputError, match="eps2d must be a finite number >= 0"):
            rasterization(**_scene(), eps2d=eps2d, backend=backend)
    with pytest.raises(InvalidInputError, match="radius_clip must be a number"):
        rasterization(**_scene(), radius_clip=float("nan"), backend=backend)
    _, alphas, _ = rasterization(**_scene(), eps2d=0.0, radius_clip=-1.0, backend=backend)  # both still allowed
    assert alphas.max() > 0.5


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_max_alpha_above_one_minus_the_transmittance_threshold_is_refused_and_the_largest_draws_opaque(backend):
    """A pixel stops before a Gaussian that would leave its transmittance at 1e-4 or less: with a larger clamp an
    opaque Gaussian would be a hole. The largest allowed clamp draws it."""
    one = dict(
        means=torch.tensor([[0.0, 0.0, 2.0]]),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        scales=torch.full((1, 3), 5.0),
        opacities=torch.tensor([1.0]),
        colors=torch.ones(1, 3),
        viewmats=torch.eye(4)[None],
        Ks=torch.tensor([[[50.0, 0, 8.0], [0, 50.0, 8.0], [0, 0, 1]]]),
        width=16,
        height=16,
    )
    with pytest.raises(InvalidInputError, match=r"max_alpha must be in \(0, 0.9999\]"):
        rasterization(**one, max_alpha=0.99995, backend=backend)
    _, alphas, _ = rasterization(**one, max_alpha=1.0 - TRANSMITTANCE_THRESHOLD, backend=backend)
    assert alphas[0, 8, 8, 0].item() == pytest.approx(1.0 - TRANSMITTANCE_THRESHOLD, abs=1e-6)  # the centre
    assert alphas.min() > 0.99


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_half_precision_inputs_are_one_clear_error(backend, dtype):
    with pytest.raises(InvalidInputError, match="means must be a float32 or float64 tensor"):
        rasterization(**_scene(dtype), backend=backend)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_finite_inputs_whose_sum_overflows_render_and_bad_ones_still_name_their_cause(backend):
    """The finiteness test sums each input: a sum past float32's range alone is no error."""
    scene = _scene()
    scene["colors"] = torch.full_like(scene["colors"], 2e38)
    _, alphas, _ = rasterization(**scene, backend=backend)
    assert alphas.max() > 0.5
    scene["colors"][0, 0, 0] = float("nan")
    with pytest.raises(InvalidInputError, match="colors contains NaN values"):
        rasterization(**scene, backend=backend)
    scene = _scene()
    scene["Ks"][0, 1, 1] = -18.0
    with pytest.raises(InvalidInputError, match="positive focal lengths"):
        rasterization(**scene, backend=backend)


# --------------------------------------------------------------------------- huge Gaussians, float32 projection


def _huge_near_camera(dtype):
    """A Gaussian 1e5 m wide 2 cm in front of the camera (fx / z = 1e5: its 2D determinant ~1e40, past float32)
    and a small one in view."""
    return dict(
        means=torch.tensor([[0.0, 0.0, 0.02], [1e-4, 5e-5, 0.03]], dtype=dtype),
        quats=torch.tensor([[1.0, 0.1, 0.2, 0.3], [0.3, 0.2, -0.5, 1.0]], dtype=dtype),
        scales=torch.tensor([[1e5, 5e4, 7e4], [2e-5, 1e-5, 3e-5]], dtype=dtype),
        opacities=torch.tensor([0.5, 0.8], dtype=dtype),
        colors=torch.tensor([[0.2, 0.5, 0.9], [0.7, 0.1, 0.3]], dtype=dtype),
    )


def _render_huge(dtype, backend, rasterize_mode, cameras_need_grad=False):
    """(colours, alphas, radii, gradients by name) of a weighted sum of every output."""
    params = {k: v.requires_grad_(True) for k, v in _huge_near_camera(dtype).items()}
    viewmats = torch.eye(4, dtype=dtype)[None].requires_grad_(cameras_need_grad)
    Ks = torch.tensor([[[2000.0, 0, 20], [0, 2000.0, 15], [0, 0, 1]]], dtype=dtype)
    colors, alphas, meta = rasterization(
        *(params[k] for k in PARAMS),
        viewmats,
        Ks,
        40,
        30,
        render_mode="RGB+D",
        rasterize_mode=rasterize_mode,
        backend=backend,
    )
    weights = torch.randn(colors.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ((colors * weights.to(dtype)).sum() + alphas.sum()).backward()
    return colors.detach(), alphas.detach(), meta["radii"], {k: params[k].grad for k in PARAMS}


@pytest.mark.parametrize(
    "backend, rasterize_mode, cameras_need_grad",
    [
        ("cpu", "antialiased", False),
        ("cpu", "classic", True),
        ("torch", "classic", False),
        ("torch", "antialiased", False),
    ],
)
def test_the_float32_torch_projection_draws_a_huge_gaussian_near_the_camera_as_float64_does(
    backend, rasterize_mode, cameras_need_grad
):
    """The cpu backend projects in torch in antialiased mode or when the cameras need gradients: the same image and
    float64 gradients as the float64 reference, where float32 determinants overflowed and culled the Gaussian."""
    want_colors, want_alphas, want_radii, want = _render_huge(torch.float64, "torch", rasterize_mode)
    assert (want_radii[0, 0] > 0).all() and want_alphas.min() > 0.4
    colors, alphas, radii, grads = _render_huge(torch.float32, backend, rasterize_mode, cameras_need_grad)
    assert torch.equal(radii, want_radii)
    torch.testing.assert_close(alphas.double(), want_alphas, rtol=0, atol=1e-6)
    torch.testing.assert_close(colors.double(), want_colors, rtol=0, atol=1e-5)
    for name in PARAMS:
        tol = 1e-4 * float(want[name].abs().max())
        torch.testing.assert_close(grads[name].double(), want[name], rtol=0, atol=tol, msg=name)


def test_the_cpu_backend_draws_a_huge_gaussian_alike_whether_or_not_the_cameras_need_gradients():
    """Its own float64 projection and the torch projection it uses for camera gradients agree."""
    own = _render_huge(torch.float32, "cpu", "classic")
    torch_projection = _render_huge(torch.float32, "cpu", "classic", cameras_need_grad=True)
    assert torch.equal(own[2], torch_projection[2])
    torch.testing.assert_close(torch_projection[1], own[1], rtol=0, atol=1e-6)
    torch.testing.assert_close(torch_projection[0], own[0], rtol=0, atol=1e-5)


# --------------------------------------------------------------------------- non-finite inputs of fused kernels


@pytest.mark.parametrize("name", ["touch_points", "means", "quats", "scales", "opacities"])
def test_the_fused_touch_loss_names_a_non_finite_input_where_the_reference_gives_nan(name):
    """The kernel's comparisons would skip a NaN pair silently (a finite loss, finite gradients)."""
    points, (means, quats, log_scales, logits), candidates = _thin_touch_scene(math.log(0.002))
    inputs = dict(
        touch_points=points, means=means, quats=quats, scales=torch.exp(log_scales), opacities=torch.sigmoid(logits)
    )
    inputs[name] = inputs[name].clone()
    inputs[name].view(-1)[3] = float("nan") if name != "scales" else float("inf")
    with pytest.raises(InvalidInputError, match=f"transmittance_loss: {name} contains NaN or infinite values"):
        losses.transmittance_loss(*inputs.values(), candidates, top_k=4, max_distance=0.05)
    if name == "means":  # the review's case: the reference's gradient is NaN
        means = inputs["means"].requires_grad_(True)
        reference = losses.transmittance_loss(*inputs.values(), candidates, top_k=4, max_distance=0.05, fused=False)
        assert not torch.isfinite(torch.autograd.grad(reference, means)[0]).all()


@pytest.mark.parametrize("name", ["rendered", "depth", "weight"])
def test_the_fused_depth_normal_consistency_names_a_non_finite_input(name):
    """A NaN depth read as a pixel behind the camera (skipped); the reference's loss is NaN."""
    g = torch.Generator().manual_seed(0)
    inputs = dict(
        rendered=torch.nn.functional.normalize(torch.randn(20, 24, 3, generator=g), dim=-1),
        depth=1.0 + torch.rand(20, 24, generator=g),
        K=torch.tensor([[20.0, 0, 12], [0, 20.0, 10], [0, 0, 1]]),
        weight=torch.ones(20, 24),
    )
    inputs[name].view(-1)[130] = float("nan")
    with pytest.raises(InvalidInputError, match=f"depth_normal_consistency: {name} contains NaN or infinite"):
        losses.depth_normal_consistency(*inputs.values())
    assert math.isnan(losses.depth_normal_consistency(*inputs.values(), fused=False).item())


def test_the_fused_gaussian_normals_name_a_non_finite_scale_and_accept_finite_ones_summing_past_float32():
    """A NaN scale is never the smallest to the kernel (a silent choice of axis)."""
    g = torch.Generator().manual_seed(0)
    quats, scales = torch.randn(8, 4, generator=g), torch.rand(8, 3, generator=g)
    scales[2, 1] = float("nan")
    with pytest.raises(InvalidInputError, match="gaussian_normals: scales contains NaN or infinite values"):
        gaussian_normals_cpu(quats, scales)
    huge = torch.full((8, 3), 3e38)
    huge[:, 1] = 1.0
    normals = gaussian_normals_cpu(quats, huge)  # the sum is infinite, every entry finite
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(8))


# --------------------------------------------------------------------------- training that diverges

TINY_RUN = ["--sh-degree", "0", "--lambda-s", "0", "--init.no-use-sfm", "--init.num-random-points", "200", "--quiet"]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    return build_sphere_scene(tmp_path_factory.mktemp("scenes") / "sphere", size=16, train_views=3, test_views=1)


@pytest.mark.parametrize(
    "backend, iterations",
    [("cpu", 4), ("torch", 4), ("cpu", 1)],  # the next step's render meets the infinite scales; no step does
)
def test_training_with_an_absurd_learning_rate_ends_with_one_error_naming_the_step_and_what_to_lower(
    tiny_scene, tmp_path, capsys, backend, iterations
):
    """A log-scale rate of 1000 overflows the scales in the first step: one error line says that training diverged
    there and names the learning rates, exit 1, and nothing of the diverged state is saved."""
    run = tmp_path / "run"
    argv = ["reconstruct", str(tiny_scene), "--out", str(run), "--iterations", str(iterations), "--lr-scales", "1e3"]
    assert main([*argv, "--backend", backend, *TINY_RUN]) == 1
    one_error_line(capsys, "training diverged at step 1", "scales", "--lr-*")
    assert not (run / "checkpoint.pt").exists() and not (run / "splat.ply").exists()


@pytest.mark.parametrize("iterations", [4, 3])  # the next step's render meets the NaN; no step does
def test_a_diverged_state_never_replaces_the_last_good_checkpoint(
    tiny_scene, tmp_path, capsys, monkeypatch, iterations
):
    """An update that turns a colour NaN after step 3 (of a run checkpointed every 2 steps): the error names step 3
    and the colours, and the checkpoint of step 2 stays."""
    real_step = Trainer.train_step

    def diverging_step(self):
        terms = real_step(self)
        if self.step == 3:
            self.gaussians.params["sh0"].data[0] = float("nan")
        return terms

    monkeypatch.setattr(Trainer, "train_step", diverging_step)
    run = tmp_path / "run"
    argv = ["reconstruct", str(tiny_scene), "--out", str(run), "--iterations", str(iterations), "--checkpoint-every"]
    assert main([*argv, "2", "--backend", "cpu", *TINY_RUN]) == 1
    one_error_line(capsys, "training diverged at step 3", "sh0")
    assert torch.load(run / "checkpoint.pt", weights_only=False)["step"] == 2
