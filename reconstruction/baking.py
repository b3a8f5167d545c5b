"""Plain 3DGS colours for Gaussians whose appearance is shaded: what a run's ``splat.ply`` carries.

The "sh-lit" appearance colours a pixel in a deferred pass (:mod:`.shading`) from blended normals and a learned
light, which no 3DGS viewer knows: its SH coefficients alone show the unlit albedo. :func:`bake_appearance` replaces each Gaussian's SH with the degree-3 SH that
best fits the colour it shows from every direction when it is shaded on its own (its own normal as the
pixel's, turned towards the viewer, as the renderer turns it), weighted by its projected area ``|<d, n>|``:
an edge-on surfel, where the turned normal flips and the colour jumps, covers nothing.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from tacsplat.reconstruction.gaussians import MAX_SH_DEGREE, Gaussians
from tacsplat.reconstruction.raster.spherical_harmonics import sh_basis
from tacsplat.reconstruction.shading import Look, gaussian_normals, shade_points

BAKE_DIRECTIONS = 256  # viewing directions the fit samples (a Fibonacci sphere)
BAKE_CHUNK = 4096  # Gaussians per batch (the samples of one batch: chunk x directions x 3 floats)


def sphere_directions(count: int, dtype=torch.float64) -> Tensor:
    """``count`` unit directions [count, 3] spread evenly over the sphere (a Fibonacci lattice)."""
    i = torch.arange(count, dtype=dtype) + 0.5
    z = 1.0 - 2.0 * i / count
    azimuth = math.pi * (3.0 - math.sqrt(5.0)) * i
    ring = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    return torch.stack([ring * torch.cos(azimuth), ring * torch.sin(azimuth), z], dim=-1)


def shaded_colors(gaussians: Gaussians, look: Look, directions: Tensor, normals: Tensor | None = None) -> Tensor:
    """The colour [N, D, 3] each Gaussian shows along each unit world view direction ``directions`` [D, 3]
    (camera to Gaussian) when the deferred shading (:func:`.shading.shade_points`) lights it alone: the pixel's
    normal is the Gaussian's (``normals`` [N, 3], default its shortest axis) turned towards the viewer, the
    pixel's albedo the Gaussian's SH colour along that direction."""
    g = gaussians
    if normals is None:
        normals = gaussian_normals(g.quats, g.scales)
    n_views = directions.shape[0]
    views = directions.to(g.means.dtype)[None].expand(len(g), -1, -1)  # [N, D, 3]
    n = normals[:, None, :].expand(-1, n_views, -1)  # [N, D, 3]
    n = torch.where((n * views).sum(-1, keepdim=True) > 0, -n, n)  # towards the viewer
    basis = sh_basis(g.sh_degree, views[0])  # [D, K]: the SH colour along each direction (3DGS's +0.5, >= 0)
    albedo = (torch.einsum("dk,nkc->ndc", basis, g.sh_coefficients(g.sh_degree)) + 0.5).clamp_min(0.0)
    shaded = shade_points(albedo.reshape(-1, 3), n.reshape(-1, 3), views.reshape(-1, 3), look.light)
    return shaded.reshape(len(g), n_views, 3)


@torch.no_grad()
def bake_appearance(gaussians: Gaussians, look: Look, directions: int = BAKE_DIRECTIONS) -> Gaussians:
    """The same Gaussians with degree-3 SH colours that a plain 3DGS renderer shows as ``look`` shades them
    (a weighted least-squares fit per Gaussian over ``directions`` views; see the module docstring). Gaussians
    of the "sh" appearance are returned as they are."""
    if look.appearance == "sh":
        return gaussians
    g = gaussians
    dirs = sphere_directions(directions).to(g.means.device)  # [D, 3] float64
    basis = sh_basis(MAX_SH_DEGREE, dirs)  # [D, 16]
    normals = gaussian_normals(g.quats, g.scales).double()  # [N, 3]
    fitted = [basis.new_zeros(0, basis.shape[1], 3)]  # (no Gaussians: no rows)
    for start in range(0, len(g), BAKE_CHUNK):
        rows = slice(start, min(start + BAKE_CHUNK, len(g)))
        part = Gaussians({k: v[rows] for k, v in g.params.items()}, g.from_touch[rows], g.sh_degree)
        target = shaded_colors(part, look, dirs, normals[rows].to(g.means.dtype)).double() - 0.5
        weight = (normals[rows] @ dirs.T).abs() + 1e-3  # [n, D]: projected area (never exactly 0)
        normal_matrix = torch.einsum("dk,nd,dl->nkl", basis, weight, basis)  # [n, 16, 16]
        normal_matrix += 1e-6 * torch.eye(basis.shape[1], dtype=basis.dtype, device=basis.device)
        rhs = torch.einsum("dk,nd,ndc->nkc", basis, weight, target)  # [n, 16, 3]
        fitted.append(torch.linalg.solve(normal_matrix, rhs))
    coeffs = torch.cat(fitted).to(g.means.dtype)  # [N, 16, 3]
    params = {k: g.params[k].detach().clone() for k in ("means", "quats", "scales", "opacities")}
    params["sh0"], params["shN"] = coeffs[:, :1].contiguous(), coeffs[:, 1:].contiguous()
    return Gaussians(params, g.from_touch.clone(), MAX_SH_DEGREE)
