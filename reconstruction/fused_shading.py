"""``shade_cpu(...)``: the deferred shading of :func:`.shading._shade` in numba for CPU tensors.

Same values and gradients as the torch reference (the diffuse light's second-order SH irradiance and camera
light, the saturation at 1, and the masks of torch's clamps), in one pass over the pixels each way instead of
some dozens of small torch operations and their autograd nodes. The forward keeps what the backward needs of
each drawn pixel (a row of ``states``, drawn pixels only); the backward sums the light's gradients per chunk of
rows (a buffer per chunk, no races) and adds the chunks at the end.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from tacsplat.reconstruction.raster.cpu_project import _np, _sh_basis, _sh_basis_grad

ALPHA_FLOOR = 1e-6  # the alpha the blended channels are divided by at least
_CHUNKS = 16  # row chunks of the backward's reductions (each with its own gradient buffers)

# one drawn pixel's forward, as the backward needs it (_pixel's ``state``)
_VIEW, _NORMAL, _VN, _FACING, _E, _SHADED, _BASIS, _STATE = 0, 3, 6, 7, 8, 11, 14, 23


@nb.njit(cache=True, inline="always")
def _pixel(blended, alpha, floor, normal, K, rotation, coefficients, camera, lit, i, j, state):
    """The forward of drawn pixel (i, j) into ``state`` (layout: the offsets above); the colour before the
    saturation is state[_SHADED:_SHADED + 3]."""
    a = max(float(alpha[i, j]), floor)
    # the unit camera ray through the pixel centre, and it and the normal in the world (rotation: camera -> world)
    cx, cy = (j + 0.5 - K[0, 2]) / K[0, 0], (i + 0.5 - K[1, 2]) / K[1, 1]
    ray = 1.0 / math.sqrt(cx * cx + cy * cy + 1.0)
    cx, cy, cz = cx * ray, cy * ray, ray
    for k in range(3):
        state[_VIEW + k] = rotation[k, 0] * cx + rotation[k, 1] * cy + rotation[k, 2] * cz
        state[_NORMAL + k] = (
            rotation[k, 0] * normal[i, j, 0] + rotation[k, 1] * normal[i, j, 1] + rotation[k, 2] * normal[i, j, 2]
        )
    vx, vy, vz = state[_VIEW], state[_VIEW + 1], state[_VIEW + 2]
    nx, ny, nz = state[_NORMAL], state[_NORMAL + 1], state[_NORMAL + 2]
    vn = vx * nx + vy * ny + vz * nz
    state[_VN] = vn
    facing = max(-vn, 0.0)
    state[_FACING] = facing
    basis = state[_BASIS : _BASIS + 9]
    if lit:
        _sh_basis(2, nx, ny, nz, basis)  # the nine degree-2 SH basis values
    for c in range(3):
        irradiance = 1.0
        if lit:
            e = facing * camera[c]
            for k in range(9):
                e += basis[k] * coefficients[k, c]
            state[_E + c] = e
            irradiance = max(e, 0.0)
        state[_SHADED + c] = float(blended[i, j, c]) * irradiance / a


@nb.njit(parallel=True, cache=True)
def _forward(blended, alpha, floor, normal, K, rotation, coefficients, camera, lit, first, states, rgb, albedo):
    """rgb and albedo [H, W, 3]; each drawn pixel's forward into its row of ``states`` [P, S], row i's drawn
    pixels from states[first[i]] on, left to right."""
    height, width = alpha.shape
    for i in nb.prange(height):
        drawn = first[i]
        for j in range(width):
            a = max(float(alpha[i, j]), floor)
            for c in range(3):
                albedo[i, j, c] = blended[i, j, c] / a
            if alpha[i, j] > 0.0:
                state = states[drawn]
                drawn += 1
                _pixel(blended, alpha, floor, normal, K, rotation, coefficients, camera, lit, i, j, state)
                for c in range(3):
                    rgb[i, j, c] = min(state[_SHADED + c], 1.0) * alpha[i, j]
            else:
                for c in range(3):
                    rgb[i, j, c] = 0.0


@nb.njit(parallel=True, cache=True)
def _backward(blended, alpha, floor, rotation, coefficients, camera, lit, first, states, g_rgb, g_albedo, grads):
    """Gradients per pixel into ``grads`` = (g_blended [H, W, 3], g_alpha [H, W], g_normal [H, W, 3], ...) from the
    forward's ``states``; the SH coefficients' and the camera light's summed per row chunk into its last two,
    g_coefficients [C, 9, 3] and g_camera [C, 3]."""
    g_blended, g_alpha, g_normal, g_coefficients, g_camera = grads
    height, width = alpha.shape
    chunks = g_coefficients.shape[0]
    for chunk in nb.prange(chunks):
        g_basis, g_diffuse = np.empty(9), np.empty(3)
        for i in range(chunk * height // chunks, (chunk + 1) * height // chunks):
            drawn = first[i]
            for j in range(width):
                a = max(float(alpha[i, j]), floor)
                g_a = 0.0  # d loss / d a (alpha after its floor)
                for c in range(3):
                    g_diffuse[c] = g_albedo[i, j, c]
                g_normal[i, j, 0] = g_normal[i, j, 1] = g_normal[i, j, 2] = 0.0
                g_alpha[i, j] = 0.0
                if alpha[i, j] > 0.0:
                    state = states[drawn]
                    drawn += 1
                    vx, vy, vz = state[_VIEW], state[_VIEW + 1], state[_VIEW + 2]
                    nx, ny, nz = state[_NORMAL], state[_NORMAL + 1], state[_NORMAL + 2]
                    vn, facing = state[_VN], state[_FACING]
                    basis = state[_BASIS : _BASIS + 9]
                    g_facing = 0.0
                    g_basis[:] = 0.0
                    for c in range(3):
                        shaded = state[_SHADED + c]
                        clipped = shaded > 1.0
                        g_alpha[i, j] += g_rgb[i, j, c] * (1.0 if clipped else shaded)
                        g_shaded = 0.0 if clipped else g_rgb[i, j, c] * alpha[i, j]
                        if lit:
                            e = state[_E + c]
                            g_diffuse[c] += g_shaded * max(e, 0.0)
                            g_e = g_shaded * float(blended[i, j, c]) / a if e >= 0.0 else 0.0
                            for k in range(9):
                                g_coefficients[chunk, k, c] += basis[k] * g_e
                                g_basis[k] += coefficients[k, c] * g_e
                            g_camera[chunk, c] += facing * g_e
                            g_facing += camera[c] * g_e
                        else:
                            g_diffuse[c] += g_shaded
                    if lit:  # basis(n) and facing = max(-<view, n>, 0)
                        g_nx, g_ny, g_nz = _sh_basis_grad(2, nx, ny, nz, g_basis)
                        if vn <= 0.0:
                            g_nx -= g_facing * vx
                            g_ny -= g_facing * vy
                            g_nz -= g_facing * vz
                        for k in range(3):  # world -> camera: the rotation's transpose
                            g_normal[i, j, k] = rotation[0, k] * g_nx + rotation[1, k] * g_ny + rotation[2, k] * g_nz
                for c in range(3):
                    g_blended[i, j, c] = g_diffuse[c] / a
                    g_a -= g_diffuse[c] * blended[i, j, c] / a / a
                if alpha[i, j] >= floor:  # where the floor passes alpha's gradient
                    g_alpha[i, j] += g_a


class _ShadeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, blended, alpha, normal, K, rotation, coefficients, camera, lit):
        arrays = tuple(_np(t) for t in (blended, alpha, normal))
        floor = float(np.asarray(ALPHA_FLOOR, arrays[1].dtype))  # as torch's clamp_min(1e-6) in alpha's dtype
        fixed = tuple(_np(t).astype(np.float64) for t in (K, rotation, coefficients, camera))
        drawn = (arrays[1] > 0).sum(axis=1)  # [H]
        first = np.concatenate([[0], np.cumsum(drawn)[:-1]])
        states = np.empty((drawn.sum(), _STATE))
        rgb, albedo = np.empty(alpha.shape + (3,), arrays[0].dtype), np.empty(alpha.shape + (3,), arrays[0].dtype)
        _forward(arrays[0], arrays[1], floor, arrays[2], *fixed, lit, first, states, rgb, albedo)
        ctx.arrays, ctx.fixed, ctx.lit, ctx.states, ctx.floor = arrays, fixed, lit, (first, states), floor
        ctx.dtypes = (coefficients.dtype, camera.dtype)
        return torch.from_numpy(rgb), torch.from_numpy(albedo)

    @staticmethod
    def backward(ctx, g_rgb, g_albedo):
        blended, alpha, normal = ctx.arrays
        g = (_np(g_rgb), _np(g_albedo))  # autograd passes zeros for an output without gradient
        g_blended, g_normal = np.empty(blended.shape, blended.dtype), np.empty(normal.shape, normal.dtype)
        g_alpha = np.empty(alpha.shape, alpha.dtype)
        chunks = min(_CHUNKS, alpha.shape[0])
        g_coefficients, g_camera = np.zeros((chunks, 9, 3)), np.zeros((chunks, 3))
        grads = (g_blended, g_alpha, g_normal, g_coefficients, g_camera)
        _backward(blended, alpha, ctx.floor, *ctx.fixed[1:], ctx.lit, *ctx.states, *g, grads)
        g_coefficients = torch.from_numpy(g_coefficients.sum(0)).to(ctx.dtypes[0])
        g_camera = torch.from_numpy(g_camera.sum(0)).to(ctx.dtypes[1])
        g_blended, g_alpha, g_normal = (torch.from_numpy(a) for a in (g_blended, g_alpha, g_normal))
        return g_blended, g_alpha, g_normal, None, None, g_coefficients, g_camera, None


def shade_cpu(
    blended: torch.Tensor,
    alpha: torch.Tensor,
    normal: torch.Tensor,
    K: torch.Tensor,
    rotation: torch.Tensor,
    coefficients: torch.Tensor | None,
    camera: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(premultiplied RGB [H, W, 3], albedo [H, W, 3]) of CPU tensors: the blended albedo [H, W, 3], alpha
    [H, W], unit camera-frame normals [H, W, 3], the intrinsics [3, 3] and the camera-to-world ``rotation``
    [3, 3] (no gradient), and the diffuse light's SH ``coefficients`` [9, 3] and ``camera`` light [3] (None:
    unlit); see :func:`.shading._shade`."""
    lit = coefficients is not None
    if not lit:
        coefficients, camera = blended.new_zeros((9, 3)), blended.new_zeros(3)
    return _ShadeCPU.apply(blended, alpha, normal, K, rotation, coefficients, camera, lit)
