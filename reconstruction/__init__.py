"""tacsplat.reconstruction: Gaussians, the rasterizer (:mod:`.raster`), losses, the trainer, evaluation.

The public names resolve here, each loading its module on first use (``import tacsplat.reconstruction`` alone
loads no torch)::

    from tacsplat.reconstruction import TrainConfig, method_config, reconstruct, rasterization
"""

import importlib

_PUBLIC = {  # name -> the module that defines it
    "rasterization": "tacsplat.reconstruction.raster.rendering",
    "TrainConfig": "tacsplat.reconstruction.config",
    "METHODS": "tacsplat.reconstruction.methods",
    "method_config": "tacsplat.reconstruction.methods",
    "Trainer": "tacsplat.reconstruction.trainer",
    "reconstruct": "tacsplat.reconstruction.trainer",
    "evaluate_run": "tacsplat.reconstruction.evaluation",
    "Gaussians": "tacsplat.reconstruction.gaussians",
    "load_ply": "tacsplat.reconstruction.ply",
    "save_ply": "tacsplat.reconstruction.ply",
    "load_run": "tacsplat.reconstruction.run_dir",
}
__all__ = list(_PUBLIC)


def __getattr__(name: str):
    if name not in _PUBLIC:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(_PUBLIC[name]), name)


def __dir__() -> list[str]:
    return sorted({*globals(), *_PUBLIC})
