"""Space a grasp proved empty: the hand's solid boxes along its recorded motion (not in the paper).

Every sample of a grasp's :class:`~tacsplat.datasets.HandMotion` before the
release (the preshape and the close) places the palm, each link and each gel
somewhere the object is not. :func:`free_space` voxelises their union, each box
shrunk by ``margin`` for the error of the hand model and its calibration, and
then gives back every voxel within reach of a contact: there the object may
push into the gel by as much as the deepest indentation recorded. Nothing
beyond a box's surface is claimed, so a gel that stopped on the object carves
up to the surface it touched and a finger that closed on nothing carves what it
swept. The release is left out: it goes back the way the fingers came.

Training penalises the opacity of every Gaussian whose centre lies in a free
voxel (:func:`free_space_loss`); the usual pruning then removes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from tacsplat.datasets.records import MOTION_PHASES

CARVING_PHASES = ("preshape", "close")  # the motion samples whose boxes are free space
MAX_VOXELS = 2**28  # a grid larger than this (256 MiB of booleans) asks for a coarser voxel


@dataclass(frozen=True)
class FreeSpace:
    """A boolean voxel grid: ``free[i, j, k]`` is True when the centre ``origin + (ijk + 0.5) * voxel`` is free."""

    free: np.ndarray  # [X, Y, Z] bool
    origin: np.ndarray  # [3] metres
    voxel: float  # metres

    @property
    def volume_m3(self) -> float:
        return float(self.free.sum()) * self.voxel**3

    def contains(self, points: np.ndarray) -> np.ndarray:
        """[N] bool: which of ``points`` [N, 3] lie in a free voxel."""
        ijk = np.floor((np.asarray(points, dtype=np.float64) - self.origin) / self.voxel).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < self.free.shape), axis=1)
        out = np.zeros(len(ijk), dtype=bool)
        i, j, k = ijk[inside].T
        out[inside] = self.free[i, j, k]
        return out


def carving_boxes(motions, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The boxes of every motion's preshape and close samples, each shrunk by ``margin`` (those that vanish
    dropped), identical placements once: ``(T_world_box [B, 4, 4], half_extents [B, 3])``."""
    phases = [MOTION_PHASES.index(p) for p in CARVING_PHASES]
    poses, extents = [], []
    for m in motions:
        keep = np.isin(m.phase, phases)
        T = m.link_poses[keep].reshape(-1, 4, 4)  # [S * L, 4, 4]
        h = np.tile(m.link_half_extents - margin, (int(keep.sum()), 1))  # [S * L, 3]
        poses.append(T)
        extents.append(h)
    if not poses:
        return np.zeros((0, 4, 4)), np.zeros((0, 3))
    T, h = np.concatenate(poses), np.concatenate(extents)
    solid = np.all(h > 0, axis=1)
    T, h = T[solid], h[solid]
    key = np.round(np.concatenate([T[:, :3].reshape(len(T), 12), h], axis=1), 6)  # (a static palm, a still link)
    _, first = np.unique(key, axis=0, return_index=True)
    first.sort()
    return T[first], h[first]


def free_space(
    motions, contact_points: np.ndarray, max_indentation: float, margin: float = 0.001, voxel: float = 0.001
) -> FreeSpace | None:
    """The free space of ``motions`` (HandMotion records) as a voxel grid, with every voxel within
    ``max_indentation + margin`` of a contact point [M, 3] given back; None when no box is left."""
    T, h = carving_boxes(motions, margin)
    if not len(T):
        return None
    reach = np.abs(T[:, :3, :3]) @ h[:, :, None]  # [B, 3, 1]: half-size of each box's axis-aligned bounds
    lo = (T[:, :3, 3] - reach[..., 0]).min(axis=0)
    hi = (T[:, :3, 3] + reach[..., 0]).max(axis=0)
    shape = np.maximum(np.ceil((hi - lo) / voxel).astype(np.int64), 1)
    if math.prod(shape.tolist()) > MAX_VOXELS:
        raise ValueError(f"free space of {shape.tolist()} voxels of {voxel} m: use a coarser voxel")
    free = np.zeros(tuple(shape.tolist()), dtype=np.bool_)
    _fill_boxes(free, lo, voxel, np.ascontiguousarray(T[:, :3, :3]), np.ascontiguousarray(T[:, :3, 3]), h)
    points = np.asarray(contact_points, dtype=np.float64).reshape(-1, 3)
    if len(points):
        _clear_near(free, lo, voxel, points, float(max_indentation + margin))
    return FreeSpace(free, lo, voxel)


