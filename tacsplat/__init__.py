"""tacsplat: tactile-informed 3D Gaussian Splatting, from robot capture to reconstruction.

Subpackages, bottom to top (see DESIGN.md): core (``tacsplat.errors``,
``tacsplat.geometry``, ``tacsplat.types``), ``tacsplat.datasets``,
``tacsplat.drivers`` and ``tacsplat.reconstruction``, ``tacsplat.sim``,
``tacsplat.acquisition``, ``tacsplat.apps`` (benchmarks, demo, report), and
the CLI (``tacsplat.cli``).

Importing the package sets the process-wide environment defaults, here and
nowhere else; a value already in the environment always wins.
"""

import ctypes.util
import os
from importlib.metadata import PackageNotFoundError, version


def _environment_defaults() -> dict[str, str]:
    """Defaults that must be in place before torch, numba or MuJoCo are first imported."""
    gl = "egl" if ctypes.util.find_library("EGL") else "osmesa"  # MuJoCo's offscreen rendering, no display needed
    return {
        # torch's and numba's OpenMP thread pools spin-wait against each other on a small machine
        # (measured: 4-10x slower CPU rasterization on 2 cores); idle threads sleep instead
        "OMP_WAIT_POLICY": "PASSIVE",
        "MUJOCO_GL": gl,
        "PYOPENGL_PLATFORM": gl,
    }


for _key, _value in _environment_defaults().items():
    os.environ.setdefault(_key, _value)

try:
    __version__ = version("tacsplat")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
