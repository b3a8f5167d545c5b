"""`tacsplat bench next-touch`: next-best against random grasps at equal grasp budgets, views and training steps.

Per object, seed and strategy one simulated capture with 5 train views and the largest grasp budget
(``sim-capture --grasp-strategy random|next-best``); both strategies of an object and seed see the same views
(the views do not depend on the strategy). Choices are sequential, so the first ``k`` grasps of a capture are the
``k``-grasp capture: per budget ``k`` a copy of the scene keeps every frame and the touches of its first ``k``
recorded grasps, and is reconstructed with ``--method`` (default: what `tacsplat reconstruct` trains) for the
same ``--iterations`` whatever the strategy. The training next-best spends choosing (``selection_steps`` per grasp,
with the trainer's defaults) is not in these steps; it is reported as ``selection_seconds``.

Beside the table, for each object's first seed: how well the two uncertainty scores of the views-only
reconstruction that chose the first grasp predict its real error: each score rendered on the test views beside
the depth error against the ground truth, and the Spearman rank correlation of the two over the test pixels.

The captures, copies and runs are batch jobs, run here or as Ray tasks (``--executor ray``,
:mod:`tacsplat.apps.executors`); the report is written here once they are done.
Output (resumable: finished captures, copies and runs are kept)::

    OUT/scenes/<object>-s<seed>-<strategy>/        the captures (next-best's decisions in their scene.json)
    OUT/scenes/<object>-s<seed>-<strategy>-g<k>/   their first k grasps (+ <copy>.json: what it holds)
    OUT/runs/<object>-s<seed>-<strategy>-g<k>/     `tacsplat reconstruct` run folders
    OUT/results.csv  OUT/report.md  OUT/cd_vs_grasps.png  OUT/uncertainty_<object>.png
    OUT/failures.csv                               the jobs that failed, if any
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Literal

import numpy as np

from tacsplat.apps.batch import (
    CAPTURE_MARKER,
    METRICS,
    BatchJob,
    CaptureJob,
    ReconstructJob,
    SceneCopyJob,
    capture_copies_runs,
    check_slide,
)
from tacsplat.apps.executors import ExecutorOptions, Executors
from tacsplat.errors import ConfigError
from tacsplat.options import comma_separated_ints
from tacsplat.reconstruction.methods import DEFAULT_METHOD, METHODS, get_method

log = logging.getLogger(__name__)

STRATEGIES = ("random", "next-best")
RESULT_COLUMNS = (
    "object",
    "strategy",
    "grasps",
    "seed",
    "cd",
    "cd_paper",
    "psnr",
    "seconds",
    "selection_seconds",
    "touches",
)


@dataclass
class NextTouchBenchConfig:
    """The sweep; defaults: every library object, 3 seeds, budgets of 1 to 8 grasps."""

    objects: tuple[str, ...] = ()  # empty: every library object
    mesh: str | None = None  # any mesh instead of library objects
    seeds: tuple[int, ...] = (0, 1, 2)
    grasps: tuple[int, ...] = (1, 2, 3, 5, 8)
    views: int = 5  # train views (the paper's minimal-views setting)
    test_views: int = 12
    resolution: int = 128
    iterations: int = 1500  # steps of every final reconstruction
    method: str = DEFAULT_METHOD  # the method of every final reconstruction (reconstruction.methods.METHODS)
    candidates: int = 16  # next-best: approaches scored per grasp
    selection_steps: int = 300  # next-best: steps of the reconstruction that chooses each grasp
    uncertainty: str = "depth-variance"  # next-best: the score
    slide_m: float = 0.0  # each finger in contact slides its pad this far each way after the press (GraspControl)

    def validate(self) -> None:
        from tacsplat.reconstruction.uncertainty import SCORES
        from tacsplat.sim.objects import OBJECT_NAMES

        unknown = [o for o in self.objects if o not in OBJECT_NAMES]
        if unknown:
            raise ConfigError(
                "--objects", f"unknown object(s) {', '.join(unknown)}; choose from {', '.join(OBJECT_NAMES)} (or all)"
            )
        if self.mesh is not None and not Path(self.mesh).is_file():
            raise ConfigError("--mesh", f"file not found: {self.mesh}")
        if not self.seeds or min(self.seeds) < 0:
            raise ConfigError("--seeds", f"need at least one seed, each >= 0, got {self.seeds}")
        if not self.grasps or min(self.grasps) < 0:
            raise ConfigError("--grasps", f"need at least one grasp budget, each >= 0, got {self.grasps}")
        for key in ("objects", "seeds", "grasps"):  # each value names its folders (and jobs) once
            values = getattr(self, key)
            if len(set(values)) < len(values):
                raise ConfigError(f"--{key}", f"a value is repeated in {', '.join(map(str, values))}")
        for key in ("views", "test_views", "resolution", "iterations", "candidates", "selection_steps"):
            if getattr(self, key) < 1:
                raise ConfigError(f"--{key.replace('_', '-')}", f"must be >= 1, got {getattr(self, key)}")
        get_method(self.method, "--method")
        if self.uncertainty not in SCORES:
            raise ConfigError("--uncertainty", f"must be one of {', '.join(SCORES)}, got {self.uncertainty!r}")
        check_slide(self.slide_m, "--slide-m")

    @property
    def subjects(self) -> list[str]:
        """The objects' names: the mesh's stem, or the library objects."""
        if self.mesh is not None:
            return [Path(self.mesh).stem]
        from tacsplat.sim.objects import OBJECT_NAMES

        return list(self.objects or OBJECT_NAMES)


def first_grasps(scene_path: str | Path, out: str | Path, count: int) -> tuple[int, int]:
    """Copy a scene to ``out`` with every frame and the touches of its first ``count`` recorded grasps (by grasp
    number); returns ``(grasps kept, touches in contact)``. ``out`` must not exist."""
    from tacsplat.datasets import Scene, copy_scene

    scene = Scene.load(scene_path)
    kept = sorted({t.grasp for t in scene.touches})[:count]
    touches = [t for t in scene.touches if t.grasp in kept]
    extra = {**scene.meta.extra, "first_grasps": {"from": str(scene.path), "grasps": len(kept)}}
    copy_scene(scene, out, touches=touches, meta=replace(scene.meta, extra=extra))
    return len(kept), sum(t.in_contact for t in touches)


@dataclass(frozen=True, kw_only=True)
class StrategyCaptureJob(CaptureJob):
    """A capture job whose grasps follow ``grasp_strategy``: random, or next-best (``candidates`` approaches
    scored per grasp on a ``selection_steps``-step reconstruction of the scene so far by the ``uncertainty``
    score)."""

    grasp_strategy: Literal["random", "next-best"]
    candidates: int
    selection_steps: int
    uncertainty: str

    def rig(self, **options):
        keys = ("grasp_strategy", "candidates", "selection_steps", "uncertainty")
        return super().rig(**{k: getattr(self, k) for k in keys}, **options)


@dataclass(frozen=True, kw_only=True)
class FirstGraspsJob(SceneCopyJob):
    """A copy of the capture ``base`` with its first ``count`` grasps (:func:`first_grasps`); its marker holds the
    grasps and touches kept and the seconds next-best spent choosing them."""

    kind: Literal["first-grasps"] = "first-grasps"

    def make_copy(self) -> dict:
        grasps, touches = first_grasps(self.base, self.out, self.count)
        return {"grasps": grasps, "touches": touches, "selection_seconds": selection_seconds(self.base, self.count)}


class NextTouchBench:
    """The sweep in a folder; :meth:`run` does whatever is not done yet."""

    def __init__(self, out: str | Path, config: NextTouchBenchConfig | None = None):
        self.out = Path(out)
        self.config = config or NextTouchBenchConfig()
        self.config.validate()

    def sweep(self) -> list[tuple[str, int, str, int]]:
        """``(object, seed, strategy, grasps)`` of every run, in the order of the sweep."""
        c = self.config
        return [
            (subject, seed, strategy, k)
            for subject in c.subjects
            for seed in c.seeds
            for strategy in STRATEGIES
            for k in c.grasps
        ]

    def captures(self) -> list[tuple[str, int, str]]:
        """``(object, seed, strategy)`` of every capture, in the order of the sweep."""
        return list(dict.fromkeys(key[:3] for key in self.sweep()))

    def capture_job(self, subject: str, seed: int, strategy: str) -> StrategyCaptureJob:
        """The sim capture of one object, seed and strategy, with the largest grasp budget."""
        c = self.config
        out = self.out / "scenes" / f"{subject}-s{seed}-{strategy}"
        keys = ("mesh", "views", "test_views", "resolution", "candidates", "selection_steps", "uncertainty", "slide_m")
        return StrategyCaptureJob(
            out=out,
            object=subject if c.mesh is None else "teapot",
            grasps=max(c.grasps),
            seed=seed,
            grasp_strategy=strategy,
            name=f"capture {out.name}",
            **{k: getattr(c, k) for k in keys},
        )

    def copy_job(self, subject: str, seed: int, strategy: str, count: int) -> FirstGraspsJob:
        """The copy of a capture with its first ``count`` grasps."""
        base = self.capture_job(subject, seed, strategy).out
        out = base.with_name(f"{base.name}-g{count}")
        return FirstGraspsJob(out=out, base=base, count=count, name=f"copy {out.name}")

    def check_out(self) -> None:
        """Refuse a folder whose finished captures were made with another plan, or whose finished runs with
        other training settings (another number of steps or method, or a default changed since), before anything
        runs."""
        for subject, seed, strategy in self.captures():
            capture = self.capture_job(subject, seed, strategy)
            marker = capture.out / CAPTURE_MARKER
            if marker.is_file() and json.loads(marker.read_text())["plan"] != capture.rig().plan.to_json():
                raise ConfigError(
                    "--out",
                    f"{marker.parent} was captured with another plan ({marker}); use the same options or a new --out",
                )
        for key in self.sweep():
            self.reconstruct_job(*key).refuse_changed_settings()

    def jobs(self) -> list[BatchJob]:
        """Per object, seed and strategy its capture (if a copy of it is still to make), then per budget the copy
        with that many grasps and its reconstruction (``method``, ``iterations`` steps)."""
        c = self.config
        jobs: list[BatchJob] = []
        for subject, seed, strategy in self.captures():
            copies = [self.copy_job(subject, seed, strategy, k) for k in c.grasps]
            run = lambda copy: self.reconstruct_job(subject, seed, strategy, copy.count)  # noqa: E731
            jobs += capture_copies_runs(self.capture_job(subject, seed, strategy), copies, run)
        return jobs

    def reconstruct_job(self, subject: str, seed: int, strategy: str, count: int) -> ReconstructJob:
        """The final reconstruction of the copy with a capture's first ``count`` grasps."""
        scene = self.copy_job(subject, seed, strategy, count).out
        out, c = self.out / "runs" / scene.name, self.config
        return ReconstructJob(
            out=out, scene=scene, method=c.method, seed=seed, iterations=c.iterations, name=f"reconstruct {out.name}"
        )

    def results(self) -> list[dict]:
        """One row per finished run, in the order of the sweep."""
        rows = []
        for subject, seed, strategy, k in self.sweep():
            run, copy = self.reconstruct_job(subject, seed, strategy, k), self.copy_job(subject, seed, strategy, k)
            if not run.complete():
                continue
            metrics, info = json.loads((run.out / METRICS).read_text()), json.loads(copy.marker.read_text())
            rows.append(
                {
                    "object": subject,
                    "strategy": strategy,
                    "grasps": k,
                    "seed": seed,
                    "cd": metrics["cd"],
                    "cd_paper": metrics.get("cd_paper"),
                    "psnr": metrics["psnr"],
                    "seconds": metrics["train_seconds"],
                    "selection_seconds": info["selection_seconds"],
                    "touches": info["touches"],
                }
            )
        return rows

    def run(self, progress: bool = True, **executor) -> list[dict]:
        """Capture, copy and train whatever is not done yet (``executor``: the executor, ray_address and retries of
        :func:`~tacsplat.apps.executors.run_jobs`), then write the report; returns the rows. A BatchError at the
        end when jobs failed (listed in failures.csv)."""
        from tacsplat.apps.executors import run_jobs

        c = self.config
        self.check_out()
        runs = {self.reconstruct_job(*key).name: key for key in self.sweep()}

        def on_done(job, metrics: dict) -> str | None:
            if job.name not in runs:
                return None
            subject, seed, strategy, k = runs[job.name]
            touches = json.loads(self.copy_job(subject, seed, strategy, k).marker.read_text())["touches"]
            return f"{subject} s{seed} {strategy:9s} {k} grasps ({touches} touches): CD {metrics['cd']:.4f}"

        outcome = run_jobs(
            self.jobs(), self.out, on_done=on_done, desc="bench next-touch", progress=progress, **executor
        )
        rows = self.results()
        correlations = {
            subject: self.uncertainty_picture(subject, c.seeds[0])
            for subject in c.subjects
            if self.capture_job(subject, c.seeds[0], "next-best").complete()
        }
        write_report(self.out, rows, correlations, c)
        outcome.raise_if_failed(self.out)
        return rows

    def uncertainty_picture(self, subject: str, seed: int) -> dict[str, float]:
        """``uncertainty_<subject>.png`` and the Spearman correlation of each score with the depth error (on the
        views-only copy of the next-best capture, made here if 0 is not a budget)."""
        copy = self.copy_job(subject, seed, "next-best", 0)
        copy()
        return uncertainty_vs_error(
            copy.out, self.config.selection_steps, seed, self.out / f"uncertainty_{subject}.png"
        )