def free_space_loss(means, opacities, space: FreeSpace, grid=None):
    """Sum of the opacities of the Gaussians whose centres lie in free space (``means`` [N, 3], ``opacities`` [N]
    logits; ``grid``: ``space.free`` as a torch tensor on their device, to avoid a copy per call)."""
    import torch

    free = torch.as_tensor(space.free, device=means.device) if grid is None else grid
    origin = torch.as_tensor(space.origin, dtype=means.dtype, device=means.device)
    ijk = torch.floor((means.detach() - origin) / space.voxel).long()  # [N, 3]
    size = torch.tensor(free.shape, device=means.device)
    inside = torch.all((ijk >= 0) & (ijk < size), dim=1)
    ijk = torch.where(inside[:, None], ijk, torch.zeros_like(ijk))
    hit = inside & free[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    return torch.sigmoid(opacities[hit]).sum()


@nb.njit(cache=True)
def _fill_boxes(free, origin, voxel, R, t, h):
    """Set every voxel whose centre lies in one of the boxes (rotation R [B, 3, 3], centre t [B, 3], half
    extents h [B, 3]): for each column of voxel centres in a box's bounds, the z-interval inside the box."""
    nx, ny, nz = free.shape
    for b in range(R.shape[0]):
        reach = np.abs(R[b]) @ h[b]
        i0 = max(0, int(math.ceil((t[b, 0] - reach[0] - origin[0]) / voxel - 0.5)))
        i1 = min(nx - 1, int(math.floor((t[b, 0] + reach[0] - origin[0]) / voxel - 0.5)))
        j0 = max(0, int(math.ceil((t[b, 1] - reach[1] - origin[1]) / voxel - 0.5)))
        j1 = min(ny - 1, int(math.floor((t[b, 1] + reach[1] - origin[1]) / voxel - 0.5)))
        for i in range(i0, i1 + 1):
            dx = origin[0] + (i + 0.5) * voxel - t[b, 0]
            for j in range(j0, j1 + 1):
                dy = origin[1] + (j + 0.5) * voxel - t[b, 1]
                zlo, zhi = -np.inf, np.inf
                for a in range(3):  # |R[:, a] . (p - t)| <= h[a] along the column p = (x, y, z)
                    c = R[b, 0, a] * dx + R[b, 1, a] * dy
                    s = R[b, 2, a]
                    if abs(s) < 1e-12:
                        if abs(c) > h[b, a]:
                            zhi = -np.inf
                            break
                    else:
                        z1 = (-h[b, a] - c) / s
                        z2 = (h[b, a] - c) / s
                        zlo = max(zlo, min(z1, z2))
                        zhi = min(zhi, max(z1, z2))
                if zlo > zhi:
                    continue
                k0 = max(0, int(math.ceil((t[b, 2] + zlo - origin[2]) / voxel - 0.5)))
                k1 = min(nz - 1, int(math.floor((t[b, 2] + zhi - origin[2]) / voxel - 0.5)))
                for k in range(k0, k1 + 1):
                    free[i, j, k] = True


@nb.njit(cache=True)
def _clear_near(free, origin, voxel, points, radius):
    """Clear every voxel whose centre lies within ``radius`` of one of ``points`` [M, 3]."""
    n = free.shape
    r = int(math.ceil(radius / voxel)) + 1
    for p in range(points.shape[0]):
        c = np.floor((points[p] - origin) / voxel)
        for i in range(max(0, int(c[0]) - r), min(n[0], int(c[0]) + r + 1)):
            dx = origin[0] + (i + 0.5) * voxel - points[p, 0]
            for j in range(max(0, int(c[1]) - r), min(n[1], int(c[1]) + r + 1)):
                dy = origin[1] + (j + 0.5) * voxel - points[p, 1]
                for k in range(max(0, int(c[2]) - r), min(n[2], int(c[2]) + r + 1)):
                    dz = origin[2] + (k + 0.5) * voxel - points[p, 2]
                    if dx * dx + dy * dy + dz * dz <= radius * radius:
                        free[i, j, k] = False
