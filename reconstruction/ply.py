"""Save and load Gaussians in the exact PLY layout of the Inria 3DGS code (Kerbl et al.), which every viewer opens.

One binary little-endian ``vertex`` element of exactly 62 float32 properties
``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3`` (248
bytes per record, what the SIBR viewer reads): the normals are each Gaussian's
shortest axis (a flat Gaussian's normal), turned out of the surface (towards
the cameras that see it, in a run's; the Inria code writes zeros), opacity is the
logit, scales are log-scales, ``rot`` is (w, x, y, z), and the higher SH bands
are stored channel-major (all red coefficients, then green, then blue), padded
with zeros above the splat's SH degree to degree 3, as the Inria code writes
them. The ``from_touch`` flag (G_t vs G_c) is ours, so it lives beside the PLY
in ``<name>.touch.npy`` (a bool array, one flag per vertex).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement, PlyParseError

from tacsplat.errors import InvalidInputError, SceneFormatError
from tacsplat.files import atomic_file, storage_error
from tacsplat.reconstruction.gaussians import MAX_SH_DEGREE, Gaussians, num_sh_bases

INRIA_REST = num_sh_bases(MAX_SH_DEGREE) - 1  # 15 higher-band coefficients per channel


def _property_names(num_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(num_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def touch_sidecar_path(ply_path: str | Path) -> Path:
    """Where the ``from_touch`` flags of a PLY live: ``splat.ply`` -> ``splat.touch.npy``."""
    ply_path = Path(ply_path)
    return ply_path.with_name(ply_path.stem + ".touch.npy")


def save_ply(gaussians: Gaussians, path: str | Path, normals: torch.Tensor | None = None) -> Path:
    """Write ``gaussians`` to ``path`` and their touch flags to :func:`touch_sidecar_path` (parent directories
    created); returns the PLY's path. ``normals`` [N, 3]: the unit normals to write (default
    :func:`outward_normals`; a run writes :func:`.evaluation.facing_normals`). Both files are written in full before
    either replaces its old one, so a full or read-only disk (a StorageError naming the file) leaves the old pair as
    it was and no temporary file."""
    path = Path(path)
    make_parent(path)
    p = {k: v.detach().cpu().float() for k, v in gaussians.params.items()}
    n = len(gaussians)
    rest = torch.zeros(n, INRIA_REST, 3)
    rest[:, : p["shN"].shape[1]] = p["shN"]
    rest = rest.transpose(1, 2).reshape(n, 3 * INRIA_REST)  # [N, 45], channel-major
    normals = outward_normals(p["means"], p["quats"], p["scales"]) if normals is None else normals.detach().cpu()
    parts = [p["means"], normals, p["sh0"].reshape(n, 3), rest, p["opacities"][:, None], p["scales"], p["quats"]]
    columns = torch.cat(parts, dim=1).numpy()  # in _property_names' order
    data = np.rec.fromarrays(columns.T, dtype=[(name, "<f4") for name in _property_names(3 * INRIA_REST)])
    ply = io.BytesIO()
    PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<").write(ply)
    flags = io.BytesIO()
    np.save(flags, gaussians.from_touch.cpu().numpy().astype(bool))
    with atomic_file(touch_sidecar_path(path)) as sidecar:
        sidecar.write(flags.getvalue())
        sidecar.flush()  # a full disk fails here, before the PLY replaces its old one
        with atomic_file(path) as f:
            f.write(ply.getvalue())
    return path


def make_parent(path: Path) -> None:
    """Create the folder of ``path`` (and its parents); a full or read-only disk is a StorageError naming it."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise storage_error(exc, path.parent) from None


