"""``shade_cpu(...)``: the deferred shading of :func:`.shading._shade` in numba for CPU tensors.

Same values and gradients as the torch reference (the environment's mip pyramid, the lookup with
``grid_sample``'s bilinear, border-clamped sampling and the roughness tent over the levels, the diffuse light's
second-order SH irradiance and camera light, the saturation at 1, and the masks of torch's clamps), in one pass
over the pixels each way instead of some hundred small torch operations and their autograd nodes. The forward
keeps what the backward needs of each drawn pixel (a row of ``states``, drawn pixels only); the backward sums
the light's and the environment's gradients per chunk of rows (a buffer per chunk, no races) and adds the chunks
at the end.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch

from tacsplat.reconstruction.raster.cpu_project import _np
from tacsplat.reconstruction.raster.spherical_harmonics import SH_C0, SH_C1, SH_C2

TINY = 1e-12  # squared length under which a direction's azimuth (or a pixel's blended normal) is undefined
ALPHA_FLOOR = 1e-6  # the alpha the blended channels are divided by at least
_CHUNKS = 16  # row chunks of the backward's reductions (each with its own gradient buffers)

# one drawn pixel's forward, as the backward needs it (_pixel's ``state``)
_VIEW, _NORMAL, _VN, _UV, _UNIT, _LENGTH, _POSITION, _FACING, _E, _SHADED, _SPECULAR, _BASIS, _SAMPLES = (
    0, 3, 6, 7, 9, 12, 13, 14, 15, 18, 21, 24, 33)  # fmt: skip


@nb.njit(cache=True, inline="always")
def _sh2(x, y, z, basis):
    """The nine degree-2 SH basis values at (x, y, z) into ``basis`` (the order of .spherical_harmonics)."""
    basis[0] = SH_C0
    basis[1] = -SH_C1 * y
    basis[2] = SH_C1 * z
    basis[3] = -SH_C1 * x
    basis[4] = SH_C2[0] * x * y
    basis[5] = SH_C2[1] * y * z
    basis[6] = SH_C2[2] * (2.0 * z * z - x * x - y * y)
    basis[7] = SH_C2[3] * x * z
    basis[8] = SH_C2[4] * (x * x - y * y)


@nb.njit(cache=True, inline="always")
def _sh2_backward(x, y, z, g):
    """(d/dx, d/dy, d/dz) of sum_k g[k] basis_k(x, y, z)."""
    gx = (-SH_C1 * g[3] + SH_C2[0] * y * g[4] - 2.0 * SH_C2[2] * x * g[6] + SH_C2[3] * z * g[7]
          + 2.0 * SH_C2[4] * x * g[8])
    gy = (-SH_C1 * g[1] + SH_C2[0] * x * g[4] + SH_C2[1] * z * g[5] - 2.0 * SH_C2[2] * y * g[6]
          - 2.0 * SH_C2[4] * y * g[8])
    gz = SH_C1 * g[2] + SH_C2[1] * y * g[5] + 4.0 * SH_C2[2] * z * g[6] + SH_C2[3] * x * g[7]
    return gx, gy, gz


@nb.njit(cache=True, inline="always")
def _clip(coordinate, size):
    """grid_sample's border padding: the pixel coordinate clipped to [0, size - 1], and 1 where the clip passes
    the gradient (strictly inside: the borders count as outside). NaN reads texel 0 (its colour is NaN anyway:
    the index must stay inside the map)."""
    if not coordinate > 0.0:
        return 0.0, 0.0
    if coordinate >= size - 1:
        return float(size - 1), 0.0
    return coordinate, 1.0


@nb.njit(cache=True, inline="always")
def _sample(env, offset, h, w, u, v, out):
    """Bilinear sample (align_corners False, border padding) of the level [3, h, w] at ``offset`` in the flat
    ``env`` at grid (u, v) into ``out`` [3]."""
    ix, _ = _clip(((u + 1.0) * w - 1.0) / 2.0, w)
    iy, _ = _clip(((v + 1.0) * h - 1.0) / 2.0, h)
    x0, y0 = int(math.floor(ix)), int(math.floor(iy))
    wx, wy = ix - x0, iy - y0
    for c in range(3):
        total = 0.0
        for dy in range(2):
            for dx in range(2):
                yy, xx = y0 + dy, x0 + dx
                if yy < h and xx < w:
                    total += (wy if dy else 1.0 - wy) * (wx if dx else 1.0 - wx) * env[offset + (c * h + yy) * w + xx]
        out[c] = total


@nb.njit(cache=True, inline="always")
def _sample_backward(env, offset, h, w, u, v, g_out, g_env):
    """Scatter g_out [3] (d loss / d the sample) into the level's texels of g_env; returns (d/du, d/dv)."""
    ix, pass_x = _clip(((u + 1.0) * w - 1.0) / 2.0, w)
    iy, pass_y = _clip(((v + 1.0) * h - 1.0) / 2.0, h)
    x0, y0 = int(math.floor(ix)), int(math.floor(iy))
    wx, wy = ix - x0, iy - y0
    g_ix = g_iy = 0.0
    for c in range(3):
        for dy in range(2):
            for dx in range(2):
                yy, xx = y0 + dy, x0 + dx
                if yy < h and xx < w:
                    index = offset + (c * h + yy) * w + xx
                    fy, fx = (wy if dy else 1.0 - wy), (wx if dx else 1.0 - wx)
                    g_env[index] += fy * fx * g_out[c]
                    value = env[index] * g_out[c]
                    g_ix += value * fy * (1.0 if dx else -1.0)
                    g_iy += value * fx * (1.0 if dy else -1.0)
    return g_ix * pass_x * w / 2.0, g_iy * pass_y * h / 2.0


