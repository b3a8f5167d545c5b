"""The numba ``cpu`` backend against the PyTorch reference, plus numerical-safety cases for both."""

from __future__ import annotations

import math

import pytest
import torch

from tacsplat.apps.bench_rasterizer import random_scene
from tacsplat.reconstruction.raster import rasterization
from tacsplat.reconstruction.raster.reference import MAX_ALPHA

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _assert_rel(actual, expected, rtol, what):
    """|actual - expected| <= rtol * (|expected| + max|expected|): relative to each value and to the tensor's scale."""
    scale = expected.abs().max().clamp_min(1e-12)
    err = (actual - expected).abs() - rtol * (expected.abs() + scale)
    assert err.max() <= 0, f"{what}: max error {(actual - expected).abs().max():.3g}, scale {scale:.3g}"


def _render_and_grads(scene, backend, render_mode="RGB", backgrounds=None, seed=0):
    """Render, back-propagate a fixed random projection of every output; return outputs and all gradients."""
    params = {k: scene[k].detach().clone().requires_grad_(True) for k in PARAMS}
    bg = None if backgrounds is None else backgrounds.detach().clone().requires_grad_(True)
    kwargs = {k: v for k, v in scene.items() if k not in PARAMS}
    img, alpha, meta = rasterization(**params, **kwargs, render_mode=render_mode, backgrounds=bg, backend=backend)
    meta["means2d"].retain_grad()
    g = torch.Generator().manual_seed(seed)
    loss = (img * torch.randn(img.shape, generator=g)).sum() + (alpha * torch.randn(alpha.shape, generator=g)).sum()
    loss.backward()
    grads = {k: params[k].grad for k in PARAMS}
    grads["means2d"] = meta["means2d"].grad
    if bg is not None:
        grads["backgrounds"] = bg.grad
    return img.detach(), alpha.detach(), meta, grads


CASES = [
    dict(n=400, width=64, height=48, n_cams=1, sh_degree=3, render_mode="RGB", bg=False),
    dict(n=300, width=45, height=37, n_cams=2, sh_degree=3, render_mode="RGB+ED", bg=True),
    dict(n=250, width=33, height=20, n_cams=1, sh_degree=None, render_mode="RGB+D", bg=True),
    dict(n=200, width=40, height=40, n_cams=2, sh_degree=1, render_mode="D", bg=False),
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c['n']}g-{c['width']}x{c['height']}-{c['render_mode']}")
def test_cpu_matches_reference_forward_and_gradients(case):
    scene = random_scene(
        case["n"],
        case["width"],
        case["height"],
        n_cams=case["n_cams"],
        sh_degree=case["sh_degree"],
        radius_px=(1.0, 10.0),
        seed=case["n"],
    )
    n_ch = 3
    bg = torch.rand(case["n_cams"], n_ch, generator=torch.Generator().manual_seed(5)) if case["bg"] else None
    ref = _render_and_grads(scene, "torch", case["render_mode"], bg)
    cpu = _render_and_grads(scene, "cpu", case["render_mode"], bg)
    _assert_rel(cpu[0], ref[0], 1e-5, "render_colors")
    _assert_rel(cpu[1], ref[1], 1e-5, "render_alphas")
    assert torch.equal(cpu[2]["radii"], ref[2]["radii"])
    assert ref[1].max() > 0.5  # the scene is not empty
    for name, grad in ref[3].items():
        if grad is None:  # colours do not enter a depth-only render
            assert cpu[3][name] is None and case["render_mode"] == "D" and name == "colors"
            continue
        _assert_rel(cpu[3][name], grad, 1e-4, f"d/d {name}")


def test_cpu_backward_is_deterministic():
    scene = random_scene(300, 40, 40, seed=7)
    first = _render_and_grads(scene, "cpu")[3]
    second = _render_and_grads(scene, "cpu")[3]
    for name in first:
        assert torch.equal(first[name], second[name]), name


