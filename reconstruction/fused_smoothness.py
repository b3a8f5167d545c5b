"""Smoothness losses in numba for CPU tensors, with hand-written backward; the torch versions are the references.

* ``edge_aware_smoothness_cpu(depth, kernels, factors)``: paper Eq. 8. Same value and gradient as
  :func:`.losses.edge_aware_smoothness` (5x5 Sobel responses of the depth, 'valid' region, weighted by the image
  factors and by 1 - the touch proximity, averaged), without torch's convolution backward, which at one channel
  costs more than the rest of the loss: the forward correlates each valid pixel's window with both kernels and
  keeps the responses, the backward gathers each depth pixel's share of their signs from the windows that
  contain it (the adjoint of the correlation).
* ``albedo_smoothness_cpu(albedo, inside, across, down)``: :func:`.losses.albedo_smoothness_loss` (weighted L1
  differences of neighbouring pixels both inside), one pass each way instead of some thirty small torch
  operations.
"""

from __future__ import annotations

import numba as nb
import numpy as np
import torch

from tacsplat.reconstruction.raster.cpu_project import _np


@nb.njit(parallel=True, cache=True)
def _forward(depth, kernels, factors, responses, rows):
    """The Sobel responses of every valid pixel into ``responses`` [2, H-4, W-4] and rows[i] = the sum over valid
    row i of |Sx * D| f_x + |Sy * D| f_y (``factors`` [2, H-4, W-4] already include 1 - proximity).

    Both passes add one kernel tap at a time to a whole row, so the loops over a row vectorise (3.4x faster than
    a window per pixel for the forward, 7x for the adjoint, at 128 x 128 on one thread; same sums in the same
    order per pixel)."""
    out_h, out_w = factors.shape[1], factors.shape[2]
    for i in nb.prange(out_h):
        gx, gy = np.zeros(out_w), np.zeros(out_w)
        for u in range(5):
            for v in range(5):
                kx, ky = kernels[0, u, v], kernels[1, u, v]
                for j in range(out_w):
                    d = np.float64(depth[i + u, j + v])
                    gx[j] += kx * d
                    gy[j] += ky * d
        total = 0.0
        for j in range(out_w):
            responses[0, i, j], responses[1, i, j] = gx[j], gy[j]
            total += abs(gx[j]) * factors[0, i, j] + abs(gy[j]) * factors[1, i, j]
        rows[i] = total


@nb.njit(parallel=True, cache=True)
def _adjoint(kernels, signed, v_depth):
    """v_depth [H, W] = the adjoint of the valid correlation with both kernels applied to ``signed``
    [2, H-4, W-4]: each depth row gathers from the response rows whose windows contain it."""
    out_h, out_w = signed.shape[1], signed.shape[2]
    height, width = v_depth.shape
    for a in nb.prange(height):
        row = np.zeros(width)
        for u in range(max(0, a - out_h + 1), min(5, a + 1)):
            for v in range(5):
                k0, k1 = kernels[0, u, v], kernels[1, u, v]
                for t in range(out_w):
                    row[t + v] += k0 * signed[0, a - u, t] + k1 * signed[1, a - u, t]
        v_depth[a] = row


class _SmoothnessCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth, kernels, factors):
        d, k, f = (_np(t) for t in (depth, kernels, factors))
        responses = np.empty(f.shape)
        rows = np.empty(f.shape[1])
        _forward(d, k, f, responses, rows)
        ctx.arrays, ctx.shape, ctx.dtype = (k, f, responses), d.shape, d.dtype
        return torch.tensor(rows.sum() / (f.shape[1] * f.shape[2]), dtype=depth.dtype)

    @staticmethod
    def backward(ctx, grad):
        kernels, factors, responses = ctx.arrays
        # |r| passes sign(r) (0 at 0, as torch's abs does), times the factor and the mean's 1 / count
        signed = np.sign(responses) * factors * (float(grad) / (factors.shape[1] * factors.shape[2]))
        v_depth = np.empty(ctx.shape)
        _adjoint(kernels, signed, v_depth)
        return torch.from_numpy(v_depth.astype(ctx.dtype)), None, None


# mean over the valid region of |Sx * D| f_x + |Sy * D| f_y for a CPU depth map [H, W], the two 5x5 kernels
# [2, 5, 5] and the per-pixel factors [2, H-4, W-4] (no gradient)
edge_aware_smoothness_cpu = _SmoothnessCPU.apply


@nb.njit(parallel=True, cache=True)
def _albedo_forward(albedo, inside, across, down, rows):
    """rows[i] = (the weighted L1 differences of row i's pairs inside: with its right neighbour (weight
    across[i, j]) and its lower one (down[i, j]), their number)."""
    height, width = inside.shape
    for i in nb.prange(height):
        total = count = 0.0
        for j in range(width):
            if not inside[i, j]:
                continue
            if j + 1 < width and inside[i, j + 1]:
                count += 1.0
                for c in range(3):
                    total += across[i, j] * abs(np.float64(albedo[i, j + 1, c]) - albedo[i, j, c])
            if i + 1 < height and inside[i + 1, j]:
                count += 1.0
                for c in range(3):
                    total += down[i, j] * abs(np.float64(albedo[i + 1, j, c]) - albedo[i, j, c])
        rows[i, 0], rows[i, 1] = total, count


@nb.njit(parallel=True, cache=True)
def _albedo_backward(albedo, inside, across, down, scale, v_albedo):
    """v_albedo [H, W, 3] = scale * the sum of weight * sign(this pixel - its neighbour) over its four pairs inside
    (sign 0 at 0, as torch's abs)."""
    height, width = inside.shape
    for i in nb.prange(height):
        for j in range(width):
            for c in range(3):
                v = 0.0
                if inside[i, j]:
                    here = np.float64(albedo[i, j, c])
                    if j > 0 and inside[i, j - 1]:
                        v += across[i, j - 1] * np.sign(here - albedo[i, j - 1, c])
                    if j + 1 < width and inside[i, j + 1]:
                        v += across[i, j] * np.sign(here - albedo[i, j + 1, c])
                    if i > 0 and inside[i - 1, j]:
                        v += down[i - 1, j] * np.sign(here - albedo[i - 1, j, c])
                    if i + 1 < height and inside[i + 1, j]:
                        v += down[i, j] * np.sign(here - albedo[i + 1, j, c])
                v_albedo[i, j, c] = v * scale


class _AlbedoSmoothnessCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, albedo, inside, across, down):
        a, m, wa, wd = _np(albedo), _np(inside), _np(across), _np(down)
        rows = np.empty((m.shape[0], 2))
        _albedo_forward(a, m, wa, wd, rows)
        total, count = rows.sum(axis=0)
        ctx.arrays, ctx.count = (a, m, wa, wd), max(count, 1.0)
        return torch.tensor(total / ctx.count, dtype=albedo.dtype)

    @staticmethod
    def backward(ctx, grad):
        albedo, inside, across, down = ctx.arrays
        v_albedo = np.empty(albedo.shape, albedo.dtype)
        _albedo_backward(albedo, inside, across, down, float(grad) / ctx.count, v_albedo)
        return torch.from_numpy(v_albedo), None, None, None


# weighted L1 differences of neighbouring pixels of a CPU ``albedo`` [H, W, 3] that are both ``inside`` [H, W] bool,
# per pair inside (0 with no such pair), the pairs' weights ``across`` [H, W-1] and ``down`` [H-1, W] (no gradient;
# the image's pair weights, of the albedo's size); see :func:`.losses.albedo_smoothness_loss`
albedo_smoothness_cpu = _AlbedoSmoothnessCPU.apply
