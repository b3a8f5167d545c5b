"""The tactile-informed 3DGS training job: scene directory in, run directory (:mod:`.run_dir`) out.

Loss: photometric + lambda_t L_T (Eq. 7, on G_t at the touch points) +
lambda_s L_S (Eq. 8, masked near visible touches) + lambda_backdrop times the
alpha on pixels that show the fitted smooth backdrop (not in the paper; see
:func:`losses.backdrop_alpha_loss`). L_S acts by default on the expected depth
inside the object's silhouette rather than on Eq. 5's accumulated depth
(``smoothness_depth``). The initial G_c are the scene's sparse points where it
has enough (an import's COLMAP points), else SfM's; when SfM finds too few
points, they lie on the visual hull of the silhouettes. Renders are composited
over each view's backdrop (a constant, or a smooth fit to the image border).
What a scene does not need is not computed: no touches -> no G_t, no neighbour
search, no L_T; lambda_s = 0 -> RGB-only renders.

:func:`reconstruct` is the job: it claims the run directory (a new or empty
folder; an earlier run only with ``resume`` or ``overwrite``, and never a
folder of other files), holds its lock to the end, and trains. SIGINT and
SIGTERM stop training after the step in progress, with a checkpoint
(:class:`TrainingInterrupted`); a resume continues from the checkpoint, with
``progress.csv`` cut back to it. Every file of the run directory is written
through :mod:`tacsplat.files` (whole, then renamed over the old one).
"""

from __future__ import annotations

import dataclasses
import io
import logging
import signal
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from tacsplat.errors import ConfigError, InvalidInputError, SceneFormatError, TacsplatError, UsageError
from tacsplat.files import atomic_write
from tacsplat.progress import progress_bar
from tacsplat.reconstruction import losses, shading
from tacsplat.reconstruction.baking import bake_appearance
from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.densification import DensifyState
from tacsplat.reconstruction.evaluation import (
    evaluate_reconstruction,
    evaluate_views,
    facing_normals,
    load_ground_truth,
)
from tacsplat.reconstruction.gaussians import PARAM_NAMES, Gaussians, rgb_to_sh0
from tacsplat.reconstruction.initialization import (
    SfmResult,
    foreground_mask,
    initial_gaussians,
    random_points,
    sfm_points,
    silhouette_hull_points,
    thin_touch_points,
    view_colors,
)
from tacsplat.reconstruction.methods import method_of
from tacsplat.reconstruction.ply import save_ply
from tacsplat.reconstruction.run_dir import (
    LOSS_TERMS,
    check_resumed_scene,
    check_run_folder,
    checkpoint_gaussians,
    cut_progress,
    plot_error_vs_time,
    read_checkpoint,
    read_run_config,
    remove_meshes,
    remove_run_files,
    run_checkpoint,
    scene_record,
    write_progress,
    write_run_config,
)
from tacsplat.reconstruction.views import (
    camera_tensors,
    known_backdrop,
    over_black,
    scene_at,
    training_frames,
    warn_no_backdrop,
)

log = logging.getLogger(__name__)

POSTFIX_EVERY = 25  # steps between progress-bar loss readings (each one waits for the device)
NEAR_PLANE = 0.01  # metres: the rasterizer's (raster.rasterization's default), nearer Gaussians are not drawn
MIN_IMAGE_PX = 5  # the smallest training image side: the smoothness loss's 5x5 Sobel window
RUNAWAY_FACTOR = 100  # most Gaussians this many times the scene's reach from its centre: training ran away


def scene_scale(frames: list, bounds: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Kerbl et al.'s camera extent: 1.1 x the largest distance of a camera centre from their mean. Where that is
    under a millimetre (one camera, or all at one point), the largest distance of a camera from the centre of the
    scene's ``bounds`` (lo, hi) stands in: about the spread of cameras around the object."""
    centres = np.array([f.T_world_cam[:3, 3] for f in frames])
    spread = float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max())
    if spread < 1e-3 and bounds is not None:
        spread = float(np.linalg.norm(centres - (bounds[0] + bounds[1]) / 2, axis=1).max())
    return 1.1 * max(spread, 1e-3)


def check_train_views(scene, config: TrainConfig) -> None:
    """Refuse a ``train_views`` above the scene's count of training views: a UsageError naming ``--train-views``
    (the run would train on fewer views than its config.json records)."""
    count = len(scene.split("train"))
    if config.train_views is not None and config.train_views > count:
        raise UsageError(
            "--train-views",
            f"the scene {scene.path} has {count} training views: choose at most {count} (or leave it out: all of "
            f"them), got {config.train_views}",
        )