def test_exp_caches_are_reused_only_once_their_forward_is_gone():
    """A forward's exp cache goes back to the pool when its autograd context dies, never before: a pending
    backward keeps reading its own forward's values while other renders come and go."""
    from tacsplat.reconstruction.raster import cpu_composite

    def forward(scene):
        params = {k: scene[k].detach().clone().requires_grad_(True) for k in PARAMS}
        img, alpha, _ = rasterization(**params, **{k: v for k, v in scene.items() if k not in PARAMS}, backend="cpu")
        return params, img.sum() + alpha.sum()

    scene_a, scene_b = random_scene(900, 40, 32, seed=3), random_scene(300, 40, 32, seed=4)  # b fits in a's
    params, loss = forward(scene_a)
    loss.backward()
    expected = {k: p.grad for k, p in params.items()}
    params, loss = forward(scene_a)  # its backward waits
    for _ in range(3):  # renders of another scene take and return caches meanwhile
        forward(scene_b)[1].backward()
        assert cpu_composite._FREE_CACHES, "a finished render returns its cache"
    loss.backward()
    for name, grad in expected.items():
        assert torch.equal(params[name].grad, grad), name


def test_cpu_single_gaussian_alpha_profile_is_analytic():
    means = torch.tensor([[0.0, 0.0, 2.0]])
    quats = torch.tensor([[0.3, 0.0, 0.0, 0.0]])  # unnormalised identity
    scales = torch.full((1, 3), 0.1)
    K = torch.tensor([[[50.0, 0, 20.0], [0, 50.0, 15.0], [0, 0, 1]]])
    _, alpha, _ = rasterization(
        means, quats, scales, torch.tensor([0.7]), torch.ones(1, 3), torch.eye(4)[None], K, 40, 30, backend="cpu"
    )
    var = (50.0 * 0.1 / 2.0) ** 2 + 0.3
    ys, xs = torch.meshgrid(
        torch.arange(30.0, dtype=torch.float64) + 0.5, torch.arange(40.0, dtype=torch.float64) + 0.5, indexing="ij"
    )
    expected = 0.7 * torch.exp(-0.5 * ((xs - 20) ** 2 + (ys - 15) ** 2) / var)
    expected = torch.where(expected >= 1 / 255, expected, torch.zeros_like(expected))
    torch.testing.assert_close(alpha[0, :, :, 0].double(), expected, rtol=1e-5, atol=1e-6)
    assert math.isclose(float(alpha.max()), 0.7 * math.exp(-0.25 / var), rel_tol=1e-5)


