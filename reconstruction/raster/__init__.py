"""The rasterizer: ``rasterization()`` (gsplat's call) and its backends.

* :mod:`.rendering` -- ``rasterization()``: argument checks and the backend choice; ``sh_colors()`` for a
  caller that composites its own channels;
* :mod:`.reference` -- the pure-PyTorch reference (projection and tile compositing, autograd backward);
* :mod:`.cpu_project`, :mod:`.cpu_composite` -- the numba CPU backend with hand-written backward passes;
* :mod:`.gsplat_backend` -- gsplat on CUDA;
* :mod:`.spherical_harmonics` -- view-dependent colour.
"""

from tacsplat.reconstruction.raster.rendering import BACKENDS, RENDER_MODES, rasterization, sh_colors

__all__ = ["BACKENDS", "RENDER_MODES", "rasterization", "sh_colors"]
