"""The tactile-informed 3DGS training job: scene directory in, run directory out.

A run directory holds ``config.json``, ``checkpoint.pt`` (the last
checkpoint: resumable), ``splat.ply``, ``progress.csv`` (iteration, seconds of
run time excluding evaluation, each loss term averaged since the previous row,
Gaussian count, held-out PSNR and CD), ``error_vs_time.png``, ``metrics.json``
and ``renders/``. Loss: photometric + lambda_t L_T (Eq. 7, on G_t at the touch
points) + lambda_s L_S (Eq. 8, masked near visible touches) + lambda_backdrop
times the alpha on pixels that show the fitted smooth backdrop (not in the
paper; see :func:`losses.backdrop_alpha_loss`). L_S acts by default on the
expected depth inside the object's silhouette rather than on Eq. 5's
accumulated depth (``smoothness_depth``). When SfM finds too few points, the
initial G_c lie on the visual hull of the silhouettes. Renders are composited over
each view's backdrop (a constant, or a smooth fit to the image border). What a
scene does not need is not computed: no touches -> no G_t, no neighbour search,
no L_T; lambda_s = 0 -> RGB-only renders.

:func:`reconstruct` is the job: it claims the run directory (a new or empty
folder; an earlier run only with ``resume`` or ``overwrite``, and never a
folder of other files), holds its lock to the end, and trains. SIGINT and
SIGTERM stop training after the step in progress, with a checkpoint
(:class:`TrainingInterrupted`); a resume continues from the checkpoint, with
``progress.csv`` cut back to it.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import re
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import importlib

import numpy as np
import torch
from tqdm import tqdm

from tacsplat.errors import ConfigError, SceneFormatError
from tacsplat.reconstruction import losses
from tacsplat.reconstruction.densification import DensifyState, DensifyStrategy
from tacsplat.reconstruction.evaluation import (
    background_image,
    camera_tensors,
    fit_backdrop,
    composite,
    evaluate_views,
    load_ground_truth,
)
from tacsplat.reconstruction.gaussians import Gaussians
from tacsplat.reconstruction.initialization import (
    InitConfig,
    foreground_mask,
    initial_gaussians,
    random_points,
    sfm_points,
    silhouette_hull_points,
    thin_touch_points,
)
from tacsplat.reconstruction.ply import save_ply

log = logging.getLogger(__name__)
# the module, not the function the package re-exports under the same name (tests spy on its calls)
raster = importlib.import_module("tacsplat.reconstruction.rasterization")

# A run directory's own files (anything else in it is someone else's and is never deleted).
RUN_FILES = ("config.json", "checkpoint.pt", "checkpoint.pt.tmp", "splat.ply", "splat.ply.tmp", "progress.csv",
             "progress.csv.tmp", "error_vs_time.png", "metrics.json")
RENDERS = "renders"
RENDER_FILE = re.compile(r"view_\d{4,}\.png")

PROGRESS_COLUMNS = (
    "iteration", "seconds", "loss", "photometric", "transmittance", "smoothness", "backdrop", "num_gaussians",
    "psnr", "cd",
)  # fmt: skip


@dataclass
class TrainConfig:
    """Training settings; defaults aim at a 5-view 200x200 object in minutes on 2 CPU cores."""

    iterations: int = 2000
    seed: int = 0
    sh_degree: int = 3  # maximum SH degree (0 for a Lambertian scene)
    sh_degree_interval: int = 400  # one more SH band every this many steps
    train_views: int | None = None  # use only the first K training views (None = all)
    backend: str = "auto"  # rasterization backend: auto | torch | cpu | gsplat
    torch_threads: int | None = 1  # torch intra-op threads while training (the cpu backend's kernels run
    # their own threads; one torch thread avoids oversubscribing a small machine); None = torch's default
    background: tuple[float, float, float] | None = None  # None: a smooth backdrop fitted to each image's border
    # loss weights (paper Sec. 4.2)
    ssim_weight: float = 0.2
    lambda_t: float = 0.5  # transmittance L_T; 0 or no touches -> not computed
    lambda_s: float = 2.0  # edge-aware smoothness L_S (on depth / scene scale); 0 -> no depth render
    lambda_backdrop: float = 0.1  # alpha on pixels that match the fitted backdrop (not in the paper; 0 = off)
    backdrop_tolerance: float = 0.03  # a pixel within this of the backdrop in every channel shows the backdrop
    use_touch: bool = True  # False: no touch Gaussians and no L_T (the "3DGS" / "+S" variants)
    # transmittance (Sec. 4.2.1)
    touch_top_k: int = 8  # most influential G_t per touch point
    touch_candidates: int = 32  # nearest G_t fetched from the k-d tree per touch point
    touch_max_distance: float = 0.005  # metres: Gaussians farther from the point are ignored
    touch_rebuild_every: int = 50  # steps between k-d tree rebuilds (and after every densification)
    touch_points_per_step: int = 512  # random subset of touch points in L_T per step (0 = all)
    touch_loss_moves_shape: bool = False  # False: L_T moves means and opacities only (the effect Sec. 4.2.1
    # describes); True: also scales and rotations, which L_T rewards for growing around the touch point
    # smoothness (Sec. 4.2.2)
    smoothness_depth: Literal["expected", "accumulated"] = "expected"  # the depth map D of Eq. 8: "expected"
    # (Eq. 5 divided by alpha, inside the silhouette) or the paper's "accumulated" Eq. 5, whose gradients at the
    # silhouette and in semi-transparent regions are alpha's rather than the surface's
    smoothness_beta: float = 10.0  # edge sensitivity e^{-beta |dI|}
    proximity_sigma_px: float = 4.0  # Gaussian decay of the proximity mask, pixels
    occlusion_tolerance: float = 0.005  # metres: a touch point this far behind the rendered surface is hidden
    # Adam learning rates (Kerbl et al.); the position rate is multiplied by the scene scale
    lr_means: float = 1.6e-4
    lr_means_final_factor: float = 0.01  # exponential decay of the position rate to this fraction
    lr_quats: float = 1e-3
    lr_scales: float = 5e-3
    lr_opacities: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    # progress evaluation and checkpoints
    eval_every_iters: int = 250  # held-out PSNR and CD at least this often...
    eval_every_seconds: float = 30.0  # ...and at least this often in run time
    eval_max_views: int = 6  # test views used for progress rows (the final evaluation uses all)
    checkpoint_every: int = 500
    init: InitConfig = field(default_factory=InitConfig)
    densify: DensifyStrategy = field(default_factory=DensifyStrategy)

    @property
    def variant(self) -> str:
        touch = self.use_touch and self.lambda_t > 0
        smooth = self.lambda_s > 0
        return {(False, False): "3dgs", (False, True): "+S", (True, False): "+T", (True, True): "full"}[(touch, smooth)]

    def validate(self, names: dict[str, str] | None = None) -> None:
        """A ConfigError for the first setting out of its range, naming it (as ``names[field]`` when given,
        e.g. the command-line option) and the range."""
        problem = self.problem()
        if problem:
            raise ConfigError((names or {}).get(problem[0], problem[0]), problem[1])

    def problem(self) -> tuple[str, str] | None:
        """``(field, why)`` of the first setting out of its range, or None."""
        for key, (lo, hi) in _INT_RANGES.items():
            value = getattr(self, key)
            if value is None and key in _OPTIONAL:
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < lo or (hi is not None and value > hi):
                return key, f"must be an integer {_range_text(lo, hi)}, got {value!r}"
        for key, (lo, hi) in _FLOAT_RANGES.items():
            value = getattr(self, key)
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            if not ok or value < lo or (key in _POSITIVE and value == lo) or (hi is not None and value > hi):
                return key, f"must be a finite number {_range_text(lo, hi, key in _POSITIVE)}, got {value!r}"
        for key in ("use_touch", "touch_loss_moves_shape"):
            if not isinstance(getattr(self, key), bool):
                return key, f"must be true or false, got {getattr(self, key)!r}"
        if self.background is not None and not (
            len(self.background) == 3 and all(isinstance(c, (int, float)) and 0 <= c <= 1 for c in self.background)
        ):
            return "background", f"must be None or 3 numbers from 0 to 1 (RGB), got {self.background!r}"
        if self.smoothness_depth not in ("expected", "accumulated"):
            return "smoothness_depth", f"must be 'expected' or 'accumulated', got {self.smoothness_depth!r}"
        if self.backend not in raster.BACKENDS:
            return "backend", f"must be one of {raster.BACKENDS}, got {self.backend!r}"
        return None

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict, source: str | Path | None = None) -> "TrainConfig":
        """The config of ``to_json`` (a run's ``config.json``); a ConfigError naming ``source`` if it is not one."""
        try:
            data = dict(data)
            init = InitConfig(**data.pop("init", {}))
            densify = DensifyStrategy(**data.pop("densify", {}))
            if data.get("background") is not None:
                data["background"] = tuple(data["background"])
            config = cls(**data, init=init, densify=densify)
        except (TypeError, ValueError, AttributeError) as exc:
            raise ConfigError("config", f"not a training config: {exc}", source) from None
        problem = config.problem()
        if problem:
            raise ConfigError(*problem, source)
        return config


# Ranges TrainConfig.validate checks: (smallest, largest or None); _POSITIVE excludes the smallest.
_INT_RANGES = {
    "iterations": (1, None), "seed": (0, 2**32 - 1), "sh_degree": (0, 3), "sh_degree_interval": (1, None),
    "train_views": (1, None), "torch_threads": (1, None), "touch_top_k": (1, None), "touch_candidates": (1, None),
    "touch_rebuild_every": (1, None), "touch_points_per_step": (0, None), "eval_every_iters": (1, None),
    "eval_max_views": (1, None), "checkpoint_every": (1, None),
}  # fmt: skip
_OPTIONAL = {"train_views", "torch_threads"}  # None: all views, torch's default
_FLOAT_RANGES = {
    "ssim_weight": (0.0, 1.0), "lambda_t": (0.0, None), "lambda_s": (0.0, None), "lambda_backdrop": (0.0, None),
    "backdrop_tolerance": (0.0, None), "touch_max_distance": (0.0, None), "smoothness_beta": (0.0, None),
    "proximity_sigma_px": (0.0, None), "occlusion_tolerance": (0.0, None), "lr_means": (0.0, None),
    "lr_means_final_factor": (0.0, 1.0), "lr_quats": (0.0, None), "lr_scales": (0.0, None),
    "lr_opacities": (0.0, None), "lr_sh0": (0.0, None), "lr_shN": (0.0, None), "eval_every_seconds": (0.0, None),
}  # fmt: skip
_POSITIVE = {"touch_max_distance", "proximity_sigma_px", "lr_means_final_factor", "eval_every_seconds"}


def _range_text(lo, hi, exclusive: bool = False) -> str:
    if hi is None:
        return f"{'>' if exclusive else '>='} {lo}"
    return f"{lo} to {hi}" + (f" (not {lo})" if exclusive else "")


def scene_scale(frames: list) -> float:
    """Kerbl et al.'s camera extent: 1.1 x the largest distance of a camera centre from their mean."""
    centres = np.array([f.T_world_cam[:3, 3] for f in frames])
    return 1.1 * max(float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max()), 1e-3)


