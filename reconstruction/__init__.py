"""tacsplat.reconstruction: Gaussians, the rasterizer (:mod:`.raster`), losses, the trainer, evaluation.

The public names resolve here, each loading its own module on first use (``import tacsplat.reconstruction`` alone
loads no torch)::

    from tacsplat.reconstruction import TrainConfig, method_config, reconstruct, rasterization
"""

__all__ = [
    "rasterization",
    "TrainConfig",
    "METHODS",
    "method_config",
    "Trainer",
    "reconstruct",
    "evaluate_run",
    "Gaussians",
    "load_ply",
    "save_ply",
    "load_run",
]


def __getattr__(name: str):
    """A public name, imported on first use (static imports, which the layer check reads)."""
    if name == "rasterization":
        from tacsplat.reconstruction.raster import rendering as module
    elif name == "TrainConfig":
        from tacsplat.reconstruction import config as module
    elif name in ("METHODS", "method_config"):
        from tacsplat.reconstruction import methods as module
    elif name in ("Trainer", "reconstruct"):
        from tacsplat.reconstruction import trainer as module
    elif name == "evaluate_run":
        from tacsplat.reconstruction import evaluation as module
    elif name == "Gaussians":
        from tacsplat.reconstruction import gaussians as module
    elif name in ("load_ply", "save_ply"):
        from tacsplat.reconstruction import ply as module
    elif name == "load_run":
        from tacsplat.reconstruction import run_dir as module
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(module, name)


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