def _pathological_scene():
    """Normal Gaussians mixed with every degenerate case of the issue."""
    base = random_scene(40, 24, 18, sh_degree=2, seed=11)
    extra_means = torch.tensor(
        [
            [0.0, 0.0, -2.0],  # behind the camera
            [0.0, 0.0, 0.01],  # on the near plane: kept, as in gsplat (culled when z < near)
            [0.0, 0.0, 0.0099],  # just before it
            [0.1, 0.0, 3.0],  # scales 1e-8
            [0.0, 0.1, 3.0],  # scales 1e3: covers the whole image
            [0.2, 0.1, 3.0],  # opacity 0
            [-0.2, 0.1, 2.5],  # opacity 1
            [0.1, -0.1, 2.8],  # all-zero quaternion
            [0.0, 0.0, 1e-9],  # at the camera centre
            [-0.1, -0.1, 3.0],  # needle: 1e3 along one axis, 1e-8 across
        ]
    )
    k = len(extra_means)
    extra_quats = torch.tensor([[1.0, 0.2, 0.1, 0.0]]).repeat(k, 1)
    extra_quats[7] = 0.0
    extra_scales = torch.full((k, 3), 0.05)
    extra_scales[3] = 1e-8
    extra_scales[4] = 1e3
    extra_scales[9] = torch.tensor([1e3, 1e-8, 1e-8])
    extra_opac = torch.full((k,), 0.6)
    extra_opac[5] = 0.0
    extra_opac[6] = 1.0
    extra_colors = torch.randn(k, 9, 3, generator=torch.Generator().manual_seed(3)) * 0.3
    scene = dict(base)
    for name, extra in zip(PARAMS, (extra_means, extra_quats, extra_scales, extra_opac, extra_colors)):
        scene[name] = torch.cat([base[name], extra])
    return scene


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_degenerate_gaussians_stay_finite_and_backends_agree(backend):
    scene = _pathological_scene()
    img, alpha, meta, grads = _render_and_grads(scene, backend, "RGB+ED", torch.full((1, 3), 0.25))
    assert torch.isfinite(img).all() and torch.isfinite(alpha).all()
    for name, grad in grads.items():
        assert torch.isfinite(grad).all(), name
    radii = meta["radii"][0, 40:]
    assert (radii[[0, 2, 5, 8]] == 0).all() and (radii[1] > 0).all()
    assert (radii[4] > 0).all()  # the huge Gaussian is kept
    assert alpha.min() > 0.5  # ... and covers every pixel
    if backend == "cpu":
        # Agreement without the needle: its 2D covariance (~1e10 with a ~1e-8 minor axis) is so ill-conditioned
        # that the reference's float32 determinant is rounding noise (the fused cpu projection works in float64).
        tame = {k: (v[:-1] if k in PARAMS else v) for k, v in scene.items()}
        img, _, _, grads = _render_and_grads(tame, "cpu", "RGB+ED", torch.full((1, 3), 0.25))
        ref = _render_and_grads(tame, "torch", "RGB+ED", torch.full((1, 3), 0.25))
        _assert_rel(img, ref[0], 1e-5, "render_colors")
        for name, grad in ref[3].items():
            _assert_rel(grads[name], grad, 1e-4, f"d/d {name}")


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_singular_2d_covariance_is_culled_without_dilation(backend):
    # A flat disc seen edge-on has a rank-1 2D covariance; with eps2d=0 it must be culled, not NaN.
    means = torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0]])
    quats = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    scales = torch.tensor([[0.0, 0.1, 0.1], [0.1, 0.1, 0.1]])
    K = torch.tensor([[[30.0, 0, 8.0], [0, 30.0, 8.0], [0, 0, 1]]])
    _, alpha, meta = rasterization(
        means,
        quats,
        scales,
        torch.tensor([0.9, 0.9]),
        torch.ones(2, 3),
        torch.eye(4)[None],
        K,
        16,
        16,
        eps2d=0.0,
        backend=backend,
    )
    assert meta["radii"][0, 0].tolist() == [0, 0] and (meta["radii"][0, 1] > 0).all()
    assert torch.isfinite(alpha).all() and alpha.max() > 0.5


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("size", [(1, 9), (9, 1), (1, 1)])
def test_one_pixel_wide_images(backend, size):
    width, height = size
    scene = random_scene(30, width, height, sh_degree=0, radius_px=(1.0, 3.0), seed=4)
    img, alpha, _, grads = _render_and_grads(scene, backend)
    assert img.shape == (1, height, width, 3) and alpha.shape == (1, height, width, 1)
    assert alpha.max() > 0 and all(torch.isfinite(g).all() for g in grads.values())


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_empty_scenes_render_the_background(backend):
    bg = torch.tensor([[0.1, 0.2, 0.3]])
    empty = random_scene(0, 12, 10, seed=0)
    img, alpha, meta = rasterization(**empty, backgrounds=bg, backend=backend)
    assert (alpha == 0).all() and torch.equal(img[0], bg[0].expand(10, 12, 3))
    assert meta["means2d"].shape == (1, 0, 2)
    behind = random_scene(20, 12, 10, seed=0)
    behind["means"] = behind["means"] * torch.tensor([1.0, 1.0, -1.0])
    img, alpha, _, grads = _render_and_grads(behind, backend, backgrounds=bg)
    assert (alpha == 0).all() and torch.allclose(img[0], bg[0].expand(10, 12, 3))
    # no Gaussian reaches a pixel: gradients are zero (or absent where autograd saw no path)
    assert all(g is None or bool((g == 0).all()) for name, g in grads.items() if name != "backgrounds")
    weights = torch.randn(1, 10, 12, 3, generator=torch.Generator().manual_seed(0))  # as in _render_and_grads
    torch.testing.assert_close(grads["backgrounds"], weights.sum(dim=(1, 2)))


def test_cpu_falls_back_to_torch_projection_for_antialiasing_and_camera_gradients():
    scene = random_scene(120, 32, 24, n_cams=2, sh_degree=1, seed=9)
    ref, _, _ = rasterization(**scene, rasterize_mode="antialiased", backend="torch")
    img, _, _ = rasterization(**scene, rasterize_mode="antialiased", backend="cpu")
    _assert_rel(img, ref, 1e-5, "antialiased render")
    grads = {}
    for backend in ("torch", "cpu"):
        viewmats = scene["viewmats"].clone().requires_grad_(True)
        img, _, _ = rasterization(**dict(scene, viewmats=viewmats), backend=backend)
        (img * torch.linspace(-1, 1, img.numel()).reshape(img.shape)).sum().backward()
        grads[backend] = viewmats.grad
    _assert_rel(grads["cpu"], grads["torch"], 1e-4, "d/d viewmats")