def selection_seconds(scene: Path, count: int) -> float:
    """The seconds next-best spent choosing the first ``count`` grasps of a capture (0 for random)."""
    from tacsplat.acquisition.next_touch import DECISIONS_KEY
    from tacsplat.datasets import Scene

    recorded = Scene.load(scene, check_files=False).annotations.get(DECISIONS_KEY, {"grasps": []})
    decisions = sorted(recorded["grasps"], key=lambda d: d["grasp"])
    return float(sum(d["selection_seconds"] for d in decisions[:count]))


def uncertainty_vs_error(scene_path: Path, steps: int, seed: int, picture: Path, views_shown: int = 3) -> dict:
    """The reconstruction that chooses the first grasp (``steps`` on the views of ``scene_path``), each score's
    rendering on the test views beside the depth error against the ground truth (``picture``), and the Spearman
    correlation of score and error over the test pixels where both surfaces are drawn."""
    from scipy.stats import spearmanr

    from tacsplat.apps.report import pyplot, save_figure
    from tacsplat.datasets import Scene
    from tacsplat.reconstruction.config import TrainConfig
    from tacsplat.reconstruction.uncertainty import (
        SCORES,
        Views,
        brief_reconstruction,
        gaussian_uncertainty,
        render_uncertainty,
    )
    from tacsplat.reconstruction.views import camera_tensors

    scene = Scene.load(scene_path)
    gaussians = brief_reconstruction(scene, TrainConfig(iterations=steps, seed=seed, device="cpu"))
    views = Views.of_frames(scene, scene.split("train"))
    scores = {name: gaussian_uncertainty(gaussians, views, name, seed=seed) for name in SCORES}
    maps = {name: [] for name in SCORES}
    errors = []
    tests = [f for f in scene.split("test") if scene.gt_depth(f) is not None]
    for frame in tests:
        viewmat, K = camera_tensors([frame])
        w, h = frame.intrinsics.width, frame.intrinsics.height
        for name in SCORES:
            u, alpha, depth = render_uncertainty(gaussians, scores[name], viewmat[0], K[0], w, h)
            maps[name].append(u.numpy())
        gt = scene.gt_depth(frame)
        drawn = (alpha.numpy() > 0.5) & (gt > 0)
        errors.append(np.where(drawn, np.abs(depth.numpy() - gt), np.nan))
    pixels = np.isfinite(np.stack(errors)) if errors else np.zeros((0,), bool)
    correlation = {}
    for name in SCORES:
        score_pixels = np.stack(maps[name])[pixels] if errors else np.zeros(0)
        error_pixels = np.stack(errors)[pixels] if errors else np.zeros(0)
        rho = spearmanr(score_pixels, error_pixels).statistic if len(error_pixels) > 2 else float("nan")
        correlation[name] = float(rho)
    shown = range(min(views_shown, len(tests)))
    plt = pyplot()
    fig, axes = plt.subplots(
        len(shown) or 1, 2 + len(SCORES), figsize=(3.0 * (2 + len(SCORES)), 3.0 * max(len(shown), 1)), squeeze=False
    )
    scale = np.nanpercentile(np.stack(errors), 95) if errors and pixels.any() else 1.0
    limits = {
        name: tuple(np.percentile(np.stack(maps[name])[pixels], [2, 98])) if errors and pixels.any() else (0, 1)
        for name in SCORES
    }  # each score on its own scale over the surface: its order is what counts
    for row, i in enumerate(shown):
        axes[row, 0].imshow(scene.load_image(tests[i]))
        axes[row, 0].set_title("test view" if row == 0 else "")
        for col, name in enumerate(SCORES, start=1):
            axes[row, col].imshow(
                np.where(pixels[i], maps[name][i], np.nan), cmap="magma", vmin=limits[name][0], vmax=limits[name][1]
            )
            if row == 0:
                axes[row, col].set_title(f"{name} (rho {correlation[name]:+.2f})")
        axes[row, -1].imshow(np.ma.masked_invalid(errors[i]), cmap="magma", vmin=0, vmax=scale)
        axes[row, -1].set_title("|depth - GT depth|" if row == 0 else "")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{scene.meta.object}: uncertainty of the reconstruction that chose the first grasp ({steps} steps)")
    fig.tight_layout()
    save_figure(fig, picture)
    return correlation


