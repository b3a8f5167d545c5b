"""How little the views constrain a reconstruction's geometry: per Gaussian, per pixel of any camera, per point.

Two scores, each in [0, 1], 1 for geometry that no view constrains:

* ``"fisher"`` (FisherRF, Jiang et al., ECCV 2024): the diagonal Fisher information of each Gaussian's
  position under the photometric loss with Gaussian pixel noise, ``F_i = sum over views, pixels and channels of
  |dI/dmu_i|^2`` of the image composited over its backdrop (so silhouettes inform too), estimated with
  Rademacher probes ``v`` (Hutchinson: ``E[(J^T v)_i^2] = (J^T J)_ii``); the score is the Laplace posterior
  variance relative to a prior of precision ``lam``, ``lam / (F_i + lam)``, ``lam`` a fraction of the median
  information of the Gaussians some view sees.
* ``"depth-variance"``: the spread of depth along each training ray, the variance of the Gaussians' depths
  under the blending weights, ``Var = sum w z^2 / a - (sum w z / a)^2`` (``a`` the pixel's alpha), as
  ``Var / (Var + tol^2)`` per pixel (``tol``: 5 % of the extent, or the median spread of the views' rays
  where larger, so the score ranks rays rather than saturating); per Gaussian the blending-weight mean over every pixel it draws, with a
  prior of one pixel of full uncertainty (a Gaussian no view draws scores 1).

A per-Gaussian score is seen from any camera with :func:`render_uncertainty` (blended like a colour) and at
3D points with :func:`point_uncertainty`; :func:`depth_moments` gives the depth spread of any camera's rays
(a fingertip's approach, say). :func:`brief_reconstruction` trains a scene for a short budget reproducibly,
for the grasp choices of :mod:`tacsplat.acquisition.next_touch`.
"""

from __future__ import annotations

import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from tacsplat.errors import InvalidInputError
from tacsplat.reconstruction.gaussians import Gaussians, precisions
from tacsplat.reconstruction.raster import rendering as raster
from tacsplat.reconstruction.views import background_image, camera_tensors

SCORES = ("fisher", "depth-variance")
FISHER_PROBES = 4  # Rademacher probes per estimate of the Fisher diagonal
FISHER_PRIOR = 0.1  # prior precision, as a fraction of the median information of the seen Gaussians
MIN_DEPTH_TOLERANCE = 0.05  # the least depth spread that scores 0.5, as a fraction of the Gaussians' extent
MIN_ALPHA = 0.05  # pixels drawn less than this have no depth spread to speak of
POINT_NEIGHBOURS = 16  # Gaussians that a point's score is read from


@dataclass
class Views:
    """Cameras of one image size: ``viewmats`` [C, 4, 4] world-to-camera, ``Ks`` [C, 3, 3] and the backdrops
    [C, H, W, 3] their images are composited over (None: black), all on one device."""

    viewmats: Tensor
    Ks: Tensor
    width: int
    height: int
    backgrounds: Tensor | None = None

    @classmethod
    def of_frames(cls, scene, frames: list, device="cpu") -> "Views":
        """The views of a scene's ``frames``, with the backdrop fitted to each image (as the trainer does)."""
        if not frames:
            raise InvalidInputError("frames: need at least one view")
        sizes = {(f.intrinsics.width, f.intrinsics.height) for f in frames}
        if len(sizes) > 1:
            raise InvalidInputError(f"frames: the views must share one image size, got {sorted(sizes)}")
        ((width, height),) = sizes
        viewmats, Ks = camera_tensors(frames)
        backgrounds = np.stack([background_image(scene.load_image(f)) for f in frames])
        return cls(viewmats.to(device), Ks.to(device), width, height, torch.from_numpy(backgrounds).to(device))


def _render(g: Gaussians, colors: Tensor, viewmats: Tensor, Ks: Tensor, size: tuple, means=None, **options):
    """``raster.rasterization`` of the Gaussians (detached; ``means``: the means to differentiate instead) in
    cameras of ``size`` (width, height)."""
    means = g.means.detach() if means is None else means
    return raster.rasterization(
        means, g.quats.detach(), g.scales.detach(), g.opacities.detach(), colors, viewmats, Ks, *size, **options
    )


def fisher_information(
    gaussians: Gaussians, views: Views, probes: int = FISHER_PROBES, seed: int = 0, backend: str = "auto"
) -> Tensor:
    """The Fisher information [N] of each Gaussian's position (trace of its 3x3 diagonal block's diagonal) under
    the photometric loss of ``views``, estimated with ``probes`` Rademacher probes seeded by ``seed``."""
    g = gaussians
    means = g.means.detach().clone().requires_grad_(True)
    size = (views.width, views.height)
    sh = g.sh_coefficients().detach()
    colors, alphas, _ = _render(g, sh, views.viewmats, views.Ks, size, means, sh_degree=g.sh_degree, backend=backend)
    image = colors if views.backgrounds is None else colors + (1.0 - alphas) * views.backgrounds
    generator = torch.Generator(device=means.device).manual_seed(seed)
    information = torch.zeros(len(g), device=means.device)
    for probe in range(probes):
        signs = torch.randint(0, 2, image.shape, generator=generator, device=means.device).to(image.dtype) * 2 - 1
        (grad,) = torch.autograd.grad(image, means, grad_outputs=signs, retain_graph=probe < probes - 1)
        information += grad.pow(2).sum(dim=-1)
    return information / probes


