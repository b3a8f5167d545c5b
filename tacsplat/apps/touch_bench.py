"""`tacsplat bench touches`: Chamfer distance against the number of touches (the paper's Fig. 6).

How the number of touches is controlled: per seed, one simulated capture of
the object with 5 train views and ``ceil(1.5 max_touches / 4)`` grasps (4
fingertips each; the margin because some fingers touch nothing). For every count ``n`` a copy of that scene is written through
:class:`~tacsplat.datasets.SceneWriter` with every frame (and its ground truth)
and only the first ``n`` touches *in contact* in capture order, i.e. whole
grasps first: 4 touches = the first grasp, 8 = the first two, ... so the
touches grow the way a robot would add grasps, and every count of one seed
sees the same views. Fingers that touched nothing are dropped (they add no
points). When the capture has fewer than ``n`` touches in contact (a grasp was
skipped or a finger missed), the copy holds all of them and the CSV records
the count actually used. ``n = 0`` is the same method without touch (no G_t, no
L_T; the smoothness term is unmasked). Every run is ``method``, by default the
paper's full method (``full``; the trainer's defaults otherwise).

Output: ``OUT/touches.csv`` (one row per run), ``OUT/summary.csv`` (mean and
standard deviation per requested count), ``OUT/cd_vs_touches.png``; the scenes in
``OUT/scenes/<object>-s<seed>[-t<count>]``, the runs in ``OUT/runs/<object>/t<count>-s<seed>``.
Resumable: runs with a metrics.json are skipped (and need no scene: a finished sweep
whose scenes were deleted makes none); unlike `bench paper`, which notes and keeps them, a finished or
interrupted run trained with other settings, or on another scene, is refused before anything runs, and so is a
capture made with other settings (one with more grasps than the largest count needs serves it). The
captures, copies and runs are batch jobs, run here or as Ray tasks
(``--executor ray``, :mod:`tacsplat.apps.executors`).
"""

from __future__ import annotations

import itertools
import json
import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from tacsplat.apps.batch import (
    BatchJob,
    CaptureJob,
    ReconstructJob,
    SceneCopyJob,
    capture_copies_runs,
    check_bench_jobs,
)
from tacsplat.apps.executors import ExecutorOptions, Executors, run_jobs
from tacsplat.errors import ConfigError
from tacsplat.options import comma_separated_ints, first_repeat, options_error
from tacsplat.reconstruction.methods import METHODS, get_method

log = logging.getLogger(__name__)

FINGERS_PER_GRASP = 4
GRASP_MARGIN = 1.5  # a grasp often has a finger that touches nothing (16 grasps gave 49 of 64 in a test)


@dataclass
class TouchBenchConfig:
    """Defaults: 6 counts x 3 seeds of a 128 px teapot, about 6 minutes on 2 cores."""

    object: str = "teapot"
    touch_counts: tuple[int, ...] = (0, 4, 8, 16, 32, 64)
    seeds: tuple[int, ...] = (0, 1, 2)
    views: int = 5  # train views (the paper's minimal-views setting)
    test_views: int = 8
    resolution: int = 128
    iterations: int = 800
    method: str = "paper"  # the method of every run (reconstruction.methods.METHODS); the paper's for its Fig. 6

    @property
    def grasps(self) -> int:
        """Grasps captured per seed: half again as many as the largest count needs (some fingers miss)."""
        return math.ceil(GRASP_MARGIN * max(self.touch_counts) / FINGERS_PER_GRASP)

    def validate(self) -> None:
        from tacsplat.sim.objects import OBJECT_NAMES

        if self.object not in OBJECT_NAMES:
            raise ConfigError("object", f"unknown object {self.object!r}; choose from {', '.join(OBJECT_NAMES)}")
        if not self.touch_counts or any(n < 0 for n in self.touch_counts):
            raise ConfigError("touch_counts", f"need non-negative counts, got {self.touch_counts}")
        if not self.seeds:
            raise ConfigError("seeds", "need at least one seed")
        for key in ("touch_counts", "seeds"):  # (each names run folders)
            if (value := first_repeat(getattr(self, key))) is not None:
                raise ConfigError(key, f"{value!r} is given twice")
        for key in ("views", "test_views", "resolution", "iterations"):
            if getattr(self, key) < 1:
                raise ConfigError(key, f"must be >= 1, got {getattr(self, key)}")
        get_method(self.method)


def subsample_touches(scene_path: str | Path, out: str | Path, num_touches: int) -> int:
    """Copy a scene to ``out`` keeping every frame and its ground truth but only the first ``num_touches``
    touches in contact; returns the number kept. ``out`` must not exist."""
    from tacsplat.datasets import Scene, copy_scene

    scene = Scene.load(scene_path)
    kept = [t for t in scene.touches if t.in_contact][:num_touches]
    extra = {**scene.meta.extra, "touch_subsample": {"from": str(scene.path), "touches": len(kept)}}
    copy_scene(scene, out, touches=kept, meta=replace(scene.meta, extra=extra))
    return len(kept)


