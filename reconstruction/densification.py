"""Adaptive density control of Kerbl et al. (clone, split, prune, opacity reset) as a strategy object.

Like gsplat's ``DefaultStrategy``: the trainer calls :meth:`DensifyStrategy.step_pre_backward`
before ``loss.backward()`` (to keep the gradient of the 2D means) and
:meth:`DensifyStrategy.step_post_backward` after it. Gaussians whose mean
view-space gradient exceeds ``grad_threshold`` grow: small ones (max scale
<= ``clone_max_scale`` x scene scale) are cloned, large ones are split into
two children sampled from the parent's Gaussian with scales divided by
``split_scale_divisor``. Gaussians with opacity < ``prune_opacity`` (and, after
the first opacity reset, those larger than ``prune_max_scale`` x scene scale)
are removed. Every ``reset_every`` steps opacities are clamped down to
``2 x prune_opacity``. Children inherit ``from_touch``; each optimizer's Adam
moments follow their Gaussians (zeros for new ones).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

from tacsplat.reconstruction.gaussians import Gaussians, quats_to_rotmats


@dataclass
class DensifyState:
    """Running statistics between refinements."""

    scene_scale: float
    grad2d: torch.Tensor  # [N] summed norms of the normalised 2D mean gradients
    count: torch.Tensor  # [N] number of views in which each Gaussian was visible
    history: list = field(default_factory=list)  # (step, cloned, split, pruned) per refinement


@dataclass
class DensifyStrategy:
    """Named thresholds and schedule (defaults scaled for short CPU runs; Kerbl et al. use 500/15000/3000)."""

    grad_threshold: float = 0.0002
    """mean |d loss / d means2d| in NDC units that triggers growth"""
    clone_max_scale: float = 0.01
    """x scene scale: at most this large -> clone, larger -> split"""
    split_scale_divisor: float = 1.6
    """children of a split get the parent's scales divided by this"""
    prune_opacity: float = 0.005
    """opacity below which a Gaussian is removed"""
    prune_max_scale: float = 0.1
    """x scene scale: larger Gaussians are removed after the first reset"""
    start_iter: int = 100
    """first refinement step"""
    stop_iter: int = 1200
    """no refinement from this step on"""
    refine_every: int = 100
    """steps between refinements"""
    reset_every: int = 1000
    """steps between opacity resets"""
    pause_after_reset: int = 0
    """no refinement for this many steps after a reset"""
    max_gaussians: int = 30_000
    """growth stops at this count (keeps CPU iterations fast)"""

    def initialize_state(self, num_gaussians: int, scene_scale: float, device=None) -> DensifyState:
        return DensifyState(
            scene_scale, torch.zeros(num_gaussians, device=device), torch.zeros(num_gaussians, device=device)
        )

    def step_pre_backward(self, meta: dict) -> None:
        """Ask autograd to keep ``meta["means2d"].grad``."""
        meta["means2d"].retain_grad()

    def step_post_backward(
        self,
        gaussians: Gaussians,
        optimizers: dict[str, torch.optim.Optimizer],
        state: DensifyState,
        step: int,
        meta: dict,
        generator: torch.Generator | None = None,
    ) -> bool:
        """Accumulate gradient statistics and refine on schedule; True when the Gaussians changed."""
        if step >= self.stop_iter:
            return False
        self._accumulate(state, meta)
        changed = False
        refine_now = step > self.start_iter and step % self.refine_every == 0
        if refine_now and step % self.reset_every >= self.pause_after_reset:
            cloned, split = self.grow(gaussians, optimizers, state, generator)
            pruned = self.prune(gaussians, optimizers, state, step)
            state.history.append((step, cloned, split, pruned))
            state.grad2d = torch.zeros(len(gaussians), device=gaussians.means.device)
            state.count = torch.zeros(len(gaussians), device=gaussians.means.device)
            changed = True
        if step > 0 and step % self.reset_every == 0:
            reset_opacities(gaussians, optimizers, 2.0 * self.prune_opacity)
        return changed

    def _accumulate(self, state: DensifyState, meta: dict) -> None:
        grads = meta["means2d"].grad  # [C, N, 2] in pixels
        if grads is None:
            return
        grads = grads.detach().clone()
        grads[..., 0] *= meta["width"] / 2.0 * meta["n_cameras"]
        grads[..., 1] *= meta["height"] / 2.0 * meta["n_cameras"]
        visible = (meta["radii"] > 0).all(dim=-1)  # [C, N]
        state.grad2d += (grads.norm(dim=-1) * visible).sum(dim=0)
        state.count += visible.sum(dim=0).float()

    def grow(
        self, gaussians: Gaussians, optimizers: dict, state: DensifyState, generator: torch.Generator | None = None
    ) -> tuple[int, int]:
        """Clone small and split large Gaussians with high mean 2D gradient; returns (cloned, split)."""
        mean_grad = state.grad2d / state.count.clamp_min(1)
        high = mean_grad > self.grad_threshold
        budget = max(self.max_gaussians - len(gaussians), 0)
        if int(high.sum()) > budget:  # keep the steepest within the budget
            keep = torch.argsort(mean_grad, descending=True)[:budget]
            high = torch.zeros_like(high)
            high[keep] = True
        small = gaussians.scales.detach().max(dim=-1).values <= self.clone_max_scale * state.scene_scale
        clone_mask = high & small
        split_mask = high & ~small
        n_clone, n_split = int(clone_mask.sum()), int(split_mask.sum())
        if n_clone:
            duplicate(gaussians, optimizers, clone_mask)
            split_mask = torch.cat([split_mask, torch.zeros(n_clone, dtype=torch.bool, device=split_mask.device)])
        if n_split:
            split(gaussians, optimizers, split_mask, self.split_scale_divisor, generator)
        return n_clone, n_split

    def prune(self, gaussians: Gaussians, optimizers: dict, state: DensifyState, step: int) -> int:
        """Remove transparent Gaussians (and, after the first reset, oversized ones); returns how many."""
        doomed = gaussians.opacities.detach() < self.prune_opacity
        if step > self.reset_every:
            doomed |= gaussians.scales.detach().max(dim=-1).values > self.prune_max_scale * state.scene_scale
        n = int(doomed.sum())
        if n:
            remove(gaussians, optimizers, doomed)
        return n


