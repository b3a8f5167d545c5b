"""Normals in numba for CPU tensors, with hand-written backward; the torch versions are the references.

* ``gaussian_normals_cpu(quats, scales)``: each Gaussian's shortest axis (:func:`.shading.gaussian_normals`:
  the rotation of the normalised quaternion, its column of the smallest scale; the choice carries no
  gradient), one pass over the Gaussians each way instead of some forty elementwise torch operations.
* ``depth_normal_consistency_cpu(normal, depth, K, weight)``: 2DGS's depth-normal consistency
  (:func:`.losses.normal_consistency_loss` of :func:`.losses.depth_normals`) per pixel in one pass: the
  depth's normal from central differences of the unprojected points, 1 - <rendered, depth normal>; the
  backward gathers each depth pixel's share from the four normals whose differences it enters.

Both raise :class:`~tacsplat.errors.InvalidInputError` on NaN or infinite inputs, which their kernels would
misread silently (a NaN depth as a pixel not in front of the camera, a NaN scale as never the smallest).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from tacsplat.reconstruction.fused_touch import require_finite
from tacsplat.reconstruction.raster.cpu_project import _CHUNK, _np, _rotation, _rotation_backward


@nb.njit(cache=True, inline="always")
def _shortest_axis(scales, g):
    """Index of Gaussian g's smallest scale (the first of equal ones, as argmin)."""
    k = 0
    if scales[g, 1] < scales[g, k]:
        k = 1
    if scales[g, 2] < scales[g, k]:
        k = 2
    return k


@nb.njit(parallel=True, cache=True)
def _forward(quats, scales, normals):
    """normals[g] = column argmin(scales[g]) of the rotation of quats[g] (normalised; zero -> identity)."""
    for g in nb.prange(quats.shape[0]):
        r = _rotation(float(quats[g, 0]), float(quats[g, 1]), float(quats[g, 2]), float(quats[g, 3]))
        k = _shortest_axis(scales, g)
        normals[g, 0], normals[g, 1], normals[g, 2] = r[k], r[3 + k], r[6 + k]


@nb.njit(parallel=True, cache=True, fastmath={"contract"})
def _backward(quats, scales, v_normals, v_quats):
    """v_quats[g] = d loss / d quats[g] from d loss / d normals[g]."""
    n = quats.shape[0]
    for chunk in nb.prange((n + _CHUNK - 1) // _CHUNK):
        vr = np.zeros((3, 3))
        for g in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            r = _rotation(float(quats[g, 0]), float(quats[g, 1]), float(quats[g, 2]), float(quats[g, 3]))
            k = _shortest_axis(scales, g)
            for i in range(3):
                vr[i, k] = v_normals[g, i]
            v_quats[g, 0], v_quats[g, 1], v_quats[g, 2], v_quats[g, 3] = _rotation_backward(
                r[9], r[10], r[11], r[12], r[13], vr
            )
            for i in range(3):
                vr[i, k] = 0.0


class _GaussianNormalsCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, quats, scales):
        require_finite("gaussian_normals", quats=quats, scales=scales)
        q, s = _np(quats), _np(scales)
        normals = np.empty((q.shape[0], 3), q.dtype)
        _forward(q, s, normals)
        ctx.arrays = (q, s)
        return torch.from_numpy(normals)

    @staticmethod
    def backward(ctx, v_normals):
        q, s = ctx.arrays
        v_quats = np.empty_like(q)
        _backward(q, s, _np(v_normals), v_quats)
        return torch.from_numpy(v_quats), None


# unit normals [N, 3] of CPU quaternions [N, 4] and scales [N, 3] (see :func:`.shading.gaussian_normals`)
gaussian_normals_cpu = _GaussianNormalsCPU.apply


@nb.njit(cache=True, inline="always")
def _depth_normal(depth, rx, ry, i, j):
    """The depth map's unit normal at interior pixel (i, j) (central differences of the unprojected points,
    turned towards the camera) as (the raw cross product u x v, 1 / its clamped length, the sign), or a zero
    length where a pixel around is not in front of the camera."""
    for a in range(i - 1, i + 2):
        for b in range(j - 1, j + 2):
            if not depth[a, b] > 0.0:
                return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    zr, zl, zd, zu = float(depth[i, j + 1]), float(depth[i, j - 1]), float(depth[i + 1, j]), float(depth[i - 1, j])
    ux, uy, uz = rx[j + 1] * zr - rx[j - 1] * zl, ry[i] * (zr - zl), zr - zl  # along the row
    vx, vy, vz = rx[j] * (zd - zu), ry[i + 1] * zd - ry[i - 1] * zu, zd - zu  # down the column
    nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
    inv = 1.0 / math.sqrt(max(nx * nx + ny * ny + nz * nz, 1e-24))
    z = float(depth[i, j])
    sign = -1.0 if nx * rx[j] * z + ny * ry[i] * z + nz * z > 0.0 else 1.0
    return nx, ny, nz, inv, sign, ux, uy, uz, vx, vy, vz


@nb.njit(parallel=True, cache=True)
def _consistency_forward(normal, depth, weight, rx, ry, sums):
    """sums[i] = (sum over row i of w (1 - <rendered, depth normal>), sum of w), w the weight where the depth
    normal is known (unit length: more than 0.5 long after normalising)."""
    height, width = depth.shape
    for i in nb.prange(1, height - 1):
        total = counted = 0.0
        for j in range(1, width - 1):
            nx, ny, nz, inv, sign, _, _, _, _, _, _ = _depth_normal(depth, rx, ry, i, j)
            f = sign * inv
            fx, fy, fz = nx * f, ny * f, nz * f
            if fx * fx + fy * fy + fz * fz > 0.25:
                w = float(weight[i, j])
                total += w * (1.0 - (normal[i, j, 0] * fx + normal[i, j, 1] * fy + normal[i, j, 2] * fz))
                counted += w
        sums[i, 0], sums[i, 1] = total, counted


