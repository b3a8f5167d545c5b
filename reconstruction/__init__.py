"""tacsplat.reconstruction (see DESIGN.md)."""

import os

# torch (its own OpenMP runtime) and numba's parallel kernels (another one) take turns on
# the same few cores; OpenMP's default spin-waiting after each parallel region then steals
# the cores from the other runtime (measured: 4x slower cpu rasterization on 2 cores).
# Sleeping idle threads avoid that. It only takes effect when set before torch is first
# imported, and a value already in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from tacsplat.reconstruction.rasterization import rasterization  # noqa: E402

__all__ = ["rasterization"]
