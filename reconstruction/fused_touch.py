"""The touch loss fused in numba for CPU tensors: ``transmittance_cpu`` (paper Eq. 6-7).

Same value and gradients as the torch reference :func:`.losses.transmittance_loss` (``fused=False``, which CUDA
tensors use): for each touch point, the influence f alpha (Eq. 1) of each candidate Gaussian in reach, the
``top_k`` highest, and T(p) the mean of 1 - f alpha over them (1 with none); the loss is the mean of T(p).
The forward evaluates each (point, candidate) pair in registers -- rotation from the quaternion, the offset in
the Gaussian's unit frame, the exponent clamped like the reference's -- and keeps which pairs were chosen; the
backward recomputes the chosen pairs' derivatives in parallel and sums them per Gaussian in one serial pass
(a Gaussian is a candidate of many points). Scales are floored at ``min_scale`` as in the reference, and
non-finite inputs raise :class:`~tacsplat.errors.InvalidInputError` (the kernels' comparisons would skip them).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from tacsplat.errors import InvalidInputError
from tacsplat.reconstruction.raster.cpu_project import _np, _rotation, _rotation_backward

N_ROW = 11  # per (point, candidate) gradient: mean (3), quaternion (4), scale (3), opacity (1)


def require_finite(function: str, **tensors: torch.Tensor) -> None:
    """Raise InvalidInputError naming the first of ``tensors`` with a NaN or infinite entry, where a fused kernel
    would skip it silently (a comparison with NaN is false) and the torch reference would return NaN.

    One sum per tensor decides (a non-finite entry makes it non-finite); only a sum that fails is looked at
    closer, as finite entries may sum past the dtype's range."""
    for name, value in tensors.items():
        if not bool(torch.isfinite(value.detach().sum())) and not bool(torch.isfinite(value).all()):
            raise InvalidInputError(f"{function}: {name} contains NaN or infinite values")


@nb.njit(cache=True, inline="always")
def _unit_offset(points, means, quats, scales, min_scale, p, g):
    """The point's offset from Gaussian g in the Gaussian's unit frame, S^-1 R^T (p - mu) (3 values, the scales
    floored at ``min_scale``), and what the backward needs: the offset (3), the rotation's 9 entries, the
    normalised quaternion and its norm (5)."""
    ox = float(points[p, 0]) - float(means[g, 0])
    oy = float(points[p, 1]) - float(means[g, 1])
    oz = float(points[p, 2]) - float(means[g, 2])
    r00, r01, r02, r10, r11, r12, r20, r21, r22, w, qx, qy, qz, qnorm = _rotation(
        float(quats[g, 0]), float(quats[g, 1]), float(quats[g, 2]), float(quats[g, 3])
    )
    lx = (r00 * ox + r10 * oy + r20 * oz) / max(float(scales[g, 0]), min_scale)
    ly = (r01 * ox + r11 * oy + r21 * oz) / max(float(scales[g, 1]), min_scale)
    lz = (r02 * ox + r12 * oy + r22 * oz) / max(float(scales[g, 2]), min_scale)
    return lx, ly, lz, ox, oy, oz, r00, r01, r02, r10, r11, r12, r20, r21, r22, w, qx, qy, qz, qnorm


@nb.njit(parallel=True, cache=True)
def _forward(points, means, quats, scales, opacities, candidates, top_k, max_d2, max_m, min_scale, chosen, per_point):
    """T(p) of every touch point into ``per_point`` [P]; ``chosen`` [P, C] marks the pairs it averages."""
    n_points, n_cand = candidates.shape
    for p in nb.prange(n_points):
        influence = np.empty(n_cand)
        for c in range(n_cand):
            chosen[p, c] = False
            influence[c] = -1.0
            g = candidates[p, c]
            if g < 0:
                continue
            unit = _unit_offset(points, means, quats, scales, min_scale, p, g)
            lx, ly, lz, ox, oy, oz = unit[0], unit[1], unit[2], unit[3], unit[4], unit[5]
            if ox * ox + oy * oy + oz * oz > max_d2:
                continue
            m = min(lx * lx + ly * ly + lz * lz, max_m)
            influence[c] = math.exp(-0.5 * m) * float(opacities[g])
        total, count = 0.0, 0
        for _ in range(min(top_k, n_cand)):  # the top_k highest in reach, one maximum at a time
            best = -1
            for c in range(n_cand):
                if influence[c] >= 0.0 and not chosen[p, c] and (best < 0 or influence[c] > influence[best]):
                    best = c
            if best < 0:
                break
            chosen[p, best] = True
            total += 1.0 - influence[best]
            count += 1
        per_point[p] = total / count if count > 0 else 1.0


