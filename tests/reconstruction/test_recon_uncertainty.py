"""Uncertainty of a reconstruction: a hand-made sphere of Gaussians seen by cameras on one side only scores higher
on the side no view sees, for both scores, per Gaussian, per pixel and per point; a brief reconstruction is
reproducible bit for bit."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.gaussians import Gaussians, rgb_to_sh0
from tacsplat.reconstruction.uncertainty import (
    SCORES,
    Views,
    brief_reconstruction,
    depth_moments,
    gaussian_uncertainty,
    point_uncertainty,
    render_uncertainty,
)

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import CAMERA_DISTANCE, RADIUS, build_sphere_scene, sphere_gaussians  # noqa: E402

SIZE = 48
K = torch.tensor([[60.0, 0, SIZE / 2], [0, 60.0, SIZE / 2], [0, 0, 1]])


def _sphere() -> Gaussians:
    means, quats, scales, opacities, colors = (t.float() for t in sphere_gaussians(600))
    params = {
        "means": means,
        "quats": quats,
        "scales": torch.log(scales),
        "opacities": torch.logit(opacities),
        "sh0": rgb_to_sh0(colors)[:, None, :],
        "shN": torch.zeros(600, 0, 3),
    }
    return Gaussians(params, torch.zeros(600, dtype=torch.bool), sh_degree=0)


def _viewmat(direction) -> torch.Tensor:
    eye = CAMERA_DISTANCE * np.asarray(direction, float) / np.linalg.norm(direction)
    return torch.tensor(invert_pose(look_at(eye, np.zeros(3))), dtype=torch.float32)


def _views_from_plus_x() -> Views:
    """Four cameras, all on the +x side of the sphere: its -x side is seen by none."""
    directions = [(1, 0, 0.3), (0.8, 0.6, 0.1), (0.8, -0.6, 0.1), (0.9, 0, -0.4)]
    viewmats = torch.stack([_viewmat(d) for d in directions])
    return Views(viewmats, K.expand(4, 3, 3).clone(), SIZE, SIZE, torch.full((4, SIZE, SIZE, 3), 0.2))


@pytest.mark.parametrize("score", SCORES)
def test_a_side_no_view_sees_scores_higher_than_the_side_every_view_sees(score):
    g = _sphere()
    u = gaussian_uncertainty(g, _views_from_plus_x(), score)
    assert u.shape == (600,) and bool(((u >= 0) & (u <= 1)).all())
    x = g.means[:, 0].detach()
    seen, hidden = u[x > 0.6 * RADIUS], u[x < -0.6 * RADIUS]
    assert hidden.median() > 0.9, hidden.median()  # nothing constrains them: the prior (some light leaks through)
    assert seen.median() < 0.5 and hidden.mean() > seen.mean() + 0.4, (seen.median(), hidden.mean())

    # per point on the surface, and per pixel of a camera looking at each side
    directions = torch.nn.functional.normalize(torch.randn(2000, 3, generator=torch.Generator().manual_seed(0)), dim=1)
    points = RADIUS * directions
    at_points = point_uncertainty(g, u, points)
    assert at_points[directions[:, 0] < -0.6].mean() > at_points[directions[:, 0] > 0.6].mean() + 0.4
    far_side, _, _ = render_uncertainty(g, u, _viewmat((-1, 0, 0)), K, SIZE, SIZE)
    near_side, alpha, depth = render_uncertainty(g, u, _viewmat((1, 0, 0)), K, SIZE, SIZE)
    drawn = alpha > 0.5
    assert far_side[drawn].mean() > near_side[drawn].mean() + 0.4
    assert depth[drawn].min() > CAMERA_DISTANCE - RADIUS - 0.01  # the blended depth is the front surface's


def test_points_far_from_every_gaussian_are_unknown():
    g = _sphere()
    u = torch.zeros(600)  # every Gaussian perfectly known ...
    far = torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.0, -0.4]])
    assert torch.allclose(point_uncertainty(g, u, far), torch.ones(2))  # ... but nothing is there
    assert point_uncertainty(g, u, RADIUS * torch.tensor([[1.0, 0.0, 0.0]])).item() < 0.01


def test_depth_spread_is_zero_on_one_surface_and_the_weights_spread_across_two():
    """Two half-transparent layers of Gaussians 2 cm apart, the back one behind the left half only: a ray through
    one layer has no depth spread; a ray through both has the spread of its two blending weights,
    p (1 - p) gap^2 with p the back layer's share of the alpha."""
    xy = torch.stack(
        torch.meshgrid(torch.linspace(-0.03, 0.03, 20), torch.linspace(-0.03, 0.03, 20), indexing="ij"), -1
    ).reshape(-1, 2)
    front = torch.cat([xy, torch.zeros(len(xy), 1)], 1)
    back = torch.cat([xy[xy[:, 0] < 0], torch.full((int((xy[:, 0] < 0).sum()), 1), 0.02)], 1)

    def layers(means):
        m = len(means)
        params = {
            "means": means,
            "quats": torch.tensor([1.0, 0, 0, 0]).expand(m, 4).clone(),
            "scales": torch.log(torch.tensor([0.003, 0.003, 0.0003])).expand(m, 3).clone(),
            "opacities": torch.full((m,), -2.0),
            "sh0": torch.zeros(m, 1, 3),
            "shN": torch.zeros(m, 0, 3),
        }
        return Gaussians(params, torch.zeros(m, dtype=torch.bool), 0)

    viewmat = torch.tensor(invert_pose(look_at([0, 0, -0.2], [0, 0, 0], up=(0, 1, 0))), dtype=torch.float32)
    alpha, mean, variance = depth_moments(layers(torch.cat([front, back])), viewmat, K, SIZE, SIZE)
    alpha_front, _, _ = depth_moments(layers(front), viewmat, K, SIZE, SIZE)
    cols = torch.arange(SIZE)[None, :]  # image x is world -x here: columns right of the centre see x < 0
    two_layers = (alpha_front > 0.3) & (cols > SIZE / 2 + 4) & (cols < SIZE / 2 + 14)
    one_layer = (alpha_front > 0.3) & (cols < SIZE / 2 - 4) & (cols > SIZE / 2 - 14)
    assert two_layers.sum() > 20 and one_layer.sum() > 20
    assert variance[one_layer].max() < 1e-9 and torch.allclose(mean[one_layer], torch.tensor(0.2), atol=1e-4)
    p = ((alpha - alpha_front) / alpha)[two_layers]
    assert p.min() > 0.1  # the back layer carries real weight
    assert torch.allclose(variance[two_layers], p * (1 - p) * 0.02**2, rtol=0.05)
    assert torch.allclose(mean[two_layers], 0.2 + p * 0.02, atol=1e-4)


