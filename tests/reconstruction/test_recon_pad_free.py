"""The pads' free space (``lambda_pad_free``): the points a pad in contact proves empty, and the loss on opacity
there: a Gaussian in that space loses opacity, one on the felt surface keeps it; gradients against float64."""

import numpy as np
import pytest
import torch

from tacsplat.geometry import make_pose, tactile_free_points
from tacsplat.reconstruction.losses import TouchNeighbours, free_space_loss


def _pad_reading():
    """A 6 x 8 pad of 1 mm pixels pressed 0.5 mm deep on its middle 2 x 2 pixels, its gel facing +x in the world."""
    depth = np.zeros((6, 8), np.float32)
    depth[2:4, 3:5] = 5e-4
    R = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # sensor z (gel normal) -> world +x
    return depth, make_pose(R, [0.1, 0.0, 0.0])


def test_free_points_lie_behind_what_each_pixel_felt_by_the_margin():
    depth, T = _pad_reading()
    free = tactile_free_points(depth, 1e-3, T, 0.002)
    assert free.shape == (48, 3)
    # the object lies in +x (the gel's outward normal): felt pixels 0.5 mm behind the gel plane x = 0.1, the rest at it
    x = free[:, 0].reshape(6, 8)
    np.testing.assert_allclose(x[2:4, 3:5], 0.1 - 0.0005 - 0.002, atol=1e-12)
    np.testing.assert_allclose(np.delete(x.ravel(), [19, 20, 27, 28]), 0.1 - 0.002, atol=1e-12)
    with pytest.raises(Exception, match="NaN"):
        tactile_free_points(np.full((2, 2), np.nan), 1e-3, T, 0.002)


def _gaussians(means, opacity=0.9, scale=0.0005, dtype=torch.float64):
    n = len(means)
    return (
        torch.tensor(np.array(means), dtype=dtype),
        torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=dtype),
        torch.full((n, 3), scale, dtype=dtype),
        torch.full((n,), opacity, dtype=dtype, requires_grad=True),
    )


def test_a_gaussian_in_the_free_space_loses_opacity_and_one_on_the_felt_surface_keeps_it():
    depth, T = _pad_reading()
    free = tactile_free_points(depth, 1e-3, T, 0.002)
    inside = free[20]  # in the space the pad proves empty
    surface = inside + [0.002, 0.0, 0.0]  # on the felt surface: the margin beyond the free point
    means, quats, scales, opacities = _gaussians([inside, surface])
    neighbours = TouchNeighbours(free, 8, 0.005, 50)
    candidates = neighbours.candidates(means, torch.ones(2, dtype=torch.bool))
    points = torch.tensor(free)
    loss = free_space_loss(points, means, quats, scales, opacities, candidates, 0.005)
    loss.backward()
    grad = opacities.grad
    assert loss.item() > 0 and grad[0] > 0  # descending lowers the opacity of the one in free space ...
    assert abs(grad[1].item()) < 1e-2 * grad[0].item()  # ... and all but leaves the surface's alone (4 sigma away)


def test_free_space_gradients_match_float64_finite_differences():
    rng = np.random.default_rng(0)
    points = torch.tensor(rng.normal(0, 0.002, (5, 3)))
    means = torch.tensor(rng.normal(0, 0.002, (4, 3)), requires_grad=True)
    quats = torch.nn.functional.normalize(torch.tensor(rng.normal(size=(4, 4))), dim=1).requires_grad_()
    scales = torch.tensor(rng.uniform(0.001, 0.003, (4, 3)), requires_grad=True)
    opacities = torch.tensor(rng.uniform(0.2, 0.8, 4), requires_grad=True)
    candidates = torch.tensor([[0, 1, 2, 3, -1]] * 5)

    def f(m, q, s, o):
        return free_space_loss(points, m, q, s, o, candidates, 0.01)

    assert torch.autograd.gradcheck(f, (means, quats, scales, opacities))


def test_no_gaussian_in_reach_costs_nothing():
    means, quats, scales, opacities = _gaussians([[1.0, 1.0, 1.0]])
    candidates = torch.tensor([[0, -1]])
    points = torch.zeros((1, 3), dtype=torch.float64)
    assert free_space_loss(points, means, quats, scales, opacities, candidates, 0.005).item() == 0.0