def fisher_uncertainty(
    gaussians: Gaussians,
    views: Views,
    probes: int = FISHER_PROBES,
    prior: float = FISHER_PRIOR,
    seed: int = 0,
    backend: str = "auto",
) -> Tensor:
    """The ``"fisher"`` score [N]: ``lam / (F + lam)``, ``lam = prior x`` the median information of the Gaussians
    that some view sees (1 where none does)."""
    information = fisher_information(gaussians, views, probes, seed, backend)
    seen = information[information > 0]
    lam = prior * seen.median() if len(seen) else torch.ones((), device=information.device)
    return lam / (information + lam)


def _camera_depths(means: Tensor, viewmat: Tensor) -> Tensor:
    """Depth [N] of each mean in a camera (its z in the camera frame)."""
    return means @ viewmat[2, :3] + viewmat[2, 3]


def depth_moments(
    gaussians: Gaussians,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    backend: str = "auto",
    near_plane: float = 0.01,
) -> tuple[Tensor, Tensor, Tensor]:
    """``(alpha, mean depth, depth variance)`` [H, W] of one camera (``viewmat`` [4, 4], ``K`` [3, 3]): the moments
    of the Gaussians' depths under each ray's blending weights (mean and variance 0 where alpha < MIN_ALPHA)."""
    with torch.no_grad():
        alpha, moments, _ = _depth_render(gaussians, viewmat, K, width, height, None, backend, near_plane)
    return alpha, moments[..., 0], moments[..., 1]


def _depth_render(g: Gaussians, viewmat, K, width, height, probe, backend, near_plane):
    """One camera's render of the depth moments (and of ``probe`` [N, D] as extra colours, for attribution)."""
    z = _camera_depths(g.means.detach(), viewmat)
    shift = z.median() if len(z) else z.new_zeros(())  # moments about a typical depth: float32 keeps the variance
    colors = torch.stack([z - shift, (z - shift) ** 2], dim=-1)
    if probe is not None:
        colors = torch.cat([colors, probe], dim=-1)
    out, alphas, _ = _render(
        g, colors[None], viewmat[None], K[None], (width, height), near_plane=near_plane, backend=backend
    )
    alpha = alphas[0, ..., 0]
    drawn = alpha >= MIN_ALPHA
    a = alpha.clamp_min(MIN_ALPHA)
    centred = out[0, ..., 0] / a
    mean = torch.where(drawn, centred + shift, torch.zeros_like(a))
    variance = torch.where(drawn, (out[0, ..., 1] / a - centred * centred).clamp_min(0.0), torch.zeros_like(a))
    return alpha, torch.stack([mean, variance], dim=-1).detach(), out[0, ..., 2:]


def extent(gaussians: Gaussians) -> float:
    """The size of the reconstruction: the diagonal of the 2nd-98th percentile box of the means (metres)."""
    means = gaussians.means.detach()
    if len(means) < 2:
        return 1.0
    q = torch.quantile(means, torch.tensor([0.02, 0.98], device=means.device, dtype=means.dtype), dim=0)
    return max(float((q[1] - q[0]).norm()), 1e-6)


def depth_tolerance(gaussians: Gaussians, views: Views, backend: str = "auto") -> float:
    """The depth spread (standard deviation, metres) that scores 0.5: ``MIN_DEPTH_TOLERANCE`` of the :func:`extent`,
    or the median spread over the pixels ``views`` draw where that is larger, so that the score of a reconstruction
    whose every ray is uncertain (a brief one) still ranks its rays instead of saturating at 1."""
    spreads = []
    for viewmat, K in zip(views.viewmats, views.Ks):
        alpha, _, variance = depth_moments(gaussians, viewmat, K, views.width, views.height, backend)
        spreads.append(variance[alpha >= MIN_ALPHA].sqrt())
    drawn = torch.cat(spreads)
    floor = MIN_DEPTH_TOLERANCE * extent(gaussians)
    return max(float(drawn.median()), floor) if len(drawn) else floor