@nb.njit(cache=True, inline="always")
def _pixel(blended, alpha, floor, normal, K, rotation, env, level_h, level_w, level_offset, coefficients, camera,
           lit, i, j, state):
    """The forward of drawn pixel (i, j) into ``state`` (layout: the offsets above); the colour before the
    saturation is state[_SHADED:_SHADED + 3]."""
    a = max(float(alpha[i, j]), floor)
    # the unit camera ray through the pixel centre, and it and the normal in the world (rotation: camera -> world)
    cx, cy = (j + 0.5 - K[0, 2]) / K[0, 0], (i + 0.5 - K[1, 2]) / K[1, 1]
    ray = 1.0 / math.sqrt(cx * cx + cy * cy + 1.0)
    cx, cy, cz = cx * ray, cy * ray, ray
    for k in range(3):
        state[_VIEW + k] = rotation[k, 0] * cx + rotation[k, 1] * cy + rotation[k, 2] * cz
        state[_NORMAL + k] = rotation[k, 0] * normal[i, j, 0] + rotation[k, 1] * normal[i, j, 1] + rotation[
            k, 2] * normal[i, j, 2]
    vx, vy, vz = state[_VIEW], state[_VIEW + 1], state[_VIEW + 2]
    nx, ny, nz = state[_NORMAL], state[_NORMAL + 1], state[_NORMAL + 2]
    vn = vx * nx + vy * ny + vz * nz
    state[_VN] = vn
    for c in range(3):
        state[_SPECULAR + c] = 0.0
    if blended.shape[2] > 3:  # reflective: the specular
        # the reflected direction -> the map's (u, v) (EnvironmentMap.lookup's mapping)
        dx, dy, dz = vx - 2.0 * vn * nx, vy - 2.0 * vn * ny, vz - 2.0 * vn * nz
        squared = dx * dx + dy * dy + dz * dz
        length = math.sqrt(squared) if squared > TINY else 0.0  # 0: no direction, the horizon at azimuth 0
        x, y, z = (dx / length, dy / length, dz / length) if length > 0.0 else (1.0, 0.0, 0.0)
        flat = x * x + y * y
        u = math.atan2(y, x) / math.pi if flat > TINY else 0.0  # straight up or down: azimuth 0
        v = -math.atan2(z, math.sqrt(flat + TINY)) / (math.pi / 2)
        state[_UV], state[_UV + 1] = u, v
        state[_UNIT], state[_UNIT + 1], state[_UNIT + 2], state[_LENGTH] = x, y, z, length
        # the levels around roughness * (levels - 1), tent-weighted (every level within 1 is sampled: the
        # backward needs those a weight of exactly 0 passes the gradient of)
        levels = level_h.shape[0]
        position = min(max(float(blended[i, j, 6]) / a, 0.0), 1.0) * (levels - 1)
        state[_POSITION] = position
        for level in range(levels):
            weight = 1.0 - abs(position - level)
            if weight >= 0.0:
                sample = state[_SAMPLES + 3 * level : _SAMPLES + 3 * level + 3]
                _sample(env, level_offset[level], level_h[level], level_w[level], u, v, sample)
                for c in range(3):
                    state[_SPECULAR + c] += weight * sample[c]
    facing = max(-vn, 0.0)
    state[_FACING] = facing
    basis = state[_BASIS : _BASIS + 9]
    if lit:
        _sh2(nx, ny, nz, basis)
    for c in range(3):
        irradiance = 1.0
        if lit:
            e = facing * camera[c]
            for k in range(9):
                e += basis[k] * coefficients[k, c]
            state[_E + c] = e
            irradiance = max(e, 0.0)
        state[_SHADED + c] = float(blended[i, j, c]) * irradiance / a
        if blended.shape[2] > 3:
            state[_SHADED + c] += float(blended[i, j, 3 + c]) * state[_SPECULAR + c] / a


