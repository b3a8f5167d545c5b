"""Real spherical harmonics up to degree 3, in gsplat's (and 3DGS's) basis and order.

The colour of a Gaussian seen along the unit direction ``d`` (camera centre to
Gaussian mean) is ``max(sum_k Y_k(d) * c_k + 0.5, 0)`` (gsplat's convention).
"""

from __future__ import annotations

import torch
from torch import Tensor

from tacsplat.reconstruction.gaussians import SH_C0, num_sh_bases  # (band 0 and the coefficient count: the model's)

# Normalisation constants of the real SH basis (bands 1 to 3).
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Basis functions evaluated at unit directions ``dirs`` [..., 3] -> [..., (degree+1)^2]."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        basis += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        basis += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(basis, dim=-1)


def spherical_harmonics(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Raw SH value (no +0.5 offset) of ``coeffs`` [..., K, D] along ``dirs`` [..., 3] -> [..., D].

    ``dirs`` need not be normalised (a zero vector gives the degree-0 term only).
    Only the first (degree+1)^2 of the K >= (degree+1)^2 coefficients are used.
    """
    n_bases = num_sh_bases(degree)
    if coeffs.shape[-2] < n_bases:
        raise ValueError(f"SH degree {degree} needs {n_bases} coefficients, colors has {coeffs.shape[-2]}")
    unit = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, unit)  # [..., n_bases]
    return (basis.unsqueeze(-1) * coeffs[..., :n_bases, :]).sum(dim=-2)
