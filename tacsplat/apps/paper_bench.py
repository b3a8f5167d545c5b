"""`tacsplat bench paper`: the paper's glossy-object tables (Tables 1-3) on the twin's objects.

Per object and seed, one seeded simulated capture per setting:

- ``minimal``: 5 train views and 5 grasps (20 touches), as the paper's Table 2;
- ``full-views``: ``--full-views`` train views (at least 32, the Glossy Synthetic
  train split) and the same 5 grasps, as Table 1.

Both captures of an object use the same seed and test-view count, so their
held-out test views (an even Fibonacci spiral, independent of the train views)
are the same for every run of that object. Each setting is reconstructed with
the four methods of Table 3: ``3dgs`` (no touch, no smoothness), ``3dgs+s``,
``3dgs+t`` and ``paper``, and with what ``tacsplat reconstruct`` runs by
default (``default``, beyond the paper); ``--methods`` picks others, among them
the ablation rows of ``ablations.yaml`` (a method with settings changed).
Everything else is the trainer's defaults.

With ``--dataset DIR`` the objects are instead the scene directories in
``DIR``, imported from the paper's own datasets (``tacsplat import nero``,
``tacsplat import blender``; ``docs/datasets.md``): per setting a copy of each
keeps its test views and, as train views, all of them (``full-views``) or the
five the paper's code keeps (``minimal``: :func:`paper_views`), and gets
``--grasps`` simulated grasps on its ground truth (``simulate-touches``; the
paper's touches by default); the report prints the paper's Tables 1-3
(``paper_tables.yaml``) beside ours, in the dataset's units.

The job is resumable: a finished capture is marked by ``capture.json``, a run
with a ``metrics.json`` is skipped, a run with only a checkpoint is continued
(with the settings it started with). A finished or interrupted run trained with
other settings than the bench's now (a default changed since) is kept and named in
report.md; one trained with another value of an option (``--iterations``,
``--downscale``), and a finished capture made with other settings, are refused
before anything runs, and so is a non-empty ``--out`` that holds no bench
(:func:`refuse_foreign_out`). A row renamed since (:data:`RENAMED_ROWS`) keeps
reading its runs under the old name.
The captures and runs are batch jobs (:mod:`tacsplat.apps.batch`): run one
after another here, or as Ray tasks (:mod:`tacsplat.apps.executors`).
Output::

    REPORT/scenes/<object>/<setting>-s<seed>/      scene directories (+ capture.json)
    REPORT/runs/<object>/<setting>/<method>-s<seed>/   run directories of `tacsplat reconstruct`
    REPORT/results.csv  REPORT/report.md  REPORT/*.png
"""

from __future__ import annotations

import functools
import itertools
import json
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from tacsplat.apps import report
from tacsplat.apps.batch import CaptureJob, ReconstructJob, SceneCopyJob, check_bench_jobs
from tacsplat.apps.executors import ExecutorOptions, Executors, resolve_executor, run_jobs, side_by_side
from tacsplat.errors import ConfigError, UsageError
from tacsplat.options import comma_separated_ints, first_repeat, options_error
from tacsplat.reconstruction.methods import DEFAULT_METHOD, METHODS, PAPER_METHODS, get_method, mechanisms, method_label

log = logging.getLogger(__name__)

SETTINGS = ("minimal", "full-views")
MINIMAL_VIEWS = 5
GRASPS = 5  # 5 grasps x 4 fingertips = 20 touches (paper: 5 grasps)
QUICK_OBJECTS = ("teapot", "bell")
ABLATIONS = Path(__file__).with_name("ablations.yaml")  # the bench's rows beyond the methods
PAPER_TABLES = Path(__file__).with_name("paper_tables.yaml")  # the paper's own numbers
DATASETS = {"nero": "glossy-synthetic", "blender": "shiny-blender"}  # importer -> the paper's dataset


@functools.cache
def paper_tables() -> dict:
    """``{dataset: {setting: {metric: {method: {object: value}}}}}`` of :data:`PAPER_TABLES`."""
    import yaml

    return yaml.safe_load(PAPER_TABLES.read_text())