def outward_normals(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Unit normals [N, 3]: each Gaussian's shortest axis, signed to point away from the means' centroid."""
    from tacsplat.reconstruction.shading import gaussian_normals

    normals = gaussian_normals(quats, scales, fused=False)  # [N, 3], sign arbitrary
    away = ((means - means.mean(dim=0)) * normals).sum(dim=-1, keepdim=True) < 0
    return torch.where(away, -normals, normals)


def _touch_flags(ply_path: Path, vertex, n: int) -> torch.Tensor:
    """The sidecar's flags; all False without one (a splat of any other program). Files of earlier tacsplat
    versions kept the flag as a ``from_touch`` vertex property."""
    sidecar = touch_sidecar_path(ply_path)
    if not sidecar.is_file():
        legacy = "from_touch" in vertex.data.dtype.names
        return torch.from_numpy(np.asarray(vertex["from_touch"]) > 0) if legacy else torch.zeros(n, dtype=torch.bool)
    try:
        flags = np.load(sidecar, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise SceneFormatError(sidecar, None, f"not a .npy array of touch flags: {exc}") from exc
    if flags.dtype != np.bool_ or flags.shape != (n,):
        expected = f"expected {n} bool flags, one per Gaussian of {ply_path.name}"
        got = f"got {flags.size} flags for {n} Gaussians (dtype {flags.dtype})"
        raise SceneFormatError(sidecar, None, f"{expected}; {got}: the sidecar of another splat")
    return torch.from_numpy(flags.copy())


def _lowest_degree(shN: torch.Tensor) -> int:
    """The lowest SH degree whose bands hold every non-zero coefficient of ``shN`` [N, K, 3]."""
    nonzero = shN.ne(0).any(dim=(0, 2)).nonzero()
    if len(nonzero) == 0:
        return 0
    last = int(nonzero[-1]) + 1  # coefficients up to this one are needed
    return next(d for d in range(MAX_SH_DEGREE + 1) if num_sh_bases(d) - 1 >= last)


def load_ply(path: str | Path) -> Gaussians:
    """Read a 3DGS PLY (ours or any Inria-layout one) and its touch flags (:func:`touch_sidecar_path`).

    The SH degree is the lowest one whose bands hold every non-zero coefficient
    (the zero padding of the Inria layout renders identically at that degree).
    """
    path = Path(path)
    try:
        vertex = PlyData.read(str(path))["vertex"]
    except (OSError, KeyError, ValueError, PlyParseError) as exc:
        raise SceneFormatError(path, "vertex", f"cannot read a 3DGS PLY: {exc}") from exc
    names = set(vertex.data.dtype.names)
    num_rest = sum(1 for name in names if name.startswith("f_rest_"))
    file_degree = next((d for d in range(MAX_SH_DEGREE + 1) if 3 * (num_sh_bases(d) - 1) == num_rest), None)
    if file_degree is None:
        raise SceneFormatError(path, "f_rest_*", f"{num_rest} higher-order SH properties match no SH degree <= 3")
    if missing := [name for name in _property_names(num_rest) if name not in names and name[0] != "n"]:
        raise SceneFormatError(path, missing[0], "property missing from the vertex element")

    def cols(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertex[k], dtype=np.float32) for k in keys], axis=1))

    n = len(vertex.data)
    k_rest = num_sh_bases(file_degree) - 1
    shN = cols(*[f"f_rest_{i}" for i in range(num_rest)]).reshape(n, 3, k_rest).transpose(1, 2)
    degree = _lowest_degree(shN)
    params = {
        "means": cols("x", "y", "z"),
        "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
        "scales": cols("scale_0", "scale_1", "scale_2"),
        "opacities": cols("opacity")[:, 0],
        "sh0": cols("f_dc_0", "f_dc_1", "f_dc_2").reshape(n, 1, 3),
        "shN": shN[:, : num_sh_bases(degree) - 1].contiguous(),
    }
    flags = _touch_flags(path, vertex, n)
    try:
        return Gaussians(params, flags, degree)
    except InvalidInputError as exc:  # NaN or infinite values: the file is at fault
        raise SceneFormatError(path, "vertex", str(exc)) from None
