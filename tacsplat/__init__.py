"""tacsplat: tactile-informed 3D Gaussian Splatting, from robot capture to reconstruction.

Subpackages (see DESIGN.md): ``tacsplat.drivers``, ``tacsplat.sim``,
``tacsplat.acquisition``, ``tacsplat.datasets``, ``tacsplat.reconstruction``.
"""

import os
from importlib.metadata import PackageNotFoundError, version

# Before torch or numba load an OpenMP runtime: their two thread pools spin-wait against each other
# on a small machine (a 10x slowdown of the cpu rasterizer with torch losses on 2 cores).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

try:
    __version__ = version("tacsplat")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
