"""The Gaussian scene model: means, rotations, log-scales, opacity logits, SH colours, ``from_touch``.

Parameters are stored un-activated, as in Kerbl et al. and gsplat: ``scales``
are log-scales, ``opacities`` are logits, quaternions are (w, x, y, z) and
unnormalised, colours are real spherical-harmonic coefficients (``sh0`` the DC
band [N, 1, 3], ``shN`` the higher bands [N, (d+1)^2 - 1, 3]). The boolean
``from_touch`` marks the set G_t of the paper (Gaussians initialised on touch
points, and their clones and splits); the rest form G_c.
"""

from __future__ import annotations

import numpy as np
import torch

from tacsplat.errors import InvalidInputError

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi))
PARAM_NAMES = ("means", "quats", "scales", "opacities", "sh0", "shN")
MAX_SH_DEGREE = 3


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """DC SH coefficient whose colour is ``rgb`` (the renderer adds 0.5 to the SH sum)."""
    return (rgb - 0.5) / SH_C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    return sh0 * SH_C0 + 0.5


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients for a degree (1, 4, 9, 16)."""
    return (degree + 1) ** 2


def quats_to_rotmats(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N, 3, 3] of quaternions [N, 4] (w, x, y, z), normalised first."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([entry for row in rows for entry in row], dim=-1).reshape(quats.shape[:-1] + (3, 3))


def whitening(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """S^-1 R^T [N, 3, 3] from activated scales [N, 3]: maps an offset from a Gaussian's mean into its unit frame,
    so that |W d|^2 = d^T Sigma^-1 d with Sigma = R S S^T R^T (paper Eq. 3), without a 3x3 matrix product."""
    return quats_to_rotmats(quats).transpose(-1, -2) / scales[..., :, None]


class Gaussians:
    """A set of 3D Gaussians: a dict of ``torch.nn.Parameter`` (``PARAM_NAMES``, one row per Gaussian) plus the
    ``from_touch`` mask."""

    def __init__(self, params: dict[str, torch.Tensor], from_touch: torch.Tensor, sh_degree: int):
        if set(params) != set(PARAM_NAMES):
            raise InvalidInputError(f"Gaussians: expected the parameters {list(PARAM_NAMES)}, got {list(params)}")
        n = params["means"].shape[0]
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "scales": (n, 3),
            "opacities": (n,),
            "sh0": (n, 1, 3),
            "shN": (n, num_sh_bases(sh_degree) - 1, 3),
        }
        for name, shape in expected.items():
            if tuple(params[name].shape) != shape:
                raise InvalidInputError(f"Gaussians.{name}: expected shape {shape}, got {tuple(params[name].shape)}")
            if not torch.isfinite(params[name]).all():
                raise InvalidInputError(f"Gaussians.{name}: contains NaN or infinite values")
        if tuple(from_touch.shape) != (n,):
            raise InvalidInputError(f"Gaussians.from_touch: expected shape ({n},), got {tuple(from_touch.shape)}")
        if not 0 <= sh_degree <= MAX_SH_DEGREE:
            raise InvalidInputError(f"Gaussians: sh_degree must be in [0, {MAX_SH_DEGREE}], got {sh_degree}")
        self.params = {
            k: v if isinstance(v, torch.nn.Parameter) else torch.nn.Parameter(v.detach().float().contiguous())
            for k, v in ((k, params[k]) for k in PARAM_NAMES)
        }
        self.from_touch = from_touch.to(torch.bool)
        self.sh_degree = sh_degree

    @classmethod
    def from_points(
        cls,
        points: np.ndarray,  # [N, 3]
        colors: np.ndarray,  # [N, 3] in [0, 1]
        scales: np.ndarray,  # [N] isotropic scale in metres
        from_touch: np.ndarray,  # [N] bool
        sh_degree: int = 3,
        initial_opacity: float | np.ndarray = 0.1,  # one for all, or [N]
    ) -> "Gaussians":
        """Isotropic Gaussians at ``points`` with the given colours, scales and opacities, identity rotations."""
        n = len(points)
        opacity = np.broadcast_to(np.asarray(initial_opacity, dtype=np.float64), (n,))
        if not ((opacity > 0.0) & (opacity < 1.0)).all():
            raise InvalidInputError(f"initial_opacity must be in (0, 1), got {initial_opacity}")
        scales = np.asarray(scales, dtype=np.float64)
        if (scales <= 0).any() or not np.isfinite(scales).all():
            raise InvalidInputError("Gaussians.from_points: scales must be finite and positive")
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        params = {
            "means": torch.as_tensor(np.asarray(points), dtype=torch.float32).reshape(n, 3),
            "quats": quats,
            "scales": torch.as_tensor(np.log(scales), dtype=torch.float32)[:, None].repeat(1, 3),
            "opacities": torch.as_tensor(np.log(opacity / (1.0 - opacity)), dtype=torch.float32),
            "sh0": rgb_to_sh0(torch.as_tensor(np.asarray(colors), dtype=torch.float32).reshape(n, 1, 3)),
            "shN": torch.zeros(n, num_sh_bases(sh_degree) - 1, 3),
        }
        return cls(params, torch.as_tensor(np.asarray(from_touch, dtype=bool)), sh_degree)

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def num_touch(self) -> int:
        return int(self.from_touch.sum())

    @property
    def means(self) -> torch.Tensor:
        return self.params["means"]

    @property
    def quats(self) -> torch.Tensor:
        return self.params["quats"]

    @property
    def scales(self) -> torch.Tensor:
        """Activated scales [N, 3] (metres)."""
        return torch.exp(self.params["scales"])

    @property
    def opacities(self) -> torch.Tensor:
        """Activated opacities [N] in (0, 1)."""
        return torch.sigmoid(self.params["opacities"])

    def sh_coefficients(self, degree: int | None = None) -> torch.Tensor:
        """SH coefficients [N, (degree+1)^2, 3] up to ``degree`` (default: the model's)."""
        degree = self.sh_degree if degree is None else min(degree, self.sh_degree)
        return torch.cat([self.params["sh0"], self.params["shN"][:, : num_sh_bases(degree) - 1]], dim=1)

    def to(self, device) -> "Gaussians":
        """The same Gaussians with every tensor on ``device`` (new leaf parameters)."""
        params = {k: torch.nn.Parameter(v.detach().to(device)) for k, v in self.params.items()}
        return Gaussians(params, self.from_touch.to(device), self.sh_degree)

    def state_dict(self) -> dict:
        return {
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            "from_touch": self.from_touch.clone(),
            "sh_degree": self.sh_degree,
        }

    @classmethod
    def from_state_dict(cls, state: dict) -> "Gaussians":
        return cls(state["params"], state["from_touch"], int(state["sh_degree"]))
