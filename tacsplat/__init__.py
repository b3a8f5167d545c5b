"""tacsplat: tactile-informed 3D Gaussian Splatting, from robot capture to reconstruction.

Subpackages (see DESIGN.md): ``tacsplat.drivers``, ``tacsplat.sim``,
``tacsplat.acquisition``, ``tacsplat.datasets``, ``tacsplat.reconstruction``.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("tacsplat")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