@nb.njit(parallel=True, cache=True, fastmath={"contract"})
def _consistency_backward(normal, depth, weight, rx, ry, scale, v_normal, g_u, g_v):
    """d loss / d rendered normal into ``v_normal`` and d loss / d (u, v) of each pixel's differences into g_u,
    g_v [H, W, 3], the loss being ``scale`` times the weighted sum."""
    height, width = depth.shape
    for i in nb.prange(height):
        for j in range(width):
            v_normal[i, j] = g_u[i, j] = g_v[i, j] = 0.0
            if i == 0 or j == 0 or i == height - 1 or j == width - 1:
                continue
            nx, ny, nz, inv, sign, ux, uy, uz, vx, vy, vz = _depth_normal(depth, rx, ry, i, j)
            f = sign * inv
            fx, fy, fz = nx * f, ny * f, nz * f
            if not fx * fx + fy * fy + fz * fz > 0.25:
                continue
            w = scale * float(weight[i, j])
            v_normal[i, j, 0], v_normal[i, j, 1], v_normal[i, j, 2] = -w * fx, -w * fy, -w * fz
            dx, dy, dz = -w * normal[i, j, 0], -w * normal[i, j, 1], -w * normal[i, j, 2]  # d / d depth normal
            if nx * nx + ny * ny + nz * nz >= 1e-24:  # through n / |n| (a clamped length is a constant)
                hx, hy, hz = nx * inv, ny * inv, nz * inv
                dot = hx * dx + hy * dy + hz * dz
                dx, dy, dz = dx - hx * dot, dy - hy * dot, dz - hz * dot
            gx, gy, gz = f * dx, f * dy, f * dz  # d / d (u x v)
            g_u[i, j, 0], g_u[i, j, 1], g_u[i, j, 2] = vy * gz - vz * gy, vz * gx - vx * gz, vx * gy - vy * gx
            g_v[i, j, 0], g_v[i, j, 1], g_v[i, j, 2] = gy * uz - gz * uy, gz * ux - gx * uz, gx * uy - gy * ux


@nb.njit(parallel=True, cache=True)
def _gather_depth(g_u, g_v, rx, ry, v_depth):
    """d loss / d depth[a, b]: its point enters u of the pixels left and right of it and v of those above and
    below, with the ray (rx[b], ry[a], 1) and the sign of the difference."""
    height, width = v_depth.shape
    for a in nb.prange(height):
        for b in range(width):
            sx = sy = sz = 0.0
            if b >= 1:  # pixel (a, b - 1): u = P(a, b) - P(a, b - 2)
                sx += g_u[a, b - 1, 0]
                sy += g_u[a, b - 1, 1]
                sz += g_u[a, b - 1, 2]
            if b + 1 < width:  # pixel (a, b + 1): u = P(a, b + 2) - P(a, b)
                sx -= g_u[a, b + 1, 0]
                sy -= g_u[a, b + 1, 1]
                sz -= g_u[a, b + 1, 2]
            if a >= 1:
                sx += g_v[a - 1, b, 0]
                sy += g_v[a - 1, b, 1]
                sz += g_v[a - 1, b, 2]
            if a + 1 < height:
                sx -= g_v[a + 1, b, 0]
                sy -= g_v[a + 1, b, 1]
                sz -= g_v[a + 1, b, 2]
            v_depth[a, b] = sx * rx[b] + sy * ry[a] + sz


def _pixel_rays(K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """x / z of each column and y / z of each row through the pixel centres (+0.5), float64."""
    rx = (np.arange(width) + 0.5 - K[0, 2]) / K[0, 0]
    ry = (np.arange(height) + 0.5 - K[1, 2]) / K[1, 1]
    return rx, ry


class _DepthNormalConsistencyCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal, depth, K, weight):
        require_finite("depth_normal_consistency", rendered=normal, depth=depth, K=K, weight=weight)
        arrays = tuple(_np(t) for t in (normal, depth, weight))
        rx, ry = _pixel_rays(K.detach().double().numpy(), depth.shape[1], depth.shape[0])
        sums = np.zeros((depth.shape[0], 2))
        _consistency_forward(arrays[0], arrays[1], arrays[2], rx, ry, sums)
        denominator = max(sums[:, 1].sum(), 1e-6)
        ctx.arrays, ctx.rays, ctx.denominator = arrays, (rx, ry), denominator
        return torch.tensor(sums[:, 0].sum() / denominator, dtype=normal.dtype)

    @staticmethod
    def backward(ctx, grad):
        normal, depth, weight = ctx.arrays
        rx, ry = ctx.rays
        v_normal = np.empty(normal.shape, np.float64)
        g_u, g_v = np.empty(normal.shape, np.float64), np.empty(normal.shape, np.float64)
        _consistency_backward(normal, depth, weight, rx, ry, float(grad) / ctx.denominator, v_normal, g_u, g_v)
        v_depth = np.empty(depth.shape, np.float64)
        _gather_depth(g_u, g_v, rx, ry, v_depth)
        grads = (torch.from_numpy(v.astype(a.dtype)) for v, a in ((v_normal, normal), (v_depth, depth)))
        return *grads, None, None


# depth-normal consistency of CPU tensors: rendered unit normals [H, W, 3], z-depth [H, W], intrinsics [3, 3],
# per-pixel weight [H, W] (no gradient); see :func:`.losses.normal_consistency_loss`
depth_normal_consistency_cpu = _DepthNormalConsistencyCPU.apply