def summarise(rows: list[dict]) -> dict[tuple[str, int], dict]:
    """Per (strategy, grasps): the mean CD over every object and seed, and the spread over seeds of the mean over
    objects."""
    summary = {}
    for strategy in STRATEGIES:
        for k in sorted({r["grasps"] for r in rows}):
            group = [r for r in rows if r["strategy"] == strategy and r["grasps"] == k and math.isfinite(r["cd"])]
            if not group:
                continue
            per_seed = [np.mean([r["cd"] for r in group if r["seed"] == s]) for s in sorted({r["seed"] for r in group})]
            summary[strategy, k] = {
                "cd": float(np.mean([r["cd"] for r in group])),
                "spread": float(np.std(per_seed)),
                "runs": len(group),
            }
    return summary


def write_report(out: Path, rows: list[dict], correlations: dict[str, dict], config: NextTouchBenchConfig) -> None:
    """``results.csv``, ``cd_vs_grasps.png`` and ``report.md``."""
    from tacsplat.apps.report import md_table, pyplot, save_figure, write_csv

    write_csv(rows, out / "results.csv", RESULT_COLUMNS)
    summary = summarise(rows)
    budgets = sorted({r["grasps"] for r in rows})
    fig, ax = pyplot().subplots(figsize=(5.5, 4))
    for strategy, color in zip(STRATEGIES, ("tab:blue", "tab:red")):
        ks = [k for k in budgets if (strategy, k) in summary]
        mean = np.array([summary[strategy, k]["cd"] for k in ks])
        spread = np.array([summary[strategy, k]["spread"] for k in ks])
        ax.plot(ks, mean, "o-", color=color, label=strategy)
        ax.fill_between(ks, mean - spread, mean + spread, color=color, alpha=0.2)
    ax.set(xlabel="grasps (4 fingertips each)", ylabel="Chamfer distance [x GT radius]")
    ax.set_title("CD against grasps (mean; band: spread over seeds)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, out / "cd_vs_grasps.png")

    def mean_cd(subject: str, strategy: str, k: int) -> str:
        cds = [r["cd"] for r in rows if (r["object"], r["strategy"], r["grasps"]) == (subject, strategy, k)]
        return f"{np.mean(cds):.4f}" if cds else "–"

    subjects = list(dict.fromkeys(r["object"] for r in rows))
    lines = [
        "# Next-best touch against random grasps",
        "",
        f"{len(subjects)} object(s), seeds {', '.join(map(str, config.seeds))}; {config.views} train views, "
        f"{config.test_views} test views, {config.resolution} px; every reconstruction `{config.method}`, "
        f"{config.iterations} steps. Next-best: {config.candidates} candidate approaches per grasp, scored on a "
        f"{config.selection_steps}-step reconstruction of the scene so far with the {config.uncertainty} score.",
        "",
        "## Mean CD (x GT radius, lower is better) over seeds",
        "",
        *md_table(
            ["object", "strategy", *(f"{k} grasps" for k in budgets)],
            [[s, g, *(mean_cd(s, g, k) for k in budgets)] for s in subjects for g in STRATEGIES],
            "ll" + "r" * len(budgets),
        ),
        "",
        "## Over every object and seed",
        "",
    ]
    table = []
    for k in budgets:
        if ("random", k) in summary and ("next-best", k) in summary:
            (r, r_spread), (n, n_spread) = ((summary[s, k]["cd"], summary[s, k]["spread"]) for s in STRATEGIES)
            choosing = np.mean(
                [x["selection_seconds"] for x in rows if x["strategy"] == "next-best" and x["grasps"] == k]
            )
            table.append(
                [
                    k,
                    f"{r:.4f} ± {r_spread:.4f}",
                    f"{n:.4f} ± {n_spread:.4f}",
                    f"{100 * (n - r) / r:+.1f} %",
                    f"{choosing:.0f}",
                ]
            )
    scores = next(iter(correlations.values()), {})
    lines += [
        *md_table(
            ["grasps", "random CD", "next-best CD", "change", "next-best choosing (s, mean per capture)"],
            table,
            "rrrrr",
        ),
        "",
        "![CD against grasps](cd_vs_grasps.png)",
        "",
        "## Does the uncertainty predict the error?",
        "",
        "Spearman rank correlation, over the test pixels, of each score of the views-only reconstruction that "
        "chose the first grasp with its depth error against the ground truth (1: perfectly ordered).",
        "",
        *md_table(["object", *scores], [[s, *(f"{v:+.3f}" for v in rho.values())] for s, rho in correlations.items()]),
    ]
    lines += [""] + [f"![uncertainty {s}](uncertainty_{s}.png)" for s in correlations] + [""]
    (out / "report.md").write_text("\n".join(lines))


@dataclass
class NextTouchBenchCommand:
    """next-best against random grasps: CD against the number of grasps, both strategies

    Per object, seed and strategy one sim capture (5 views, the largest grasp budget); per budget k a copy with the
    first k grasps, reconstructed with --iterations steps whatever the strategy. Writes OUT/results.csv,
    OUT/report.md (tables, uncertainty against error), OUT/cd_vs_grasps.png. Resumable. --executor ray runs the
    captures, copies and runs as Ray tasks (an embedded local Ray, or the cluster at --ray-address; --out on storage
    every node sees)."""

    out: Path
    """output folder"""
    objects: str = "all"
    """'all' or comma-separated library objects"""
    mesh: str | None = None
    """any .obj/.ply/.stl mesh instead of the library objects"""
    seeds: str = "0,1,2"
    """comma-separated seeds (capture and training)"""
    grasps: str = "1,2,3,5,8"
    """comma-separated grasp budgets"""
    resolution: int = 128
    """image size in pixels"""
    test_views: int = 12
    """held-out test views"""
    iterations: int = 1500
    """steps of every final reconstruction"""
    method: Literal[tuple(METHODS)] = DEFAULT_METHOD
    """the method of every final reconstruction (default: what `tacsplat reconstruct` trains; `paper` for the
    paper's)"""
    candidates: int = 16
    """next-best: approaches scored per grasp"""
    selection_steps: int = 300
    """next-best: steps of the reconstruction that chooses each grasp"""
    uncertainty: str = "depth-variance"
    """next-best: the score (depth-variance or fisher)"""
    slide_m: float = 0.0
    """after each press every finger in contact slides its pad this many metres each way and back (0: press only)"""

    executors: Executors = field(default_factory=ExecutorOptions)


def register(cli) -> None:
    cli.typed("bench next-touch", NextTouchBenchCommand, _run)


def _run(args: NextTouchBenchCommand) -> int:
    executor = args.executors.run_jobs_args()
    given = {f.name: getattr(args, f.name) for f in fields(NextTouchBenchConfig) if hasattr(args, f.name)}
    given["objects"] = () if args.objects == "all" else tuple(o.strip() for o in args.objects.split(",") if o.strip())
    given.update({key: comma_separated_ints(getattr(args, key), f"--{key}") for key in ("seeds", "grasps")})
    config = NextTouchBenchConfig(**given)
    started = time.perf_counter()
    bench = NextTouchBench(args.out, config)
    bench.run(**executor)
    print((bench.out / "report.md").read_text())
    print(f"done in {(time.perf_counter() - started) / 60:.1f} min; report: {bench.out / 'report.md'}")
    return 0
