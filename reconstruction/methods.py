"""The reconstruction methods by name: the paper's Table 3 rows and ours.

A method is a name, the label the tables print, and the :class:`~tacsplat.reconstruction.config.TrainConfig`
fields it sets on top of TrainConfig's defaults, which are ``default`` (ours, beyond the paper). Any other
combination is a configuration: a method plus overrides (``--config FILE.yaml`` and options of `tacsplat
reconstruct`, the ablation rows of `tacsplat bench paper`). A run's metrics.json records the method whose
mechanisms (:func:`mechanisms`) it has, ``custom`` when none has them, and the mechanisms themselves, as the run
used them: touch is off in a run that had no touch points (its scene has no touches), and a mechanism that starts
at a step the run never reached is off.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tacsplat.errors import ConfigError


@dataclass(frozen=True)
class Method:
    name: str  # as in file names, results.csv and metrics.json
    label: str  # as the tables print it
    description: str
    overrides: dict = field(default_factory=dict)  # TrainConfig fields it sets ("init.x": its InitConfig's x)


# the paper's method: touch and smoothness with view-dependent SH colour; none of our surface-normal losses,
# unlit colour, touch Gaussians starting with random colours
_PAPER = {
    "lambda_flatten": 0.0,
    "lambda_depth_normal": 0.0,
    "appearance": "sh",
    "lambda_albedo_smoothness": 0.0,
    "init.colors_from_views": False,
}

METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method(
            "3dgs", "3DGS", "vanilla 3DGS: no touch, no smoothness", {**_PAPER, "use_touch": False, "lambda_s": 0.0}
        ),
        Method(
            "3dgs+s", "3DGS + S", "edge-aware depth smoothness L_S (Eq. 8), no touch", {**_PAPER, "use_touch": False}
        ),
        Method(
            "3dgs+t",
            "3DGS + T",
            "touch Gaussians and transmittance L_T (Eq. 7), no smoothness",
            {**_PAPER, "lambda_s": 0.0},
        ),
        Method("paper", "Paper (T + S)", "touch and smoothness: the paper's full method", _PAPER),
        Method(
            "default",
            "Default (ours)",
            "the paper's method plus flat Gaussians, depth-normal consistency, SH colour lit at the rendered "
            "normals with a smooth albedo, and touch Gaussians coloured from the views (beyond the paper)",
        ),
    )
}
PAPER_METHODS = ("3dgs", "3dgs+s", "3dgs+t", "paper")  # the paper's Table 3
DEFAULT_METHOD = "default"


def get_method(name: str, option: str = "--method") -> Method:
    """The method called ``name``; a ConfigError naming ``option`` and the choices otherwise."""
    if name not in METHODS:
        raise ConfigError(option, f"unknown method {name!r}; choose one of {', '.join(METHODS)}")
    return METHODS[name]


def method_config(name: str, option: str = "--method"):
    """The TrainConfig of method ``name``."""
    from tacsplat.reconstruction.config import TrainConfig, set_fields

    return set_fields(TrainConfig(), get_method(name, option).overrides)


# the mechanisms that start at a step (their TrainConfig field): a run that ends at or before it never uses them
START_STEPS = {
    "smoothness": "smoothness_start_iter",
    "depth_normal": "depth_normal_start_iter",
    "sh_lit": "lit_start_iter",
}


def mechanisms(config, touched: bool | None = None) -> dict[str, bool]:
    """Which of the optional mechanisms a TrainConfig switches on: touch (used, with lambda_t > 0), smoothness,
    flattening, depth-normal consistency, the sh-lit appearance, a smooth albedo (with it), initial colours from the
    views. ``touched``: None for the config as set up; for a run, whether it had touch points, and then those it
    used: touch only with touch points (a scene without touches trains without), and none whose start step
    (:data:`START_STEPS`) is at or past its iterations (a run ending before it never reaches it)."""
    on = {
        "touch": config.use_touch and config.lambda_t > 0 and (touched is None or bool(touched)),
        "smoothness": config.lambda_s > 0,
        "flattening": config.lambda_flatten > 0,
        "depth_normal": config.lambda_depth_normal > 0,
        "sh_lit": config.appearance == "sh-lit",
        "albedo_smoothness": config.appearance != "sh" and config.lambda_albedo_smoothness > 0,
        "view_colors": config.init.colors_from_views,
    }
    if touched is not None:
        for name, start in START_STEPS.items():
            on[name] = on[name] and getattr(config, start) < config.iterations
    return on


def method_of(config, touched: bool | None = None) -> str:
    """The name of the method whose mechanisms a TrainConfig has (``custom`` if none's); its other settings
    (schedule, weights, rates) may differ from the method's. ``touched``: as :func:`mechanisms` (a run is the method
    of what it used: ``3dgs+t`` on a scene without touches is ``3dgs``, ``paper`` run for no more steps than its
    smoothness_start_iter is ``3dgs+t``)."""
    on = mechanisms(config, touched)
    return next((name for name in METHODS if mechanisms(method_config(name)) == on), "custom")


def method_label(name: str) -> str:
    """The label the tables print for a method, or the name itself for any other row."""
    return METHODS[name].label if name in METHODS else name
