"""The method variants (the paper's Table 3, and ours beyond it), one table read by the CLI, the benchmarks and
the report.

A variant is a name, the label the paper's tables print, and the
:class:`~tacsplat.reconstruction.config.TrainConfig` fields it sets; every
other field keeps its default. A config's variant is the row whose fields it
matches on the switches that define variants (touch on/off, smoothness on/off, surface normals on/off).
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


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("3dgs", "3DGS", {"use_touch": False, "lambda_s": 0.0}, "vanilla 3DGS: no touch, no smoothness"),
        Variant("3dgs+s", "3DGS + S", {"use_touch": False}, "edge-aware smoothness L_S (Eq. 8), no touch"),
        Variant("3dgs+t", "3DGS + T", {"lambda_s": 0.0}, "touch Gaussians and transmittance L_T (Eq. 7), no smoothness"),
        Variant("full", "Ours (full)", {}, "touch and smoothness: the paper's method"),
        Variant("full+n", "Ours + normals",
                {"lambda_flatten": 10.0, "lambda_depth_normal": 0.05, "depth_normal_start_iter": 300},
                "full, plus flat Gaussians (minimum-scale loss) and depth-normal consistency from step 300 "
                "(beyond the paper)"),
    )
}
DEFAULT_VARIANT = "full"


def get_variant(name: str, option: str = "variant") -> Variant:
    """The variant called ``name``; a ConfigError naming ``option`` and the choices otherwise."""
    if name not in VARIANTS:
        raise ConfigError(option, f"unknown variant {name!r}; choose one of {', '.join(VARIANTS)}")
    return VARIANTS[name]


def variant_of(config) -> str:
    """The name of the variant a TrainConfig runs: touch used (with lambda_t > 0), smoothness (lambda_s > 0) and,
    for the full method, surface normals (flattening and depth-normal consistency both on)."""
    touch = config.use_touch and config.lambda_t > 0
    smooth = config.lambda_s > 0
    name = {(False, False): "3dgs", (False, True): "3dgs+s", (True, False): "3dgs+t", (True, True): "full"}[(touch, smooth)]
    if name == "full" and config.lambda_flatten > 0 and config.lambda_depth_normal > 0:
        return "full+n"
    return name


def variant_label(name: str) -> str:
    return VARIANTS[name].label if name in VARIANTS else name