@dataclass(frozen=True, kw_only=True)
class SubsampleJob(SceneCopyJob):
    """A copy of the capture ``base`` with its first ``count`` touches in contact; its marker holds the requested
    and kept counts."""

    kind: Literal["subsample"] = "subsample"

    def make_copy(self) -> dict:
        return {"requested": self.count, "touches": subsample_touches(self.base, self.out, self.count)}


class TouchBench:
    """The sweep in a folder; :meth:`run` does whatever is not done yet."""

    def __init__(self, out: str | Path, config: TouchBenchConfig | None = None):
        self.out = Path(out)
        self.config = config or TouchBenchConfig()
        self.config.validate()
        jobs = [self.capture_job(seed) for seed in self.config.seeds]
        check_bench_jobs(jobs + [job for job in self.jobs() if isinstance(job, ReconstructJob)], {"seed": "seeds"})

    def capture_job(self, seed: int) -> CaptureJob:
        """The capture of one seed, with enough grasps for the largest count."""
        c, base = self.config, self.out / "scenes" / f"{self.config.object}-s{seed}"
        keys = ("object", "views", "test_views", "grasps", "resolution")
        return CaptureJob(out=base, seed=seed, name=f"capture {base.name}", **{k: getattr(c, k) for k in keys})

    def copy_job(self, seed: int, count: int) -> SubsampleJob:
        """The copy of a seed's capture with ``count`` touches."""
        base = self.capture_job(seed).out
        name = f"{base.name}-t{count}"
        return SubsampleJob(out=base.with_name(name), base=base, count=count, name=f"subsample {name}")

    def jobs(self) -> list[BatchJob]:
        """Per seed its capture (if a copy of it is still to make), then per count the copy with that many
        touches (if its run is still to do) and its reconstruction (``method``), in the order of the sweep."""
        jobs: list[BatchJob] = []
        for seed in self.config.seeds:
            copies = [self.copy_job(seed, n) for n in self.config.touch_counts]
            jobs += capture_copies_runs(self.capture_job(seed), copies, lambda copy: self.reconstruct_job(seed, copy))
        return jobs

    def reconstruct_job(self, seed: int, copy: SubsampleJob) -> ReconstructJob:
        c = self.config
        out = self.out / "runs" / c.object / f"t{copy.count:03d}-s{seed}"
        name = f"reconstruct {out.relative_to(self.out / 'runs')}"
        return ReconstructJob(out=out, scene=copy.out, method=c.method, seed=seed, iterations=c.iterations, name=name)

    def results(self) -> list[dict]:
        """One row per finished run, in the order of the sweep; the touches each had from its copy's marker, or
        for a copy deleted since from the last touches.csv (None where neither says)."""
        from tacsplat.apps.report import read_csv

        c = self.config
        reported = {  # (seed, requested) -> touches, of this object's rows in the last report
            (row["seed"], row["requested_touches"]): row["touches"]
            for row in read_csv(self.out / "touches.csv")
            if row.get("object") == c.object
        }
        rows = []
        for seed, count in itertools.product(c.seeds, c.touch_counts):
            copy = self.copy_job(seed, count)
            job = self.reconstruct_job(seed, copy)
            if not job.complete():
                continue
            metrics = json.loads((job.out / "metrics.json").read_text())
            if copy.complete():
                touches = json.loads(copy.marker.read_text())["touches"]
            else:
                touches = int(known) if (known := reported.get((str(seed), str(count)))) else None
            row = dict(object=c.object, seed=seed, requested_touches=count, touches=touches)
            rows.append(row | {k: metrics.get(k) for k in TOUCH_COLUMNS[len(row) :]})  # (and the run's metrics)
        return rows

    def run(self, progress: bool = True, **executor) -> list[dict]:
        """Capture, copy and train whatever is not done yet (``executor``: the executor, ray_address and retries of
        :func:`~tacsplat.apps.executors.run_jobs`), then write the report; returns the rows. A BatchError at the
        end when jobs failed (listed in failures.csv)."""
        from tacsplat.datasets.outputs import claim_output_dir

        def on_done(job, metrics: dict) -> str | None:
            if not isinstance(job, ReconstructJob):
                return None
            kept = json.loads(job.scene.with_name(job.scene.name + ".json").read_text())["touches"]
            return f"seed {job.seed}: {kept:3d} touches -> CD {metrics['cd']:.4f}  PSNR {metrics['psnr']:.2f}"

        with claim_output_dir(self.out, "--out"):
            # a folder whose captures or runs were made with other settings is refused before anything runs
            for seed in self.config.seeds:  # (a capture's first grasps do not depend on how many follow)
                self.capture_job(seed).refuse_changed_settings(more_grasps_ok=True)
            jobs = self.jobs()
            for job in jobs:
                if isinstance(job, ReconstructJob):
                    job.refuse_changed_settings()
            outcome = run_jobs(jobs, self.out, on_done=on_done, desc="bench touches", progress=progress, **executor)
            rows = self.results()
            write_touch_report(self.out, rows, self.config.method)
        outcome.raise_if_failed(self.out)
        return rows