def _rebuild(
    gaussians: Gaussians,
    optimizers: dict[str, torch.optim.Optimizer],
    new_param: Callable[[str, torch.Tensor], torch.Tensor],
    new_moment: Callable[[torch.Tensor], torch.Tensor],
    names: tuple[str, ...] | None = None,  # None: every parameter
) -> None:
    """Replace each named parameter by ``new_param(name, old)`` and its Adam moments by ``new_moment(old)``."""
    for name in tuple(gaussians.params) if names is None else names:
        old = gaussians.params[name]
        param = torch.nn.Parameter(new_param(name, old.detach()).contiguous())
        if (optimizer := optimizers.get(name)) is not None:
            moments = optimizer.state.pop(old, {})
            for key, value in moments.items():
                if key != "step" and torch.is_tensor(value) and value.shape == old.shape:
                    moments[key] = new_moment(value)
            optimizer.param_groups[0]["params"] = [param]
            if moments:
                optimizer.state[param] = moments
        gaussians.params[name] = param


def _append_zeros(moment: torch.Tensor, n: int) -> torch.Tensor:
    """``moment`` followed by ``n`` zero rows (the Adam moments of new Gaussians)."""
    return torch.cat([moment, moment.new_zeros((n,) + moment.shape[1:])])


def duplicate(gaussians: Gaussians, optimizers: dict, mask: torch.Tensor) -> None:
    """Append an exact copy of each masked Gaussian (same set, zero Adam moments)."""
    n_new = int(mask.sum())
    _rebuild(gaussians, optimizers, lambda _, p: torch.cat([p, p[mask]]), lambda m: _append_zeros(m, n_new))
    gaussians.from_touch = torch.cat([gaussians.from_touch, gaussians.from_touch[mask]])


def split(
    gaussians: Gaussians,
    optimizers: dict,
    mask: torch.Tensor,
    scale_divisor: float = 1.6,
    generator: torch.Generator | None = None,
) -> None:
    """Replace each masked Gaussian by two children drawn from it, with scales / ``scale_divisor``."""
    n_split = int(mask.sum())
    keep = ~mask
    scales = gaussians.scales.detach()[mask]  # [S, 3]
    rotations = quats_to_rotmats(gaussians.quats.detach()[mask])  # [S, 3, 3]
    noise = torch.randn((2, n_split, 3), generator=generator, device=scales.device) * scales
    offsets = torch.einsum("sij,ksj->ksi", rotations, noise).reshape(2 * n_split, 3)

    def child(name: str, p: torch.Tensor) -> torch.Tensor:
        parents = p[mask].repeat((2,) + (1,) * (p.ndim - 1))
        if name == "means":
            parents = parents + offsets
        elif name == "scales":
            parents = parents - math.log(scale_divisor)
        return torch.cat([p[keep], parents])

    _rebuild(gaussians, optimizers, child, lambda m: _append_zeros(m[keep], 2 * n_split))
    gaussians.from_touch = torch.cat([gaussians.from_touch[keep], gaussians.from_touch[mask].repeat(2)])


def remove(gaussians: Gaussians, optimizers: dict, mask: torch.Tensor) -> None:
    """Delete the masked Gaussians."""
    keep = ~mask
    _rebuild(gaussians, optimizers, lambda _, p: p[keep], lambda m: m[keep])
    gaussians.from_touch = gaussians.from_touch[keep]


def reset_opacities(gaussians: Gaussians, optimizers: dict, max_opacity: float) -> None:
    """Clamp opacities to at most ``max_opacity`` and zero their Adam moments."""
    cap = math.log(max_opacity / (1.0 - max_opacity))
    _rebuild(gaussians, optimizers, lambda _, p: p.clamp_max(cap), torch.zeros_like, names=("opacities",))