@dataclass
class LoadedRun:
    scene_path: Path
    config: TrainConfig
    gaussians: Gaussians
    step: int
    train_seconds: float


def is_run_folder(path: Path) -> bool:
    """Whether a folder holds a reconstruction run (its config or checkpoint)."""
    return (path / "config.json").is_file() or (path / "checkpoint.pt").is_file()


def run_checkpoint(run_dir: str | Path) -> Path:
    """The checkpoint file of a run directory; a SceneFormatError if there is none."""
    path = Path(run_dir) / "checkpoint.pt"
    if not path.is_file():
        raise SceneFormatError(path, None, "no checkpoint: not a reconstruction run directory")
    return path


def read_checkpoint(path: Path) -> dict:
    """A checkpoint's contents; a SceneFormatError naming the file if it is cut short or not one."""
    try:
        ckpt = torch.load(path, weights_only=False)
    except Exception as exc:  # torch.load raises whatever its zip reader or unpickler meets
        first_line = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise SceneFormatError(path, None, f"corrupt or truncated checkpoint ({first_line})") from None
    keys = ("scene_path", "config", "step", "train_seconds", "gaussians")
    missing = [k for k in keys if k not in ckpt] if isinstance(ckpt, dict) else list(keys)
    if missing:
        raise SceneFormatError(path, None, f"corrupt checkpoint: it has no {', '.join(missing)}")
    return ckpt


