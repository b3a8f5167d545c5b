"""Densification clones, splits and prunes exactly the Gaussians its rules name, keeping from_touch."""

import math

import pytest
import torch

from tacsplat.reconstruction.densification import DensifyStrategy, duplicate, reset_opacities
from tacsplat.reconstruction.gaussians import Gaussians

SCENE_SCALE = 1.0


def _logit(p):
    return math.log(p / (1 - p))


def _four_gaussians() -> Gaussians:
    """0: small, high grad (clone). 1: large, high grad (split). 2: transparent (prune). 3: quiet, kept."""
    params = {
        "means": torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]]),
        "quats": torch.tensor([[1.0, 0, 0, 0]] * 4),
        "scales": torch.log(torch.tensor([[0.005] * 3, [0.05, 0.02, 0.02], [0.005] * 3, [0.005] * 3])),
        "opacities": torch.tensor([_logit(0.5), _logit(0.5), _logit(0.001), _logit(0.5)]),
        "sh0": torch.arange(12, dtype=torch.float32).reshape(4, 1, 3),
        "shN": torch.zeros(4, 3, 3),
    }
    return Gaussians(params, torch.tensor([False, True, False, True]), sh_degree=1)


def _optimizers(g: Gaussians) -> dict:
    opts = {k: torch.optim.Adam([p], lr=0.01) for k, p in g.params.items()}
    loss = sum((p**2).sum() for p in g.params.values())
    loss.backward()
    for o in opts.values():
        o.step()
    return opts


def _strategy_state(strategy: DensifyStrategy, n: int):
    state = strategy.initialize_state(n, SCENE_SCALE)
    state.grad2d = torch.tensor([0.003, 0.003, 0.0, 0.00001]) * 3
    state.count = torch.tensor([3.0, 3.0, 3.0, 3.0])
    return state


def test_grow_clones_small_and_splits_large_high_gradient_gaussians_and_prune_removes_transparent():
    strategy = DensifyStrategy(grad_threshold=0.0002, clone_max_scale=0.01, prune_opacity=0.005)
    g = _four_gaussians()
    opts = _optimizers(g)
    before = {k: v.detach().clone() for k, v in g.params.items()}
    state = _strategy_state(strategy, 4)
    cloned, split = strategy.grow(g, opts, state, torch.Generator().manual_seed(0))
    assert (cloned, split) == (1, 1)
    # kept: 0, 2, 3 (order preserved), then the clone of 0, then the two children of 1
    assert len(g) == 6
    means = g.means.detach()
    assert torch.equal(means[0], means[3])  # the clone is an exact copy
    children_scales = g.scales.detach()[4:]
    torch.testing.assert_close(children_scales, torch.exp(before["scales"][1]).expand(2, 3) / 1.6)
    assert not torch.equal(means[4], means[5])  # children are sampled apart around the parent
    assert ((means[4:] - before["means"][1]).abs().max() < 0.2).item()
    assert g.from_touch.tolist() == [False, False, True, False, True, True]
    pruned = strategy.prune(g, opts, state, step=10)
    assert pruned == 1
    assert len(g) == 5
    assert (g.opacities.detach() > 0.1).all()
    assert g.from_touch.tolist() == [False, True, False, True, True]
    for name, opt in opts.items():  # each optimizer holds the new parameter with moments of matching shape
        (param,) = opt.param_groups[0]["params"]
        assert param is g.params[name]
        assert opt.state[param]["exp_avg"].shape == param.shape


def test_prune_of_oversized_gaussians_only_after_the_first_reset():
    strategy = DensifyStrategy(prune_max_scale=0.04, reset_every=100)
    g = _four_gaussians()
    opts = _optimizers(g)
    state = _strategy_state(strategy, 4)
    assert strategy.prune(g, opts, state, step=50) == 1  # only the transparent one
    assert strategy.prune(g, opts, state, step=150) == 1  # now the 0.05-wide one as well
    assert len(g) == 2


def test_duplicate_keeps_adam_moments_of_old_rows_and_zeros_new_ones():
    g = _four_gaussians()
    opts = _optimizers(g)
    old = opts["means"].state[g.params["means"]]["exp_avg"].clone()
    duplicate(g, opts, torch.tensor([False, True, False, False]))
    new = opts["means"].state[g.params["means"]]["exp_avg"]
    torch.testing.assert_close(new[:4], old)
    assert (new[4] == 0).all()


def test_opacity_reset_clamps_and_schedule_refines_only_on_refine_steps():
    strategy = DensifyStrategy(start_iter=10, refine_every=10, reset_every=30, stop_iter=100, prune_opacity=0.005)
    g = _four_gaussians()
    opts = _optimizers(g)
    reset_opacities(g, opts, 0.01)
    assert g.opacities.detach().max().item() == pytest.approx(0.01, rel=1e-5)

    g = _four_gaussians()
    opts = _optimizers(g)
    state = strategy.initialize_state(4, SCENE_SCALE)
    means2d = torch.zeros(1, 4, 2, requires_grad=True)
    (means2d * torch.tensor([[[0.01, 0.0]]] * 4).reshape(1, 4, 2)).sum().backward()
    meta = {
        "means2d": means2d,
        "radii": torch.ones(1, 4, 2, dtype=torch.int32),
        "width": 100,
        "height": 100,
        "n_cameras": 1,
    }
    changed = [strategy.step_post_backward(g, opts, state, step, meta) for step in range(0, 21)]
    assert [s for s, c in enumerate(changed) if c] == [20]  # > start_iter and a multiple of refine_every
    assert state.history[0][0] == 20
    # the mean normalised gradient was 0.01 * 50 = 0.5 > threshold for all: small ones cloned, large one split
    assert state.history[0][1:3] == (3, 1)
    assert strategy.step_post_backward(g, opts, state, 200, meta) is False  # after stop_iter nothing happens