@nb.njit(parallel=True, cache=True, fastmath={"contract"})
def _pair_gradients(
    points, means, quats, scales, opacities, candidates, chosen, scale_per_point, max_m, min_scale, rows
):
    """rows[p, c] = d loss / d (mean, quaternion, scale, opacity) of pair (p, c) when chosen (else 0); the loss
    weighs each chosen pair's 1 - f alpha by ``scale_per_point[p]``."""
    n_points, n_cand = candidates.shape
    for p in nb.prange(n_points):
        vr = np.empty((3, 3))
        for c in range(n_cand):
            rows[p, c] = 0.0
            if not chosen[p, c]:
                continue
            g = candidates[p, c]
            lx, ly, lz, ox, oy, oz, r00, r01, r02, r10, r11, r12, r20, r21, r22, w, qx, qy, qz, qnorm = _unit_offset(
                points, means, quats, scales, min_scale, p, g
            )
            m = lx * lx + ly * ly + lz * lz
            f = math.exp(-0.5 * min(m, max_m))
            alpha = float(opacities[g])
            v_influence = -scale_per_point[p]  # d loss / d (f alpha)
            rows[p, c, 10] = v_influence * f
            if not m <= max_m:  # clamped: no gradient but the opacity's
                continue
            v_m = -0.5 * f * alpha * v_influence
            vl = (2.0 * lx * v_m, 2.0 * ly * v_m, 2.0 * lz * v_m)  # d / d local
            s = (
                max(float(scales[g, 0]), min_scale),
                max(float(scales[g, 1]), min_scale),
                max(float(scales[g, 2]), min_scale),
            )
            a0, a1, a2 = vl[0] / s[0], vl[1] / s[1], vl[2] / s[2]  # d / d (R^T o)
            # local_i = sum_k R_ki o_k / s_i, o = p - mu
            rows[p, c, 0] = -(r00 * a0 + r01 * a1 + r02 * a2)
            rows[p, c, 1] = -(r10 * a0 + r11 * a1 + r12 * a2)
            rows[p, c, 2] = -(r20 * a0 + r21 * a1 + r22 * a2)
            # a scale under the floor is the floor, a constant: no gradient
            rows[p, c, 7] = -vl[0] * lx / s[0] if float(scales[g, 0]) >= min_scale else 0.0
            rows[p, c, 8] = -vl[1] * ly / s[1] if float(scales[g, 1]) >= min_scale else 0.0
            rows[p, c, 9] = -vl[2] * lz / s[2] if float(scales[g, 2]) >= min_scale else 0.0
            o = (ox, oy, oz)
            for k in range(3):
                vr[k, 0], vr[k, 1], vr[k, 2] = o[k] * a0, o[k] * a1, o[k] * a2
            rows[p, c, 3], rows[p, c, 4], rows[p, c, 5], rows[p, c, 6] = _rotation_backward(w, qx, qy, qz, qnorm, vr)


@nb.njit(cache=True)
def _sum_rows(candidates, counted, rows, out):
    """out[g] = the sum of rows[p, c] over the ``counted`` pairs whose candidate is Gaussian g (serial: a Gaussian
    is many points' candidate)."""
    for p in range(candidates.shape[0]):
        for c in range(candidates.shape[1]):
            g = candidates[p, c]
            if g >= 0 and counted[p, c]:
                for j in range(out.shape[1]):
                    out[g, j] += rows[p, c, j]


class _TransmittanceCPU(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, points, means, quats, scales, opacities, candidates, top_k, max_distance, max_mahalanobis, min_scale
    ):
        inputs = dict(touch_points=points, means=means, quats=quats, scales=scales, opacities=opacities)
        require_finite("transmittance_loss", **inputs)
        arrays = tuple(_np(t) for t in (points, means, quats, scales, opacities, candidates))
        n_points = candidates.shape[0]
        chosen = np.empty(candidates.shape, np.bool_)
        per_point = np.empty(n_points, np.float64)
        limits = float(max_mahalanobis), float(min_scale)
        _forward(*arrays, int(top_k), float(max_distance) ** 2, *limits, chosen, per_point)
        ctx.arrays, ctx.chosen, ctx.limits = arrays, chosen, limits
        return torch.tensor(per_point.mean(), dtype=means.dtype)

    @staticmethod
    def backward(ctx, grad):
        points, means, quats, scales, opacities, candidates = ctx.arrays
        chosen = ctx.chosen
        counts = chosen.sum(axis=1)
        scale_per_point = float(grad) / (len(counts) * np.maximum(counts, 1))  # d loss / d T(p) / count
        rows = np.empty(candidates.shape + (N_ROW,), np.float64)
        _pair_gradients(points, means, quats, scales, opacities, candidates, chosen, scale_per_point, *ctx.limits, rows)
        summed = np.zeros((len(means), N_ROW))
        _sum_rows(candidates, chosen, rows, summed)
        v = torch.from_numpy(summed.astype(means.dtype))
        return None, v[:, 0:3], v[:, 3:7], v[:, 7:10], v[:, 10], None, None, None, None, None


# L_T of CPU tensors (see :func:`.losses.transmittance_loss`): (points, means, quats, scales, opacities, candidates,
# top_k, max_distance, max_mahalanobis, min_scale), the exponent clamped at ``max_mahalanobis``, the scales floored
# at ``min_scale``
transmittance_cpu = _TransmittanceCPU.apply
