"""Training settings: :class:`TrainConfig` (its ranges checked by :meth:`TrainConfig.validate`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Literal, get_args, get_origin, get_type_hints

import torch

from tacsplat.config_files import field_kinds, yaml_number
from tacsplat.errors import ConfigError, UsageError
from tacsplat.reconstruction.densification import DensifyStrategy
from tacsplat.reconstruction.initialization import InitConfig

Appearance = Literal["sh", "sh-lit"]  # how Gaussians are coloured (see TrainConfig.appearance)


@dataclass
class TrainConfig:
    """Training settings; defaults aim at a 5-view 200x200 object in minutes on 2 CPU cores."""

    iterations: int = 2000
    """optimisation steps"""
    seed: int = 0
    """seeds every random draw (initialisation, view order, touch subsets)"""
    sh_degree: int = 3
    """maximum SH degree (0 for a Lambertian scene)"""
    sh_degree_interval: int = 400
    """one more SH band every this many steps (0: every band from the start)"""
    train_views: int | None = None
    """use only the first K training views (None = all)"""
    downscale: int = 1
    """train and evaluate at 1/N of the images' size (area-averaged; intrinsics scaled)"""
    coarse_factors: tuple[int, ...] = ()
    """coarse to fine: the first steps train at 1/N of the training size for each N here in turn (coarsest first,
    e.g. 4 2), each for an equal share of ``coarse_until``; () = every step at full size"""
    coarse_until: float = 0.5
    """fraction of the steps after which training is at full size"""
    crop_margin: float | None = None
    """each step trains on the bounding box of its view's silhouette widened by this share of the image's width on
    every side (the bare backdrop farther out has nothing to teach); None: the whole image. A view without a known
    backdrop (no silhouette) always trains whole"""
    backend: Literal["auto", "torch", "cpu", "gsplat"] = "auto"
    """rasterization backend (auto: gsplat on CUDA, else the numba CPU backend for float32); "torch" also keeps
    the losses' torch references (no fused kernels)"""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """where training runs (auto: CUDA when torch sees a GPU)"""
    torch_threads: int | None = 1
    """torch intra-op threads while training (the cpu backend's kernels run their own threads; one torch thread
    avoids oversubscribing a small machine); None = torch's default"""
    background: tuple[float, float, float] | None = None
    """None: a smooth backdrop fitted to each image's border"""
    # -- loss weights (paper Sec. 4.2)
    ssim_weight: float = 0.2
    """D-SSIM share of the photometric loss (Kerbl et al.: 0.8 L1 + 0.2 D-SSIM)"""
    lambda_t: float = 0.5
    """transmittance L_T; 0 or no touches -> not computed"""
    lambda_s: float = 2.0
    """edge-aware smoothness L_S (on depth / scene scale); 0 -> no depth render"""
    lambda_backdrop: float = 0.1
    """alpha on pixels that match the fitted backdrop (not in the paper; 0 = off)"""
    backdrop_tolerance: float = 0.03
    """a pixel within this of the backdrop in every channel shows the backdrop"""
    use_touch: bool = True
    """False: no touch Gaussians and no L_T (methods 3dgs and 3dgs+s)"""
    # -- transmittance (Sec. 4.2.1)
    touch_top_k: int = 8
    """most influential G_t per touch point"""
    touch_candidates: int = 32
    """nearest G_t fetched from the k-d tree per touch point"""
    touch_max_distance: float = 0.005
    """metres: Gaussians farther from the point are ignored"""
    touch_rebuild_every: int = 50
    """steps between k-d tree rebuilds (and after every densification)"""
    touch_points_per_step: int = 512
    """random subset of touch points in L_T per step (0 = all)"""
    touch_loss_moves_shape: bool = False
    """False: L_T moves means and opacities only (the effect Sec. 4.2.1 describes); True: also scales and
    rotations, which L_T rewards for growing around the touch point"""
    # -- smoothness (Sec. 4.2.2)
    smoothness_depth: Literal["expected", "accumulated"] = "expected"
    """the depth map D of Eq. 8: "expected" (Eq. 5 divided by alpha, inside the silhouette) or the paper's
    "accumulated" Eq. 5, whose gradients at the silhouette and in semi-transparent regions are alpha's rather
    than the surface's"""
    smoothness_beta: float = 10.0
    """edge sensitivity e^{-beta |dI|}"""
    smoothness_start_iter: int = 0
    """L_S (and the depth render) from this step on"""
    use_proximity_mask: bool = True
    """L_S weighted by 1 - the proximity mask of the visible touches"""
    proximity_sigma_px: float = 4.0
    """Gaussian decay of the proximity mask, pixels"""
    occlusion_tolerance: float = 0.005
    """metres: a touch point this far behind the rendered surface is hidden"""
    # -- surfaces and shading (beyond the paper; each 0 / "sh" = off, as the paper's methods set them)
    lambda_flatten: float = 10.0
    """minimum-scale loss (PGSR): surfel-like Gaussians whose shortest axis is a normal"""
    lambda_depth_normal: float = 0.05
    """depth-normal consistency (2DGS): rendered normals agree with the depth's"""
    depth_normal_start_iter: int = 700
    """... from this step on (after the geometry has formed; from 300, the paper metric's completeness was 16 per
    cent worse on the twin's glossy objects: docs/experiments.md); a step number, as the other start steps
    are, so a run of 700 steps or fewer has none"""
    appearance: Appearance = "sh-lit"
    """colour: view-dependent SH (3DGS), or "sh-lit": that colour as an albedo times a learned distant light's
    irradiance at the rendered normal, saturating at 1 (deferred shading)"""
    lit_start_iter: int = 300
    """"sh-lit": the light shades the albedo from this step on (before: unlit)"""
    lambda_albedo_smoothness: float = 0.1
    """L1 differences of neighbouring pixels' rendered diffuse colour inside the silhouette ("sh-lit"): shading
    has to come from the normals"""
    albedo_smoothness_beta: float = 10.0
    """albedo smoothness: each pair of neighbouring pixels weighted e^{-beta |dI|} by the training image's own
    difference there, so a texture's edges stay in the albedo (0: all 1)"""
    # -- Adam learning rates (Kerbl et al.); the position rate is multiplied by the scene scale
    lr_means: float = 1.6e-4
    """means (times the scene scale)"""
    lr_means_final_factor: float = 0.01
    """exponential decay of the position rate to this fraction"""
    lr_quats: float = 1e-3
    """rotations (quaternions)"""
    lr_scales: float = 5e-3
    """log scales"""
    lr_opacities: float = 5e-2
    """logit opacities"""
    lr_sh0: float = 2.5e-3
    """SH band 0 (base colour)"""
    lr_shN: float = 2.5e-3 / 20
    """higher SH bands"""
    lr_light: float = 1e-2
    """"sh-lit": the diffuse light's SH coefficients and camera light"""
    # -- progress evaluation and checkpoints
    eval_every_iters: int = 250
    """held-out PSNR and CD at least this often..."""
    eval_every_seconds: float = 30.0
    """...and at least this often in run time"""
    eval_max_views: int = 6
    """test views used for progress rows (the final evaluation uses all)"""
    checkpoint_every: int = 500
    """steps between checkpoints (and one at the end, on Ctrl-C and SIGTERM)"""
    init: InitConfig = field(default_factory=InitConfig)
    densify: DensifyStrategy = field(default_factory=DensifyStrategy)

    def unused_fields(self) -> set[str]:
        """The fields that cannot change what this config trains: the settings of the mechanisms it switches off."""
        unused = set()
        if self.lambda_depth_normal == 0:
            unused.add("depth_normal_start_iter")
        if self.appearance == "sh" or self.lambda_albedo_smoothness == 0:
            unused.add("albedo_smoothness_beta")
        if self.appearance == "sh":
            unused |= {"lambda_albedo_smoothness", "lit_start_iter"}
        if not self.coarse_factors:
            unused.add("coarse_until")
        return unused

    def never_started(self) -> list[str]:
        """``"smoothness_start_iter 20000"``, ... for each mechanism that is on but starts at or after the last step
        (start steps are step numbers: a settings file written for 30000 steps, run for fewer, keeps them)."""
        starts = {
            "smoothness_start_iter": self.lambda_s > 0,
            "depth_normal_start_iter": self.lambda_depth_normal > 0,
            "lit_start_iter": self.appearance != "sh",
            "densify.start_iter": self.densify.stop_iter > self.densify.start_iter,
        }
        values = flat_settings(self.to_json())
        return [f"{key} {values[key]}" for key, on in starts.items() if on and values[key] >= self.iterations]

    def validate(self, names: dict[str, str] | None = None) -> None:
        """A ConfigError for the first setting out of its range, naming it (as ``names[field]`` when given,
        e.g. the command-line option) and the range."""
        if problem := self.problem():
            raise ConfigError((names or {}).get(problem[0], problem[0]), problem[1])

    def problem(self) -> tuple[str, str] | None:
        """``(field, why)`` of the first setting out of its range, or None: a number by its type and ``_RANGES``
        (by default >= 0), a flag true or false, a choice one of its Literal's."""
        for prefix, owner in (("", self), ("init.", self.init), ("densify.", self.densify)):
            hints = get_type_hints(type(owner))
            for f in dataclasses.fields(owner):
                key, value, kind = prefix + f.name, getattr(owner, f.name), hints[f.name]
                kinds = field_kinds(kind)
                if value is None and type(None) in kinds:
                    continue
                lo, hi = _RANGES.get(key, (0, None))
                positive, open_ = key in _POSITIVE or key in _OPEN, key in _OPEN
                number = isinstance(value, (int, float)) and not isinstance(value, bool)
                outside = number and (
                    value < lo
                    or (positive and value == lo)
                    or (hi is not None and (value > hi or (open_ and value == hi)))
                )
                if bool in kinds and not isinstance(value, bool):
                    return key, f"must be true or false, got {value!r}"
                if get_origin(kind) is Literal and value not in get_args(kind):
                    return key, f"must be one of {', '.join(map(repr, get_args(kind)))}, got {value!r}"
                if int in kinds and (not number or not isinstance(value, int) or outside):
                    note = f" ({_RANGE_NOTES[key]})" if key in _RANGE_NOTES else ""
                    return key, f"must be an integer {_range_text(lo, hi)}{note}, got {value!r}"
                if float in kinds and (not number or not math.isfinite(value) or outside):
                    return key, f"must be a finite number {_range_text(lo, hi, positive, open_)}, got {value!r}"
        background = self.background  # (a YAML file may give any value: a list read as a tuple)
        if background is not None and not (
            isinstance(background, tuple)
            and len(background) == 3
            and all(isinstance(c, (int, float)) and 0 <= c <= 1 for c in background)
        ):
            return "background", f"must be None or 3 numbers from 0 to 1 (RGB), got {background!r}"
        factors = self.coarse_factors
        if not isinstance(factors, tuple) or not all(
            isinstance(f, int) and not isinstance(f, bool) and 2 <= f <= 64 for f in factors
        ):
            return "coarse_factors", f"must be integers from 2 to 64, coarsest first, got {factors!r}"
        if list(factors) != sorted(factors, reverse=True):
            return "coarse_factors", f"must run coarsest first (decreasing), got {factors!r}"
        if self.backend == "cpu" and self.device == "cuda":
            return "backend", "the cpu backend runs on the CPU: use --backend gsplat (or auto) with --device cuda"
        return None

    def torch_device(self) -> torch.device:
        """The device training runs on (auto: CUDA where torch sees it, except for the cpu backend, which runs on the
        CPU); a ConfigError at once when CUDA is asked for and torch sees none."""
        if self.device == "cpu" or (self.device == "auto" and (self.backend == "cpu" or not torch.cuda.is_available())):
            return torch.device("cpu")
        if not torch.cuda.is_available():
            build = "a CPU-only build" if torch.version.cuda is None else f"built for CUDA {torch.version.cuda}"
            raise ConfigError(
                "device",
                f"cuda was asked for but torch {torch.__version__} ({build}) sees no CUDA "
                "device; use --device cpu, or install a CUDA build of torch and gsplat (README: GPU)",
            )
        return torch.device("cuda")

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict, source: str | Path | None = None, resuming: bool = False) -> "TrainConfig":
        """The config of ``to_json`` (a run's ``config.json``; a field it lacks was written before the field existed:
        see ``_BEFORE_THEY_EXISTED``; its ``scene``, the run's record of its scene, is not a setting); a ConfigError
        naming ``source`` if it is not one, or (``resuming``: the config a resume continues with) if it trained
        with a removed loss (``_REMOVED_LOSSES``)."""
        try:
            data = {**_BEFORE_THEY_EXISTED, **data}
            data.pop("scene", None)
            _drop_removed(data, source, resuming)
            init = data.pop("init", {})
            if "colours_from_views" in init:  # its name before identifiers spelled color
                init.setdefault("colors_from_views", init.pop("colours_from_views"))
            init = InitConfig(**{**_INIT_BEFORE_THEY_EXISTED, **init})
            densify = DensifyStrategy(**data.pop("densify", {}))
            if data.get("background") is not None:
                data["background"] = tuple(data["background"])
            if "coarse_factors" in data:  # (a JSON list)
                data["coarse_factors"] = tuple(data["coarse_factors"])
            config = cls(**data, init=init, densify=densify)
        except (TypeError, ValueError, AttributeError) as exc:
            raise ConfigError("config", f"not a training config: {exc}", source) from None
        if problem := config.problem():
            raise ConfigError(*problem, source)
        return config


