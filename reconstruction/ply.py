"""Save and load Gaussians in the standard 3DGS PLY layout (Kerbl et al.), readable by common viewers.

One binary little-endian ``vertex`` element with float32 properties
``x y z nx ny nz f_dc_0..2 f_rest_0..(3*(K-1)-1) opacity scale_0..2 rot_0..3``:
opacity is the logit, scales are log-scales, ``rot`` is (w, x, y, z), and the
higher SH bands are stored channel-major (all red coefficients, then green,
then blue), as the reference implementation writes them. One extra uchar
property, ``from_touch``, keeps the G_t / G_c split; viewers ignore it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from tacsplat.errors import SceneFormatError
from tacsplat.reconstruction.gaussians import MAX_SH_DEGREE, Gaussians, num_sh_bases


def _property_names(num_rest: int) -> list[str]:
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(num_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def save_ply(gaussians: Gaussians, path: str | Path) -> Path:
    """Write ``gaussians`` to ``path`` (parent directories created); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    p = {k: v.detach().cpu().float() for k, v in gaussians.params.items()}
    n = len(gaussians)
    rest = p["shN"].transpose(1, 2).reshape(n, -1)  # [N, 3 * (K - 1)], channel-major
    columns = torch.cat(
        [p["means"], torch.zeros(n, 3), p["sh0"].reshape(n, 3), rest, p["opacities"][:, None], p["scales"], p["quats"]],
        dim=1,
    ).numpy()
    names = _property_names(rest.shape[1])
    dtype = [(name, "f4") for name in names] + [("from_touch", "u1")]
    data = np.empty(n, dtype=dtype)
    for i, name in enumerate(names):
        data[name] = columns[:, i]
    data["from_touch"] = gaussians.from_touch.cpu().numpy().astype(np.uint8)
    tmp = path.with_name(path.name + ".tmp")
    PlyData([PlyElement.describe(data, "vertex")], text=False).write(str(tmp))
    tmp.replace(path)
    return path


def load_ply(path: str | Path) -> Gaussians:
    """Read a 3DGS PLY (ours or any standard one; ``from_touch`` defaults to False)."""
    path = Path(path)
    try:
        vertex = PlyData.read(str(path))["vertex"]
    except (OSError, KeyError, ValueError) as exc:
        raise SceneFormatError(path, "vertex", f"cannot read a 3DGS PLY: {exc}") from exc
    names = set(vertex.data.dtype.names)
    num_rest = sum(1 for name in names if name.startswith("f_rest_"))
    degree = next((d for d in range(MAX_SH_DEGREE + 1) if 3 * (num_sh_bases(d) - 1) == num_rest), None)
    if degree is None:
        raise SceneFormatError(path, "f_rest_*", f"{num_rest} higher-order SH properties match no SH degree <= 3")
    missing = [name for name in _property_names(num_rest) if name not in names and name[0] != "n"]
    if missing:
        raise SceneFormatError(path, missing[0], "property missing from the vertex element")

    def cols(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertex[k], dtype=np.float32) for k in keys], axis=1))

    n = len(vertex.data)
    k_rest = num_sh_bases(degree) - 1
    params = {
        "means": cols("x", "y", "z"),
        "quats": cols("rot_0", "rot_1", "rot_2", "rot_3"),
        "scales": cols("scale_0", "scale_1", "scale_2"),
        "opacities": cols("opacity")[:, 0],
        "sh0": cols("f_dc_0", "f_dc_1", "f_dc_2").reshape(n, 1, 3),
        "shN": (
            cols(*[f"f_rest_{i}" for i in range(num_rest)]).reshape(n, 3, k_rest).transpose(1, 2).contiguous()
            if num_rest
            else torch.zeros(n, 0, 3)
        ),
    }
    from_touch = torch.zeros(n, dtype=torch.bool)
    if "from_touch" in names:
        from_touch = torch.from_numpy(np.asarray(vertex["from_touch"]) > 0)
    return Gaussians(params, from_touch, degree)
