"""The method variants (the paper's Table 3, and ours beyond it), one table read by the CLI, the benchmarks and
the report.

A variant is a name, the label the paper's tables print, and the
:class:`~tacsplat.reconstruction.config.TrainConfig` fields it sets; every
other field keeps its default. TrainConfig's defaults are ``DEFAULT_VARIANT``
(beyond the paper), so the paper's rows switch the surface-normal losses off.
A config's variant is the row whose fields it matches on the switches that
define variants (touch on/off, smoothness on/off, surface normals on/off, then
tactile normals and reflective appearance).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tacsplat.errors import ConfigError


@dataclass(frozen=True)
class Variant:
    name: str  # as in file names, results.csv and metrics.json
    label: str  # as in the paper's tables
    overrides: dict = field(default_factory=dict)  # TrainConfig fields it sets
    description: str = ""


PAPER = {"lambda_flatten": 0.0, "lambda_depth_normal": 0.0, "lambda_touch_normal": 0.0, "appearance": "sh"}
NORMALS = {"lambda_flatten": 10.0, "lambda_depth_normal": 0.05, "depth_normal_start_iter": 300}  # (TrainConfig's)

VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("3dgs", "3DGS", {"use_touch": False, "lambda_s": 0.0, **PAPER},
                "vanilla 3DGS: no touch, no smoothness"),
        Variant("3dgs+s", "3DGS + S", {"use_touch": False, **PAPER}, "edge-aware smoothness L_S (Eq. 8), no touch"),
        Variant("3dgs+t", "3DGS + T", {"lambda_s": 0.0, **PAPER},
                "touch Gaussians and transmittance L_T (Eq. 7), no smoothness"),
        Variant("full", "Ours (full)", PAPER, "touch and smoothness: the paper's method"),
        Variant("full+n", "Ours + normals", {**NORMALS, "lambda_touch_normal": 0.0, "appearance": "sh"},
                "full, plus flat Gaussians (minimum-scale loss) and depth-normal consistency from step 300 "
                "(beyond the paper)"),
        Variant("full+n+tn", "Ours + normals + tactile normals",
                {**NORMALS, "lambda_touch_normal": 0.1, "appearance": "sh"},
                "full+n, plus touch Gaussians' normals aligned with the tactile maps' normals (beyond the paper; "
                "TrainConfig's defaults, what `tacsplat reconstruct` runs)"),
        Variant("full+n+r", "Ours + normals + reflections",
                {**NORMALS, "lambda_touch_normal": 0.0, "appearance": "reflective"},
                "full+n, with diffuse + specular environment-map shading instead of view-dependent SH "
                "(beyond the paper)"),
    )
}
PAPER_VARIANTS = ("3dgs", "3dgs+s", "3dgs+t", "full")  # the paper's Table 3
DEFAULT_VARIANT = "full+n+tn"  # the best on the twin's glossy objects (bench paper; see the README)


def get_variant(name: str, option: str = "variant") -> Variant:
    """The variant called ``name``; a ConfigError naming ``option`` and the choices otherwise."""
    if name not in VARIANTS:
        raise ConfigError(option, f"unknown variant {name!r}; choose one of {', '.join(VARIANTS)}")
    return VARIANTS[name]


def variant_of(config) -> str:
    """The name of the variant a TrainConfig runs: touch used (with lambda_t > 0), smoothness (lambda_s > 0) and,
    for the full method, surface normals (flattening and depth-normal consistency both on), then tactile normals
    and reflective appearance on top of them (a combination without a row, e.g. both, names itself the same way)."""
    touch = config.use_touch and config.lambda_t > 0
    smooth = config.lambda_s > 0
    name = {(False, False): "3dgs", (False, True): "3dgs+s", (True, False): "3dgs+t", (True, True): "full"}[(touch, smooth)]
    if name == "full" and config.lambda_flatten > 0 and config.lambda_depth_normal > 0:
        name = "full+n"
        if config.lambda_touch_normal > 0:
            name += "+tn"
        if config.appearance == "reflective":
            name += "+r"
    return name


def variant_label(name: str) -> str:
    return VARIANTS[name].label if name in VARIANTS else name