def changed_settings(
    recorded: TrainConfig, now: TrainConfig, fields: Iterable[str] | None = None
) -> list[tuple[str, object, object]]:
    """``(field, recorded value, value now)`` for each setting of ``fields`` (dotted paths such as
    ``densify.max_gaussians``; None: every one) that differs, the settings of a mechanism both configs switch off
    aside (:meth:`TrainConfig.unused_fields`)."""
    unused = recorded.unused_fields() & now.unused_fields()
    before, after = flat_settings(recorded.to_json()), flat_settings(now.to_json())
    chosen = after if fields is None else [k for k in after if k in set(fields)]
    return [(k, before.get(k), after[k]) for k in chosen if k not in unused and before.get(k) != after[k]]


def flat_settings(settings: dict, prefix: str = "") -> dict:
    """``{"densify.max_gaussians": ...}`` of nested settings."""
    flat = {}
    for key, value in settings.items():
        flat.update(flat_settings(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return flat


# Fields a config.json written before they existed leaves out, with the value such a run trained with (where that
# differs from today's default): no surface-normal losses, and the colour was unlit SH without a smooth albedo.
_BEFORE_THEY_EXISTED = {
    "lambda_flatten": 0.0,
    "lambda_depth_normal": 0.0,
    "appearance": "sh",
    "lambda_albedo_smoothness": 0.0,
    "albedo_smoothness_beta": 0.0,
}
_INIT_BEFORE_THEY_EXISTED = {"colors_from_views": False}  # ... and of its InitConfig: random initial colours

# Fields of mechanisms measured not to help and removed (docs/experiments.md, "Removed"): a config.json that has
# them off (or holds only their settings) reads as today's config; one that used them cannot be resumed or shown.
_REMOVED_OFF = {"depth_render": "centre", "lambda_touch_normal_pixels": 0.0, "lambda_pad_free": 0.0}  # its off value
_REMOVED_SETTINGS = ("plane_depth_start_iter", "env_map_height", "lr_reflective", "pad_free_margin")
_REMOVED_APPEARANCES = ("reflective", "lit")
# Losses measured not to help and removed that shaped the Gaussians but not how they render: a config.json that used
# one reads as today's config (its run evaluates, shows and exports as before), but its run cannot be resumed, as
# it would go on training without the loss. Field -> what the refusal says of it.
_REMOVED_LOSSES = {
    "lambda_touch_normal": "the tactile-normal loss, removed (no gain on held-out meshes: docs/experiments.md)",
}


def removed_losses(data: dict) -> dict[str, object]:
    """``{field: value}`` of the removed losses (``_REMOVED_LOSSES``) that a config.json's ``data`` switched on."""
    return {key: data[key] for key in _REMOVED_LOSSES if data.get(key, 0) != 0}


def _drop_removed(data: dict, source, resuming: bool = False) -> None:
    """Remove from ``data`` the fields of removed mechanisms; a ConfigError if it switched one of them on that
    changes rendering, or (``resuming``) one of the removed losses."""
    if resuming and (used := removed_losses(data)):
        key = next(iter(used))
        message = f"this run trained with {_REMOVED_LOSSES[key]}; reconstruct the scene again"
        raise ConfigError(key, message, source)
    for key in _REMOVED_LOSSES:
        data.pop(key, None)
    used = [key for key, off in _REMOVED_OFF.items() if data.pop(key, off) != off]
    used += ["appearance"] if data.get("appearance") in _REMOVED_APPEARANCES else []
    if used:
        what = f"the {data['appearance']!r} appearance" if used[0] == "appearance" else "a mechanism"
        message = f"this run used {what} tacsplat no longer has (measured not to help: docs/experiments.md)"
        raise ConfigError(used[0], f"{message}; reconstruct the scene again", source)
    for key in _REMOVED_SETTINGS:
        data.pop(key, None)
    if "lr_env_map" in data:  # the light's rate, named after the environment map it was shared with
        data.setdefault("lr_light", data.pop("lr_env_map"))


# Ranges TrainConfig.problem checks where they differ from >= 0: (smallest, largest or None); _POSITIVE excludes the
# smallest, _OPEN both.
_RANGES = {
    "iterations": (1, None),
    "seed": (0, 2**32 - 1),
    "downscale": (1, 64),
    "sh_degree": (0, 3),
    "train_views": (1, None),  # (None: all views)
    "torch_threads": (1, None),  # (None: torch's default)
    "touch_top_k": (1, None),
    "touch_candidates": (1, 1024),  # (a [touch points, candidates] table, and the k-d tree search's results)
    "touch_rebuild_every": (1, None),
    "eval_every_iters": (1, None),
    "eval_max_views": (1, None),
    "checkpoint_every": (1, None),
    "ssim_weight": (0, 1),
    "coarse_until": (0, 1),
    "crop_margin": (0, 1),
    "lr_means_final_factor": (0, 1),
    "init.hull_resolution": (1, 256),  # (its carving grid: about 125 bytes a voxel, at most resolution^3 voxels)
    "init.num_random_points": (0, 1_000_000),  # (each an initial Gaussian: about 3 kB of training memory on the CPU)
    "init.sift_max_features": (1, None),
    "init.initial_opacity": (0, 1),
    "init.touch_initial_opacity": (0, 1),
    "densify.prune_opacity": (0, 0.5),  # (an opacity reset caps opacities at twice it, a logit of 0 to 1)
    "densify.refine_every": (1, None),  # (steps between refinements and between resets: a modulus)
    "densify.reset_every": (1, None),
}
_POSITIVE = {
    "touch_max_distance",
    "proximity_sigma_px",
    "lr_means_final_factor",
    "eval_every_seconds",
    "init.touch_voxel_size",
    "init.min_triangulation_angle_deg",
    "densify.split_scale_divisor",  # (a split subtracts its log from the log scales)
}
_OPEN = {"init.initial_opacity", "init.touch_initial_opacity", "densify.prune_opacity"}  # excludes both ends
_RANGE_NOTES = {  # why a largest value
    "init.hull_resolution": "256: 256^3 voxels, about 2 GB of memory",
    "touch_candidates": "about 24 bytes per touch point and candidate: 1024 is 25 MB for the 1000 touch points kept "
    "by default (--init.max-touch-points)",
    "init.num_random_points": "each an initial Gaussian of about 3 kB of training memory: 1000000 is about 3 GB",
}


def _range_text(lo, hi, exclusive: bool = False, open_: bool = False) -> str:
    if open_:
        return f"strictly between {lo} and {hi}"
    if hi is None:
        return f"{'>' if exclusive else '>='} {lo}"
    return f"{lo} to {hi}" + (f" (not {lo})" if exclusive else "")


# ------------------------------------------------------------------------------------- settings files

PAPER_ITERATIONS = 30_000
PAPER_SCHEDULE = Path(__file__).with_name("paper_schedule.yaml")  # the official code's schedule, cited line by line
_STEP_SETTINGS = (
    "smoothness_start_iter",
    "densify.start_iter",
    "densify.stop_iter",
    "densify.refine_every",
    "densify.reset_every",
)  # the step numbers of the paper schedule that scale with its iterations


def set_fields(config: TrainConfig, settings: dict, source: str | Path | None = None) -> TrainConfig:
    """Set ``settings`` (``{"lambda_s": 0.0, "init.use_sfm": False}``) on a TrainConfig and return it; a
    ConfigError naming ``source`` for a key that is not a field, a UsageError for a value in place of the
    settings of ``init`` or ``densify``."""
    for key, value in settings.items():
        *path, name = key.split(".")
        target = config
        for part in path:
            target = getattr(target, part, None)
        if not dataclasses.is_dataclass(target) or name not in {f.name for f in dataclasses.fields(target)}:
            raise ConfigError(key, "not a training setting (a TrainConfig field, or init.x / densify.x)", source)
        if dataclasses.is_dataclass(getattr(target, name)):  # (a mapping of them arrives as dotted keys)
            raise UsageError(key, f"must be a mapping of {key}.x settings, got {value!r}", source)
        if isinstance(value, str):  # (YAML reads 1e-3, with no dot, as a string)
            value = yaml_number(value, get_type_hints(type(target))[name])
        setattr(target, name, tuple(value) if isinstance(value, list) else value)
    return config


def read_settings(path: str | Path) -> dict:
    """The training settings of a YAML file (``field: value``, ``init:`` and ``densify:`` nested or dotted) as
    ``{"lambda_s": 5.8, "densify.stop_iter": 15000}``; a ConfigError naming the file if it is not one."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as exc:
        raise ConfigError("--config", f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError("settings", "not a text file (YAML, UTF-8)", path) from None
    except yaml.YAMLError as exc:
        raise ConfigError("settings", f"not YAML: {str(exc).splitlines()[0]}", path) from None
    if data is None:  # (empty, or only comments: no settings)
        return {}
    if not isinstance(data, dict):
        raise ConfigError("settings", f"expected a mapping of training settings, got {type(data).__name__}", path)
    return flat_settings(data)


def paper_schedule(iterations: int | None = None) -> dict:
    """The settings of :data:`PAPER_SCHEDULE`, every step number scaled to ``iterations`` (default its 30000)."""
    settings = read_settings(PAPER_SCHEDULE)
    if iterations is None:
        return settings
    scale = iterations / settings["iterations"]
    return {**settings, "iterations": iterations, **{k: max(1, round(settings[k] * scale)) for k in _STEP_SETTINGS}}


def paper_departures(config: TrainConfig, touch_model: str = "gel", resolution: int | None = None) -> list[str]:
    """What still differs from the paper's official runs for ``config`` (one line each)."""
    lines = []
    if config.lambda_flatten > 0 or config.lambda_depth_normal > 0:
        lines.append("surface normals (flattening, depth-normal consistency): not in the paper (its method is `paper`)")
    if config.appearance != "sh":
        lines.append(
            "sh-lit appearance: the view-dependent SH colour shaded by a learned light at the rendered "
            "normals; not in the paper"
        )
    if config.appearance != "sh" and config.lambda_albedo_smoothness > 0:
        lines.append(
            f"smooth albedo (lambda_albedo_smoothness {config.lambda_albedo_smoothness}, pairs weighted by the "
            f"image with albedo_smoothness_beta {config.albedo_smoothness_beta}); not in the paper"
        )
    if config.init.use_silhouette_hull:
        lines.append(
            "initialisation: G_c on the visual hull of the silhouettes when SfM finds too few points (the "
            "official data preparation triangulates COLMAP points from the train and test images)"
        )
    if config.init.colors_from_views and (config.use_touch or config.init.use_silhouette_hull):
        lines.append(
            "initial colours of the touch Gaussians (and of a failed SfM's points) from the training pixels "
            "they project to; the paper: random"
        )
    if config.lambda_backdrop > 0:
        lines.append(
            f"backdrop alpha loss (lambda_backdrop {config.lambda_backdrop}) on pixels showing the fitted "
            "backdrop; not in the paper"
        )
    if config.smoothness_depth != "accumulated":
        lines.append("edge-aware smoothness on the expected depth inside the silhouette (the paper: accumulated depth)")
    if config.background is None:
        lines.append("renders composited over each view's fitted backdrop (the paper: a black background)")
    if resolution is not None and resolution != 800:
        lines.append(f"resolution {resolution} px (the paper: 800 px)")
    if config.iterations != PAPER_ITERATIONS:
        lines.append(
            f"{config.iterations} steps (the paper: {PAPER_ITERATIONS}; step-based numbers scaled)"
            if config.smoothness_start_iter
            else f"{config.iterations} steps and our schedule (the paper: "
            f"{PAPER_ITERATIONS} steps, smoothness from step 20000, densification until 15000)"
        )
    if touch_model != "paper":
        lines.append(
            "touches: gel contact patches of simulated grasps (the paper: 50 surface samples around the "
            "furthest hit of a random ray from the centroid, anywhere on the object)"
        )
    lines.append(
        "no clipping of depth gradients at +-5 and no second opacity-based pruning at step 5000 (official "
        "code details not reproduced)"
    )
    return lines


PRESETS = {
    "default": lambda iterations=None: {} if iterations is None else {"iterations": iterations},
    "paper": paper_schedule,
}  # the benchmarks' --preset


def preset_config(name: str, iterations: int | None = None) -> TrainConfig:
    """The TrainConfig of a benchmark preset (``default``: TrainConfig's defaults; ``paper``: :func:`paper_schedule`)."""
    if name not in PRESETS:
        raise ConfigError("preset", f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return set_fields(TrainConfig(), PRESETS[name](iterations), PAPER_SCHEDULE.name)
