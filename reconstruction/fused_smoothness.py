"""``edge_aware_smoothness_cpu(depth, weights, proximity)``: paper Eq. 8 in numba for CPU tensors.

Same value and gradient as the torch reference in :func:`.losses.edge_aware_smoothness` (5x5 Sobel responses
of the depth, 'valid' region, weighted by the image factors and by 1 - the touch proximity, averaged), without
torch's convolution backward, which at one channel costs more than the rest of the loss: the forward
correlates each valid pixel's window with both kernels, the backward gathers each depth pixel's share from
the windows that contain it (the adjoint of the correlation).
"""

from __future__ import annotations

import numba as nb
import numpy as np
import torch


@nb.njit(parallel=True, cache=True)
def _forward(depth, kernels, factors, rows):
    """rows[i] = sum over valid row i of |Sx * D| f_x + |Sy * D| f_y (``factors`` [2, H-4, W-4] already include
    1 - proximity)."""
    out_h, out_w = factors.shape[1], factors.shape[2]
    for i in nb.prange(out_h):
        total = 0.0
        for j in range(out_w):
            gx = gy = 0.0
            for u in range(5):
                for v in range(5):
                    d = float(depth[i + u, j + v])
                    gx += kernels[0, u, v] * d
                    gy += kernels[1, u, v] * d
            total += abs(gx) * factors[0, i, j] + abs(gy) * factors[1, i, j]
        rows[i] = total


@nb.njit(parallel=True, cache=True)
def _backward(depth, kernels, factors, scale, signed, v_depth):
    """v_depth = scale times the adjoint correlation of the signed factors (``signed`` [2, H-4, W-4] is scratch:
    sign(S * D) f for each kernel)."""
    out_h, out_w = factors.shape[1], factors.shape[2]
    for i in nb.prange(out_h):
        for j in range(out_w):
            gx = gy = 0.0
            for u in range(5):
                for v in range(5):
                    d = float(depth[i + u, j + v])
                    gx += kernels[0, u, v] * d
                    gy += kernels[1, u, v] * d
            signed[0, i, j] = (1.0 if gx > 0.0 else -1.0 if gx < 0.0 else 0.0) * factors[0, i, j] * scale
            signed[1, i, j] = (1.0 if gy > 0.0 else -1.0 if gy < 0.0 else 0.0) * factors[1, i, j] * scale
    height, width = depth.shape
    for a in nb.prange(height):
        for b in range(width):
            total = 0.0
            for u in range(max(0, a - out_h + 1), min(5, a + 1)):
                for v in range(max(0, b - out_w + 1), min(5, b + 1)):
                    total += kernels[0, u, v] * signed[0, a - u, b - v] + kernels[1, u, v] * signed[1, a - u, b - v]
            v_depth[a, b] = total


class _SmoothnessCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, depth, kernels, factors):
        arrays = tuple(np.ascontiguousarray(t.detach().numpy()) for t in (depth, kernels, factors))
        rows = np.empty(factors.shape[1])
        _forward(*arrays, rows)
        ctx.arrays = arrays
        return torch.tensor(rows.sum() / (factors.shape[1] * factors.shape[2]), dtype=depth.dtype)

    @staticmethod
    def backward(ctx, grad):
        depth, kernels, factors = ctx.arrays
        v_depth = np.empty(depth.shape, np.float64)
        scale = float(grad) / (factors.shape[1] * factors.shape[2])
        _backward(depth, kernels, factors, scale, np.empty(factors.shape, np.float64), v_depth)
        return torch.from_numpy(v_depth.astype(depth.dtype)), None, None


def edge_aware_smoothness_cpu(depth: torch.Tensor, kernels: torch.Tensor, factors: torch.Tensor) -> torch.Tensor:
    """Mean over the valid region of |Sx * D| f_x + |Sy * D| f_y for a CPU depth map [H, W], the two 5x5 kernels
    [2, 5, 5] and the per-pixel factors [2, H-4, W-4] (no gradient)."""
    return _SmoothnessCPU.apply(depth, kernels, factors)