def test_parallel_binning_matches_the_reference_tile_lists():
    # enough Gaussians for several chunks of the parallel counting sort, two cameras
    from tacsplat.reconstruction.raster.cpu_composite import bin_gaussians
    from tacsplat.reconstruction.raster.reference import project_gaussians, tile_intersections

    scene = random_scene(20000, 64, 48, n_cams=2, sh_degree=0, seed=12)
    proj = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["viewmats"], scene["Ks"], 64, 48
    )
    tile_start, tile_gauss, offsets, isect = bin_gaussians(
        proj.means2d.reshape(-1, 2).numpy(),
        proj.radii.reshape(-1, 2).double().numpy(),
        proj.depths.reshape(-1).numpy(),
        2,
        20000,
        64,
        48,
        16,
    )
    tiles_per_cam = 4 * 3
    assert tile_start.shape == (2 * tiles_per_cam + 1,)
    for cam in range(2):
        tile_ids, gauss_ids = tile_intersections(proj.means2d[cam], proj.radii[cam], proj.depths[cam], 64, 48, 16)
        lo, hi = tile_start[cam * tiles_per_cam], tile_start[(cam + 1) * tiles_per_cam]
        assert (tile_gauss[lo:hi] - cam * 20000).tolist() == gauss_ids.tolist()
        counts = torch.bincount(tile_ids, minlength=tiles_per_cam)
        assert (
            torch.from_numpy(tile_start[cam * tiles_per_cam : (cam + 1) * tiles_per_cam + 1]).diff() == counts
        ).all()
    # every Gaussian finds its own intersections
    owners = torch.repeat_interleave(torch.arange(40000), torch.from_numpy(offsets).diff())
    assert (torch.from_numpy(tile_gauss[isect]) == owners).all()


def test_depth_order_is_by_depth_then_index_and_skips_gaussians_without_tiles():
    # the binning's radix sort against numpy's lexsort, with many equal depths (ties keep the index order)
    import numpy as np

    from tacsplat.reconstruction.raster import cpu_composite as rc

    rng = np.random.default_rng(3)
    depths = rng.choice(np.float32([0.01, 0.5, 1.0, 2.5, 1e3, 3e38]), size=5000).astype(np.float32)
    depths[::7] = rng.random(len(depths[::7])).astype(np.float32) + 0.1
    counts = (rng.random(5000) > 0.2).astype(np.int64)
    order = rc._depth_order(depths.view(np.int32), counts)
    visible = np.flatnonzero(counts)
    expected = visible[np.lexsort((visible, depths[visible]))]
    assert np.array_equal(order, expected)


def _cpu_forward(width, height, n, seed, radius_px=(1.0, 8.0)):
    """Project a random scene and run the cpu forward kernel directly -> (kernel args, its outputs as a dict)."""
    import numpy as np

    from tacsplat.reconstruction.raster import cpu_composite as rc
    from tacsplat.reconstruction.raster.reference import project_gaussians

    scene = random_scene(n, width, height, sh_degree=0, seed=seed, radius_px=radius_px)
    proj = project_gaussians(
        scene["means"],
        scene["quats"],
        scene["scales"],
        scene["opacities"],
        scene["viewmats"],
        scene["Ks"],
        width,
        height,
    )
    m2d, con = proj.means2d[0].numpy().copy(), proj.conics[0].numpy().copy()
    opa = proj.opacities[0].detach().numpy().copy()
    tile_start, tile_gauss, _, _ = rc.bin_gaussians(
        m2d, proj.radii[0].double().numpy(), proj.depths[0].numpy(), 1, n, width, height, 16
    )
    n_tiles, n_isect = tile_start.shape[0] - 1, tile_gauss.shape[0]
    tiles_x = math.ceil(width / 16)
    limits = (np.log(np.float32(255.0) * opa) + rc._LOG_SLACK).astype(np.float32)
    colors = np.random.default_rng(0).random((n, 3), dtype=np.float32)
    args = (
        tile_start,
        tile_gauss,
        m2d,
        con,
        opa,
        limits,
        colors,
        np.zeros((1, 3), np.float32),
        width,
        height,
        16,
        tiles_x,
        n_tiles,
        np.float32(MAX_ALPHA),
    )
    capacity = np.empty(n_isect, np.int64)
    rc._pair_capacity(tile_start, tile_gauss, m2d, con, limits, width, height, 16, tiles_x, n_tiles, capacity)
    out = {
        "cache_start": np.concatenate([[0], np.cumsum(capacity)]),
        "pair_start": np.zeros(n_isect, np.int64),
        "cached": np.empty(n_tiles, np.bool_),
        "spans": np.empty((n_isect, 16, 2), np.uint8),
        "trans": np.empty((1, height, width), np.float32),
        "last": np.empty((1, height, width), np.int64),
    }
    out["vis_cache"] = np.empty(int(out["cache_start"][-1]), np.float32)
    outputs = (
        np.empty((1, height, width, 3), np.float32),
        out["trans"],
        out["last"],
        np.empty((1, height, width), np.float32),
        np.empty(n_tiles, np.int64),
    )
    cache = (out["cache_start"], out["vis_cache"], out["pair_start"], out["cached"], out["spans"])
    rc._forward(*args, proj.depths[0].numpy(), *outputs, *cache, (0, 1, 2))
    return args, out