def load_run(run_dir: Path) -> LoadedRun:
    """The last checkpoint of a run directory (for evaluation)."""
    ckpt_path = run_checkpoint(run_dir)
    ckpt = read_checkpoint(ckpt_path)
    return LoadedRun(
        Path(ckpt["scene_path"]),
        TrainConfig.from_json(ckpt["config"], ckpt_path),
        Gaussians.from_state_dict(ckpt["gaussians"]),
        int(ckpt["step"]),
        float(ckpt["train_seconds"]),
    )


def evaluate_run(run_dir: str | Path, gt_path: str | Path | None = None, backend: str | None = None) -> dict:
    """Evaluate a finished (or checkpointed) run: writes ``metrics.json`` and ``renders/``; returns the metrics."""
    from tacsplat.datasets import Scene

    run = load_run(Path(run_dir))
    scene = Scene.load(run.scene_path)
    test = scene.split("test")
    backend = backend or run.config.backend
    ground_truth = load_ground_truth(scene, test, gt_path)
    metrics = evaluate_views(
        run.gaussians, scene, test, run.config.background, backend, ground_truth, Path(run_dir) / "renders"
    )
    if ground_truth is None:
        log.warning("no ground truth for the test views (no gt/ depth and no --gt-mesh): cd is NaN")
    result = {
        **metrics,
        "train_seconds": run.train_seconds,
        "iterations": run.step,
        "num_gaussians": len(run.gaussians),
        "num_touch_gaussians": run.gaussians.num_touch,
        "num_test_views": len(test),
        "variant": run.config.variant,
        "gt_source": ground_truth.source if ground_truth else None,
        "gt_radius": ground_truth.radius if ground_truth else None,
        "scene": str(run.scene_path),
        "settings": run.config.to_json(),
    }
    result = {k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in result.items()}
    (Path(run_dir) / "metrics.json").write_text(json.dumps(result, indent=2, default=_json_default))
    return result


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


class TrainingInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM stopped training after a step, and that step is checkpointed.

    A KeyboardInterrupt, so that whatever stops on Ctrl-C stops on it too.
    """

    def __init__(self, signum: int, step: int):
        self.signum, self.step = signum, step
        super().__init__(f"{signal.Signals(signum).name} at step {step}: checkpoint saved")


class _StopRequests:
    """While active (in the main thread), SIGINT and SIGTERM ask training to stop after the step in progress
    (``signum``); a second one stops at once (KeyboardInterrupt, nothing saved)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __enter__(self) -> "_StopRequests":
        self.signum: int | None = None
        self._previous = {}
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._request) for s in self.SIGNALS}
        return self

    def _request(self, signum, frame) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt
        self.signum = signum

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():  # (None: a handler installed outside Python, e.g. glog's)
            signal.signal(s, signal.SIG_DFL if handler is None else handler)


class Trainer:
    """Optimises Gaussians on one scene; see the module docstring for the run directory."""

    def __init__(self, scene, out_dir: str | Path, config: TrainConfig):
        config.validate()
        self.scene = scene
        self.out = Path(out_dir)
        self.config = config
        train = scene.split("train")
        if config.train_views is not None:
            train = train[: config.train_views]
        if not train:
            raise SceneFormatError(scene.path / "transforms.json", "frames", "no training views")
        self.train_frames = train
        self.test_frames = scene.split("test")
        self.images = [torch.from_numpy(scene.load_image(f)) for f in train]
        self.viewmats, self.Ks = camera_tensors(train)
        self.scene_scale = scene_scale(train)
        self.rng = np.random.default_rng(config.seed)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.touch_points = np.zeros((0, 3))
        if config.use_touch and scene.touches:
            self.touch_points = thin_touch_points(scene.touch_points(), config.init, self.rng)
        self.use_touch_loss = len(self.touch_points) > 0 and config.lambda_t > 0
        self.neighbours = (
            losses.TouchNeighbours(
                self.touch_points, config.touch_candidates, config.touch_max_distance, config.touch_rebuild_every
            )
            if self.use_touch_loss
            else None
        )
        self.touch_tensor = torch.as_tensor(self.touch_points, dtype=torch.float32)
        self.backgrounds = [torch.from_numpy(background_image(im.numpy(), config.background)) for im in self.images]
        self.backdrop_masks: list[torch.Tensor | None] = [None] * len(self.images)  # None: no known backdrop
        for i, image in enumerate(self.images):
            if config.background is not None or fit_backdrop(image.numpy()) is not None:
                difference = (image - self.backgrounds[i]).abs().amax(dim=-1)
                self.backdrop_masks[i] = difference < config.backdrop_tolerance
        self.step = 0
        self.train_seconds = 0.0
        self.order: list[int] = []
        self.gaussians: Gaussians | None = None
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.densify_state: DensifyState | None = None
        self._ground_truth = None
        self._edge_weights: dict[int, torch.Tensor] = {}  # per training view, Eq. 8's image factors
        self._sums = {"loss": 0.0, "photometric": 0.0, "transmittance": 0.0, "smoothness": 0.0, "backdrop": 0.0}
        self._sum_count = 0
        self._last_eval = (0, 0.0)  # (step, train seconds) of the last progress row

    # ------------------------------------------------------------------ setup

    def initialize(self) -> None:
        """Initial Gaussians: SfM (or random) G_c plus G_t on the touch points."""
        cfg = self.config
        sfm = None
        if cfg.init.use_sfm:
            sfm = sfm_points(
                [im.numpy() for im in self.images],
                [f.intrinsics.K for f in self.train_frames],
                [f.T_world_cam for f in self.train_frames],
                cfg.init,
                cfg.seed,
            )
        if sfm is not None and len(sfm.points) >= cfg.init.min_sfm_points:
            points, colors = sfm.points, sfm.colors
            log.info("initialisation: %d SfM points", len(points))
        else:
            found = 0 if sfm is None else len(sfm.points)
            points, colors, where = self._fallback_points()
            log.info("initialisation: %d SfM points (< %d): %d random points %s",
                     found, cfg.init.min_sfm_points, len(points), where)  # fmt: skip
        self.gaussians = initial_gaussians(points, colors, self.touch_points, cfg.sh_degree, cfg.init, self.rng)
        self._make_optimizers()
        self.densify_state = cfg.densify.initialize_state(len(self.gaussians), self.scene_scale)

    def _fallback_points(self) -> tuple[np.ndarray, np.ndarray, str]:
        """Random coloured points on the silhouettes' visual hull, or in the scene bounds without silhouettes."""
        cfg = self.config
        lo, hi = self.scene.bounds()
        points, colors = random_points(lo, hi, cfg.init.num_random_points, self.rng)
        views = [i for i, mask in enumerate(self.backdrop_masks) if mask is not None]
        if cfg.init.use_silhouette_hull and views:
            hull = silhouette_hull_points(
                [foreground_mask(self.backdrop_masks[i].numpy()) for i in views],
                [self.train_frames[i].intrinsics.K for i in views],
                [self.train_frames[i].T_world_cam for i in views],
                lo, hi, cfg.init.num_random_points, cfg.init.hull_resolution, self.rng,
            )  # fmt: skip
            if len(hull):
                return hull, colors, f"on the visual hull of {len(views)} silhouettes"
        return points, colors, "in the scene bounds"

    def _make_optimizers(self) -> None:
        cfg = self.config
        rates = {
            "means": cfg.lr_means * self.scene_scale, "quats": cfg.lr_quats, "scales": cfg.lr_scales,
            "opacities": cfg.lr_opacities, "sh0": cfg.lr_sh0, "shN": cfg.lr_shN,
        }  # fmt: skip
        self.optimizers = {
            name: torch.optim.Adam([self.gaussians.params[name]], lr=lr, eps=1e-15)
            for name, lr in rates.items()
        }

    # ------------------------------------------------------------------ one step

    def _next_view(self) -> int:
        if not self.order:
            self.order = self.rng.permutation(len(self.train_frames)).tolist()
        return self.order.pop()

    def train_step(self) -> dict:
        """One optimisation step on one training view; returns the loss terms."""
        cfg, g = self.config, self.gaussians
        view = self._next_view()
        frame = self.train_frames[view]
        active_degree = min(cfg.sh_degree, self.step // cfg.sh_degree_interval)
        with_depth = cfg.lambda_s > 0
        renders, alphas, meta = raster.rasterization(
            g.means, g.quats, g.scales, g.opacities, g.sh_coefficients(active_degree),
            self.viewmats[view : view + 1], self.Ks[view : view + 1],
            frame.intrinsics.width, frame.intrinsics.height,
            sh_degree=active_degree, render_mode="RGB+D" if with_depth else "RGB", backend=cfg.backend,
        )  # fmt: skip
        target = self.images[view]
        rgb = composite(renders[0, ..., :3], alphas[0], self.backgrounds[view])
        photometric = losses.photometric_loss(rgb, target, cfg.ssim_weight)
        loss = photometric
        terms = {"photometric": float(photometric.detach()), "transmittance": 0.0, "smoothness": 0.0, "backdrop": 0.0}
        if cfg.lambda_backdrop > 0 and self.backdrop_masks[view] is not None:
            backdrop = losses.backdrop_alpha_loss(alphas[0, ..., 0], self.backdrop_masks[view])
            loss = loss + cfg.lambda_backdrop * backdrop
            terms["backdrop"] = float(backdrop.detach())
        if self.use_touch_loss:
            candidates = self.neighbours.candidates(g.means, g.from_touch)
            points = self.touch_tensor
            if 0 < cfg.touch_points_per_step < len(points):  # an unbiased estimate of the mean over P_t
                subset = torch.randperm(len(points), generator=self.generator)[: cfg.touch_points_per_step]
                points, candidates = points[subset], candidates[subset]
            quats, scales = (g.quats, g.scales) if cfg.touch_loss_moves_shape else (g.quats.detach(), g.scales.detach())
            transmittance = losses.transmittance_loss(
                points, g.means, quats, scales, g.opacities, candidates,
                cfg.touch_top_k, cfg.touch_max_distance,
            )  # fmt: skip
            loss = loss + cfg.lambda_t * transmittance
            terms["transmittance"] = float(transmittance.detach())
        if with_depth:
            depth = renders[0, ..., 3]  # accumulated depth, paper Eq. 5
            proximity = None
            if len(self.touch_points):
                alpha = alphas[0, ..., 0].detach()
                surface = torch.where(alpha > 0.5, depth.detach() / alpha.clamp_min(1e-6), torch.zeros_like(alpha))
                rows, cols = losses.visible_touch_pixels(
                    self.touch_points, frame.intrinsics.K, frame.T_world_cam, frame.intrinsics.width,
                    frame.intrinsics.height, surface.numpy(), cfg.occlusion_tolerance,
                )  # fmt: skip
                proximity = torch.from_numpy(
                    losses.proximity_mask(rows, cols, frame.intrinsics.width, frame.intrinsics.height,
                                          cfg.proximity_sigma_px)
                )  # fmt: skip
            weights = self._smoothness_weights(view, alphas[0, ..., 0].detach())
            if cfg.smoothness_depth == "expected":
                depth = losses.expected_depth(depth, alphas[0, ..., 0])
            smoothness = losses.edge_aware_smoothness(depth / self.scene_scale, proximity=proximity, weights=weights)
            loss = loss + cfg.lambda_s * smoothness
            terms["smoothness"] = float(smoothness.detach())
        terms["loss"] = float(loss.detach())

        cfg.densify.step_pre_backward(meta)
        loss.backward()
        decay = cfg.lr_means_final_factor ** min(self.step / max(cfg.iterations, 1), 1.0)
        self.optimizers["means"].param_groups[0]["lr"] = cfg.lr_means * self.scene_scale * decay
        for optimizer in self.optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            changed = cfg.densify.step_post_backward(
                g, self.optimizers, self.densify_state, self.step, meta, self.generator
            )
        if changed and self.neighbours is not None:
            self.neighbours.invalidate()
        self.step += 1
        return terms

    def _smoothness_weights(self, view: int, alpha: torch.Tensor) -> torch.Tensor:
        """Eq. 8's image factors of a view [2, H-4, W-4]; for expected depth, zero outside the object.

        Expected depth is only defined on the object, so its smoothness counts
        only Sobel windows inside the silhouette (the view's image against its
        backdrop, or else the rendered alpha > 0.5).
        """
        cfg = self.config
        if view not in self._edge_weights:
            weights = losses.image_edge_weights(self.images[view], cfg.smoothness_beta)
            if cfg.smoothness_depth == "expected" and self.backdrop_masks[view] is not None:
                silhouette = torch.from_numpy(foreground_mask(self.backdrop_masks[view].numpy()))
                weights = weights * losses.window_inside(silhouette)
            self._edge_weights[view] = weights
        weights = self._edge_weights[view]
        if cfg.smoothness_depth == "expected" and self.backdrop_masks[view] is None:
            weights = weights * losses.window_inside(alpha > 0.5)
        return weights

    # ------------------------------------------------------------------ progress, checkpoints

    def _progress_row(self, writer) -> tuple[float, float]:
        cfg = self.config
        psnr_value, cd_value = float("nan"), float("nan")
        if self.test_frames:
            count = min(cfg.eval_max_views, len(self.test_frames))
            idx = np.unique(np.linspace(0, len(self.test_frames) - 1, count).round().astype(int))
            frames = [self.test_frames[i] for i in idx]
            if self._ground_truth is None:
                self._ground_truth = load_ground_truth(self.scene, self.test_frames) or False
            metrics = evaluate_views(
                self.gaussians, self.scene, frames, cfg.background, cfg.backend, self._ground_truth or None
            )
            psnr_value, cd_value = metrics["psnr"], metrics["cd"]
        n = max(self._sum_count, 1)
        writer.writerow(
            [self.step, f"{self.train_seconds:.3f}"]
            + [f"{self._sums[k] / n:.6g}" for k in ("loss", "photometric", "transmittance", "smoothness", "backdrop")]
            + [len(self.gaussians), f"{psnr_value:.4f}", f"{cd_value:.6g}"]
        )
        self._sums = dict.fromkeys(self._sums, 0.0)
        self._sum_count = 0
        return psnr_value, cd_value

    def save_checkpoint(self) -> None:
        state = {
            "scene_path": str(self.scene.path),
            "config": self.config.to_json(),
            "step": self.step,
            "train_seconds": self.train_seconds,
            "gaussians": self.gaussians.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "densify_state": dataclasses.asdict(self.densify_state),
            "rng": self.rng.bit_generator.state,
            "generator": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "order": list(self.order),
            "touch_points": self.touch_points,
            "neighbours": None if self.neighbours is None else self.neighbours.state_dict(),
            "progress": {"sums": dict(self._sums), "count": self._sum_count, "last_eval": self._last_eval},
        }
        tmp = self.out / "checkpoint.pt.tmp"
        torch.save(state, tmp)
        tmp.replace(self.out / "checkpoint.pt")

    def load_checkpoint(self) -> None:
        ckpt = read_checkpoint(run_checkpoint(self.out))
        self.step = int(ckpt["step"])
        self.train_seconds = float(ckpt["train_seconds"])
        self.gaussians = Gaussians.from_state_dict(ckpt["gaussians"])
        self._make_optimizers()
        for name, optimizer in self.optimizers.items():
            optimizer.load_state_dict(ckpt["optimizers"][name])
        self.densify_state = DensifyState(**ckpt["densify_state"])
        self.rng.bit_generator.state = ckpt["rng"]
        self.generator.set_state(ckpt["generator"])
        torch.set_rng_state(ckpt["torch_rng"])
        self.order = list(ckpt["order"])
        self.touch_points = np.asarray(ckpt["touch_points"])
        self.touch_tensor = torch.as_tensor(self.touch_points, dtype=torch.float32)
        if self.neighbours is not None:
            self.neighbours.touch_points = self.touch_points
            self.neighbours.load_state_dict(ckpt["neighbours"])
        progress = ckpt.get("progress")  # (checkpoints of older runs have none)
        if progress is not None:
            self._sums, self._sum_count = dict(progress["sums"]), int(progress["count"])
            self._last_eval = tuple(progress["last_eval"])
        else:
            self._last_eval = (self.step, self.train_seconds)

    # ------------------------------------------------------------------ the job

    def run(self, resume: bool = False, show_progress: bool = True) -> Gaussians:
        """Train to ``config.iterations`` (continuing the checkpoint with ``resume``); writes the run directory.

        SIGINT or SIGTERM (in the main thread) stop after the step in progress: its checkpoint is saved, then
        :class:`TrainingInterrupted` is raised.
        """
        threads = torch.get_num_threads()
        if self.config.torch_threads is not None:
            torch.set_num_threads(self.config.torch_threads)
        if self.config.init.use_sfm and not resume:
            import pycolmap  # noqa: F401  (its import installs glog's SIGTERM handler: ours must come after)
        try:
            with _StopRequests() as stop:
                return self._run(resume, show_progress, stop)
        finally:
            torch.set_num_threads(threads)

    def _run(self, resume: bool, show_progress: bool, stop: _StopRequests) -> Gaussians:
        cfg = self.config
        self.out.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(cfg.seed)
        progress_path = self.out / "progress.csv"
        if resume:
            self.load_checkpoint()
            cut_progress(progress_path, self.step)
            log.info("resuming %s at step %d", self.out, self.step)
        else:
            (self.out / "config.json").write_text(json.dumps(cfg.to_json(), indent=2))
            started = time.perf_counter()
            self.initialize()
            self.train_seconds = time.perf_counter() - started
            with progress_path.open("w", newline="") as fh:
                csv.writer(fh).writerow(PROGRESS_COLUMNS)
                self._progress_row(csv.writer(fh))
            self._last_eval = (self.step, self.train_seconds)
        bar = tqdm(total=cfg.iterations, initial=self.step, disable=not show_progress, unit="it", dynamic_ncols=True)
        with progress_path.open("a", newline="") as fh:
            writer = csv.writer(fh)
            while self.step < cfg.iterations and stop.signum is None:
                started = time.perf_counter()
                terms = self.train_step()
                self.train_seconds += time.perf_counter() - started
                for k in self._sums:
                    self._sums[k] += terms[k]
                self._sum_count += 1
                bar.update(1)
                bar.set_postfix(loss=f"{terms['loss']:.4f}", gaussians=len(self.gaussians), refresh=False)
                done = self.step >= cfg.iterations
                if (
                    done
                    or self.step - self._last_eval[0] >= cfg.eval_every_iters
                    or self.train_seconds - self._last_eval[1] >= cfg.eval_every_seconds
                ):
                    psnr_value, cd_value = self._progress_row(writer)
                    fh.flush()
                    self._last_eval = (self.step, self.train_seconds)
                    bar.set_postfix(loss=f"{terms['loss']:.4f}", gaussians=len(self.gaussians),
                                    psnr=f"{psnr_value:.2f}", cd=f"{cd_value:.4g}")  # fmt: skip
                if done or self.step % cfg.checkpoint_every == 0:
                    self.save_checkpoint()
        bar.close()
        if stop.signum is not None:
            self.save_checkpoint()
            raise TrainingInterrupted(stop.signum, self.step)
        save_ply(self.gaussians, self.out / "splat.ply")
        plot_error_vs_time(progress_path, self.out / "error_vs_time.png")
        return self.gaussians


def cut_progress(path: Path, step: int) -> None:
    """Keep the rows of ``progress.csv`` up to ``step`` (a resumed checkpoint's): later ones are redone."""
    rows = []
    if path.is_file():
        with path.open(newline="") as fh:
            rows = [r for r in csv.reader(fh)][1:]
    kept = [r for r in rows if r and r[0].isdigit() and int(r[0]) <= step]
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as fh:
        csv.writer(fh).writerows([PROGRESS_COLUMNS, *kept])
    tmp.replace(path)


def read_progress(path: Path) -> dict[str, np.ndarray]:
    with Path(path).open() as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in PROGRESS_COLUMNS}