def check_image_sizes(scene, config: TrainConfig) -> None:
    """Refuse a ``downscale`` or ``coarse_factors`` that leaves a training image under ``MIN_IMAGE_PX`` a side: a
    UsageError naming the option (the sizes as :class:`~.views.ScaledScene` makes them)."""
    for frame in training_frames(scene, config.train_views):
        size = scaled = (frame.intrinsics.width, frame.intrinsics.height)
        for option, factor in (
            ("--downscale", config.downscale),
            ("--coarse-factors", max(config.coarse_factors, default=1)),
        ):
            scaled = tuple(max(side // factor, 1) for side in scaled)
            if min(scaled) < MIN_IMAGE_PX:
                raise UsageError(
                    option,
                    f"leaves training images of {scaled[0]}x{scaled[1]} px (the scene's are {size[0]}x{size[1]}): "
                    f"training needs at least {MIN_IMAGE_PX} px a side (its 5x5 filters); choose a smaller factor",
                )


class TrainingInterrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM stopped training after a step, and that step is checkpointed.

    A KeyboardInterrupt, so that whatever stops on Ctrl-C stops on it too.
    """

    def __init__(self, signum: int, step: int):
        self.signum, self.step = signum, step
        super().__init__(f"{signal.Signals(signum).name} at step {step}: checkpoint saved")


class TrainingDiverged(TacsplatError):
    """Training's parameters became NaN or infinite (``names``, after ``step`` steps): a learning rate or a loss
    weight too high. Nothing of the diverged state is saved."""

    def __init__(self, step: int, names: list[str]):
        self.step, self.names = step, names
        super().__init__(
            f"training diverged at step {step}: the Gaussians' {', '.join(names)} became NaN or infinite; lower the "
            "learning rates (--lr-*), or a loss weight that was raised (--lambda-*)"
        )


class TrainingRanAway(TrainingDiverged):
    """Most of the Gaussians' centres lie over ``RUNAWAY_FACTOR`` times the scene's ``reach`` from its centre (their
    median distance ``distance``, after ``step`` steps), every value finite: a learning rate (the position's, most
    likely) or a loss weight far too high; ``raised`` names those set above their defaults. Nothing of that state is
    saved."""

    def __init__(self, step: int, distance: float, reach: float, raised: list[str]):
        self.step, self.names = step, ["means"]
        given = f"; set above their defaults: {', '.join(raised)}" if raised else ""
        TacsplatError.__init__(
            self,
            f"training diverged at step {step}: the Gaussians ran away from the scene, half of them over "
            f"{distance:.3g} m from its centre, more than {RUNAWAY_FACTOR}x its reach of {reach:.3g} m; lower the "
            f"learning rates (--lr-*, --lr-means first), or a loss weight that was raised (--lambda-*){given}",
        )


def raised_settings(config: TrainConfig) -> list[str]:
    """The learning rates and loss weights of ``config`` above their defaults, as options (``--lr-means 1000
    (default 0.00016)``): the likely cause of training that diverged."""
    defaults = TrainConfig()
    return [
        f"--{f.name.replace('_', '-')} {getattr(config, f.name):g} (default {getattr(defaults, f.name):g})"
        for f in dataclasses.fields(TrainConfig)
        if f.name.startswith(("lr_", "lambda_"))
        and f.name != "lr_means_final_factor"
        and getattr(config, f.name) > getattr(defaults, f.name)
    ]


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
        train = training_frames(scene, config.train_views)
        if not train:
            raise SceneFormatError(scene.path / "transforms.json", "frames", "no training views")
        self.test_frames = scene.split("test")
        self.device = dev = config.torch_device()
        self.viewmats = camera_tensors(train)[0].to(dev)
        lo, hi = scene.bounds()
        self.scene_scale = scene_scale(train, (lo, hi))
        # the run-away check's centre and reach: the bounds' centre, and the farthest of a camera and a bounds corner
        # from it (the initial Gaussians' median distance too, once they exist: _set_reach)
        self.centre = (lo + hi) / 2
        cameras = np.array([f.T_world_cam[:3, 3] for f in scene.frames])
        self.scene_reach = max(
            float(np.linalg.norm(cameras - self.centre, axis=1).max()), float(np.linalg.norm(hi - lo)) / 2
        )
        self.reach = self.scene_reach
        self.rng = np.random.default_rng(config.seed)
        self.generator = torch.Generator(device=dev).manual_seed(config.seed)
        self.touch_points = np.zeros((0, 3))
        if config.use_touch and scene.touches:
            kept = thin_touch_points(scene.touch_points(), config.init, self.rng)
            self.touch_points = scene.touch_points()[kept]
        self.use_touch_loss = len(self.touch_points) > 0 and config.lambda_t > 0
        if config.use_touch and config.lambda_t > 0 and not self.use_touch_loss:
            log.warning(
                "the scene %s has no touches (no contact points): touch is off for this run, recorded as method %s",
                scene.path,
                method_of(config, touched=False),
            )
        self.fused_losses = shading.fused_kernels(config.backend)
        reach = (config.touch_candidates, config.touch_max_distance, config.touch_rebuild_every)
        self.neighbours = losses.TouchNeighbours(self.touch_points, *reach) if self.use_touch_loss else None
        self.touch_tensor = torch.as_tensor(self.touch_points, dtype=torch.float32, device=dev)
        self.light = shading.DiffuseLight(device=dev) if config.appearance == "sh-lit" else None
        self.look = shading.Look(config.appearance, self.light)
        self.splat: Gaussians | None = None  # splat.ply's Gaussians: the final ones, shading baked (run() sets it)
        self.scene_record = scene_record(scene)  # what config.json records of the scene
        self.progress: list[dict] = []  # progress.csv's rows, rewritten whole with each new one
        self.step = 0
        # (start, start's schedule step, end, planned): steps start..end run the schedules from start's schedule step
        # to their end at ``planned`` (schedule_step); a resume with another --iterations moves start and end
        self.schedule = (0, 0.0, config.iterations, config.iterations)
        self.train_seconds = 0.0
        self.order: list[int] = []
        self.gaussians: Gaussians | None = None
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.densify_state: DensifyState | None = None
        self._ground_truth = None
        self.factor = 0  # the training views' downscale (set_resolution)
        self.set_resolution(1)
        self._zero = torch.zeros((), device=dev)
        self._sums = dict.fromkeys(LOSS_TERMS, self._zero)  # device scalars: read at progress rows only
        self._sum_count = 0
        self._last_eval = (0, 0.0)  # (step, train seconds) of the last progress row

    def set_resolution(self, factor: int) -> None:
        """Train on the views at 1/``factor`` of their size from now on (area-averaged images, scaled intrinsics):
        the images, backdrops, silhouettes and per-view loss weights a step reads."""
        if factor == self.factor:
            return
        cfg, dev = self.config, self.device
        scene = scene_at(self.scene, factor)
        self.train_frames = frames = training_frames(scene, cfg.train_views)
        self.Ks = camera_tensors(frames)[1].to(dev)
        images = [scene.load_image(f) for f in frames]  # [H, W, 3] float32 numpy
        known = [known_backdrop(im, cfg.background) for im in images]  # None: no known backdrop (black then)
        backgrounds = [over_black(bg, im) for im, bg in zip(images, known)]
        # pixels showing the bare backdrop, per view (None: no known backdrop); numpy for the silhouettes
        self.backdrop_pixels: list[np.ndarray | None] = [
            None if bg is None else np.abs(im - bg).max(axis=-1) < cfg.backdrop_tolerance
            for im, bg in zip(images, known)
        ]
        self.silhouettes = [None if m is None else foreground_mask(m) for m in self.backdrop_pixels]  # [H, W] bool
        # everything a step reads lives on the device, created once per resolution
        self.images = [torch.from_numpy(im).to(dev) for im in images]
        self.backgrounds = [torch.from_numpy(bg).to(dev) for bg in backgrounds]
        self.backdrop_masks = [None if m is None else torch.from_numpy(m).to(dev) for m in self.backdrop_pixels]
        self.factor = factor
        self.set_windows()

    def set_windows(self) -> None:
        """The window of each training view a step trains on (:meth:`_window`): its intrinsics, the share of the
        view's backdrop pixels inside it; the per-view loss weights are made anew, of the window's size."""
        self.windows = [self._window(view) for view in range(len(self.train_frames))]  # (x0, y0, w, h)
        self.window_Ks = self.Ks.clone()  # [V, 3, 3]: the principal point moved to each window's corner
        self.window_Ks[:, :2, 2] -= torch.tensor([w[:2] for w in self.windows], dtype=self.Ks.dtype, device=self.device)
        self._edge_weights: dict[int, torch.Tensor] = {}  # per training view, Eq. 8's image factors (its window's)
        self._pair_weights: dict[int, tuple] = {}  # per training view, the albedo smoothness's pair weights (ditto)
        self.backdrop_shares = [
            None if m is None else float(m[y0 : y0 + h, x0 : x0 + w].sum() / max(m.sum(), 1))
            for m, (x0, y0, w, h) in zip(self.backdrop_pixels, self.windows)
        ]

    def schedule_step(self, step: int) -> float:
        """Where ``step`` is in the schedules of fractions of the steps (coarse to fine, the position rate's decay),
        in steps of the count they were planned for: ``step`` itself unless a resume changed the count."""
        start, start_at, end, planned = self.schedule
        return start_at + (step - start) * (planned - start_at) / (end - start)

    def factor_at(self, step: int) -> int:
        """The training views' downscale at ``step`` (``coarse_factors``, then 1 from ``coarse_until``)."""
        factors, planned = self.config.coarse_factors, self.schedule[3]
        phase = int(self.schedule_step(step) / max(self.config.coarse_until * planned, 1e-9) * len(factors))
        return factors[phase] if phase < len(factors) else 1

    # ------------------------------------------------------------------ setup

    def initialize(self) -> None:
        """Initial Gaussians: SfM (or random) G_c plus G_t on the touch points."""
        cfg, images = self.config, [im.cpu().numpy() for im in self.images]
        no_backdrop = [self.scene.path / f.file_path for f, s in zip(self.train_frames, self.silhouettes) if s is None]
        warn_no_backdrop("training", no_backdrop)
        for frame, silhouette in zip(self.train_frames, self.silhouettes):
            if silhouette is not None and not silhouette.any():  # (_fallback_points leaves it out of the hull)
                log.warning(
                    "training image %s shows no object against its backdrop (a blank frame, or the object out of "
                    "view): it is left out of the visual hull, and training makes everything in its view transparent",
                    self.scene.path / frame.file_path,
                )
        sfm, what = self._sfm(images) if cfg.init.use_sfm else (None, "")
        found = 0 if sfm is None else len(sfm.points)
        sfm_found = sfm is not None and found >= cfg.init.min_sfm_points
        if sfm_found:
            points, colors = sfm.points, sfm.colors
            log.info("initialisation: %d %s", found, what)
        else:
            points, colors, where = self._fallback_points()
            message = "initialisation: %d SfM points (< %d): %d random points %s"
            log.info(message, found, cfg.init.min_sfm_points, len(points), where)
        gaussians = initial_gaussians(points, colors, self.touch_points, cfg.sh_degree, cfg.init, self.rng)
        self._check_in_view(gaussians.means.detach().numpy())
        if cfg.init.colors_from_views:
            # the randomly coloured ones, G_t (after the fallback's points if SfM failed), take the view_colors of the
            # training views (on their silhouettes where known); those on no view's object keep their colour
            first = len(points) if sfm_found else 0
            recolored = self.touch_points if sfm_found else np.concatenate([points, self.touch_points])
            view_rgb = view_colors(recolored, images, *self._cameras(), self.silhouettes)  # [M, 3]
            seen = np.isfinite(view_rgb).all(axis=1)
            sh0 = rgb_to_sh0(torch.as_tensor(view_rgb[seen], dtype=torch.float32)[:, None])
            gaussians.params["sh0"].data[torch.from_numpy(first + np.flatnonzero(seen))] = sh0
        self.gaussians = gaussians.to(self.device)
        self._make_optimizers()
        self.densify_state = cfg.densify.initialize_state(len(self.gaussians), self.scene_scale, self.device)

    def _sfm(self, images: list[np.ndarray]) -> tuple[SfmResult, str]:
        """The SfM points G_c start from, and what they are: the scene's sparse points (an import's COLMAP points)
        when it has at least ``min_sfm_points`` and training uses every train view, else points triangulated from
        the training ``images``. (The scene's points were built from all its images, the held-out ones included:
        a run on fewer views would start from what its views cannot show.)"""
        init, where = self.config.init, self.scene.sparse_points_file
        train = len(self.scene.split("train"))
        if where is not None and len(self.train_frames) < train:
            log.info(
                "the scene's sparse points (%s) come from all its images: training on %d of its %d train views "
                "(--train-views), triangulating from those",
                where,
                len(self.train_frames),
                train,
            )
        elif (sparse := self.scene.sparse_points()) is not None:
            count = len(sparse[0])
            if count >= init.min_sfm_points:
                return SfmResult(sparse[0], sparse[1] / 255.0), f"sparse points from the scene ({where})"
            log.info(
                "the scene's %d sparse points (%s) are fewer than %d: triangulating", count, where, init.min_sfm_points
            )
        return sfm_points(images, *self._cameras(), init, self.config.seed), "SfM points"

    def _check_in_view(self, means: np.ndarray) -> None:
        """A SceneFormatError when no initial Gaussian (``means`` [N, 3]) lies inside a training view beyond the
        renderer's near plane: nothing would render (a scene whose cameras are millimetres from the object, say),
        and training would 'succeed' on empty images."""
        for K, T_world_cam, frame in zip(*self._cameras(), self.train_frames):
            camera = (means - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]  # [N, 3] in the camera's frame
            ahead = camera[camera[:, 2] > NEAR_PLANE]
            u = ahead[:, 0] / ahead[:, 2] * K[0, 0] + K[0, 2]
            v = ahead[:, 1] / ahead[:, 2] * K[1, 1] + K[1, 2]
            if ((u >= 0) & (u < frame.intrinsics.width) & (v >= 0) & (v < frame.intrinsics.height)).any():
                return
        raise SceneFormatError(
            self.scene.path / "transforms.json",
            None,
            f"no initial Gaussian lies inside a training view farther than the renderer's near plane ({NEAR_PLANE} m) "
            "from its camera, so nothing would render: are the poses in metres, and do the cameras face the object?",
        )

    def _cameras(self, views: list[int] | None = None) -> tuple[list, list]:
        """The intrinsics [3, 3] and camera-to-world poses [4, 4] of the training views (``views``: of those)."""
        frames = self.train_frames if views is None else [self.train_frames[i] for i in views]
        return [f.intrinsics.K for f in frames], [f.T_world_cam for f in frames]

    def _fallback_points(self) -> tuple[np.ndarray, np.ndarray, str]:
        """Random coloured points on the silhouettes' visual hull, or in the scene bounds without silhouettes."""
        init = self.config.init
        lo, hi = self.scene.bounds()
        points, colors = random_points(lo, hi, init.num_random_points, self.rng)
        # (an empty silhouette, a view that shows only its backdrop, would carve the whole hull away)
        views = [i for i, silhouette in enumerate(self.silhouettes) if silhouette is not None and silhouette.any()]
        if init.use_silhouette_hull and views:
            silhouettes, count = [self.silhouettes[i] for i in views], init.num_random_points
            hull = silhouette_hull_points(
                silhouettes, *self._cameras(views), lo, hi, count, init.hull_resolution, self.rng
            )
            if len(hull):
                return hull, colors, f"on the visual hull of {len(views)} silhouettes"
            return points, colors, f"in the scene bounds (the visual hull of {len(views)} silhouettes is empty)"
        return points, colors, "in the scene bounds"

    def _make_optimizers(self) -> None:
        cfg = self.config
        rates = {name: getattr(cfg, f"lr_{name}") for name in PARAM_NAMES}  # (the position's times the scene scale)
        rates["means"] *= self.scene_scale
        # fused: one kernel per parameter instead of a dozen elementwise ops (about 4x less CPU time per step)
        self.optimizers = {
            name: torch.optim.Adam([self.gaussians.params[name]], lr=lr, eps=1e-15, fused=True)
            for name, lr in rates.items()
        }
        if self.light is not None:
            self.optimizers["light"] = torch.optim.Adam(self.light.parameters(), lr=cfg.lr_light, fused=True)

    # ------------------------------------------------------------------ one step

    def train_step(self) -> dict:
        """One optimisation step on one training view; returns the loss terms."""
        cfg, g = self.config, self.gaussians
        if not self.order:  # each view once in a random order, then again
            self.order = self.rng.permutation(len(self.train_frames)).tolist()
        view = self.order.pop()
        x0, y0, w, h = self.windows[view]  # the pixels this step trains on (crop_margin), and their intrinsics
        size, K, full = (w, h), self.window_Ks[view], self.train_frames[view].intrinsics
        rows, cols = slice(y0, y0 + h), slice(x0, x0 + w)
        degree = min(cfg.sh_degree, self.step // cfg.sh_degree_interval) if cfg.sh_degree_interval else cfg.sh_degree
        with_depth = cfg.lambda_s > 0 and self.step >= cfg.smoothness_start_iter
        with_normals = cfg.lambda_depth_normal > 0 and self.step >= cfg.depth_normal_start_iter
        out = shading.render(
            g,
            self.viewmats[view : view + 1],
            K[None],
            *size,
            sh_degree=degree,
            backend=cfg.backend,
            depth_mode="D" if with_depth or with_normals else None,
            normals=with_normals,
            appearance=cfg.appearance,
            light=self.light if self.step >= cfg.lit_start_iter else None,
        )
        meta, alpha = out.meta, out.alpha
        meta["width"], meta["height"] = full.width, full.height  # densification's NDC: the whole view's
        target = self.images[view][rows, cols]
        rgb = out.rgb + (1.0 - alpha[..., None]) * self.backgrounds[view][rows, cols]
        # the image losses are means over the whole view, in which the pixels outside a window add nothing
        share = w * h / (full.width * full.height)
        photometric = share * losses.photometric_loss(rgb, target, cfg.ssim_weight, fused=self.fused_losses)
        loss, terms = photometric, dict.fromkeys(LOSS_TERMS, self._zero)  # terms: detached device scalars (no sync)

        def add(term: str, weight: float, value: torch.Tensor) -> None:
            nonlocal loss
            loss = loss + weight * value
            terms[term] = terms[term] + value.detach()

        terms["photometric"] = photometric.detach()
        if cfg.lambda_backdrop > 0 and self.backdrop_masks[view] is not None:
            backdrop = losses.backdrop_alpha_loss(alpha, self.backdrop_masks[view][rows, cols])
            add("backdrop", cfg.lambda_backdrop, backdrop * self.backdrop_shares[view])
        if self.use_touch_loss:
            candidates = self.neighbours.candidates(g.means, g.from_touch)
            points = self.touch_tensor
            if 0 < cfg.touch_points_per_step < len(points):  # an unbiased estimate of the mean over P_t
                subset = torch.randperm(len(points), generator=self.generator, device=self.device)
                subset = subset[: cfg.touch_points_per_step]
                points, candidates = points[subset], candidates[subset]
            quats, scales = (g.quats, g.scales) if cfg.touch_loss_moves_shape else (g.quats.detach(), g.scales.detach())
            shape = (g.means, quats, scales, g.opacities, candidates, cfg.touch_top_k, cfg.touch_max_distance)
            transmittance = losses.transmittance_loss(points, *shape, fused=self.fused_losses)
            add("transmittance", cfg.lambda_t, transmittance)
        if cfg.lambda_albedo_smoothness > 0 and out.albedo is not None:
            if view not in self._pair_weights and cfg.albedo_smoothness_beta > 0:
                pairs = losses.image_pair_weights(self.images[view][rows, cols], cfg.albedo_smoothness_beta)
                self._pair_weights[view] = tuple(p.contiguous() for p in pairs)
            flat_albedo = losses.albedo_smoothness_loss(
                out.albedo, alpha.detach() > 0.5, self._pair_weights.get(view), self.fused_losses
            )
            add("albedo_smoothness", cfg.lambda_albedo_smoothness, flat_albedo)
        if cfg.lambda_flatten > 0:
            add("normals", cfg.lambda_flatten, losses.flatten_loss(g.scales, self.scene_scale))
        if with_normals:
            seen = alpha.detach() > 0.5
            surface = torch.where(seen, losses.expected_depth(out.depth, alpha), torch.zeros_like(alpha))
            consistency = losses.depth_normal_consistency(
                out.normal, surface, K, alpha.detach() * seen, fused=self.fused_losses
            )
            add("normals", cfg.lambda_depth_normal, consistency)
        if with_depth:
            depth = out.depth  # accumulated depth, paper Eq. 5
            proximity = None
            if len(self.touch_points) and cfg.use_proximity_mask:
                drawn = alpha.detach()
                surface = torch.where(drawn > 0.5, depth.detach() / drawn.clamp_min(1e-6), torch.zeros_like(drawn))
                seen = losses.visible_touch_pixels(
                    self.touch_tensor, K, self.viewmats[view], *size, surface, cfg.occlusion_tolerance
                )
                proximity = losses.proximity_mask(seen, cfg.proximity_sigma_px / self.factor)
            weights = self._smoothness_weights(view, alpha.detach())
            if cfg.smoothness_depth == "expected":
                depth = losses.expected_depth(depth, alpha)
            smoothness = losses.edge_aware_smoothness(
                depth / self.scene_scale, proximity=proximity, weights=weights, fused=self.fused_losses
            ) * ((w - 4) * (h - 4) / ((full.width - 4) * (full.height - 4)))
            add("smoothness", cfg.lambda_s, smoothness)
        terms["loss"] = loss.detach()

        cfg.densify.step_pre_backward(meta)
        loss.backward()
        decay = cfg.lr_means_final_factor ** min(self.schedule_step(self.step) / max(self.schedule[3], 1), 1.0)
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

    def _window(self, view: int) -> tuple[int, int, int, int]:
        """``(x0, y0, width, height)`` of the pixels of training view ``view`` a step trains on: the bounding box of
        its silhouette widened by ``crop_margin`` of the image's width (at least 8 pixels a side), or the whole
        view."""
        frame = self.train_frames[view]
        width, height = frame.intrinsics.width, frame.intrinsics.height
        silhouette = self.silhouettes[view]
        if self.config.crop_margin is None or silhouette is None or not silhouette.any():
            return 0, 0, width, height
        margin = int(np.ceil(self.config.crop_margin * width))
        box = []
        for hits, size in ((silhouette.any(axis=0), width), (silhouette.any(axis=1), height)):
            first, last = np.flatnonzero(hits)[[0, -1]]
            start, stop = max(first - margin, 0), min(last + margin + 1, size)
            extent = min(max(stop - start, 8), size)
            box.append((int(min(start, size - extent)), int(extent)))
        (x0, w), (y0, h) = box
        return x0, y0, w, h

    def _smoothness_weights(self, view: int, alpha: torch.Tensor) -> torch.Tensor:
        """Eq. 8's image factors of a view's window [2, h-4, w-4]; for expected depth, zero outside the object.

        Expected depth is only defined on the object, so its smoothness counts
        only Sobel windows inside the silhouette (the view's image against its
        backdrop, or else the rendered alpha > 0.5).
        """
        cfg = self.config
        if view not in self._edge_weights:
            weights = losses.image_edge_weights(self.images[view], cfg.smoothness_beta)
            if cfg.smoothness_depth == "expected" and self.backdrop_pixels[view] is not None:
                silhouette = torch.from_numpy(self.silhouettes[view]).to(self.device)
                weights = weights * losses.window_inside(silhouette)
            x0, y0, w, h = self.windows[view]
            self._edge_weights[view] = weights[:, y0 : y0 + h - 4, x0 : x0 + w - 4].contiguous()
        weights = self._edge_weights[view]
        if cfg.smoothness_depth == "expected" and self.backdrop_masks[view] is None:
            weights = weights * losses.window_inside(alpha > 0.5)
        return weights

    # ------------------------------------------------------------------ progress, checkpoints

    def _distances(self) -> torch.Tensor:
        """[N] distances of the Gaussians' centres from the scene's centre."""
        means = self.gaussians.means.detach()
        return (means - torch.as_tensor(self.centre, dtype=means.dtype, device=means.device)).norm(dim=-1)

    def _set_reach(self) -> None:
        """The run-away check's reach: the scene's, or the median distance of the Gaussians training starts (or goes on)
        from where that is farther (a forward-facing capture's points lie far beyond its cameras)."""
        median = float(self._distances().median()) if len(self.gaussians) else 0.0
        self.reach = max(self.scene_reach, median)

    def _check_diverged(self) -> None:
        """Raise :class:`TrainingDiverged` where a parameter, or a scale it stands for, is NaN or infinite, and
        :class:`TrainingRanAway` where more than half of the Gaussians lie over ``RUNAWAY_FACTOR`` times the reach
        from the scene's centre (a scale-free test: the median distance)."""
        g = self.gaussians
        values = dict(g.params) | {"scales": g.scales}  # (a finite log-scale past 88 overflows float32's exp)
        if self.light is not None:
            values |= {f"light {name}": p for name, p in self.light.named_parameters()}
        distances = self._distances()
        near = (distances > RUNAWAY_FACTOR * self.reach).sum() * 2 <= len(g)
        checks = torch.stack([torch.isfinite(v).all() for v in values.values()] + [near]).tolist()  # (one wait)
        finite = checks[:-1]
        if not all(finite):
            raise TrainingDiverged(self.step, [name for name, ok in zip(values, finite) if not ok])
        if not checks[-1]:
            raise TrainingRanAway(self.step, float(distances.median()), self.reach, raised_settings(self.config))

    def _progress_row(self) -> tuple[float, float]:
        """Evaluate on the held-out views and add a row to ``progress.csv`` (the last evaluation's); returns (PSNR,
        CD). Training that diverged raises :class:`TrainingDiverged` instead (:meth:`_check_diverged`)."""
        self._check_diverged()
        cfg = self.config
        metrics = dict.fromkeys(("psnr", "cd", "cd_paper"), float("nan"))
        if self.test_frames:
            count = min(cfg.eval_max_views, len(self.test_frames))
            idx = np.unique(np.linspace(0, len(self.test_frames) - 1, count).round().astype(int))
            frames = [self.test_frames[i] for i in idx]
            if self._ground_truth is None:
                self._ground_truth = load_ground_truth(self.scene, self.test_frames) or False
            truth = self._ground_truth or None  # (False: the scene has none)
            metrics = evaluate_views(
                self.gaussians, self.scene, frames, cfg.background, cfg.backend, truth, look=self.look, progress=True
            )
        n = max(self._sum_count, 1)
        row = {"iteration": self.step, "seconds": f"{self.train_seconds:.3f}", "num_gaussians": len(self.gaussians)}
        row |= {"psnr": f"{metrics['psnr']:.4f}", **{k: f"{metrics[k]:.6g}" for k in ("cd", "cd_paper")}}
        self.progress.append(row | {k: f"{float(self._sums[k]) / n:.6g}" for k in LOSS_TERMS})
        write_progress(self.out / "progress.csv", self.progress)
        self._sums = dict.fromkeys(LOSS_TERMS, self._zero)
        self._sum_count = 0
        self._last_eval = (self.step, self.train_seconds)
        return metrics["psnr"], metrics["cd"]

    def save_checkpoint(self) -> None:
        """Write ``checkpoint.pt``; training that diverged raises :class:`TrainingDiverged` instead, and the last
        checkpoint stays."""
        self._check_diverged()
        state = {
            "scene_path": self.scene_record["path"],  # (resolved: evaluate and export find it from anywhere)
            "config": self.config.to_json(),
            "step": self.step,
            "schedule": self.schedule,
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
            "progress": {
                "sums": {k: float(v) for k, v in self._sums.items()},
                "count": self._sum_count,
                "last_eval": self._last_eval,
            },
            "device": self.device.type,
            "light": None if self.light is None else self.light.state_dict(),
        }
        data = io.BytesIO()  # (torch.save into the file itself fails a full disk with its own RuntimeError)
        torch.save(state, data)
        atomic_write(self.out / "checkpoint.pt", data.getbuffer())

    def load_checkpoint(self) -> None:
        path = run_checkpoint(self.out)
        ckpt = read_checkpoint(path)
        saved_on = ckpt.get("device", "cpu")
        if saved_on != self.device.type:
            raise ConfigError(
                "--resume",
                f"{self.out} was trained on {saved_on} and this run would continue on "
                f"{self.device.type}: resume on the same kind of device (--device {saved_on})",
            )
        self.step = int(ckpt["step"])
        trained_for = int(ckpt["config"]["iterations"])  # (checkpoints of older runs have no schedule)
        self.schedule = tuple(ckpt.get("schedule", (0, 0.0, trained_for, trained_for)))
        if self.schedule[2] != self.config.iterations and self.step < self.config.iterations:
            # another --iterations: the schedules go on from where they are, to their end at the new count
            self.schedule = (self.step, self.schedule_step(self.step), self.config.iterations, self.schedule[3])
        self.train_seconds = float(ckpt["train_seconds"])
        self.gaussians = checkpoint_gaussians(ckpt, path).to(self.device)
        if self.light is not None:
            self.light.load_state_dict(ckpt["light"])
        self._make_optimizers()
        for name, optimizer in self.optimizers.items():
            optimizer.load_state_dict(ckpt["optimizers"][name])
        densify = {k: v.to(self.device) if torch.is_tensor(v) else v for k, v in ckpt["densify_state"].items()}
        self.densify_state = DensifyState(**densify)
        self.rng.bit_generator.state = ckpt["rng"]
        self.generator.set_state(ckpt["generator"])
        torch.set_rng_state(ckpt["torch_rng"])
        self.order = list(ckpt["order"])
        self.touch_points = np.asarray(ckpt["touch_points"])
        self.touch_tensor = torch.as_tensor(self.touch_points, dtype=torch.float32, device=self.device)
        if self.neighbours is not None:
            self.neighbours.touch_points = self.touch_points
            self.neighbours.load_state_dict(ckpt["neighbours"])
        if (progress := ckpt.get("progress")) is not None:  # (checkpoints of older runs have none)
            sums = progress["sums"]  # (a term added since the checkpoint was written: nothing summed yet)
            self._sums = {k: torch.tensor(float(sums.get(k, 0.0)), device=self.device) for k in LOSS_TERMS}
            self._sum_count = int(progress["count"])
            self._last_eval = tuple(progress["last_eval"])
        else:
            self._last_eval = (self.step, self.train_seconds)

    def _wait_for_device(self) -> float:
        """Seconds spent waiting for the device to finish the queued work (0 on the CPU)."""
        if self.device.type != "cuda":
            return 0.0
        started = time.perf_counter()
        torch.cuda.synchronize(self.device)
        return time.perf_counter() - started

    # ------------------------------------------------------------------ the job

    def run(self, resume: bool = False, show_progress: bool = True) -> Gaussians:
        """Train to ``config.iterations`` (continuing the checkpoint with ``resume``); writes the run directory.

        SIGINT or SIGTERM (in the main thread) stop after the step in progress: its checkpoint is saved, then
        :class:`TrainingInterrupted` is raised. torch's global random state is seeded for the run and given back as
        it was (a script's own random stream goes on unchanged).
        """
        threads = torch.get_num_threads()
        if self.config.torch_threads is not None:
            torch.set_num_threads(self.config.torch_threads)
        if self.config.init.use_sfm and not resume:
            import pycolmap  # noqa: F401  (its import installs glog's SIGTERM handler: ours must come after)
        cuda = [self.device] if self.device.type == "cuda" else []
        try:
            with _StopRequests() as stop, torch.random.fork_rng(devices=cuda):
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
            if self.step > cfg.iterations:
                raise UsageError(
                    "--iterations",
                    f"{self.out} has reached step {self.step}: to resume it, it must be "
                    f"{self.step} or more, got {cfg.iterations}",
                )
            write_run_config(self.out, cfg, self.scene_record)  # (a new step count or scene path: one record)
            self.progress = cut_progress(progress_path, self.step)
            if self.step < cfg.iterations:  # the Gaussians will change: a mesh exported from them no longer matches
                remove_meshes(self.out)
            log.info("resuming %s at step %d of %d", self.out, self.step, cfg.iterations)
            self._set_reach()
        else:
            write_run_config(self.out, cfg, self.scene_record)
            started = time.perf_counter()
            self.initialize()
            self._set_reach()
            self.train_seconds = time.perf_counter() - started
            self._progress_row()
        bar = progress_bar(total=cfg.iterations, initial=self.step, enabled=show_progress, desc="train", unit="it")
        try:
            while self.step < cfg.iterations and stop.signum is None:
                started = time.perf_counter()
                self.set_resolution(self.factor_at(self.step))
                try:
                    terms = self.train_step()
                except InvalidInputError:  # a kernel's or the rasterizer's check of non-finite inputs
                    self._check_diverged()  # (diverged: TrainingDiverged; else the kernel's error stands)
                    raise
                self.train_seconds += time.perf_counter() - started
                for k in LOSS_TERMS:
                    self._sums[k] = self._sums[k] + terms[k]
                self._sum_count += 1
                bar.update(1)
                if self.step % POSTFIX_EVERY == 0:
                    bar.set_postfix(loss=f"{float(terms['loss']):.4f}", gaussians=len(self.gaussians), refresh=False)
                done = self.step >= cfg.iterations
                steps, seconds = self.step - self._last_eval[0], self.train_seconds - self._last_eval[1]  # since then
                if done or steps >= cfg.eval_every_iters or seconds >= cfg.eval_every_seconds:
                    self.train_seconds += self._wait_for_device()  # queued steps are training time
                    psnr_value, cd_value = self._progress_row()
                    shown = {"psnr": f"{psnr_value:.2f}", "cd": f"{cd_value:.4g}"}
                    bar.set_postfix(loss=f"{float(terms['loss']):.4f}", gaussians=len(self.gaussians), **shown)
                if done or self.step % cfg.checkpoint_every == 0:
                    self.save_checkpoint()
        finally:
            bar.close()  # (a failed write's error then starts a line of its own)
        if stop.signum is not None:
            self.save_checkpoint()
            raise TrainingInterrupted(stop.signum, self.step)
        self.splat = bake_appearance(self.gaussians, self.look)  # what a 3DGS viewer can show
        save_ply(self.splat, self.out / "splat.ply", facing_normals(self.splat, self.train_frames, self.config.backend))
        plot_error_vs_time(progress_path, self.out / "error_vs_time.png")
        return self.gaussians


def reconstruct(
    scene_path: str | Path,
    out_dir: str | Path,
    config: TrainConfig,
    resume: bool = False,
    show_progress: bool = True,
    overwrite: bool = False,
    resumed: Callable[[TrainConfig], TrainConfig] | None = None,
) -> dict:
    """Train on a scene directory and evaluate the result; returns the metrics written to ``metrics.json``.

    ``out_dir`` must be new or empty, or hold an earlier run: continued with
    ``resume`` (from its checkpoint, with its own ``config.json``, on the scene
    it recorded; ``resumed(recorded config)``, where given, returns the config to continue with, or refuses it: only
    the iteration count may change, not below the step reached, and config.json then records it) or replaced with
    ``overwrite`` (its files only). It is locked for the whole job. A folder of other files, a run without ``resume``
    or ``overwrite``, ``resume`` of no run, on another scene or of a run that trained with a removed loss, or a folder
    that cannot take a file (read-only, full) is an error before any training; the gsplat backend where torch sees no
    CUDA, a ``train_views`` above the scene's training views (:func:`check_train_views`), and a ``downscale`` or
    ``coarse_factors`` that leaves training images under ``MIN_IMAGE_PX`` a side (:func:`check_image_sizes`), are
    errors before the folder is made. Every file is replaced atomically: a disk that fills up stops the job with a
    StorageError naming the file, and the files written before (the last checkpoint) stay, so that ``resume``
    continues once there is space.
    """
    from tacsplat.datasets import Scene
    from tacsplat.datasets.outputs import claim_output_dir

    out_dir = Path(out_dir)
    if resume and overwrite:
        raise UsageError("--overwrite", "replaces a run, --resume continues it: choose one")
    config.validate()
    device = config.torch_device()  # --device cuda without CUDA fails here, before anything is read or written
    if config.backend == "gsplat" and device.type != "cuda":
        raise UsageError(
            "--backend", f"gsplat renders on CUDA and this run would train on {device.type}: use --backend auto or cpu"
        )
    check_run_folder(out_dir, resume, overwrite, locked=False)
    base = Scene.load(scene_path)
    if not resume:  # (a resumed run trains on the views and at the sizes it has trained on and at)
        check_train_views(base, config)
        check_image_sizes(base, config)
    with claim_output_dir(out_dir, "--out"):
        check_run_folder(out_dir, resume, overwrite, locked=True)
        if resume:
            config, recorded_scene = read_run_config(out_dir)
            check_resumed_scene(out_dir, recorded_scene, base)
            if resumed is not None:
                config = resumed(config)
                config.validate({"iterations": "--iterations"})
        elif overwrite:
            remove_run_files(out_dir)
        scene = scene_at(base, config.downscale)
        trainer = Trainer(scene, out_dir, config)
        trainer.run(resume=resume, show_progress=show_progress)  # (a resume without a checkpoint was refused)
        return evaluate_reconstruction(trainer, scene, out_dir, trainer.splat)
