"""Projection and SH colour of the ``cpu`` backend: numba kernels with hand-written backward.

The maths is :func:`.reference.project_gaussians` (classic mode) and
:func:`spherical_harmonics.spherical_harmonics` + gsplat's ``max(value + 0.5, 0)``,
fused per (camera, Gaussian) and computed in float64 registers. Gradients flow
to means, quats, scales and SH coefficients (not to the cameras: the caller
uses the torch projection when viewmats or Ks require gradients).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
import torch
from torch import Tensor

from tacsplat.reconstruction.raster.reference import ALPHA_THRESHOLD, FOV_CLAMP, GAUSSIAN_EXTEND
from tacsplat.reconstruction.raster.spherical_harmonics import SH_C0, SH_C1, SH_C2, SH_C3

_C2_0, _C2_1, _C2_2, _C2_3, _C2_4 = SH_C2
_C3_0, _C3_1, _C3_2, _C3_3, _C3_4, _C3_5, _C3_6 = SH_C3


_CHUNK = 256  # Gaussians per parallel work item of a backward (its scratch array is allocated once per chunk)


@nb.njit(cache=True, inline="always")
def _rotation(qw, qx, qy, qz):
    """Rotation matrix entries of a quaternion (normalised here, zero -> identity) and the norm used.

    Computed in the quaternion's own precision (float32 here, as in the reference and gsplat, so that a
    quaternion too large to square overflows the same way in every backend)."""
    norm = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
    w, x, y, z = qw / norm, qx / norm, qy / norm, qz / norm
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return r00, r01, r02, r10, r11, r12, r20, r21, r22, w, x, y, z, norm


@nb.njit(cache=True, inline="always")
def _rotation_backward(w, qx, qy, qz, qnorm, vr):
    """d loss / d (unnormalised) quaternion from vr [3, 3] = d loss / d R, with (w, qx, qy, qz) and qnorm the
    normalised quaternion and the norm :func:`_rotation` returned."""
    v00, v01, v02, v10, v11 = vr[0, 0], vr[0, 1], vr[0, 2], vr[1, 0], vr[1, 1]
    v12, v20, v21, v22 = vr[1, 2], vr[2, 0], vr[2, 1], vr[2, 2]
    v_w = 2.0 * (-qz * v01 + qy * v02 + qz * v10 - qx * v12 - qy * v20 + qx * v21)
    v_x = 2.0 * (qy * v01 + qz * v02 + qy * v10 - 2.0 * qx * v11 - w * v12 + qz * v20 + w * v21 - 2.0 * qx * v22)
    v_y = 2.0 * (-2.0 * qy * v00 + qx * v01 + w * v02 + qx * v10 + qz * v12 - w * v20 + qz * v21 - 2.0 * qy * v22)
    v_z = 2.0 * (-2.0 * qz * v00 - w * v01 + qx * v02 + w * v10 - 2.0 * qz * v11 + qy * v12 + qx * v20 + qy * v21)
    # through q / max(|q|, 1e-12)
    dot = (w * v_w + qx * v_x + qy * v_y + qz * v_z) if qnorm > 1e-12 else 0.0
    return (v_w - w * dot) / qnorm, (v_x - qx * dot) / qnorm, (v_y - qy * dot) / qnorm, (v_z - qz * dot) / qnorm


@nb.njit(cache=True, inline="always")
def _mul3(a, b):
    """a @ b of 3x3 matrices held as row-major 9-tuples (in registers, not arrays)."""
    return (
        a[0] * b[0] + a[1] * b[3] + a[2] * b[6],
        a[0] * b[1] + a[1] * b[4] + a[2] * b[7],
        a[0] * b[2] + a[1] * b[5] + a[2] * b[8],
        a[3] * b[0] + a[4] * b[3] + a[5] * b[6],
        a[3] * b[1] + a[4] * b[4] + a[5] * b[7],
        a[3] * b[2] + a[4] * b[5] + a[5] * b[8],
        a[6] * b[0] + a[7] * b[3] + a[8] * b[6],
        a[6] * b[1] + a[7] * b[4] + a[8] * b[7],
        a[6] * b[2] + a[7] * b[5] + a[8] * b[8],
    )


@nb.njit(cache=True, inline="always")
def _add3(a, b):
    """a + b of 3x3 matrices held as 9-tuples."""
    return (
        a[0] + b[0],
        a[1] + b[1],
        a[2] + b[2],
        a[3] + b[3],
        a[4] + b[4],
        a[5] + b[5],
        a[6] + b[6],
        a[7] + b[7],
        a[8] + b[8],
    )


@nb.njit(cache=True, inline="always")
def _transpose3(a):
    return a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8]


@nb.njit(parallel=True, cache=True)
def _project_forward(means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d, radius_clip, out):
    """EWA projection of every (camera, Gaussian) into ``out`` = (means2d, conics, depths, radii); culled ones get
    zeros. viewmats, Ks: float64."""
    means2d, conics, depths, radii = out
    n_cams, n = means2d.shape[0], means2d.shape[1]
    margin = FOV_CLAMP - 1.0
    for g in nb.prange(n):
        r00, r01, r02, r10, r11, r12, r20, r21, r22, _, _, _, _, _ = _rotation(
            quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3]
        )
        sx, sy, sz = np.float64(scales[g, 0]), np.float64(scales[g, 1]), np.float64(scales[g, 2])
        m = (r00 * sx, r01 * sy, r02 * sz, r10 * sx, r11 * sy, r12 * sz, r20 * sx, r21 * sy, r22 * sz)
        cov = _mul3(m, _transpose3(m))
        opac = np.float64(opacities[g])
        px, py, pz = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
        for c in range(n_cams):
            rv = viewmats[c]
            x = rv[0, 0] * px + rv[0, 1] * py + rv[0, 2] * pz + rv[0, 3]
            y = rv[1, 0] * px + rv[1, 1] * py + rv[1, 2] * pz + rv[1, 3]
            z = rv[2, 0] * px + rv[2, 1] * py + rv[2, 2] * pz + rv[2, 3]
            means2d[c, g, 0] = means2d[c, g, 1] = 0.0
            conics[c, g, 0] = conics[c, g, 1] = conics[c, g, 2] = 0.0
            depths[c, g] = 0.0
            radii[c, g, 0] = radii[c, g, 1] = 0
            if not (z >= near and z <= far):
                continue
            fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
            tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
            lim_xp, lim_xn = (width - cx) / fx + margin * tan_fovx, cx / fx + margin * tan_fovx
            lim_yp, lim_yn = (height - cy) / fy + margin * tan_fovy, cy / fy + margin * tan_fovy
            rz = 1.0 / z
            ux = min(lim_xp, max(-lim_xn, x * rz))
            uy = min(lim_yp, max(-lim_yn, y * rz))
            rot = (rv[0, 0], rv[0, 1], rv[0, 2], rv[1, 0], rv[1, 1], rv[1, 2], rv[2, 0], rv[2, 1], rv[2, 2])
            cc_ = _mul3(_mul3(rot, cov), _transpose3(rot))  # the camera-frame covariance
            # cov2d = J cov_c J^T with J = [[j00, 0, j02], [0, j11, j12]]
            j00, j02 = fx * rz, -fx * ux * rz
            j11, j12 = fy * rz, -fy * uy * rz
            jc00, jc01, jc02 = j00 * cc_[0] + j02 * cc_[6], j00 * cc_[1] + j02 * cc_[7], j00 * cc_[2] + j02 * cc_[8]
            jc11, jc12 = j11 * cc_[4] + j12 * cc_[7], j11 * cc_[5] + j12 * cc_[8]
            a = jc00 * j00 + jc02 * j02 + eps2d
            b = jc01 * j11 + jc02 * j12
            cc = jc11 * j11 + jc12 * j12 + eps2d
            det = a * cc - b * b
            if not det > 0 or opac < ALPHA_THRESHOLD:
                continue
            extend = min(GAUSSIAN_EXTEND, math.sqrt(2.0 * math.log(opac / ALPHA_THRESHOLD)))
            # in float, as on the torch backend: math.ceil's int64 overflows to a negative radius past 2**63
            rad_x, rad_y = np.ceil(extend * math.sqrt(a)), np.ceil(extend * math.sqrt(cc))
            if rad_x <= radius_clip and rad_y <= radius_clip:
                continue
            mx, my = fx * x * rz + cx, fy * y * rz + cy
            if mx + rad_x <= 0 or mx - rad_x >= width or my + rad_y <= 0 or my - rad_y >= height:
                continue
            if not (math.isfinite(rad_x) and math.isfinite(rad_y)):
                continue
            means2d[c, g, 0], means2d[c, g, 1] = mx, my
            conics[c, g, 0], conics[c, g, 1], conics[c, g, 2] = cc / det, -b / det, a / det
            depths[c, g] = z
            radii[c, g, 0], radii[c, g, 1] = min(rad_x, 2.0**30), min(rad_y, 2.0**30)


@nb.njit(parallel=True, cache=True, fastmath={"contract"})
def _project_backward(means, quats, scales, viewmats, Ks, width, height, eps2d, radii, v_out, grads):
    """Gradients ``v_out`` of means2d, conics and depths into ``grads``, those of means, quats and scales (summed
    over cameras); the small matrices are 9-tuples (J's two zeros left out), so they stay in registers."""
    v_means2d, v_conics, v_depths = v_out
    v_means, v_quats, v_scales = grads
    n_cams, n = v_means2d.shape[0], v_means2d.shape[1]
    margin = FOV_CLAMP - 1.0
    for chunk in nb.prange((n + _CHUNK - 1) // _CHUNK):
        vr = np.empty((3, 3))
        for g in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            r00, r01, r02, r10, r11, r12, r20, r21, r22, w, qx, qy, qz, qnorm = _rotation(
                quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3]
            )
            sx, sy, sz = np.float64(scales[g, 0]), np.float64(scales[g, 1]), np.float64(scales[g, 2])
            m = (r00 * sx, r01 * sy, r02 * sz, r10 * sx, r11 * sy, r12 * sz, r20 * sx, r21 * sy, r22 * sz)
            cov = _mul3(m, _transpose3(m))
            px, py, pz = np.float64(means[g, 0]), np.float64(means[g, 1]), np.float64(means[g, 2])
            vm0 = vm1 = vm2 = 0.0
            v_cov = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            for c in range(n_cams):
                if radii[c, g, 0] <= 0 or radii[c, g, 1] <= 0:
                    continue
                rv = viewmats[c]
                x = rv[0, 0] * px + rv[0, 1] * py + rv[0, 2] * pz + rv[0, 3]
                y = rv[1, 0] * px + rv[1, 1] * py + rv[1, 2] * pz + rv[1, 3]
                z = rv[2, 0] * px + rv[2, 1] * py + rv[2, 2] * pz + rv[2, 3]
                fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
                tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
                lim_xp, lim_xn = (width - cx) / fx + margin * tan_fovx, cx / fx + margin * tan_fovx
                lim_yp, lim_yn = (height - cy) / fy + margin * tan_fovy, cy / fy + margin * tan_fovy
                rz = 1.0 / z
                ux, uy = x * rz, y * rz
                clamp_x = ux < -lim_xn or ux > lim_xp
                clamp_y = uy < -lim_yn or uy > lim_yp
                ux, uy = min(lim_xp, max(-lim_xn, ux)), min(lim_yp, max(-lim_yn, uy))
                rot = (rv[0, 0], rv[0, 1], rv[0, 2], rv[1, 0], rv[1, 1], rv[1, 2], rv[2, 0], rv[2, 1], rv[2, 2])
                cc_ = _mul3(_mul3(rot, cov), _transpose3(rot))  # the camera-frame covariance
                # J = [[j00, 0, j02], [0, j11, j12]]
                j00, j02 = fx * rz, -fx * ux * rz
                j11, j12 = fy * rz, -fy * uy * rz
                jc00, jc01, jc02 = j00 * cc_[0] + j02 * cc_[6], j00 * cc_[1] + j02 * cc_[7], j00 * cc_[2] + j02 * cc_[8]
                jc10, jc11, jc12 = j11 * cc_[3] + j12 * cc_[6], j11 * cc_[4] + j12 * cc_[7], j11 * cc_[5] + j12 * cc_[8]
                a = jc00 * j00 + jc02 * j02 + eps2d
                b = jc01 * j11 + jc02 * j12
                cc = jc11 * j11 + jc12 * j12 + eps2d
                det = a * cc - b * b
                # conic = (cc, -b, a) / det
                pa, pb, pc = np.float64(v_conics[c, g, 0]), np.float64(v_conics[c, g, 1]), np.float64(v_conics[c, g, 2])
                inv, inv2 = 1.0 / det, 1.0 / (det * det)
                va = pa * (-cc * cc * inv2) + pb * (b * cc * inv2) + pc * (inv - a * cc * inv2)
                vb = pa * (2.0 * b * cc * inv2) + pb * (-inv - 2.0 * b * b * inv2) + pc * (2.0 * a * b * inv2)
                vc = pa * (inv - a * cc * inv2) + pb * (a * b * inv2) + pc * (-a * a * inv2)
                # d / d cov_c = J^T V J with V = [[va, vb], [0, vc]] (cov2d's [0, 1] entry stands for both)
                t0, t1, t2 = va * j00, vb * j11, va * j02 + vb * j12  # V J, first row
                u1, u2 = vc * j11, vc * j12  # second row (its first entry is 0)
                w1, w2 = j02 * t1 + j12 * u1, j02 * t2 + j12 * u2  # (the last row's)
                vcc = (j00 * t0, j00 * t1, j00 * t2, 0.0, j11 * u1, j11 * u2, j02 * t0, w1, w2)  # d / d cov_c
                v_cov = _add3(v_cov, _mul3(_mul3(_transpose3(rot), vcc), rot))
                # d / d J = (V + V^T) J cov_c: only the entries J depends on
                vj00 = 2.0 * va * jc00 + vb * jc10
                vj02 = 2.0 * va * jc02 + vb * jc12
                vj11 = vb * jc01 + 2.0 * vc * jc11
                vj12 = vb * jc02 + 2.0 * vc * jc12
                vmx, vmy = np.float64(v_means2d[c, g, 0]), np.float64(v_means2d[c, g, 1])
                v_x = vmx * fx * rz
                v_y = vmy * fy * rz
                v_z = -(vmx * fx * x + vmy * fy * y) * rz * rz + np.float64(v_depths[c, g])
                v_z += -(vj00 * fx + vj11 * fy) * rz * rz
                # J02 = -fx * ux / z with ux = clamp(x / z), likewise J12
                if clamp_x:
                    v_z += vj02 * fx * ux * rz * rz
                else:
                    v_x += vj02 * (-fx * rz * rz)
                    v_z += vj02 * 2.0 * fx * x * rz * rz * rz
                if clamp_y:
                    v_z += vj12 * fy * uy * rz * rz
                else:
                    v_y += vj12 * (-fy * rz * rz)
                    v_z += vj12 * 2.0 * fy * y * rz * rz * rz
                vm0 += rv[0, 0] * v_x + rv[1, 0] * v_y + rv[2, 0] * v_z
                vm1 += rv[0, 1] * v_x + rv[1, 1] * v_y + rv[2, 1] * v_z
                vm2 += rv[0, 2] * v_x + rv[1, 2] * v_y + rv[2, 2] * v_z
            v_means[g, 0], v_means[g, 1], v_means[g, 2] = vm0, vm1, vm2
            # covariance = M M^T with M = R diag(s): d / d M = (V + V^T) M
            v_m = _mul3(_add3(v_cov, _transpose3(v_cov)), m)
            rot_g = (r00, r01, r02, r10, r11, r12, r20, r21, r22)
            s3 = (sx, sy, sz)
            for k in range(3):
                v_scales[g, k] = v_m[k] * rot_g[k] + v_m[3 + k] * rot_g[3 + k] + v_m[6 + k] * rot_g[6 + k]
                for r in range(3):
                    vr[r, k] = v_m[3 * r + k] * s3[k]  # d loss / d R
            v_quats[g, 0], v_quats[g, 1], v_quats[g, 2], v_quats[g, 3] = _rotation_backward(w, qx, qy, qz, qnorm, vr)


@nb.njit(cache=True, inline="always")
def _sh_basis(degree, x, y, z, out):
    xx, yy, zz = x * x, y * y, z * z
    out[0] = SH_C0
    if degree >= 1:
        out[1], out[2], out[3] = -SH_C1 * y, SH_C1 * z, -SH_C1 * x
    if degree >= 2:
        out[4], out[5] = _C2_0 * x * y, _C2_1 * y * z
        out[6] = _C2_2 * (2.0 * zz - xx - yy)
        out[7], out[8] = _C2_3 * x * z, _C2_4 * (xx - yy)
    if degree >= 3:
        out[9] = _C3_0 * y * (3.0 * xx - yy)
        out[10] = _C3_1 * x * y * z
        out[11] = _C3_2 * y * (4.0 * zz - xx - yy)
        out[12] = _C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
        out[13] = _C3_4 * x * (4.0 * zz - xx - yy)
        out[14] = _C3_5 * z * (xx - yy)
        out[15] = _C3_6 * x * (xx - 3.0 * yy)


@nb.njit(cache=True, inline="always")
def _sh_basis_grad(degree, x, y, z, weights):
    """Sum_k weights[k] * grad basis_k at (x, y, z)."""
    gx = gy = gz = 0.0
    xx, yy, zz = x * x, y * y, z * z
    if degree >= 1:
        gx -= SH_C1 * weights[3]
        gy -= SH_C1 * weights[1]
        gz += SH_C1 * weights[2]
    if degree >= 2:
        w4, w5, w6 = weights[4] * _C2_0, weights[5] * _C2_1, weights[6] * _C2_2
        w7, w8 = weights[7] * _C2_3, weights[8] * _C2_4
        gx += w4 * y - 2.0 * w6 * x + w7 * z + 2.0 * w8 * x
        gy += w4 * x + w5 * z - 2.0 * w6 * y - 2.0 * w8 * y
        gz += w5 * y + 4.0 * w6 * z + w7 * x
    if degree >= 3:
        w9, w10, w11 = weights[9] * _C3_0, weights[10] * _C3_1, weights[11] * _C3_2
        w12, w13, w14, w15 = weights[12] * _C3_3, weights[13] * _C3_4, weights[14] * _C3_5, weights[15] * _C3_6
        gx += (
            w9 * 6.0 * x * y
            + w10 * y * z
            - w11 * 2.0 * x * y
            - w12 * 6.0 * x * z
            + w13 * (4.0 * zz - 3.0 * xx - yy)
            + w14 * 2.0 * x * z
            + w15 * (3.0 * xx - 3.0 * yy)
        )
        gy += (
            w9 * (3.0 * xx - 3.0 * yy)
            + w10 * x * z
            + w11 * (4.0 * zz - xx - 3.0 * yy)
            - w12 * 6.0 * y * z
            - w13 * 2.0 * x * y
            - w14 * 2.0 * y * z
            - w15 * 6.0 * x * y
        )
        gz += (
            w10 * x * y
            + w11 * 8.0 * y * z
            + w12 * (6.0 * zz - 3.0 * xx - 3.0 * yy)
            + w13 * 8.0 * x * z
            + w14 * (xx - yy)
        )
    return gx, gy, gz


@nb.njit(parallel=True, cache=True)
def _sh_forward(degree, means, campos, coeffs, radii, colors):
    """colors[c, g] = max(SH(coeffs[g], direction camera->mean) + 0.5, 0); culled Gaussians get 0.5."""
    n_cams, n, n_ch = colors.shape
    n_bases = (degree + 1) ** 2
    for g in nb.prange(n):
        basis = np.empty(16)
        for c in range(n_cams):
            dx = np.float64(means[g, 0]) - campos[c, 0]
            dy = np.float64(means[g, 1]) - campos[c, 1]
            dz = np.float64(means[g, 2]) - campos[c, 2]
            norm = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            visible = radii[c, g, 0] > 0 and radii[c, g, 1] > 0
            _sh_basis(degree, dx / norm, dy / norm, dz / norm, basis)
            for ch in range(n_ch):
                value = 0.0
                if visible:
                    for k in range(n_bases):
                        value += basis[k] * coeffs[g, k, ch]
                colors[c, g, ch] = max(value + 0.5, 0.0)


@nb.njit(parallel=True, cache=True, fastmath={"contract"})
def _sh_backward(degree, means, campos, coeffs, radii, colors, v_colors, v_coeffs, v_means):
    """Gradients of the SH colours w.r.t. coefficients and means (summed over cameras)."""
    n_cams, n, n_ch = colors.shape
    n_bases = (degree + 1) ** 2
    for g in nb.prange(n):
        basis = np.empty(16)
        weights = np.zeros(16)
        v_coeffs[g] = 0.0
        v_means[g] = 0.0
        for c in range(n_cams):
            if radii[c, g, 0] <= 0 or radii[c, g, 1] <= 0:
                continue
            dx = np.float64(means[g, 0]) - campos[c, 0]
            dy = np.float64(means[g, 1]) - campos[c, 1]
            dz = np.float64(means[g, 2]) - campos[c, 2]
            norm = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
            ux, uy, uz = dx / norm, dy / norm, dz / norm
            _sh_basis(degree, ux, uy, uz, basis)
            weights[:n_bases] = 0.0
            for ch in range(n_ch):
                if colors[c, g, ch] <= 0.0:  # clamped at 0: no gradient
                    continue
                v = np.float64(v_colors[c, g, ch])
                for k in range(n_bases):
                    v_coeffs[g, k, ch] += basis[k] * v
                    weights[k] += coeffs[g, k, ch] * v
            gx, gy, gz = _sh_basis_grad(degree, ux, uy, uz, weights)
            if norm > 1e-12:
                dot = ux * gx + uy * gy + uz * gz
                v_means[g, 0] += (gx - ux * dot) / norm
                v_means[g, 1] += (gy - uy * dot) / norm
                v_means[g, 2] += (gz - uz * dot) / norm


def _np(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().numpy())


class _ProjectCPU(torch.autograd.Function):
    """Classic-mode projection: ``apply(means [N, 3] float32, quats [N, 4], scales [N, 3], opacities [N], viewmats
    [C, 4, 4], Ks [C, 3, 3], width, height, near_plane, far_plane, eps2d, radius_clip)`` -> (means2d [C, N, 2],
    conics [C, N, 3], depths [C, N], radii [C, N, 2] int32)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d, radius_clip):
        n_cams, n = viewmats.shape[0], means.shape[0]
        means2d = torch.empty(n_cams, n, 2)
        conics = torch.empty(n_cams, n, 3)
        depths = torch.empty(n_cams, n)
        radii = torch.empty(n_cams, n, 2, dtype=torch.int32)
        args = (_np(means), _np(quats), _np(scales))
        cams = (_np(viewmats).astype(np.float64), _np(Ks).astype(np.float64))
        planes = (float(np.float32(near)), float(np.float32(far)))
        out = (means2d.numpy(), conics.numpy(), depths.numpy(), radii.numpy())
        _project_forward(*args, _np(opacities), *cams, width, height, *planes, float(eps2d), float(radius_clip), out)
        ctx.arrays = args + cams + (width, height, float(eps2d), radii.numpy())
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii):
        means, quats, scales, radii = ctx.arrays[0], ctx.arrays[1], ctx.arrays[2], ctx.arrays[-1]
        v_means, v_quats, v_scales = torch.empty(means.shape), torch.empty(quats.shape), torch.empty(scales.shape)
        v_depths = v_depths if v_depths is not None else torch.zeros(radii.shape[:2])
        v_out = (_np(v_means2d), _np(v_conics), _np(v_depths))
        _project_backward(*ctx.arrays, v_out, (v_means.numpy(), v_quats.numpy(), v_scales.numpy()))
        return v_means, v_quats, v_scales, None, None, None, None, None, None, None, None, None


class _SphericalHarmonicsCPU(torch.autograd.Function):
    """gsplat's SH colours max(SH + 0.5, 0) of every (camera, Gaussian): ``apply(degree, means [N, 3], campos
    [C, 3], coeffs [N, K, D], radii [C, N, 2])`` -> [C, N, D]."""

    @staticmethod
    def forward(ctx, degree, means, campos, coeffs, radii):
        n_cams, n = radii.shape[:2]
        colors = torch.empty(n_cams, n, coeffs.shape[-1])
        arrays = (_np(means), _np(campos).astype(np.float64), _np(coeffs), _np(radii))
        _sh_forward(degree, *arrays, colors.numpy())
        ctx.degree, ctx.arrays = degree, arrays
        ctx.save_for_backward(colors)
        return colors

    @staticmethod
    def backward(ctx, v_colors):
        (colors,) = ctx.saved_tensors
        means, _, coeffs, _ = ctx.arrays
        v_coeffs, v_means = torch.empty(coeffs.shape), torch.empty(means.shape)
        _sh_backward(ctx.degree, *ctx.arrays, colors.numpy(), _np(v_colors), v_coeffs.numpy(), v_means.numpy())
        return None, v_means, None, v_coeffs, None


project_gaussians_cpu = _ProjectCPU.apply
sh_colors_cpu = _SphericalHarmonicsCPU.apply
