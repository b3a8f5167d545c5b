"""The method variants (the paper's Table 3, and ours beyond it), one table read by the CLI, the benchmarks and
the report.

A variant is a name, the label the paper's tables print, and the
:class:`~tacsplat.reconstruction.config.TrainConfig` fields it sets; every
other field keeps its default. TrainConfig's defaults are ``DEFAULT_VARIANT``
(beyond the paper), so the paper's rows switch the surface-normal losses, the initial
colours from the views and the lit colour off.
A config's variant is the row whose fields it matches on the switches that
define variants (touch on/off, smoothness on/off, surface normals on/off, then
tactile normals, appearance, a smooth albedo and initial colours from the views). The rows measured
before the initial colours from the views existed set them off (``RANDOM_COLOURS``), as they were measured.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tacsplat.errors import ConfigError
from tacsplat.reconstruction.options import set_field


@dataclass(frozen=True)
class Variant:
    name: str  # as in file names, results.csv and metrics.json
    label: str  # as in the paper's tables
    overrides: dict = field(default_factory=dict)  # TrainConfig fields it sets ("init.x": its InitConfig's x)
    description: str = ""

    def apply(self, config):
        """Set the variant's fields on a TrainConfig (and its InitConfig) and return it."""
        for key, value in self.overrides.items():
            set_field(config, tuple(key.split(".")), value)
        return config


SH = {"appearance": "sh", "lambda_albedo_smoothness": 0.0}  # view-dependent colour, unlit (3DGS)
RANDOM_COLOURS = {"init.colours_from_views": False}  # G_t (and a failed SfM's points) start with random colours
PAPER = {"lambda_flatten": 0.0, "lambda_depth_normal": 0.0, "lambda_touch_normal": 0.0, **SH, **RANDOM_COLOURS}
NORMALS = {"lambda_flatten": 10.0, "lambda_depth_normal": 0.05, "depth_normal_start_iter": 700}  # (TrainConfig's)

VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("3dgs", "3DGS", {"use_touch": False, "lambda_s": 0.0, **PAPER},
                "vanilla 3DGS: no touch, no smoothness"),
        Variant("3dgs+s", "3DGS + S", {"use_touch": False, **PAPER}, "edge-aware smoothness L_S (Eq. 8), no touch"),
        Variant("3dgs+t", "3DGS + T", {"lambda_s": 0.0, **PAPER},
                "touch Gaussians and transmittance L_T (Eq. 7), no smoothness"),
        Variant("full", "Ours (full)", PAPER, "touch and smoothness: the paper's method"),
        Variant("full+n", "Ours + normals", {**NORMALS, **RANDOM_COLOURS, "lambda_touch_normal": 0.0, **SH},
                "full, plus flat Gaussians (minimum-scale loss) and depth-normal consistency from step 700 "
                "(beyond the paper)"),
        Variant("full+n+tn", "Ours + normals + tactile normals",
                {**NORMALS, **RANDOM_COLOURS, "lambda_touch_normal": 0.1, **SH},
                "full+n, plus touch Gaussians' normals aligned with the tactile maps' normals (beyond the paper)"),
        # full+n+tn with one mechanism off or on, for the ablation (README: "each mechanism on and off")
        Variant("full+tn", "Ours + tactile normals", {**PAPER, "lambda_touch_normal": 0.1},
                "full plus tactile normals only (ablation)"),
        Variant("full+vc", "Ours + view colours", {**PAPER, "init.colours_from_views": True},
                "full plus initial colours from the views only (ablation)"),
        Variant("full+flat+tn", "Ours + flat Gaussians + tactile normals",
                {**NORMALS, **RANDOM_COLOURS, "lambda_depth_normal": 0.0, "lambda_touch_normal": 0.1, **SH},
                "full+n+tn without depth-normal consistency (ablation)"),
        Variant("full+dn+tn", "Ours + depth-normal consistency + tactile normals",
                {**NORMALS, **RANDOM_COLOURS, "lambda_flatten": 0.0, "lambda_touch_normal": 0.1, **SH},
                "full+n+tn without flattening (ablation)"),
        Variant("full+n+tn+sl+as", "Ours + normals + tactile normals + lit SH colour",
                {**NORMALS, **RANDOM_COLOURS, "lambda_touch_normal": 0.1, "appearance": "sh-lit",
                 "lambda_albedo_smoothness": 0.1},
                "full+n+tn with the view-dependent colour lit by a learned light at the rendered normals (sh-lit) "
                "and kept smooth, so that shading has to come from the geometry (beyond the paper)"),
        Variant("full+n+tn+sl+as+vc", "Ours + normals + tactile normals + lit SH colour + view colours",
                {**NORMALS, "lambda_touch_normal": 0.1, "appearance": "sh-lit", "lambda_albedo_smoothness": 0.1},
                "full+n+tn+sl+as with the touch Gaussians (and a failed SfM's points) starting with the median colour "
                "of the training pixels they project to instead of random colours (beyond the paper; TrainConfig's "
                "defaults, what `tacsplat reconstruct` runs)"),
    )
}
PAPER_VARIANTS = ("3dgs", "3dgs+s", "3dgs+t", "full")  # the paper's Table 3
DEFAULT_VARIANT = "full+n+tn+sl+as+vc"  # the lowest CD on the twin's glossy objects, at a step cost under 1.5x the
# paper method's (bench paper, bench step and the README)