def plot_error_vs_time(progress_path: Path, png_path: Path) -> None:
    """CD and PSNR of the held-out views against run time (seconds excluding evaluation)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = read_progress(progress_path)
    fig, (ax_cd, ax_psnr) = plt.subplots(1, 2, figsize=(10, 4))
    ax_cd.plot(data["seconds"], data["cd"], "o-", color="tab:red")
    ax_cd.set_xlabel("run time [s] (evaluation excluded)")
    ax_cd.set_ylabel("Chamfer distance [x GT radius]")
    ax_cd.set_title("geometry error")
    ax_psnr.plot(data["seconds"], data["psnr"], "o-", color="tab:blue")
    ax_psnr.set_xlabel("run time [s] (evaluation excluded)")
    ax_psnr.set_ylabel("held-out PSNR [dB]")
    ax_psnr.set_title("image error")
    for ax in (ax_cd, ax_psnr):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(png_path, dpi=100)
    plt.close(fig)


def reconstruct(scene_path: str | Path, out_dir: str | Path, config: TrainConfig, resume: bool = False,
                show_progress: bool = True, iterations_override: int | None = None, overwrite: bool = False) -> dict:
    """Train on a scene directory and evaluate the result; returns the metrics written to ``metrics.json``.

    ``out_dir`` must be new or empty, or hold an earlier run: continued with
    ``resume`` (from its checkpoint, with its own ``config.json``; only the
    iteration count may change, with ``iterations_override``) or replaced with
    ``overwrite`` (its files only). It is locked for the whole job. A folder of
    other files, a run without ``resume`` or ``overwrite``, or ``resume``
    without a checkpoint is a ConfigError, before anything is written.
    """
    from tacsplat.datasets import Scene
    from tacsplat.datasets.outputs import claim_output_dir

    out_dir = Path(out_dir)
    if resume and overwrite:
        raise ConfigError("--overwrite", "replaces a run, --resume continues it: choose one")
    config.validate()
    _check_run_folder(out_dir, resume, overwrite, locked=False)
    scene = Scene.load(scene_path)
    with claim_output_dir(out_dir, "--out"):
        _check_run_folder(out_dir, resume, overwrite, locked=True)
        if resume:
            config = TrainConfig.from_json(_read_json(out_dir / "config.json"), out_dir / "config.json")
            if iterations_override is not None:
                config.iterations = iterations_override
                config.validate({"iterations": "--iterations"})
        elif overwrite:
            _remove_run_files(out_dir)
        Trainer(scene, out_dir, config).run(resume=resume, show_progress=show_progress)
        return evaluate_run(out_dir)


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError("config", f"unreadable: {exc}", path) from None
    if not isinstance(data, dict):
        raise ConfigError("config", "expected a JSON object", path)
    return data


def _check_run_folder(out: Path, resume: bool, overwrite: bool, locked: bool) -> None:
    """Refuse an ``--out`` that is neither new, empty, nor (with ``resume``/``overwrite``) an earlier run.

    Before the lock (``locked=False``) only what no other job can change is
    refused (a folder of someone else's files, a resume of no run), so that no
    folder or lock file is made for nothing; the rest is decided under the lock.
    """
    from tacsplat.datasets.outputs import LOCK_NAME

    entries = sorted(p.name for p in out.iterdir() if p.name != LOCK_NAME) if out.is_dir() else []
    is_run = is_run_folder(out)
    if entries and not is_run:
        shown = ", ".join(entries[:5]) + (f" and {len(entries) - 5} more" if len(entries) > 5 else "")
        raise ConfigError("--out", f"{out} holds files that are not a reconstruction run ({shown}); choose a new "
                          "or empty folder")
    if (locked or not is_run) and resume and not (out / "checkpoint.pt").is_file():
        again = "; pass --overwrite to start it again" if is_run else ""
        raise ConfigError("--resume", f"{out} has no checkpoint.pt: no checkpoint to resume{again}")
    if locked and is_run and not (resume or overwrite):
        raise ConfigError("--out", f"{out} already holds a reconstruction run; pass --resume to continue it or "
                          "--overwrite to replace it")


def _remove_run_files(out: Path) -> None:
    """Delete an earlier run's files (RUN_FILES and renders/view_*.png); anything else stays."""
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)
    renders = out / RENDERS
    if renders.is_dir():
        for p in renders.iterdir():
            if RENDER_FILE.fullmatch(p.name) and p.is_file():
                p.unlink()
        if not any(renders.iterdir()):
            renders.rmdir()