def test_brief_reconstruction_is_the_same_bit_for_bit(tmp_path):
    from tacsplat.datasets import Scene

    scene = Scene.load(build_sphere_scene(tmp_path / "scene", size=32, train_views=3, test_views=1))
    config = TrainConfig(iterations=6, device="cpu", seed=1)
    first, second = brief_reconstruction(scene, config), brief_reconstruction(scene, config)
    assert len(first) > 0
    for name, value in first.params.items():
        assert torch.equal(value, second.params[name]), name


def test_the_depth_tolerance_grows_to_the_median_spread_so_a_fuzzy_reconstruction_still_ranks_its_rays():
    from tacsplat.reconstruction.uncertainty import MIN_DEPTH_TOLERANCE, depth_tolerance, extent

    views = _views_from_plus_x()
    sharp = _sphere()
    assert depth_tolerance(sharp, views) == pytest.approx(MIN_DEPTH_TOLERANCE * extent(sharp))  # a crisp surface
    fuzzy = _sphere()  # the same Gaussians scattered in depth, half transparent: every ray blends many depths
    radial = torch.empty(600, 1).uniform_(0.3, 1.7, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        fuzzy.params["means"].mul_(radial)
        fuzzy.params["opacities"].fill_(0.0)
    floor = MIN_DEPTH_TOLERANCE * extent(fuzzy)
    tolerance = depth_tolerance(fuzzy, views)
    assert tolerance > 1.5 * floor
    saturated = gaussian_uncertainty(fuzzy, views, "depth-variance", tolerance_m=floor)
    ranked = gaussian_uncertainty(fuzzy, views, "depth-variance")
    seen = fuzzy.means[:, 0].detach() > 0.3 * RADIUS
    assert saturated[seen].median() > ranked[seen].median() + 0.1
    assert ranked[seen].std() > saturated[seen].std()