def get_variant(name: str, option: str = "variant") -> Variant:
    """The variant called ``name``; a ConfigError naming ``option`` and the choices otherwise."""
    if name not in VARIANTS:
        raise ConfigError(option, f"unknown variant {name!r}; choose one of {', '.join(VARIANTS)}")
    return VARIANTS[name]


def variant_of(config) -> str:
    """The name of the variant a TrainConfig runs, built from what is switched on: touch used (with lambda_t > 0)
    and smoothness (lambda_s > 0) give the paper's four rows; then ``+n`` for surface normals (flattening and
    depth-normal consistency both on; ``+flat`` or ``+dn`` for one of them alone), ``+tn`` for tactile normals
    (with touch on), ``+sl`` for the sh-lit appearance, ``+as`` for a smooth albedo (with it) and ``+vc`` for
    initial colours from the views (InitConfig.colours_from_views). A combination without
    a row names itself the same way, so a run's metrics.json never calls it by a row it is not."""
    on = mechanisms(config)
    name = {(False, False): "3dgs", (False, True): "3dgs+s", (True, False): "3dgs+t",
            (True, True): "full"}[(on["touch"], on["smoothness"])]  # fmt: skip
    flat, depth_normal = on["flattening"], on["depth_normal"]
    name += "+n" if flat and depth_normal else "+flat" if flat else "+dn" if depth_normal else ""
    name += "+tn" if on["tactile_normals"] else ""
    name += "+sl" if on["sh_lit"] else ""
    name += "+as" if on["albedo_smoothness"] else ""
    name += "+vc" if on["view_colours"] else ""
    return name


def mechanisms(config) -> dict[str, bool]:
    """Which of the optional mechanisms a TrainConfig switches on, read once for the variant's name
    (:func:`variant_of`) and for how much work its step does (``bench paper``'s scheduling): touch (used, with
    lambda_t > 0), smoothness, flattening, depth-normal consistency, tactile normals (with touch), the sh-lit
    appearance, a smooth albedo (with it), initial colours from the views."""
    touch = config.use_touch and config.lambda_t > 0
    return {
        "touch": touch, "smoothness": config.lambda_s > 0, "flattening": config.lambda_flatten > 0,
        "depth_normal": config.lambda_depth_normal > 0, "tactile_normals": touch and config.lambda_touch_normal > 0,
        "sh_lit": config.appearance == "sh-lit",
        "albedo_smoothness": config.appearance != "sh" and config.lambda_albedo_smoothness > 0,
        "view_colours": config.init.colours_from_views,
    }  # fmt: skip


def variant_label(name: str) -> str:
    return VARIANTS[name].label if name in VARIANTS else name
