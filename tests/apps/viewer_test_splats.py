"""Splats for the `tacsplat view` tests: Gaussians of a small object with whatever sizes a test needs."""

from __future__ import annotations

import numpy as np
import torch

from tacsplat.reconstruction.gaussians import Gaussians


def splat(log_scales: np.ndarray, seed: int = 0) -> Gaussians:
    """Gaussians around a 10 cm object with the given log-scales [N, 3]; every 4th one is a touch Gaussian."""
    rng = np.random.default_rng(seed)
    n = len(log_scales)
    return Gaussians(
        {
            "means": torch.tensor(rng.normal(0, 0.05, (n, 3)), dtype=torch.float32),
            "quats": torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
            "scales": torch.tensor(log_scales, dtype=torch.float32),
            "opacities": torch.tensor(rng.choice([-1e4, 0.0, 1e4], n), dtype=torch.float32),
            "sh0": torch.tensor(rng.choice([-1e4, 0.0, 1e4], (n, 1, 3)), dtype=torch.float32),
            "shN": torch.zeros(n, 0, 3),
        },
        torch.arange(n) % 4 == 0,
        0,
    )
