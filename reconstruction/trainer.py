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
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
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

    def validate(self) -> None:
        if self.iterations < 1:
            raise ConfigError("iterations", f"must be >= 1, got {self.iterations}")
        if not 0 <= self.sh_degree <= 3:
            raise ConfigError("sh_degree", f"must be in 0..3, got {self.sh_degree}")
        if self.train_views is not None and self.train_views < 1:
            raise ConfigError("train_views", f"must be >= 1, got {self.train_views}")
        for key in ("lambda_t", "lambda_s"):
            if getattr(self, key) < 0:
                raise ConfigError(key, f"must be >= 0, got {getattr(self, key)}")
        if self.smoothness_depth not in ("expected", "accumulated"):
            raise ConfigError("smoothness_depth", f"must be 'expected' or 'accumulated', got {self.smoothness_depth!r}")
        if self.backend not in raster.BACKENDS:
            raise ConfigError("backend", f"must be one of {raster.BACKENDS}, got {self.backend!r}")

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> "TrainConfig":
        data = dict(data)
        init = InitConfig(**data.pop("init", {}))
        densify = DensifyStrategy(**data.pop("densify", {}))
        if data.get("background") is not None:
            data["background"] = tuple(data["background"])
        return cls(**data, init=init, densify=densify)


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


def load_run(run_dir: Path) -> LoadedRun:
    """The last checkpoint of a run directory (for evaluation)."""
    ckpt_path = run_dir / "checkpoint.pt"
    if not ckpt_path.is_file():
        raise SceneFormatError(ckpt_path, None, "no checkpoint: not a reconstruction run directory")
    ckpt = torch.load(ckpt_path, weights_only=False)
    return LoadedRun(
        Path(ckpt["scene_path"]),
        TrainConfig.from_json(ckpt["config"]),
        Gaussians.from_state_dict(ckpt["gaussians"]),
        int(ckpt["step"]),
        float(ckpt["train_seconds"]),
    )


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
        }
        tmp = self.out / "checkpoint.pt.tmp"
        torch.save(state, tmp)
        tmp.replace(self.out / "checkpoint.pt")

    def load_checkpoint(self) -> None:
        ckpt = torch.load(self.out / "checkpoint.pt", weights_only=False)
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

    # ------------------------------------------------------------------ the job

    def run(self, resume: bool = False, show_progress: bool = True) -> Gaussians:
        """Train to ``config.iterations`` (continuing a checkpoint with ``resume``); writes the run directory."""
        threads = torch.get_num_threads()
        if self.config.torch_threads is not None:
            torch.set_num_threads(self.config.torch_threads)
        try:
            return self._run(resume, show_progress)
        finally:
            torch.set_num_threads(threads)

    def _run(self, resume: bool, show_progress: bool) -> Gaussians:
        cfg = self.config
        self.out.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(cfg.seed)
        progress_path = self.out / "progress.csv"
        if resume and (self.out / "checkpoint.pt").is_file():
            self.load_checkpoint()
            log.info("resuming %s at step %d", self.out, self.step)
        else:
            (self.out / "config.json").write_text(json.dumps(cfg.to_json(), indent=2))
            started = time.perf_counter()
            self.initialize()
            self.train_seconds = time.perf_counter() - started
            with progress_path.open("w", newline="") as fh:
                csv.writer(fh).writerow(PROGRESS_COLUMNS)
                self._progress_row(csv.writer(fh))
        last_eval_step, last_eval_seconds = self.step, self.train_seconds
        bar = tqdm(total=cfg.iterations, initial=self.step, disable=not show_progress, unit="it", dynamic_ncols=True)
        with progress_path.open("a", newline="") as fh:
            writer = csv.writer(fh)
            while self.step < cfg.iterations:
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
                    or self.step - last_eval_step >= cfg.eval_every_iters
                    or self.train_seconds - last_eval_seconds >= cfg.eval_every_seconds
                ):
                    psnr_value, cd_value = self._progress_row(writer)
                    fh.flush()
                    last_eval_step, last_eval_seconds = self.step, self.train_seconds
                    bar.set_postfix(loss=f"{terms['loss']:.4f}", gaussians=len(self.gaussians),
                                    psnr=f"{psnr_value:.2f}", cd=f"{cd_value:.4g}")  # fmt: skip
                if done or self.step % cfg.checkpoint_every == 0:
                    self.save_checkpoint()
        bar.close()
        save_ply(self.gaussians, self.out / "splat.ply")
        plot_error_vs_time(progress_path, self.out / "error_vs_time.png")
        return self.gaussians


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
                show_progress: bool = True, iterations_override: int | None = None) -> dict:
    """Train on a scene directory and evaluate the result; returns the metrics written to ``metrics.json``.

    With ``resume`` and an existing run, the run's own ``config.json`` is used
    (only the iteration count may be raised with ``iterations_override``).
    """
    from tacsplat.datasets import Scene
    from tacsplat.reconstruction.evaluation import evaluate_run

    out_dir = Path(out_dir)
    if resume and (out_dir / "config.json").is_file():
        config = TrainConfig.from_json(json.loads((out_dir / "config.json").read_text()))
        if iterations_override is not None:
            config.iterations = iterations_override
    scene = Scene.load(scene_path)
    Trainer(scene, out_dir, config).run(resume=resume, show_progress=show_progress)
    return evaluate_run(out_dir)