TOUCH_COLUMNS = (
    "object",
    "seed",
    "requested_touches",
    "touches",
    "cd",
    "psnr",
    "ssim",
    "train_seconds",
    "num_gaussians",
)


def summarise(rows: list[dict]) -> list[dict]:
    """Mean and standard deviation over seeds (ddof 1, as :func:`~tacsplat.apps.report.seed_spread`: NaN for one
    run) of CD and PSNR per requested touch count, and the mean of the touches the runs had."""
    from tacsplat.apps.report import finite_mean

    summary = []
    for count in sorted({r["requested_touches"] for r in rows}):
        group = [r for r in rows if r["requested_touches"] == count]
        line = dict(requested_touches=count, mean_touches=finite_mean([r["touches"] for r in group]), runs=len(group))
        for key in ("cd", "psnr"):
            values = np.array([r[key] for r in group if r[key] is not None], dtype=float)
            line[f"{key}_mean"] = float(values.mean()) if len(values) else float("nan")
            line[f"{key}_std"] = float(values.std(ddof=1)) if len(values) > 1 else float("nan")
        summary.append(line)
    return summary


def write_touch_report(out: str | Path, rows: list[dict], method: str) -> dict[str, Path]:
    """``touches.csv``, ``summary.csv`` and ``cd_vs_touches.png`` (mean +- std over seeds, each run a dot; the
    title names the ``method`` the runs trained)."""
    from tacsplat.apps.report import pyplot, save_figure, write_csv

    out = Path(out)
    paths = {"runs": out / "touches.csv", "summary": out / "summary.csv", "plot": out / "cd_vs_touches.png"}
    write_csv(rows, paths["runs"], TOUCH_COLUMNS)
    summary = summarise(rows)
    write_csv(summary, paths["summary"], list(summary[0]) if summary else ["requested_touches"])
    fig, ax = pyplot().subplots(figsize=(5.5, 4))
    x = np.array([s["requested_touches"] for s in summary], dtype=float)
    mean = np.array([s["cd_mean"] for s in summary])
    std = np.array([s["cd_std"] for s in summary])
    ax.plot(x, mean, "o-", color="tab:red", label="mean over seeds")
    ax.fill_between(x, mean - std, mean + std, color="tab:red", alpha=0.2, label="± 1 std")
    ax.scatter(
        [r["requested_touches"] for r in rows], [r["cd"] for r in rows], s=10, color="k", alpha=0.5, label="runs"
    )
    ax.set_xscale("symlog", linthresh=4)
    ax.set_xticks(x, [str(int(v)) for v in x])
    ax.set(xlabel="number of touches", ylabel="Chamfer distance [x GT radius]")
    ax.set_title(f"CD against number of touches ({method})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, paths["plot"])
    return paths


@dataclass
class TouchBenchCommand:
    """Chamfer distance against the number of touches (paper Fig. 6), several seeds

    Per seed one sim capture with enough grasps for the largest count; per count a copy of it with the first N
    touches in contact (whole grasps first), reconstructed with --method. Writes OUT/touches.csv, OUT/summary.csv,
    OUT/cd_vs_touches.png. Resumable."""

    out: Path
    """output folder"""
    object: str = "teapot"
    """library object"""
    touches: str = "0,4,8,16,32,64"
    """comma-separated touch counts"""
    seeds: str = "0,1,2"
    """comma-separated seeds (capture and training)"""
    resolution: int = 128
    """image size in pixels"""
    iterations: int = 800
    """steps per run"""
    method: Annotated[
        Literal[tuple(METHODS)], tyro.conf.arg(help_behavior_hint="(default: paper, as in the paper's Fig. 6)")
    ] = TouchBenchConfig.method
    """the method of every run"""

    executors: Executors = field(default_factory=ExecutorOptions)


def register(cli) -> None:
    cli.typed("bench touches", TouchBenchCommand, _run)


def _run(args: TouchBenchCommand) -> int:
    executor = args.executors.run_jobs_args()
    config = TouchBenchConfig(
        object=args.object,
        touch_counts=comma_separated_ints(args.touches, "--touches"),
        seeds=comma_separated_ints(args.seeds, "--seeds"),
        resolution=args.resolution,
        iterations=args.iterations,
        method=args.method,
    )
    started = time.perf_counter()
    try:
        bench = TouchBench(args.out, config)
    except ConfigError as exc:  # an option's value (the grasps follow from --touches)
        raise options_error(exc, {"touch_counts": "--touches", "grasps": "--touches"}) from None
    rows = bench.run(**executor)
    print("touches  runs  CD mean     CD std      PSNR mean")
    for s in summarise(rows):
        print(
            f"{s['requested_touches']:7d}  {s['runs']:4d}  {s['cd_mean']:.5f}  {s['cd_std']:.5f}  {s['psnr_mean']:.2f}"
        )
    print(
        f"{len(rows)} runs in {(time.perf_counter() - started) / 60:.1f} min; plot: {bench.out / 'cd_vs_touches.png'}"
    )
    return 0