def depth_variance_uncertainty(
    gaussians: Gaussians, views: Views, tolerance_m: float | None = None, backend: str = "auto"
) -> Tensor:
    """The ``"depth-variance"`` score [N]; ``tolerance_m``: the depth spread that scores 0.5 (default
    :func:`depth_tolerance`)."""
    g = gaussians
    tol = depth_tolerance(g, views, backend) if tolerance_m is None else float(tolerance_m)
    uncertain = torch.zeros(len(g), device=g.means.device)
    weight = torch.zeros(len(g), device=g.means.device)
    for viewmat, K in zip(views.viewmats, views.Ks):
        probe = torch.zeros(len(g), 2, device=g.means.device, requires_grad=True)
        alpha, moments, attributed = _depth_render(g, viewmat, K, views.width, views.height, probe, backend, 0.01)
        drawn = (alpha >= MIN_ALPHA).to(alpha.dtype)
        per_pixel = moments[..., 1] / (moments[..., 1] + tol * tol) * drawn
        (grad,) = torch.autograd.grad(attributed, probe, grad_outputs=torch.stack([per_pixel, drawn], dim=-1))
        uncertain += grad[:, 0]
        weight += grad[:, 1]
    return (uncertain + 1.0) / (weight + 1.0)


def gaussian_uncertainty(
    gaussians: Gaussians,
    views: Views,
    score: str = "fisher",
    seed: int = 0,
    backend: str = "auto",
    tolerance_m: float | None = None,
) -> Tensor:
    """The per-Gaussian ``score`` [N] (one of ``SCORES``) of a reconstruction seen by ``views`` (``tolerance_m``:
    the depth-variance score's, default :func:`depth_tolerance`)."""
    if score == "fisher":
        return fisher_uncertainty(gaussians, views, seed=seed, backend=backend)
    if score == "depth-variance":
        return depth_variance_uncertainty(gaussians, views, tolerance_m, backend=backend)
    raise InvalidInputError(f"score: must be one of {', '.join(SCORES)}, got {score!r}")


@torch.no_grad()
def render_uncertainty(
    gaussians: Gaussians,
    scores: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    backend: str = "auto",
    near_plane: float = 0.01,
) -> tuple[Tensor, Tensor, Tensor]:
    """``(uncertainty, alpha, expected depth)`` [H, W] of one camera: the per-Gaussian ``scores`` [N] blended like a
    colour and divided by alpha (1 where nothing is drawn: nothing there is known)."""
    colors = scores[:, None].to(gaussians.means.dtype)
    options = dict(near_plane=near_plane, render_mode="RGB+ED", backend=backend)
    out, alphas, _ = _render(gaussians, colors, viewmat[None], K[None], (width, height), **options)
    alpha = alphas[0, ..., 0]
    drawn = alpha >= MIN_ALPHA
    uncertainty = torch.where(drawn, out[0, ..., 0] / alpha.clamp_min(MIN_ALPHA), torch.ones_like(alpha))
    return uncertainty.clamp(0.0, 1.0), alpha, out[0, ..., 1]


@torch.no_grad()
def point_uncertainty(
    gaussians: Gaussians,
    scores: Tensor,
    points: Tensor,
    neighbours: int = POINT_NEIGHBOURS,
    prior: float = 1e-3,
    chunk: int = 4096,
) -> Tensor:
    """The score [P] at 3D ``points`` [P, 3]: the mean of the nearest Gaussians' ``scores`` weighted by each one's
    opacity times its density at the point, with a prior of weight ``prior`` at 1 (far from every Gaussian: 1)."""
    g = gaussians
    means, opacities = g.means, g.opacities
    points = points.to(means.device, means.dtype)
    if len(g) == 0:
        return torch.ones(len(points), device=means.device)
    k = min(neighbours, len(g))
    precision = precisions(g.quats, g.scales)  # [N, 3, 3]
    result = []
    for start in range(0, len(points), chunk):
        p = points[start : start + chunk]
        idx = torch.cdist(p, means).topk(k, dim=1, largest=False).indices  # [p, k]
        diff = p[:, None, :] - means[idx]  # [p, k, 3]
        mahalanobis = torch.einsum("pki,pkij,pkj->pk", diff, precision[idx], diff)
        w = opacities[idx] * torch.exp(-0.5 * mahalanobis)
        result.append(((w * scores[idx]).sum(1) + prior) / (w.sum(1) + prior))
    return torch.cat(result) if result else torch.zeros(0, device=means.device)


@contextmanager
def one_thread():
    """Torch and the CPU rasterizer on one thread each: a CPU result is then the same bit for bit on every run."""
    import numba

    threads = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads[0])
        numba.set_num_threads(threads[1])


def brief_reconstruction(scene, config) -> Gaussians:
    """The Gaussians after ``config.iterations`` training steps on ``scene`` (a ``TrainConfig``), trained on one
    thread (:func:`one_thread`): the same scene and config give the same Gaussians on every CPU run. Nothing is
    written (no run folder)."""
    from tacsplat.reconstruction.trainer import Trainer

    with one_thread():
        trainer = Trainer(scene, Path(tempfile.gettempdir()), config)  # its run folder is never written
        trainer.initialize()
        for _ in range(config.iterations):
            trainer.train_step()
    return trainer.gaussians