@nb.njit(parallel=True, cache=True)
def _forward(blended, alpha, floor, normal, K, rotation, env, level_h, level_w, level_offset, coefficients, camera,
             lit, saturate, first, states, rgb, albedo):
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
                _pixel(blended, alpha, floor, normal, K, rotation, env, level_h, level_w, level_offset,
                       coefficients, camera, lit, i, j, state)
                for c in range(3):
                    shaded = state[_SHADED + c]
                    rgb[i, j, c] = (min(shaded, 1.0) if saturate else shaded) * alpha[i, j]
            else:
                for c in range(3):
                    rgb[i, j, c] = 0.0


@nb.njit(parallel=True, cache=True)
def _backward(blended, alpha, floor, rotation, env, level_h, level_w, level_offset, coefficients, camera, lit,
              saturate, first, states, g_rgb, g_albedo, g_blended, g_alpha, g_normal, g_env, g_coefficients,
              g_camera):
    """Gradients per pixel into g_blended [H, W, 7 or 3], g_alpha [H, W], g_normal [H, W, 3] from the forward's
    ``states``; the environment's (flat pyramid), the SH coefficients' and the camera light's summed per row chunk
    into g_env [C, E], g_coefficients [C, 9, 3], g_camera [C, 3]."""
    height, width = alpha.shape
    chunks, levels, reflective = g_coefficients.shape[0], level_h.shape[0], blended.shape[2] > 3
    for chunk in nb.prange(chunks):
        g_spec, g_sample, g_basis, g_diffuse = np.empty(3), np.empty(3), np.empty(9), np.empty(3)
        for i in range(chunk * height // chunks, (chunk + 1) * height // chunks):
            drawn = first[i]
            for j in range(width):
                a = max(float(alpha[i, j]), floor)
                g_a = 0.0  # d loss / d a (alpha after its floor)
                for c in range(3):
                    g_diffuse[c] = g_albedo[i, j, c]
                for k in range(3, blended.shape[2]):
                    g_blended[i, j, k] = 0.0
                g_normal[i, j, 0] = g_normal[i, j, 1] = g_normal[i, j, 2] = 0.0
                g_alpha[i, j] = 0.0
                if alpha[i, j] > 0.0:
                    state = states[drawn]
                    drawn += 1
                    vx, vy, vz = state[_VIEW], state[_VIEW + 1], state[_VIEW + 2]
                    nx, ny, nz = state[_NORMAL], state[_NORMAL + 1], state[_NORMAL + 2]
                    vn, facing, position = state[_VN], state[_FACING], state[_POSITION]
                    basis = state[_BASIS : _BASIS + 9]
                    g_facing = 0.0
                    g_basis[:] = 0.0
                    for c in range(3):
                        shaded = state[_SHADED + c]
                        clipped = saturate and shaded > 1.0
                        g_alpha[i, j] += g_rgb[i, j, c] * (1.0 if clipped else shaded)
                        g_shaded = 0.0 if clipped else g_rgb[i, j, c] * alpha[i, j]
                        if reflective:
                            tint = float(blended[i, j, 3 + c]) / a
                            g_tint = g_shaded * state[_SPECULAR + c]
                            g_spec[c] = g_shaded * tint
                            g_blended[i, j, 3 + c] = g_tint / a
                            g_a -= g_tint * tint / a
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
                    g_nx = g_ny = g_nz = 0.0
                    if reflective:
                        # the lookup: tent over the levels, bilinear samples
                        u, v = state[_UV], state[_UV + 1]
                        g_position = g_u = g_v = 0.0
                        for level in range(levels):
                            distance = position - level
                            weight = 1.0 - abs(distance)
                            if weight >= 0.0:  # clamp_min passes its gradient at 0 too
                                sample = state[_SAMPLES + 3 * level : _SAMPLES + 3 * level + 3]
                                sign = 1.0 if distance > 0.0 else (-1.0 if distance < 0.0 else 0.0)
                                g_position -= sign * (g_spec[0] * sample[0] + g_spec[1] * sample[1]
                                                      + g_spec[2] * sample[2])
                            if weight > 0.0:
                                for c in range(3):
                                    g_sample[c] = weight * g_spec[c]
                                gu, gv = _sample_backward(env, level_offset[level], level_h[level], level_w[level],
                                                          u, v, g_sample, g_env[chunk])
                                g_u += gu
                                g_v += gv
                        roughness = float(blended[i, j, 6]) / a
                        g_roughness = g_position * (levels - 1) if 0.0 <= roughness <= 1.0 else 0.0
                        g_blended[i, j, 6] = g_roughness / a
                        g_a -= g_roughness * roughness / a
                        # (u, v) -> unit direction -> reflected direction
                        x, y, z, length = state[_UNIT], state[_UNIT + 1], state[_UNIT + 2], state[_LENGTH]
                        flat = x * x + y * y
                        gx = gy = gz = 0.0
                        if flat > TINY:
                            gx -= g_u * y / (flat * math.pi)
                            gy += g_u * x / (flat * math.pi)
                        s = math.sqrt(flat + TINY)
                        d_atan = -g_v / (math.pi / 2) / (z * z + s * s)
                        gz += d_atan * s
                        gx -= d_atan * z * x / s
                        gy -= d_atan * z * y / s
                        g_dx = g_dy = g_dz = 0.0
                        if length > 0.0:
                            dot = x * gx + y * gy + z * gz
                            g_dx, g_dy, g_dz = ((gx - x * dot) / length, (gy - y * dot) / length,
                                                (gz - z * dot) / length)
                        # reflected = view - 2 <view, n> n
                        g_dn = g_dx * nx + g_dy * ny + g_dz * nz
                        g_nx = -2.0 * (vx * g_dn + vn * g_dx)
                        g_ny = -2.0 * (vy * g_dn + vn * g_dy)
                        g_nz = -2.0 * (vz * g_dn + vn * g_dz)
                    if lit:  # basis(n) and facing = max(-<view, n>, 0)
                        bx, by, bz = _sh2_backward(nx, ny, nz, g_basis)
                        g_nx += bx - (g_facing * vx if vn <= 0.0 else 0.0)
                        g_ny += by - (g_facing * vy if vn <= 0.0 else 0.0)
                        g_nz += bz - (g_facing * vz if vn <= 0.0 else 0.0)
                    for k in range(3):  # world -> camera: the rotation's transpose
                        g_normal[i, j, k] = rotation[0, k] * g_nx + rotation[1, k] * g_ny + rotation[2, k] * g_nz
                for c in range(3):
                    g_blended[i, j, c] = g_diffuse[c] / a
                    g_a -= g_diffuse[c] * blended[i, j, c] / a / a
                if alpha[i, j] >= floor:  # where the floor passes alpha's gradient
                    g_alpha[i, j] += g_a


def _pyramid(log_radiance: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """EnvironmentMap.pyramid of log radiance [3, H, 2H] as one flat array (each level [3, h, w] after the
    last) and the levels' heights, widths and offsets: exp, then 2 x 2 means (avg_pool2d: odd edges dropped)
    until one row is left."""
    levels = [np.exp(log_radiance)]
    while levels[-1].shape[1] > 1:
        c, h, w = levels[-1].shape
        levels.append(levels[-1][:, : h // 2 * 2, : w // 2 * 2].reshape(c, h // 2, 2, w // 2, 2).mean(axis=(2, 4)))
    sizes = np.array([level.size for level in levels])
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    return (np.concatenate([level.ravel() for level in levels]), np.array([level.shape[1] for level in levels]),
            np.array([level.shape[2] for level in levels]), offsets)


def _pyramid_backward(g_flat: np.ndarray, radiance: np.ndarray, heights, widths, offsets) -> np.ndarray:
    """d loss / d log radiance [3, H, 2H] from the flat pyramid's gradient: each level's share spread back over
    the 2 x 2 texels it averages, from the coarsest level to the finest, then times exp's derivative."""
    g_level = None
    for h, w, offset in reversed(list(zip(heights, widths, offsets))):
        g = g_flat[offset : offset + 3 * h * w].reshape(3, h, w).copy()
        if g_level is not None:
            g[:, : 2 * g_level.shape[1], : 2 * g_level.shape[2]] += np.repeat(np.repeat(g_level, 2, 1), 2, 2) / 4
        g_level = g
    return g_level * radiance


class _ShadeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, blended, alpha, normal, K, rotation, log_radiance, coefficients, camera, lit, saturate):
        arrays = tuple(_np(t) for t in (blended, alpha, normal))
        floor = float(np.asarray(ALPHA_FLOOR, arrays[1].dtype))  # as torch's clamp_min(1e-6) in alpha's dtype
        fixed = tuple(_np(t).astype(np.float64) for t in (K, rotation, coefficients, camera))
        if log_radiance is None:  # no specular: no pyramid
            layout = (np.zeros(0),) + (np.zeros(0, np.int64),) * 3
        else:
            layout = _pyramid(_np(log_radiance).astype(np.float64))
        env, heights, widths, offsets = layout
        drawn = (arrays[1] > 0).sum(axis=1)  # [H]
        first = np.concatenate([[0], np.cumsum(drawn)[:-1]])
        states = np.empty((drawn.sum(), _SAMPLES + 3 * len(heights)))
        rgb, albedo = np.empty(alpha.shape + (3,), arrays[0].dtype), np.empty(alpha.shape + (3,), arrays[0].dtype)
        _forward(arrays[0], arrays[1], floor, arrays[2], *fixed[:2], env, heights, widths, offsets, *fixed[2:], lit,
                 saturate, first, states, rgb, albedo)
        ctx.arrays, ctx.fixed, ctx.layout, ctx.flags, ctx.states = arrays, fixed, layout, (lit, saturate), (first,
                                                                                                         states)
        ctx.floor = floor
        ctx.dtypes = tuple(None if t is None else t.dtype for t in (log_radiance, coefficients, camera))
        return torch.from_numpy(rgb), torch.from_numpy(albedo)

    @staticmethod
    def backward(ctx, g_rgb, g_albedo):
        blended, alpha, normal = ctx.arrays
        env, heights, widths, offsets = ctx.layout
        g = (_np(g_rgb), _np(g_albedo))  # autograd passes zeros for an output without gradient
        g_blended, g_normal = np.empty(blended.shape, blended.dtype), np.empty(normal.shape, normal.dtype)
        g_alpha = np.empty(alpha.shape, alpha.dtype)
        chunks = min(_CHUNKS, alpha.shape[0])
        g_env, g_coefficients, g_camera = np.zeros((chunks, env.size)), np.zeros((chunks, 9, 3)), np.zeros((chunks, 3))
        _backward(blended, alpha, ctx.floor, ctx.fixed[1], env, heights, widths, offsets, *ctx.fixed[2:], *ctx.flags,
                  *ctx.states, *g, g_blended, g_alpha, g_normal, g_env, g_coefficients, g_camera)
        g_log = None
        if len(heights):
            radiance = env[: 3 * heights[0] * widths[0]].reshape(3, heights[0], widths[0])  # the finest level
            g_log = _pyramid_backward(g_env.sum(0), radiance, heights, widths, offsets)
        g_log, g_coefficients, g_camera = (None if array is None else torch.from_numpy(array).to(dtype)
                                           for array, dtype in zip((g_log, g_coefficients.sum(0), g_camera.sum(0)),
                                                                   ctx.dtypes))
        return (torch.from_numpy(g_blended), torch.from_numpy(g_alpha), torch.from_numpy(g_normal), None, None, g_log,
                g_coefficients, g_camera, None, None)


def shade_cpu(blended: torch.Tensor, alpha: torch.Tensor, normal: torch.Tensor, K: torch.Tensor,
              rotation: torch.Tensor, log_radiance: torch.Tensor | None, coefficients: torch.Tensor | None,
              camera: torch.Tensor | None, saturate: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """(premultiplied RGB [H, W, 3], albedo [H, W, 3]) of CPU tensors: blended [H, W, 7] (diffuse, tint,
    roughness; [H, W, 3] without the environment: diffuse only), alpha [H, W], unit camera-frame normals [H, W, 3],
    the intrinsics [3, 3] and the camera-to-world ``rotation`` [3, 3] (no gradient), the environment's
    ``log_radiance`` [3, H, 2H] (None: no specular), and the diffuse light's SH ``coefficients`` [9, 3] and
    ``camera`` light [3] (None: unlit); see :func:`.shading._shade`."""
    lit = coefficients is not None
    if not lit:
        coefficients, camera = blended.new_zeros((9, 3)), blended.new_zeros(3)
    return _ShadeCPU.apply(blended, alpha, normal, K, rotation, log_radiance, coefficients, camera, lit, saturate)
