"""Baking a shaded appearance into plain SH colours (what a run's splat.ply carries)."""

import math

import torch
from scipy.spatial.transform import Rotation

from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction.baking import bake_appearance, shaded_colors, sphere_directions
from tacsplat.reconstruction.gaussians import Gaussians, num_sh_bases, rgb_to_sh0
from tacsplat.reconstruction.shading import DiffuseLight, Look, render

NORMAL = torch.tensor([0.3, -0.2, 1.0]) / math.sqrt(1.13)  # the surfel's normal (world)


def _surfel(sh_degree: int = 3) -> Gaussians:
    """One opaque surfel (5 cm across, 0.05 mm thin) at the origin whose shortest axis is NORMAL, with a
    view-dependent SH colour."""
    rotation = Rotation.align_vectors([NORMAL.numpy()], [[0.0, 0.0, 1.0]])[0]
    g = torch.Generator().manual_seed(0)
    params = {
        "means": torch.zeros(1, 3),
        "quats": torch.tensor(rotation.as_quat(scalar_first=True), dtype=torch.float32)[None],
        "scales": torch.log(torch.tensor([[0.05, 0.05, 5e-5]])),
        "opacities": torch.full((1,), 8.0),
        "sh0": rgb_to_sh0(torch.tensor([[[0.5, 0.35, 0.2]]])),
        "shN": 0.1 * torch.randn(1, num_sh_bases(sh_degree) - 1, 3, generator=g),
    }
    return Gaussians(params, torch.zeros(1, dtype=torch.bool), sh_degree)


def _look() -> Look:
    """The sh-lit appearance with a light far from uniform (its SH and a camera light)."""
    g = torch.Generator().manual_seed(1)
    look = Look("sh-lit", DiffuseLight())
    with torch.no_grad():
        look.light.coefficients.add_(0.4 * torch.randn(9, 3, generator=g))
        look.light.camera.fill_(0.4)
    return look


def _view(direction) -> tuple[torch.Tensor, torch.Tensor]:
    """A 32 x 32 px camera 0.3 m from the surfel, looking at it from ``direction`` (world, from the surfel)."""
    eye = 0.3 * torch.nn.functional.normalize(torch.tensor(direction, dtype=torch.float32), dim=0)
    up = [0.0, 0.0, 1.0] if abs(float(eye[2])) < 0.29 else [0.0, 1.0, 0.0]
    viewmat = torch.tensor(invert_pose(look_at(eye.tolist(), [0.0, 0.0, 0.0], up=up)), dtype=torch.float32)[None]
    return viewmat, torch.tensor([[[80.0, 0, 16], [0, 80.0, 16], [0, 0, 1]]])


@torch.no_grad()
def test_a_baked_surfel_looks_as_its_shading_from_the_front_the_side_and_the_back():
    """A plain-SH render of the baked surfel is close to the deferred shading of the original from every side it
    is seen from (head-on, 60 degrees off, behind), where the unbaked SH colour is far off."""
    surfel = _surfel()
    look = _look()
    baked = bake_appearance(surfel, look)
    assert baked.sh_degree == 3 and set(baked.params) == {"means", "quats", "scales", "opacities", "sh0", "shN"}
    n = NORMAL.tolist()
    side = torch.linalg.cross(NORMAL, torch.tensor([0.0, 0.0, 1.0]))
    oblique = (0.5 * NORMAL + math.sqrt(0.75) * side / side.norm()).tolist()  # 60 degrees from the normal
    baked_total = unbaked_total = 0.0
    for direction in (n, oblique, [-c for c in n]):
        viewmat, K = _view(direction)
        shaded = render(surfel, viewmat, K, 32, 32, sh_degree=3, backend="cpu", appearance="sh-lit", light=look.light)
        plain = render(baked, viewmat, K, 32, 32, sh_degree=3, backend="cpu")
        unbaked = render(surfel, viewmat, K, 32, 32, sh_degree=3, backend="cpu")
        inside = shaded.alpha > 0.9
        assert inside.sum() > 20
        color = lambda out: out.rgb[inside] / out.alpha[inside][:, None]  # noqa: E731
        error = (color(plain) - color(shaded)).abs()
        assert error.mean() < 0.04 and error.max() < 0.07, (direction, error.mean(), error.max())
        baked_total += float(error.mean())
        unbaked_total += float((color(unbaked) - color(shaded)).abs().mean())
    # degree-3 SH cannot follow the jump where the surfel turns edge-on (its turned normal flips, and the light
    # on either side differs), which costs the few per cent above; without the bake the colours are far off
    assert baked_total < 0.25 * unbaked_total


@torch.no_grad()
def test_shaded_colors_are_the_deferred_shading_of_one_gaussian():
    """Along the ray through the surfel's centre, :func:`shaded_colors` is the colour the renderer (its fused
    shading kernels) gives the centre pixel: the same light, the normal turned towards the viewer, the SH colour
    along that ray."""
    surfel = _surfel()
    look = _look()
    eye = (0.3 * (0.8 * NORMAL + 0.6 * torch.tensor([1.0, 0.0, 0.0]))).tolist()
    viewmat = torch.tensor(invert_pose(look_at(eye, [0.0, 0.0, 0.0])), dtype=torch.float32)[None]
    K = torch.tensor([[[80.0, 0, 16], [0, 80.0, 16], [0, 0, 1]]])  # the centre maps to the corner of 4 pixels
    out = render(surfel, viewmat, K, 32, 32, sh_degree=3, backend="cpu", appearance="sh-lit", light=look.light)
    centre = (out.rgb[15:17, 15:17] / out.alpha[15:17, 15:17, None]).mean(dim=(0, 1))
    direction = -torch.nn.functional.normalize(torch.tensor(eye), dim=0)
    expected = shaded_colors(surfel, look, direction[None])[0, 0]
    torch.testing.assert_close(centre, expected, rtol=0, atol=0.01)


def test_baking_keeps_the_geometry_and_leaves_an_sh_appearance_alone():
    surfel = _surfel(sh_degree=1)
    assert bake_appearance(surfel, Look("sh")) is surfel
    baked = bake_appearance(surfel, _look())
    for name in ("means", "quats", "scales", "opacities"):
        assert torch.equal(baked.params[name], surfel.params[name])
    assert torch.equal(baked.from_touch, surfel.from_touch) and baked.params["shN"].shape == (1, 15, 3)
    assert torch.isfinite(baked.params["sh0"]).all() and torch.isfinite(baked.params["shN"]).all()


def test_no_gaussians_bake_to_no_gaussians():
    surfel = _surfel()
    look = _look()
    empty = Gaussians({k: v.detach()[:0] for k, v in surfel.params.items()}, surfel.from_touch[:0], 3)
    baked = bake_appearance(empty, look)
    assert len(baked) == 0 and baked.params["shN"].shape == (0, 15, 3)


def test_sphere_directions_are_unit_and_balanced():
    d = sphere_directions(256)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(256, dtype=torch.float64))
    assert d.mean(dim=0).abs().max() < 0.01