def test_forward_exp_recurrence_matches_float64_exp():
    # along a row the forward multiplies exp(-exponent) by a ratio instead of calling exp per pixel: every value it
    # keeps for the backward is exp(-exponent) evaluated in float64 and rounded to float32, on rows up to a tile

    from tacsplat.reconstruction.raster import cpu_composite as rc

    args, out = _cpu_forward(64, 48, 60, seed=5, radius_px=(4.0, 40.0))
    tile_start, tile_gauss, m2d, con, _, limits = args[:6]
    height, tiles_x = args[9], args[11]
    checked, worst, longest = 0, 0.0, 0
    for t in range(tile_start.shape[0] - 1):
        ty, tx = divmod(t, tiles_x)
        y_lo, x_lo = 16 * ty, 16 * tx
        for k in range(tile_start[t], tile_start[t + 1]):
            g, pos = tile_gauss[k], out["pair_start"][k]
            a, b, c = (float(v) for v in con[g])
            r0, r1 = rc._row_range(con[g, 0], con[g, 1], con[g, 2], limits[g], m2d[g, 1], y_lo, min(y_lo + 16, height))
            for y in range(r0, r1):  # the rows the forward visited, their pairs stored one after the other
                x0, x1 = (x_lo + int(v) for v in out["spans"][k, y - y_lo])
                longest = max(longest, x1 - x0)
                for x in range(x0, x1):
                    kept = float(out["vis_cache"][pos])
                    pos += 1
                    if kept == 0.0:  # a pixel the pair does not count for
                        continue
                    dx, dy = float(m2d[g, 0]) - (x + 0.5), float(m2d[g, 1]) - (y + 0.5)
                    exact = math.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy))
                    worst = max(worst, abs(kept - exact) / exact)
                    checked += 1
    assert checked > 2000 and longest == 16
    assert worst < 1e-7, worst  # float32 rounding (at most 6e-8) and nothing more


def test_backward_without_the_forward_pair_cache_gives_the_same_gradients():
    # the backward reads exp(-exponent) back from the forward; a tile whose pairs did not fit recomputes them
    import numpy as np

    from tacsplat.reconstruction.raster import cpu_composite as rc

    width, height = 40, 30
    args, out = _cpu_forward(width, height, 300, seed=13)
    n_isect, n_tiles = args[1].shape[0], args[0].shape[0] - 1
    trans, last, vis_cache, pair_start, spans = (out[k] for k in ("trans", "last", "vis_cache", "pair_start", "spans"))
    assert out["cached"].all()
    v_color = np.random.default_rng(1).standard_normal((1, height, width, 3)).astype(np.float32)
    v_alpha = np.random.default_rng(2).standard_normal((1, height, width)).astype(np.float32)
    rows = {}
    for use_cache in (True, False):
        rows[use_cache] = np.empty((n_isect, rc.N_GRAD + 3), np.float32)
        cache = (vis_cache, pair_start, np.full(n_tiles, use_cache), spans)
        rc._backward(*args, trans, last, v_color, v_alpha, *cache, rows[use_cache], (0, 1, 2))
    np.testing.assert_allclose(rows[True], rows[False], rtol=1e-5, atol=1e-6 * np.abs(rows[False]).max())
    assert np.abs(rows[False]).max() > 0