def paper_views(train: list, count: int) -> list:
    """The ``count`` train views the paper's official code keeps (``utils_data.filter_dataset``: every
    ``int(N / count)``-th of the N train views in the dataset's order, from the first); all for ``count`` 0 or at
    least N."""
    if count <= 0 or count >= len(train):
        return list(train)
    return list(train[:: len(train) // count][:count])


RENAMED_ROWS = {"default-touch": "default-no-touch"}  # a row's former name -> its name (ablations.yaml)
ROW_NOTES = {  # what report.md says of a row it holds
    "default-no-touch": "the default with `--no-use-touch`: no touch Gaussians and no tactile loss (L_T); beside "
    "the default it shows what touching did",
}
RUN_OPTIONS = {"iterations": "--iterations", "downscale": "--downscale"}  # a run's settings an option sets


@functools.cache
def ablation_rows() -> dict[str, tuple[str, dict]]:
    """``{row: (method, overrides)}`` of :data:`ABLATIONS`."""
    import yaml

    return {
        name: (row["method"], dict(row.get("overrides", {})))
        for name, row in yaml.safe_load(ABLATIONS.read_text()).items()
    }


def bench_row(name: str, option: str = "--methods") -> tuple[str, dict]:
    """``(method, overrides)`` of a row of the bench: a method (no overrides) or an ablation row; a ConfigError
    naming ``option`` otherwise (a former name, :data:`RENAMED_ROWS`, is the row's)."""
    name = RENAMED_ROWS.get(name, name)
    if name in METHODS:
        return name, {}
    if name not in ablation_rows():
        raise ConfigError(
            option,
            f"unknown method {name!r}; choose one of {', '.join(METHODS)} or a row of "
            f"{ABLATIONS.name} ({', '.join(ablation_rows())})",
        )
    return ablation_rows()[name]


def row_config(name: str, preset: str = "default", iterations: int | None = None, option: str = "--methods"):
    """The TrainConfig of bench row ``name`` (on the training preset, scaled to ``iterations``)."""
    from tacsplat.reconstruction.config import preset_config, set_fields

    method, overrides = bench_row(name, option)
    config = set_fields(preset_config(preset, iterations), get_method(method).overrides)
    return set_fields(config, overrides, ABLATIONS.name)


@dataclass
class PaperBenchConfig:
    """Size of the suite; the defaults run 6 objects x 2 settings x 5 methods in about 40 min on 2 free cores."""

    objects: tuple[str, ...] = ()  # empty: every library object
    settings: tuple[str, ...] = SETTINGS
    methods: tuple[str, ...] = (*PAPER_METHODS, DEFAULT_METHOD)  # Table 3's rows and what reconstruct runs
    seeds: tuple[int, ...] = (0,)
    resolution: int = 128  # image width and height, pixels
    iterations: int = 1500  # optimisation steps per run
    full_views: int = 32  # train views of the full-views setting (Glossy Synthetic's train split)
    test_views: int = 12  # held-out views with GT depth, shared by every run of an object
    grasps: int = GRASPS
    preset: str = "default"  # training preset (reconstruction.config.PRESETS): default or paper
    touch_model: str = "gel"  # gel (grasps with gel contact patches) or paper (the official code's sampling)
    texture: str = "none"  # the objects' surface: their one colour, or "checker" (tacsplat.sim.objects.TEXTURES)
    mesh: bool = False  # also export each run's meshes (with and without touches) and report the mesh metrics
    dataset: str | None = None  # a folder of imported scenes instead of the twin's objects (module docstring)
    downscale: int = 1  # with a dataset: its images trained and evaluated at 1/downscale of their size

    @classmethod
    def quick(cls) -> "PaperBenchConfig":
        """Two objects, minimal setting, fewer steps and pixels: about 3 minutes on 2 cores."""
        return cls(objects=QUICK_OBJECTS, settings=("minimal",), resolution=128, iterations=800, test_views=8)

    def validate(self) -> None:
        from tacsplat.reconstruction.config import PRESETS
        from tacsplat.sim.objects import OBJECT_NAMES, texture_problem

        if self.dataset is not None:
            self._validate_dataset()
        elif self.downscale != 1:  # (the twin's captures are rendered at --resolution: nothing to scale down)
            raise ConfigError("downscale", f"scales a dataset's images: give it with --dataset, got {self.downscale}")
        known = self.dataset_objects() if self.dataset else OBJECT_NAMES
        if unknown := [o for o in self.objects if o not in known and (self.dataset or not Path(o).is_file())]:
            where = f"the scenes in {self.dataset}: " if self.dataset else ""
            files = "" if self.dataset else " or give mesh files"
            raise ConfigError(
                "objects", f"unknown object(s) {', '.join(unknown)}; choose from {where}{', '.join(known)}{files}"
            )
        if (name := first_repeat(self.object_list())) is not None:  # (a mesh file is named by its stem)
            raise ConfigError("objects", f"two objects are named {name!r}")
        if unknown := [s for s in self.settings if s not in SETTINGS]:
            raise ConfigError("settings", f"unknown setting {unknown[0]!r}; choose from {', '.join(SETTINGS)}")
        for key in ("settings", "methods", "seeds"):  # (each names run folders)
            if (value := first_repeat(getattr(self, key))) is not None:
                raise ConfigError(key, f"{value!r} is given twice")
        for name in self.methods:
            bench_row(name, "methods")
        self.methods = tuple(RENAMED_ROWS.get(m, m) for m in self.methods)  # (a former name: the row's runs)
        if (value := first_repeat(self.methods)) is not None:
            raise ConfigError("methods", f"{value!r} is given twice (once by its former name)")
        if self.full_views < 32 and self.dataset is None:
            raise ConfigError(
                "full_views", f"the full-views setting needs at least 32 train views, got {self.full_views}"
            )
        for key in ("resolution", "iterations", "test_views"):
            if getattr(self, key) < 1:
                raise ConfigError(key, f"must be >= 1, got {getattr(self, key)}")
        if not self.seeds:
            raise ConfigError("seeds", "need at least one seed")
        if self.preset not in PRESETS:
            raise ConfigError("preset", f"unknown preset {self.preset!r}; choose from {', '.join(PRESETS)}")
        if self.touch_model not in ("gel", "paper"):
            raise ConfigError("touch_model", f"must be gel or paper, got {self.touch_model!r}")
        if problem := texture_problem(self.texture):
            raise ConfigError("texture", problem)

    def _validate_dataset(self) -> None:
        folder = Path(self.dataset)
        if not folder.is_dir():
            raise ConfigError("dataset", f"{folder} is not a folder")
        if not self.dataset_objects():
            raise ConfigError(
                "dataset",
                f"{folder} holds no scene directories: import each object into a folder of it (tacsplat import nero "
                "or import blender; docs/datasets.md)",
            )
        if isinstance(self.downscale, bool) or not isinstance(self.downscale, int) or self.downscale < 1:
            raise ConfigError("downscale", f"must be an integer >= 1, got {self.downscale!r}")

    def dataset_objects(self) -> list[str]:
        """The names of the scene directories in :attr:`dataset`, sorted."""
        scenes = Path(self.dataset).glob("*/transforms.json")  # (none in a folder that does not exist)
        return sorted(p.parent.name for p in scenes if p.with_name("scene.json").is_file())

    @property
    def scene_tag(self) -> str:
        """Suffix of scene folders that are not gel touches on untextured objects (so they never mix)."""
        return ("" if self.touch_model == "gel" else f"-{self.touch_model}-touches") + (
            "" if self.texture == "none" else f"-{self.texture}"
        )

    @property
    def tag(self) -> str:
        """Suffix of run folders that are not the default preset on the default scenes (so they never mix)."""
        return ("" if self.preset == "default" else f"-{self.preset}") + self.scene_tag

    def object_list(self) -> list[str]:
        """The objects' names: library objects, and the file name (without suffix) of each mesh file."""
        from tacsplat.sim.objects import OBJECT_NAMES

        if self.dataset is not None:
            return list(self.objects) or self.dataset_objects()
        return [Path(o).stem if Path(o).is_file() else o for o in self.objects] or list(OBJECT_NAMES)

    def mesh_of(self, name: str) -> str | None:
        """The mesh file of object ``name`` (None for a library object)."""
        return next((str(Path(o).resolve()) for o in self.objects if Path(o).is_file() and Path(o).stem == name), None)


@dataclass(frozen=True)
class Run:
    """One reconstruction of the suite."""

    object: str
    setting: str
    method: str
    seed: int
    scene: Path
    out: Path

    @property
    def done(self) -> bool:
        return (self.out / "metrics.json").is_file()


def step_work(method: str) -> int:
    """How many of the optional mechanisms (:func:`~tacsplat.reconstruction.methods.mechanisms`), each adding
    work to a training step, ``method`` switches on: :meth:`PaperBench.jobs` starts the methods with more of
    them first, so that on few cores the longest runs do not start last."""
    return sum(mechanisms(row_config(method)).values())


@dataclass
class PaperBench:
    """The suite in a report folder; :meth:`run` does whatever is not done yet."""

    out: Path
    config: PaperBenchConfig = field(default_factory=PaperBenchConfig)
    scenes: Path | None = None  # where its captures go (None: out/scenes; another bench's, to share them)
    first_views: dict = field(default_factory=dict, init=False, repr=False)  # render_first_test_view's renders

    def __post_init__(self):
        self.out = Path(self.out)
        self.config.validate()
        # every capture and run checked, so that a value no rig or training takes runs nothing
        jobs = self.capture_jobs() + [self.reconstruct_job(r) for r in self.runs()]
        check_bench_jobs(jobs, {"seed": "seeds", "views": "full_views"})

    def scene_dir(self, obj: str, setting: str, seed: int) -> Path:
        return (self.scenes or self.out / "scenes") / obj / f"{setting}-s{seed}{self.config.scene_tag}"

    def runs(self) -> list[Run]:
        """Every run, setting by setting (the minimal-views table fills first), then object, seed, method."""
        c = self.config
        return [  # (object, setting, method, seed)
            Run(o, s, m, seed, self.scene_dir(o, s, seed), self.run_dir(o, s, m, seed))
            for s, o, seed, m in itertools.product(c.settings, c.object_list(), c.seeds, c.methods)
        ]

    def run_dir(self, obj: str, setting: str, method: str, seed: int) -> Path:
        """The run folder of a row: named by the row, or by its former name (:data:`RENAMED_ROWS`) where only a
        folder of that name is there (a run of an earlier bench, reused as it is)."""
        folder = self.out / "runs" / obj / setting
        name = f"{method}-s{seed}{self.config.tag}"
        former = [folder / f"{old}-s{seed}{self.config.tag}" for old, new in RENAMED_ROWS.items() if new == method]
        return next((f for f in former if f.is_dir() and not (folder / name).exists()), folder / name)

    # ------------------------------------------------------------------ capture and training

    def capture_jobs(self) -> list[CaptureJob | DatasetSceneJob]:
        """The capture of each object, setting and seed of the suite (:meth:`capture_job`)."""
        return [self.capture_job(*key) for key in dict.fromkeys((r.object, r.setting, r.seed) for r in self.runs())]

    def capture_job(self, obj: str, setting: str, seed: int) -> CaptureJob | DatasetSceneJob:
        """The seeded sim capture of one object and setting (with a dataset: its scene of that setting)."""
        c = self.config
        scene = self.scene_dir(obj, setting, seed)
        if c.dataset is not None:
            return DatasetSceneJob(
                out=scene,
                base=Path(c.dataset).resolve() / obj,
                count=MINIMAL_VIEWS if setting == "minimal" else 0,
                grasps=c.grasps,
                seed=seed,
                touch_model=c.touch_model,
                name=f"prepare {os.path.relpath(scene, self.out)}",
            )
        return CaptureJob(
            out=scene,
            object=obj,
            mesh=c.mesh_of(obj),
            seed=seed,
            views=MINIMAL_VIEWS if setting == "minimal" else c.full_views,
            name=f"capture {os.path.relpath(scene, self.out)}",
            **{k: getattr(c, k) for k in ("test_views", "grasps", "resolution", "touch_model", "texture")},
        )

    def reconstruct_job(self, run: Run, needs: tuple[str, ...] = ()) -> ReconstructJob:
        """One reconstruction (continued from its checkpoint if one exists)."""
        method, overrides = bench_row(run.method)
        if self.config.downscale != 1:
            overrides = {**overrides, "downscale": self.config.downscale}
        return ReconstructJob(
            out=run.out,
            scene=run.scene,
            preset=self.config.preset,
            method=method,
            overrides=overrides,
            seed=run.seed,
            iterations=self.config.iterations,
            name=f"reconstruct {run.out.relative_to(self.out)}",
            needs=needs,
            export_mesh=self.config.mesh,
        )

    def jobs(self) -> list[tuple[Run | None, CaptureJob | ReconstructJob]]:
        """``(run, job)`` of every unfinished run, its capture first (``run`` None), in the order of :meth:`runs`
        except that a capture's runs start with the methods whose steps do more work (:func:`step_work`), so
        that the longest training is the first to start (on the processes executor, in the worker its warm-up
        made ready)."""
        runs = self.runs()
        group = {key: i for i, key in enumerate(dict.fromkeys((r.object, r.setting, r.seed) for r in runs))}
        runs.sort(key=lambda r: (group[r.object, r.setting, r.seed], -step_work(r.method)))  # (stable)
        jobs, captures = [], {}
        for run in runs:
            if self.reconstruct_job(run).complete():  # (with --mesh: its meshes exported too)
                continue
            key = (run.object, run.setting, run.seed)
            if key not in captures:
                captures[key] = self.capture_job(*key)
                jobs.append((None, captures[key]))
            jobs.append((run, self.reconstruct_job(run, needs=(captures[key].name,))))
        return jobs

    def run(self, progress: bool = True, **executor) -> list[dict]:
        """Capture and train everything not done yet (``executor``: :func:`~tacsplat.apps.executors.run_jobs`'s
        executor, ray_address and retries), writing the report as runs finish; returns the results rows. A
        BatchError at the end when jobs failed (listed in failures.csv)."""
        from tacsplat.datasets.outputs import claim_output_dir

        executor["executor"] = resolve_executor(executor.get("executor", "local"))
        how = side_by_side(executor["executor"], executor.get("workers"))
        wall_note = f" (jobs side by side as {how}: a run's train seconds include the time it shared the cores)"
        wall_note = wall_note if how else ""
        refuse_foreign_out(self.out)  # (before the claim writes its lock file into it)
        with claim_output_dir(self.out, "--out"):
            for capture in self.capture_jobs():
                if isinstance(capture, CaptureJob):  # (refused before anything runs)
                    capture.refuse_changed_settings()
            stale = self.stale_runs()
            self.refuse_changed_options(stale)
            return self._run(progress, wall_note, executor, stale)

    def refuse_changed_options(self, stale: list[tuple[Run, list[str]]]) -> None:
        """A finished or interrupted run trained with another value of an option (:data:`RUN_OPTIONS`: its step
        count, its downscale) is an error on ``--out``, not numbers shown under the new value (a run whose other
        settings differ, a default changed since, is kept and named in report.md). ``stale``: :meth:`stale_runs`."""
        refused = [(run, o) for run, changes in stale if (o := [c for c in changes if c.split()[0] in RUN_OPTIONS])]
        if not refused:
            return
        (run, options), count = refused[0], len(refused)
        others = f" and {count - 1} other run(s)" if count > 1 else ""
        then = ", ".join(f"{RUN_OPTIONS[c.split()[0]]} {c.split()[1]}" for c in options)
        raise ConfigError(
            "--out",
            f"{run.out}{others} were trained with other settings ({', '.join(options)}): rerun with {then}, or "
            "choose a new --out, or delete those run folders to train them again",
        )

    def _run(self, progress: bool, wall_note: str, executor: dict, stale: list) -> list[dict]:
        """:meth:`run` in the claimed folder (``stale``: :meth:`stale_runs` as it starts)."""
        runs = self.runs()
        unfinished = sum(not r.done for r in runs)
        if unfinished < len(runs):
            log.info("%d of %d runs already finished in %s: skipped", len(runs) - unfinished, len(runs), self.out)
        if stale_note := _stale_note(stale, self.out):
            log.warning("%s", stale_note)
        started = time.perf_counter()
        jobs = self.jobs()
        run_of = {job.name: run for run, job in jobs}

        def write_report(rows: list[dict], figures: bool = True) -> None:  # results.csv, report.md and the plots
            seconds = time.perf_counter() - started
            write_paper_report(
                self.out, rows, runs, self.config, seconds, figures, wall_note, self.first_views, stale_note
            )

        def on_done(job, metrics: dict) -> str | None:
            run = run_of[job.name]
            if run is None:
                return None
            # partial tables after every run; the pictures (re-rendered from every checkpoint, seconds) at the end
            write_report(self.results(), figures=False)
            self.prepare_pictures(run)
            return (
                f"{run.object:8s} {run.setting:10s} {run.method:7s} seed {run.seed}: "
                f"CD {report.number(metrics.get('cd'), 4, 'nan')}  "
                f"PSNR {report.number(metrics.get('psnr'), 2, 'nan')}  "
                f"SSIM {report.number(metrics.get('ssim'), 3, 'nan')}  {metrics.get('train_seconds', 0):.0f} s"
            )

        outcome = run_jobs(
            [job for _, job in jobs], self.out, on_done=on_done, desc="bench paper", progress=progress, **executor
        )
        rows = self.results()
        stale_note = _stale_note(self.stale_runs(), self.out)  # the final report's: the runs as they ended
        write_report(rows)
        outcome.raise_if_failed(self.out)
        return rows

    def stale_runs(self) -> list[tuple[Run, list[str]]]:
        """Finished runs, and interrupted ones (continued with the settings they started with), whose
        ``config.json`` differs from the config this bench trains their method with now, each with what differs
        (:meth:`ReconstructJob.changed_settings`)."""
        stale = [(run, self.reconstruct_job(run).changed_settings()) for run in self.runs()]
        return [(run, changes) for run, changes in stale if changes]

    # ------------------------------------------------------------------ report

    def results(self) -> list[dict]:
        """One row per finished run (runs without metrics.json are left out)."""
        rows = []
        for run in filter(lambda r: r.done, self.runs()):
            m = json.loads((run.out / "metrics.json").read_text())
            rows.append({"object": run.object, "setting": run.setting, "method": run.method, "seed": run.seed})
            rows[-1] |= {k: _number(m.get(k)) for k in report.NUMBER_COLUMNS}
            if self.config.dataset:
                rows[-1]["cd_paper_units"] = _in_dataset_units(m, run.scene)
        return rows

    def prepare_pictures(self, run: Run) -> None:
        """What the final report's pictures need from ``run``, which has just finished, made while other runs
        still train: pyplot imported, and the run's first test view rendered (kept in ``first_views``; a
        finished run's checkpoint no longer changes). Only the latest scene's views are kept (one render grid's
        worth of images in memory; the report renders the others). In the demo's runs this takes 0.8-0.9 s off
        the report that follows the last run. A failure here is left to that report."""
        if run.seed != self.config.seeds[0]:  # (the render grid shows the first seed)
            return
        try:
            report.pyplot()
            if run.scene not in self.first_views:  # (a scene's ground truth is kept with its first view)
                self.first_views.clear()
            render_first_test_view([run], self.first_views)
        except Exception:  # noqa: BLE001 - the final report renders it again and reports what fails
            log.debug("preparing the pictures of %s failed", run.out, exc_info=True)


def _number(value) -> float:
    return float("nan") if value is None else float(value)


def _in_dataset_units(metrics: dict, scene: Path) -> float:
    """A run's ``cd_paper`` (squared, in units of the ground-truth radius) in the units of the dataset its scene was
    imported from (``scale``: metres per dataset unit), as the paper reports it."""
    return _number(metrics.get("cd_paper")) * (_number(metrics.get("gt_radius")) / _dataset_scale(scene)) ** 2


@functools.cache
def _dataset_scale(scene: Path) -> float:
    """Metres per dataset unit of an imported scene (read once: the report is rewritten after every run)."""
    from tacsplat.datasets import Scene

    return Scene.load(scene, check_files=False).meta.extra.get("scale", 1.0)


@dataclass(frozen=True, kw_only=True)
class DatasetSceneJob(SceneCopyJob):
    """One setting's scene of the imported scene ``base``: its test views, the train views the paper keeps
    (:func:`paper_views` of ``count``; 0: all), and ``grasps`` simulated grasps on its ground truth
    (``touch_model``, seeded); a scene that holds touches already keeps them instead. Its marker records the
    dataset's train views kept and the touches."""

    kind: Literal["dataset-scene"] = "dataset-scene"
    grasps: int = GRASPS
    seed: int = 0
    touch_model: Literal["gel", "paper"] = "paper"

    def make_copy(self) -> dict:
        import shutil

        from tacsplat.acquisition.touch_simulation import simulate_touches
        from tacsplat.datasets import Scene, copy_scene

        scene = Scene.load(self.base)
        train = paper_views(scene.split("train"), self.count)
        if scene.touches:
            copy_scene(scene, self.out, frames=train + scene.split("test"))
        else:
            views = self.out.with_name(self.out.name + ".views")
            shutil.rmtree(views, ignore_errors=True)  # (a copy cut short)
            copy_scene(scene, views, frames=train + scene.split("test"))
            simulate_touches(None, views, self.grasps, self.out, seed=self.seed, touch_model=self.touch_model)
            shutil.rmtree(views)
        return {"train_views": [f.file_path for f in train], "touches": len(Scene.load(self.out).touches)}


def _cd_wins(rows: list[dict], setting: str, method: str, baseline: str) -> tuple[int, int, float, float] | None:
    """On how many objects ``method``'s mean CD is below ``baseline``'s, of how many, and their averages (NaN
    unless every object has both)."""
    objects, methods, values = report.metric_table(rows, "cd", setting)
    if method not in methods or baseline not in methods:
        return None
    ours, theirs = values[methods.index(method)], values[methods.index(baseline)]
    both = np.isfinite(ours[:-1]) & np.isfinite(theirs[:-1])
    return int((ours[:-1][both] < theirs[:-1][both]).sum()), int(both.sum()), float(ours[-1]), float(theirs[-1])


def full_vs_vanilla(rows: list[dict], setting: str) -> str:
    """One sentence: on how many objects the full method's CD is below vanilla 3DGS's, and the average ratio."""
    if (wins := _cd_wins(rows, setting, "paper", "3dgs")) is None:
        return ""
    won, n, full, vanilla = wins
    paper = "0.0026 vs 0.0111, 4.3x" if setting == "minimal" else "0.0034 vs 0.0075, 2.2x"
    average = f"average CD {full:.4f} vs {vanilla:.4f} (ratio {vanilla / full:.2f}x; paper: {paper})"
    if not np.isfinite([full, vanilla]).all():
        average = f"no average yet, a run is missing (paper: {paper})"
    return f"Full method vs vanilla 3DGS ({setting}): lower CD on {won} of {n} objects; {average}."


def default_vs_full(rows: list[dict], setting: str) -> str:
    """One sentence: how `tacsplat reconstruct`'s default method compares with the paper's full method."""
    if (wins := _cd_wins(rows, setting, DEFAULT_METHOD, "paper")) is None:
        return ""
    won, n, ours, full = wins
    average = f"average CD {ours:.4f} vs {full:.4f} ({100 * (ours / full - 1):+.0f}%)"
    if not np.isfinite([ours, full]).all():
        average = "no average yet, a run is missing"
    return (
        f"Default `{DEFAULT_METHOD}` ({method_label(DEFAULT_METHOD)}) vs the paper's full method ({setting}): "
        f"lower CD on {won} of {n} objects; {average}."
    )


def coverage_sentence(rows: list[dict], setting: str) -> str:
    """One sentence: how much of the test views' surface no training camera sees, and how each method's CD
    there compares with its CD on the seen surface ("" without the split, i.e. without a ground-truth mesh)."""
    objects, methods, unseen = report.metric_table(rows, "unseen_fraction", setting)
    seen_cd, unseen_cd = (report.metric_table(rows, metric, setting)[2] for metric in ("cd_seen", "cd_unseen"))
    fractions = np.fmax.reduce(unseen, axis=0) if len(methods) else np.array([np.nan])  # the same for every method
    fractions[-1] = np.mean(fractions[:-1])  # (NaN when an object has no run that measured it)
    if not np.isfinite(fractions[-1]):
        return ""
    per_object = ", ".join(f"{o} {100 * f:.0f}%" for o, f in zip(objects, fractions[:-1]) if np.isfinite(f))
    ratios = "; ".join(
        f"{report.row_label(v)} {unseen_cd[i, -1]:.4f} vs {seen_cd[i, -1]:.4f}"
        for i, v in enumerate(methods)
        if np.isfinite(unseen_cd[i, -1]) and np.isfinite(seen_cd[i, -1])
    )
    return (
        f"Coverage ({setting}): {100 * fractions[-1]:.0f}% of the test views' surface is seen by no training "
        f"camera on average ({per_object}); only priors and touches place it. CD there vs on the seen "
        f"surface: {ratios}."
    )


def dataset_of(config: PaperBenchConfig, obj: str) -> str | None:
    """Which of the paper's datasets (a key of :data:`PAPER_TABLES`) the scene ``obj`` of ``config.dataset`` was
    imported from: by its importer, and for ``blender`` only with Shiny Blender's ground truth; None otherwise."""
    from tacsplat.datasets import Scene

    extra = Scene.load(Path(config.dataset) / obj, check_files=False).meta.extra
    importer = extra.get("importer")
    if importer == "blender" and "ground_truth" not in extra:
        return None  # NeRF synthetic: no table of the paper's
    return DATASETS.get(importer)


def paper_tables_section(rows: list[dict], config: PaperBenchConfig, setting: str) -> str:
    """Ours beside the paper's Tables 1-3 for the objects of ``setting`` imported from its datasets: CD as the
    paper's code measures it (``cd_paper_units``: in the dataset's units), PSNR and SSIM, the paper's numbers for
    objects of the same name ("" when no table applies)."""
    selected = [r for r in rows if r["setting"] == setting]
    kinds = {obj: dataset_of(config, obj) for obj in dict.fromkeys(r["object"] for r in selected)}
    labels = {  # metric: (heading, our column, our decimals, the paper's decimals)
        "cd": ("CD (the paper's, in the dataset's units)", "cd_paper_units", 5, 4),
        "psnr": ("PSNR", "psnr", 2, 2),
        "ssim": ("SSIM", "ssim", 3, 3),
    }
    lines = []
    for kind in sorted({k for k in kinds.values() if k is not None}):
        table = paper_tables()[kind].get(setting)
        if table is None:
            continue
        ours = [r for r in selected if kinds[r["object"]] == kind]
        lines += [
            f"## Against the paper: {kind}, {setting}",
            "",
            "Ours (mean over seeds) beside the paper's own numbers (its Tables 1-3) for objects of the same name; "
            "the paper's Avg. is over all of its objects.",
            "",
        ]
        for metric, measures in table.items():
            heading, key, decimals, theirs = labels[metric]
            objects, methods, values = report.metric_table(ours, key, setting)
            table = [
                [f"{method} (ours)", *(f"{v:.{decimals}f}" for v in values[i])] for i, method in enumerate(methods)
            ]
            for method, numbers in measures.items():
                cells = [numbers.get(o.lower()) for o in objects] + [numbers.get("Avg.")]
                table.append([f"{method} (paper)", *("–" if v is None else f"{v:.{theirs}f}" for v in cells)])
            lines += [f"{heading}:", "", *report.md_table(["", *objects, "Avg."], table), ""]
    return "\n".join(lines)


def where_we_stand(rows: list[dict], config: PaperBenchConfig) -> str:
    """The minimal-views section comparing with the paper: cd_paper of 3DGS and full beside the paper's own
    numbers (objects of the same name; averages over different objects), the full/3DGS gain in both metrics, and
    the departures from the paper still in force."""
    from tacsplat.reconstruction.config import paper_departures

    objects, methods, cd_paper = report.metric_table(rows, "cd_paper", "minimal")
    _, _, cd = report.metric_table(rows, "cd", "minimal")
    if "paper" not in methods or "3dgs" not in methods:
        return ""
    full, vanilla = methods.index("paper"), methods.index("3dgs")
    columns = objects + ["Avg."]
    ours = (("3DGS (ours)", vanilla), ("full (ours)", full))
    cells = [[label, *(f"{v:.5f}" for v in cd_paper[index])] for label, index in ours]
    terms = {key: report.metric_table(rows, f"cd_paper_{key}", "minimal")[2] for key in ("accuracy", "completeness")}
    for key, what in (("accuracy", "predicted -> GT"), ("completeness", "GT -> predicted")):
        for label, index in (("3DGS", vanilla), ("full", full)):
            cells.append([f"{label}, {key} ({what})", *(f"{v:.5f}" for v in terms[key][index])])
    table = paper_tables()["glossy-synthetic"]["minimal"]["cd"]  # the paper's Table 2
    for label, key in (("3DGS (paper)", "3dgs"), ("full (paper)", "paper")):
        cells.append([label, *(f"{table[key][c]:.4f}" if c in table[key] else "–" for c in columns)])
    lines = [
        "## Where we stand against the paper (minimal views)",
        "",
        "CD as the paper's official code measures it (`cd_paper`: squared nearest-neighbour distances, mean each "
        "way, summed; median depth of the test views; in units of the ground-truth radius). The paper's numbers are "
        "its Table 2 (Glossy Synthetic, 5 views); only the teapot and the bell share a name with our objects, and "
        "its average is over its own eight objects.",
        "",
        *report.md_table(["", *columns], cells),
    ]
    paper_ratio = table["3dgs"]["Avg."] / table["paper"]["Avg."]

    def gain(values: np.ndarray) -> str:  # 3DGS's average over full's ("–" until both have every object)
        ratio = values[vanilla, -1] / values[full, -1]
        return f"{ratio:.2f}x" if np.isfinite(ratio) else "–"

    lines += [
        "",
        f"Gain of full over 3DGS on average: {gain(cd)} in our CD, "
        f"{gain(cd_paper)} in the paper's CD (the paper: {paper_ratio:.1f}x), "
        f"{gain(terms['accuracy'])} in its accuracy term. The "
        "completeness term compares with the whole ground-truth surface, including the underside that no test "
        "camera sees, so it rewards a reconstruction that bulges there as much as one that is right where it "
        "is seen.",
        "",
        "Departures from the paper in force for these runs:",
        "",
    ]
    full_config = row_config("paper", config.preset, config.iterations)
    lines += [f"- {line}" for line in paper_departures(full_config, config.touch_model, config.resolution)]
    return "\n".join(lines) + "\n"


def render_first_test_view(
    runs: list[Run], rendered: dict | None = None
) -> tuple[dict, np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``({method: (rgb, depth, normal)}, gt_rgb, gt_depth, gt_normal, gt_seen)`` of the first test view of one
    scene, rendered from each run's last checkpoint (the evaluation's renders, whose depth colours are scaled per
    run, are not reused); normals in the camera frame, the ground truth's from its depth map as the evaluation
    takes them; ``gt_seen`` [H, W] bool: which ground-truth pixels the first rendered run's training cameras see
    (None without a ground-truth mesh). ``rendered``: what earlier calls rendered (run folder -> its view, scene
    folder -> its ground truth), used and added to."""
    from tacsplat.datasets import Scene
    from tacsplat.reconstruction.run_dir import load_run, render_backend

    rendered = {} if rendered is None else rendered
    scene = Scene.load(runs[0].scene)
    frame = scene.split("test")[0]
    gt_rgb = scene.load_image(frame)
    for run in runs:
        if run.out in rendered:
            continue
        loaded = load_run(run.out)
        rendered[run.out] = _render_view(loaded, render_backend(loaded.config, run.out), frame, gt_rgb)
        if run.scene not in rendered:
            rendered[run.scene] = _first_view_truth(scene, frame, gt_rgb, loaded.config.train_views)
    return {run.method: rendered[run.out] for run in runs}, gt_rgb, *rendered[runs[0].scene]


def _render_view(loaded, backend: str, frame, gt_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(rgb, depth, normal)`` of a loaded run's Gaussians, with their appearance (its light), in
    ``frame`` over the backdrop of its image, rendered by ``backend``."""
    import torch

    from tacsplat.reconstruction.evaluation import render_frame
    from tacsplat.reconstruction.views import background_image

    background = torch.from_numpy(background_image(gt_rgb, loaded.config.background))
    view = render_frame(
        loaded.gaussians, frame, background, backend, with_depth=True, with_normals=True, look=loaded.look
    )
    return view.rgb, view.depth, view.normal


def _first_view_truth(
    scene, frame, gt_rgb: np.ndarray, train_views: int | None
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``(gt_depth, gt_normal, gt_seen)`` of ``frame`` (zeros, None, None without ground-truth depth)."""

    from tacsplat.reconstruction.evaluation import ground_truth_normals, load_ground_truth, seen_pixels
    from tacsplat.reconstruction.views import training_frames

    gt_depth = scene.gt_depth(frame)
    if gt_depth is None:
        return np.zeros(gt_rgb.shape[:2], np.float32), None, None
    gt_normal = ground_truth_normals(scene, frame, gt_depth)
    ground_truth = load_ground_truth(scene, [frame], train_frames=training_frames(scene, train_views))
    seen = getattr(ground_truth, "seen", None)  # (None without a ground truth)
    return gt_depth, gt_normal, None if seen is None else seen_pixels(gt_depth, seen[frame.id])


BENCH_LAYOUT = ("runs", "scenes")  # the folders a bench (and the demo) makes in its --out


def refuse_foreign_out(out: Path) -> None:
    """A non-empty ``out`` that holds no earlier bench (none of :data:`BENCH_LAYOUT`'s folders, or a results.csv
    that a bench did not write) is an error on ``--out``: its files are not overwritten."""
    from tacsplat.datasets.writer import has_content

    out = Path(out)
    if not out.is_dir() or not has_content(out):
        return
    bench = any((out / name).is_dir() for name in BENCH_LAYOUT)
    results = out / "results.csv"
    if bench and results.is_file():
        with results.open(errors="replace") as fh:
            bench = fh.readline().strip().split(",")[:3] == list(report.RESULT_COLUMNS[:3])
    if not bench:
        raise ConfigError(
            "--out",
            f"{out} holds other files and no bench (no {'/ or '.join(BENCH_LAYOUT)}/ of an earlier bench paper or "
            "demo); choose an empty or new folder",
        )


def _stale_note(stale: list[tuple[Run, list[str]]], out: Path) -> str:
    """What report.md and the log say about :meth:`PaperBench.stale_runs` ("" when none): the runs grouped by
    method and what differs, each group with its folders (relative to ``out``)."""
    if not stale:
        return ""
    groups: dict[tuple[str, str], list[str]] = {}  # (method, what differs) -> its run folders
    for run, changes in stale:
        groups.setdefault((run.method, ", ".join(changes)), []).append(str(run.out.relative_to(out)))
    return (
        f"{len(stale)} run(s) were trained with other settings than this bench trains their method with now (a "
        "default or an option changed since; an interrupted run is continued with the settings it started with); "
        "their numbers stand in the tables as they were measured; delete their folders to measure them again: "
        + "; ".join(
            f"{method} ({changes}), {len(folders)} run(s): {', '.join(folders)}"
            for (method, changes), folders in groups.items()
        )
    )


def write_paper_report(
    out: Path,
    rows: list[dict],
    runs: list[Run],
    config: PaperBenchConfig,
    wall_seconds: float | None = None,
    figures: bool = True,
    wall_note: str = "",
    first_views: dict | None = None,
    stale_note: str = "",
) -> None:
    """Write ``results.csv``, ``report.md`` and (``figures``) CD bar charts, error-vs-time curves and render
    grids into ``out``; without figures, report.md holds the tables only. ``wall_note`` follows the wall time
    (how the jobs ran); ``first_views``: :func:`render_first_test_view`'s renders so far; ``stale_note``: which
    finished runs were trained with other settings (:meth:`PaperBench.stale_runs`)."""
    from tacsplat.reconstruction.run_dir import read_progress

    out = Path(out)
    report.write_csv(rows, out / "results.csv", report.RESULT_COLUMNS)
    settings = [s for s in SETTINGS if any(r["setting"] == s for r in rows)]
    if config.dataset is None:
        what, size, test = "the twin's glossy objects", f"{config.resolution}x{config.resolution} px", config.test_views
        full = f"{config.full_views}"
    else:
        what, size, test, full = config.dataset, f"images at 1/{config.downscale}", "the dataset's", "all its"
    lines = [
        f"# Tactile-informed 3DGS on {what}",
        "",
        f"{len(rows)} runs: {size}, {config.iterations} steps, "
        f"{test} held-out test views per object, {config.grasps} grasps of 4 touches, "
        + "".join(f"{s} = {MINIMAL_VIEWS if s == 'minimal' else full} train views, " for s in config.settings)
        + f"seeds {', '.join(map(str, config.seeds))} (tables: mean over seeds), preset {config.preset}, "
        f"{config.touch_model} touches"
        + ("" if config.texture == "none" else f", {config.texture} texture on every object")
        + ". "
        "CD is in units of the ground-truth bounding-sphere radius; best per column in bold.",
        "",
    ]
    if wall_seconds is not None:
        lines += [
            f"Wall time of the last invocation: {wall_seconds / 60:.1f} min{wall_note}; "
            f"{len(rows)} of {len(runs)} runs finished.",
            "",
        ]
    for row, note in ROW_NOTES.items():
        if any(r["method"] == row for r in rows):
            lines += [f"`{row}` ({report.row_label(row)}): {note}.", ""]
    if stale_note:
        lines += [f"**Note:** {stale_note}.", ""]
    for setting in settings:
        lines += [f"## {setting}", ""]
        for metric in report.METRICS:
            measured = any(np.isfinite(r.get(metric, np.nan)) for r in rows if r["setting"] == setting)
            if measured or not metric.startswith("mesh"):  # (the mesh tables of `--mesh` only)
                lines += [report.markdown_table(rows, metric, setting), ""]
        for sentence in (full_vs_vanilla, default_vs_full, coverage_sentence):
            lines += [sentence(rows, setting), ""]
        if config.dataset is not None:
            lines += [paper_tables_section(rows, config, setting), ""]
        elif setting == "minimal":
            lines += [where_we_stand(rows, config), ""]
        if not figures:
            continue
        png = report.plot_cd_bars(rows, setting, out / f"cd_{setting}.png")
        lines += [f"![CD per object, {setting}]({png.name})", ""]
        shown = [r for r in runs if r.setting == setting and r.seed == config.seeds[0] and r.done]  # (first seed)
        curves: dict[str, dict] = {}
        for run in shown:
            if (run.out / "progress.csv").is_file():
                curves.setdefault(run.object, {})[run.method] = read_progress(run.out / "progress.csv")
        if curves:
            title = f"held-out error vs run time ({setting})"
            png = report.plot_error_vs_time(curves, out / f"error_vs_time_{setting}.png", title)
            lines += [f"![error vs run time, {setting}]({png.name})", ""]
        drawable = [r for r in shown if (r.out / "checkpoint.pt").is_file()]  # (what a view is rendered from)
        for obj in dict.fromkeys(r.object for r in drawable):
            views = render_first_test_view([r for r in drawable if r.object == obj], first_views)
            title, path = f"{obj}, {setting}: first test view", out / f"renders_{obj}_{setting}.png"
            png = report.render_grid(*views[:3], path, title, *views[3:])  # (panels, gt_rgb, gt_depth, ...)
            lines += [f"![renders {obj} {setting}]({png.name})", ""]
        if left_out := [str(r.out.relative_to(out)) for r in shown if r not in drawable]:
            lines += [f"Not in the render grid (no checkpoint.pt to render): {', '.join(left_out)}.", ""]
    (out / "report.md").write_text("\n".join(lines))


# ---------------------------------------------------------------------- command line


@dataclass
class PaperBenchCommand:
    """the paper's tables on the twin's glossy objects: 3DGS, +S, +T, full; minimal and full views

    Per object: a seeded sim capture per setting (minimal: 5 views + 5 grasps; full-views: >= 32 views + 5
    grasps), the four methods and reconstruct's default, then REPORT/results.csv, REPORT/report.md and plots.
    With --dataset DIR, the objects are the scenes imported into DIR from the paper's datasets (import nero, import
    blender; docs/datasets.md): minimal = the 5 train views the paper's code keeps, full-views = all, 5 grasps
    simulated on the ground truth, and the paper's Tables 1-3 beside ours.
    Resumable: rerun the same command after an interruption. --executor ray runs the captures and runs as Ray tasks
    (an embedded local Ray, or the cluster at --ray-address; --out on storage every node sees)."""

    out: Path
    """report folder (captures, runs, results.csv, report.md, PNGs)"""
    objects: str = "all"
    """'all' or comma-separated library objects, mesh files or (with --dataset) scene names (--quick: teapot,bell)"""
    dataset: Path | None = None
    """a folder of scenes imported from the paper's datasets, one per object (instead of the twin's objects)"""
    downscale: int = 1
    """with --dataset: train and evaluate at 1/N of the images' size"""
    mesh: bool = False
    """also export each run's mesh, with and without its touches fused (tacsplat export mesh), and report F-scores
    and mesh CD"""
    quick: bool = False
    """two objects, minimal setting, 128 px, 800 steps (about 3 minutes)"""
    resolution: Annotated[int | None, tyro.conf.arg(metavar="INT", help_behavior_hint="(default: 128)")] = None
    """image size in pixels"""
    iterations: Annotated[
        int | None, tyro.conf.arg(metavar="INT", help_behavior_hint="(default: 1500; --quick: 800)")
    ] = None
    """steps per run"""
    full_views: Annotated[int | None, tyro.conf.arg(metavar="INT", help_behavior_hint="(default: 32)")] = None
    """train views of the full-views setting"""
    preset: Literal["default", "paper"] = "default"
    """training preset: default, or paper (the official schedule scaled to --iterations)"""
    touch_model: Annotated[
        Literal["gel", "paper"] | None,
        tyro.conf.arg(metavar="{gel,paper}", help_behavior_hint="(default: gel; with --dataset: paper)"),
    ] = None
    """touches: gel (grasps with gel contact patches) or paper (the official code's sampling)"""
    texture: str = "none"
    """the objects' surface: none (their one colour) or checker (textured: a checker of their colour and a
    contrasting grey); textured scenes and runs get their own folders"""
    test_views: Annotated[
        int | None,
        tyro.conf.arg(metavar="INT", help_behavior_hint="(default: 12; --quick: 8)"),
    ] = None
    """held-out test views"""
    settings: Annotated[
        str | None, tyro.conf.arg(metavar="STR", help_behavior_hint="(default: minimal,full-views; --quick: minimal)")
    ] = None
    """comma-separated settings: minimal, full-views"""
    seeds: Annotated[str | None, tyro.conf.arg(metavar="STR", help_behavior_hint="(default: 0)")] = None
    """comma-separated capture and training seeds"""
    methods: Annotated[
        str | None,
        tyro.conf.arg(
            metavar="STR",
            help="comma-separated methods, or rows of ablations.yaml (a method with settings changed: "
            + ", ".join(ablation_rows())
            + ")",
            help_behavior_hint="(default: the paper's four methods and reconstruct's default)",
        ),
    ] = None

    executors: Executors = field(default_factory=ExecutorOptions)

    def config(self) -> PaperBenchConfig:
        """The :class:`PaperBenchConfig` of these options."""
        config = PaperBenchConfig.quick() if self.quick else PaperBenchConfig()
        for key in ("objects", "settings", "methods"):
            text = getattr(self, key)
            if text is not None and (key, text) != ("objects", "all"):  # (all: every object, or --quick's)
                values = tuple(v.strip() for v in text.split(",") if v.strip())
                if not values:  # ('' would otherwise mean the default: every object, a whole suite)
                    raise UsageError(f"--{key}", f"names nothing ({text!r}); give at least one, or leave it out")
                setattr(config, key, values)
        for key in ("resolution", "iterations", "full_views", "test_views", "preset", "texture", "downscale", "mesh"):
            if getattr(self, key) is not None:  # (None: the config's default)
                setattr(config, key, getattr(self, key))
        if self.seeds is not None:
            config.seeds = comma_separated_ints(self.seeds, "--seeds")
        config.touch_model = self.touch_model or ("gel" if self.dataset is None else "paper")
        config.dataset = None if self.dataset is None else str(self.dataset)
        config.validate()
        return config


def continue_hint(command: str, out: Path) -> str:
    """What an interrupted bench (``command``: bench paper, demo) says as it ends: running it again continues."""
    return (
        f"{command}: to continue, run the same command again: only the unfinished jobs run (what finished in "
        f"{out} is kept)"
    )


def register(cli) -> None:
    cli.typed("bench paper", PaperBenchCommand, _run)


def _run(args: PaperBenchCommand) -> int:
    executor = args.executors.run_jobs_args()
    try:
        bench = PaperBench(args.out, args.config())
    except ConfigError as exc:  # an option's value, refused before anything is made
        raise options_error(exc) from None
    started = time.perf_counter()
    try:
        rows = bench.run(**executor)
    except KeyboardInterrupt:
        print(continue_hint("bench paper", bench.out), file=sys.stderr)
        raise
    print((bench.out / "report.md").read_text())
    print(f"{len(rows)} runs in {bench.out}; this invocation took {(time.perf_counter() - started) / 60:.1f} min")
    print(f"report: {bench.out / 'report.md'}")
    return 0
