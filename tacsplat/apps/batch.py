"""Batch jobs (capture, reconstruct, evaluate) and `tacsplat batch JOBS.yaml --out DIR`.

Each job is a frozen dataclass: a pure function of its fields that writes one
folder and is skipped when that folder is complete (a capture's
``capture.json``, a run's ``metrics.json``, an evaluation's ``evaluated.json``
matching its settings and that metrics.json); :mod:`tacsplat.apps.executors`
runs a list of them in this process or on Ray. The benchmarks build their
suites from the same jobs.

The YAML file lists jobs; ``out``, ``scene`` and ``run`` are relative to
``--out`` (or absolute), ``mesh`` and ``gt_mesh`` to the YAML file's folder
(docs/batches.md has a smaller example, and each kind's keys)::

    jobs:
      - {kind: capture, out: scenes/teapot-s0, object: teapot, seed: 0, resolution: 128}
      - {kind: reconstruct, out: runs/teapot/paper-s0, scene: scenes/teapot-s0, method: paper, seed: 0}
      - {kind: reconstruct, out: runs/teapot/no-touch-s0, scene: scenes/teapot-s0, overrides: {use_touch: false}}
      - {kind: evaluate, run: runs/teapot/paper-s0}

A reconstruction trains ``method`` (default: what `tacsplat reconstruct` trains without options) with its
``overrides`` (TrainConfig fields, ``init.x`` / ``densify.x`` for theirs, dotted or nested) on top.
A reconstruction of a scene that a capture of the batch writes needs that
capture (listed before it), and an evaluation of a run needs its reconstruction.
An evaluation evaluates its run (its last checkpoint) with its own settings
(``gt_mesh``), rewriting the run's metrics.json, also of a run that the batch
trains or that has a metrics.json already; a run is evaluated by one job at most.
A job may also list the names of jobs it needs (``needs: [capture scenes/teapot-s0]``,
anywhere in the file): it runs after them, and not at all when one of them failed.
Writes ``DIR/results.csv`` (one row per run folder with a metrics.json, named after the last job of
the batch on that folder whose output is there: an evaluation rather than the reconstruction it
evaluated; its columns :data:`RESULT_COLUMNS`, then every other scalar any of those metrics.json holds, sorted;
rewritten as runs finish) and, when jobs fail, ``DIR/failures.csv``.
"""

from __future__ import annotations

import functools
import hashlib
import heapq
import json
import logging
import math
import shutil
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Annotated, Literal

import tyro

from tacsplat.apps.executors import ExecutorOptions, Executors, run_jobs
from tacsplat.errors import ConfigError, SceneFormatError, pydantic_problem
from tacsplat.reconstruction.methods import DEFAULT_METHOD

log = logging.getLogger(__name__)

CAPTURE_MARKER = "capture.json"
METRICS = "metrics.json"
EVALUATED = "evaluated.json"  # RUN/evaluated.json: an evaluate job's record (EvaluateJob.record)
RUN_COLUMNS = ("iterations", "cd", "cd_paper", "psnr", "ssim", "train_seconds", "num_gaussians")  # of metrics.json
# results.csv's first columns; every other scalar of the runs' metrics.json follows, sorted (result_columns)
RESULT_COLUMNS = ("job", "run", "scene", "method", "seed", *RUN_COLUMNS)
KINDS = ("capture", "reconstruct", "evaluate")


@dataclass(frozen=True, kw_only=True)
class BatchJob:
    """What every job has (the :class:`~tacsplat.apps.executors.Job` protocol); a batch file may set ``cpus``,
    ``name`` and ``needs`` (names of jobs of the file; those a job's paths imply are added)."""

    __pydantic_config__ = {"extra": "forbid"}  # in a batch file, an unknown key is an error

    cpus: float = 1.0  # CPUs it uses (Ray reserves them)
    name: str = ""  # default: "<kind> <out or run as written>"
    needs: tuple[str, ...] = ()

    def check(self) -> None:
        """A ConfigError naming the field at fault, before anything runs."""
        if not (self.cpus > 0 and math.isfinite(self.cpus)):  # (Ray and the worker threads take a count)
            raise ConfigError("cpus", f"must be a finite number > 0, got {self.cpus}")

    def gpus(self, cluster_has_gpus: bool) -> float:
        return 0

    def warm_up(self) -> None:
        """Import what the call will (the processes executor runs this ahead, in a worker that would idle)."""


@dataclass(frozen=True, kw_only=True)
class SceneCopyJob(BatchJob):
    """A reduced copy ``out`` of the capture ``base`` (``count`` of something kept), done once: marked by
    ``OUT.json`` beside it, holding what :meth:`make_copy` returned; a copy cut short before its marker is redone."""

    out: Path
    base: Path
    count: int

    @property
    def marker(self) -> Path:
        return self.out.with_name(self.out.name + ".json")

    def complete(self) -> bool:
        return self.marker.is_file()

    def make_copy(self) -> dict:
        """Write the copy into the (absent) ``out``; what the marker records."""
        raise NotImplementedError

    def __call__(self) -> dict:
        if self.complete():
            return json.loads(self.marker.read_text())
        if self.out.exists():  # a copy interrupted before its marker: ours to redo
            shutil.rmtree(self.out)
        summary = self.make_copy()
        self.marker.write_text(json.dumps(summary))
        return summary


def capture_copies_runs(capture: BatchJob, copies: list[SceneCopyJob], run) -> list[BatchJob]:
    """A bench's jobs of one capture: each copy's reconstruction ``run(copy)``, after the copy (needing it) while
    the run is still to do, and ``capture`` first (needed by the copies) while such a copy is still to make. A
    finished run needs neither its copy nor the capture (both may have been deleted since)."""
    jobs: list[BatchJob] = []
    for copy in copies:
        job = run(copy)
        jobs += [job] if job.complete() else [copy, replace(job, needs=(copy.name,))]
    if all(job.complete() for job in jobs if isinstance(job, SceneCopyJob)):
        return jobs
    return [capture] + [replace(job, needs=(capture.name,)) if isinstance(job, SceneCopyJob) else job for job in jobs]


def _renamed(exc: ConfigError, names: dict[str, str]) -> ConfigError:
    """``exc`` naming ``names[key]`` instead of its key (the same key when it is not in ``names``)."""
    return ConfigError(names.get(exc.key, exc.key), str(exc).removeprefix(f"{exc.key}: "))


def _refuse(out: Path, changes: list[str], made: str, make: str, folder: str) -> None:
    """A benchmark's refusal of the folder ``out`` that was ``made`` (captured, trained) with other settings
    (``changes``), if any: a ConfigError on ``--out`` saying to delete that ``folder`` to ``make`` it again, or to
    use those options."""
    if changes:
        raise ConfigError(
            "--out",
            f"{out} was {made} with other settings ({', '.join(changes)}): use the options it was {made} with or a "
            f"new --out, or delete that {folder} to {make} it again",
        )


def check_bench_jobs(jobs, fields: dict[str, str]) -> None:
    """A bench's ``jobs`` checked as a batch file's are (:meth:`BatchJob.check`: the rig's and the trainer's
    limits), before anything runs or is made; a ConfigError naming the bench config's field otherwise (``fields``: a
    job's field -> the config's, else the same name)."""
    for job in jobs:
        try:
            job.check()
        except ConfigError as exc:
            raise _renamed(exc, fields) from None


_RIG_FIELDS = {
    "sim.object": "object",
    "sim.mesh": "mesh",
    "sim.object_radius": "object_radius",
    "sim.resolution": "resolution",
    "sim.seed": "seed",
    "plan.grasps.seed": "seed",
    "plan.views.train": "views",
    "plan.views.test": "test_views",
    "plan.grasps.count": "grasps",
    "plan.touches.model": "touch_model",
    "sim.texture": "texture",
}  # the rig config's fields a capture job sets: its fields of the same name as sim_rig_config's arguments


@dataclass(frozen=True, kw_only=True)
class CaptureJob(BatchJob):
    """A seeded simulated capture of a library object (or of ``mesh``) into ``out``."""

    kind: Literal["capture"] = "capture"
    out: Path
    object: str = "teapot"
    mesh: str | None = None  # a mesh file instead of a library object (scaled to object_radius)
    object_radius: float = 0.08  # metres
    seed: int = 0
    views: int = 5  # train views
    test_views: int = 8  # held-out views with ground-truth depth
    grasps: int = 5  # grasps of 4 touches
    resolution: int = 128  # image width and height, pixels
    touch_model: Literal["gel", "paper"] = "gel"
    texture: Literal["none", "checker"] = "none"  # the object's surface (tacsplat.sim.objects.TEXTURES)

    def rig(self):
        """The rig config of the capture."""
        from tacsplat.acquisition.sim_capture import sim_rig_config

        return sim_rig_config(**{k: getattr(self, k) for k in dict.fromkeys(_RIG_FIELDS.values())})

    def check(self) -> None:
        super().check()
        try:
            self.rig()  # validated as a rig config
        except ConfigError as exc:  # its field named as in a batch file
            raise _renamed(exc, _RIG_FIELDS) from None

    def complete(self) -> bool:
        return (self.out / CAPTURE_MARKER).is_file()

    def changed_settings(self, more_grasps_ok: bool = False) -> list[str]:
        """What differs between the settings a finished capture in ``out`` recorded (scene.json) and this job's
        rig, as ``"name recorded -> now"`` (named as this job's field where one sets it); empty when ``out`` holds
        no finished capture. ``more_grasps_ok``: more grasps recorded than this job asks for is no change (a
        capture's first grasps do not depend on how many follow)."""
        from tacsplat.acquisition.capture_scene import (
            capture_settings,
            flatten_settings,
            recorded_settings,
            same_setting,
        )
        from tacsplat.datasets import Scene

        if not self.complete():
            return []
        try:
            recorded = recorded_settings(Scene.load(self.out, check_files=False))
        except SceneFormatError as exc:
            return [f"scene unreadable ({exc})"]
        now = flatten_settings(capture_settings(self.rig()))
        changes: dict[str, str] = {}  # (the object is recorded twice: by name, and as the twin's)
        for key, then in recorded.items():
            name = _RIG_FIELDS.get(key, key)
            if same_setting(then, now.get(key)) or (more_grasps_ok and name == "grasps" and then > now[key]):
                continue
            changes.setdefault(name, f"{name} {then!r} -> {now.get(key)!r}")
        return list(changes.values())

    def refuse_changed_settings(self, more_grasps_ok: bool = False) -> None:
        """A benchmark's check before it runs: a finished capture made with other settings than this job's is an
        error on ``--out`` (:meth:`changed_settings`), not a scene silently reused."""
        changes = self.changed_settings(more_grasps_ok)
        _refuse(self.out, changes, "captured", "capture", "scene folder and the runs trained on it")

    def warm_up(self) -> None:
        import tacsplat.acquisition.sim_capture  # noqa: F401

    def __call__(self) -> dict:
        """The capture, done once: a finished capture is marked by ``capture.json`` (its plan and timings); an
        interrupted one is resumed."""
        from tacsplat.acquisition.sim_capture import sim_capture

        if not self.complete():
            rig = self.rig()
            self.out.parent.mkdir(parents=True, exist_ok=True)
            timings = sim_capture(rig, self.out, resume=self.out.exists(), progress=False)
            (self.out / CAPTURE_MARKER).write_text(json.dumps({"plan": rig.plan.to_json(), **timings}, indent=2))
        return {"scene": str(self.out)}


@dataclass(frozen=True, kw_only=True)
class ReconstructJob(BatchJob):
    """A reconstruction of ``scene`` into the run folder ``out``: a preset, a method with overrides and a seed
    (continued from its checkpoint when one was interrupted)."""

    kind: Literal["reconstruct"] = "reconstruct"
    out: Path
    scene: Path
    preset: str = "default"  # reconstruction.config.PRESETS
    method: str = DEFAULT_METHOD  # reconstruction.methods.METHODS; by default what `tacsplat reconstruct` trains
    overrides: dict[str, bool | int | float | str | list | None] = field(default_factory=dict)  # on the method
    seed: int = 0
    iterations: int | None = None  # None: the preset's
    device: Literal["auto", "cpu", "cuda"] = "auto"
    export_mesh: bool = False  # then export the run's meshes with and without touches (reconstruction.meshing)

    def config(self):
        from tacsplat.reconstruction.config import preset_config, set_fields
        from tacsplat.reconstruction.methods import get_method

        config = preset_config(self.preset, self.iterations)
        set_fields(config, get_method(self.method, "method").overrides)
        set_fields(config, self.overrides, "overrides")
        config.seed, config.device = self.seed, self.device
        return config

    def check(self) -> None:
        super().check()
        if clash := [key for key in self.overrides if key in {f.name for f in fields(self)}]:
            raise ConfigError(
                f"overrides.{clash[0]}", f"a field of the job: set `{clash[0]}:` beside `overrides:`, not in them"
            )
        self.config().validate()

    def changed_settings(self) -> list[str]:
        """What differs between the config a run folder recorded (``out/config.json``, or a finished run's
        metrics.json) and the one this job trains now, as ``"name recorded -> now"`` (the device and the settings
        of mechanisms that both switch off aside: :meth:`TrainConfig.unused_fields`); one entry saying so for a
        record that cannot be read; and the scene, when ``scene`` holds other content than the one the run
        recorded (a scene moved elsewhere is the same; one not there is not compared). Empty for a folder with
        nothing to reuse or resume (no metrics.json, no checkpoint) or no settings recorded."""
        from tacsplat.reconstruction.config import TrainConfig, changed_settings, removed_losses
        from tacsplat.reconstruction.methods import method_of
        from tacsplat.reconstruction.run_dir import read_json

        checkpoint, path = self.out / "checkpoint.pt", self.out / "config.json"
        if not (self.complete() or checkpoint.is_file()):
            return []
        try:
            if path.is_file():
                settings = read_json(path)
            elif self.complete():  # a run trained elsewhere and evaluated here: its metrics.json has the settings
                path = self.out / METRICS
                if not (settings := read_json(path).get("settings")):
                    return []  # (none recorded: nothing to compare)
            else:
                return [f"{checkpoint.name} without {path.name}"]
            recorded = TrainConfig.from_json(settings, path)
        except ConfigError as exc:  # (read_json and from_json raise nothing else for a bad record)
            return [f"{path.name} unreadable ({exc})"]
        now = self.config()
        changes = [
            f"{key} {then!r} -> {value!r}" for key, then, value in changed_settings(recorded, now) if key != "device"
        ]
        # a loss since removed reads as today's config, but this job's training would not have it
        changes += [f"{key} {value!r} -> removed" for key, value in removed_losses(settings).items()]
        if changes and method_of(recorded) != method_of(now):
            changes.insert(0, f"method {method_of(recorded)} -> {method_of(now)}")
        if isinstance(scene := settings.get("scene"), dict) and self.scene.is_dir():
            changes += self._scene_change(scene)
        return changes

    def _scene_change(self, recorded: dict) -> list[str]:
        """``["scene: HOW"]`` when ``scene``'s content is not the one a run recorded (``recorded``: its
        :func:`~tacsplat.reconstruction.run_dir.scene_record`; :func:`~tacsplat.reconstruction.run_dir.scene_change`),
        else empty."""
        from tacsplat.datasets import Scene
        from tacsplat.reconstruction.run_dir import scene_change

        try:
            what = scene_change(recorded, Scene.load(self.scene))
        except SceneFormatError as exc:
            return [f"scene unreadable ({exc})"]
        return [] if what is None else [f"scene: {what}"]

    def refuse_changed_settings(self) -> None:
        """A benchmark's check before it runs: a finished or interrupted run trained with other settings than this
        job's is an error on ``--out`` (:meth:`changed_settings`), not a number silently reused or resumed."""
        _refuse(self.out, self.changed_settings(), "trained", "train", "run folder")

    def gpus(self, cluster_has_gpus: bool) -> float:
        """One GPU for a CUDA training (``auto`` trains on CUDA where the cluster has GPUs)."""
        return 1 if self.device == "cuda" or (self.device == "auto" and cluster_has_gpus) else 0

    def complete(self) -> bool:
        """The run's metrics.json is there and, with ``export_mesh``, both meshes ``export_meshes`` writes
        (reconstruction.run_dir.MESH_FILES): each is renamed into place only after its metrics went into
        metrics.json, so a mesh file means its metrics are recorded. A lone ``mesh.ply`` (``tacsplat export mesh``
        by hand) is not done: the untouched mesh's metrics are missing."""
        meshes = ("mesh-untouched.ply", "mesh.ply") if self.export_mesh else ()
        return (self.out / METRICS).is_file() and all((self.out / name).is_file() for name in meshes)

    def warm_up(self) -> None:
        """The trainer, and torch._dynamo, which torch.optim's first optimizer imports (a second). Not what a
        training imports later (trimesh, pyplot): the demo's warm-up would then outlast its capture, and the
        capture's worker would take the first training."""
        import torch._dynamo  # noqa: F401

        import tacsplat.reconstruction.trainer  # noqa: F401

    def __call__(self) -> dict:
        from tacsplat.reconstruction.trainer import reconstruct

        if self.complete():
            return json.loads((self.out / METRICS).read_text())
        if not (self.out / METRICS).is_file():
            resume = (self.out / "checkpoint.pt").is_file()
            reconstruct(self.scene, self.out, self.config(), resume=resume, overwrite=not resume, show_progress=False)
        if self.export_mesh:
            from tacsplat.reconstruction.meshing import export_meshes

            export_meshes(self.out)
        return json.loads((self.out / METRICS).read_text())


@dataclass(frozen=True, kw_only=True)
class EvaluateJob(BatchJob):
    """The evaluation of a run folder (its last checkpoint) with this job's settings, writing its metrics.json:
    a run trained elsewhere, or by the batch (then after its reconstruction, whose metrics.json it replaces).
    Done once: ``RUN/evaluated.json`` records the settings and a hash of the metrics.json written; another
    ground truth (or the same path with other content), or a metrics.json written since (the run trained
    again), evaluates it again."""

    kind: Literal["evaluate"] = "evaluate"
    run: Path
    gt_mesh: str | None = None  # a ground-truth mesh instead of the scene's gt/

    def check(self) -> None:
        super().check()
        if self.gt_mesh is not None and not Path(self.gt_mesh).is_file():
            raise ConfigError("gt_mesh", f"{self.gt_mesh} is not a file")

    def record(self) -> dict:
        """What ``evaluated.json`` holds once this job has evaluated its run: the ground truth it used (``gt_mesh``
        and a hash of its content; None: the scene's) and a hash of the metrics.json it wrote."""
        gt = None if self.gt_mesh is None else _sha256(Path(self.gt_mesh))
        return {"gt_mesh": self.gt_mesh, "gt_mesh_sha256": gt, "metrics_sha256": _sha256(self.run / METRICS)}

    def complete(self) -> bool:
        """The run's metrics.json is the one this job's evaluation wrote, with the settings it has now (a moved
        ground-truth mesh of the same content is the same)."""
        try:
            recorded = json.loads((self.run / EVALUATED).read_text())
            now = self.record()
        except (OSError, ValueError):  # (no record or no metrics.json: not evaluated; an unreadable record: again)
            return False
        return isinstance(recorded, dict) and all(recorded.get(k) == now[k] for k in now if k != "gt_mesh")

    def warm_up(self) -> None:
        import tacsplat.reconstruction.evaluation  # noqa: F401

    def __call__(self) -> dict:
        from tacsplat.files import atomic_write
        from tacsplat.reconstruction.evaluation import evaluate_run

        if self.complete():
            return json.loads((self.run / METRICS).read_text())
        metrics = evaluate_run(self.run, self.gt_mesh)
        atomic_write(self.run / EVALUATED, json.dumps(self.record(), indent=2).encode())
        return metrics


def _sha256(path: Path) -> str:
    """The SHA-256 of a file's content (an OSError when unreadable)."""
    with path.open("rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


@functools.cache
def _job_adapter():
    """pydantic's validator of one job of a batch file, picked by its ``kind`` (unknown keys refused)."""
    from typing import Union

    from pydantic import Field, TypeAdapter

    return TypeAdapter(Annotated[Union[CaptureJob, ReconstructJob, EvaluateJob], Field(discriminator="kind")])


def run_folder(job) -> Path | None:
    """The run folder whose metrics.json a job writes (None for a capture)."""
    return job.out if isinstance(job, ReconstructJob) else job.run if isinstance(job, EvaluateJob) else None


# ---------------------------------------------------------------------- the YAML file


def load_batch(path: str | Path, out: str | Path) -> list:
    """The jobs of a batch file, validated, with paths resolved and needs inferred, each after the jobs it needs
    (:func:`_in_needs_order`); one ConfigError naming the file, the job (``jobs[3]``) and its field otherwise."""
    import yaml

    path, out = Path(path), Path(out)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError("jobs", f"cannot read the batch file: {exc.strerror or exc}", path) from None
    except UnicodeDecodeError:
        raise ConfigError("jobs", "not a text file (YAML, UTF-8): is it the batch file?", path) from None
    except yaml.YAMLError as exc:
        raise ConfigError("jobs", f"not valid YAML: {exc}", path) from None
    if not isinstance(data, dict) or set(data) != {"jobs"}:
        raise ConfigError("jobs", "the file must hold one key, `jobs:`, a list of jobs", path)
    if not isinstance(data["jobs"], list) or not data["jobs"]:
        raise ConfigError("jobs", "expected a non-empty list of jobs", path)
    jobs: list = []
    made: dict[Path, object] = {}  # folder (resolved: x/../a is a) -> the job of the batch writing it
    holding: dict[Path, object] = {}  # each folder holding a job's out -> the first such job (nested outs)
    evaluated: dict[Path, object] = {}  # run folder (resolved) -> the evaluate job of the batch evaluating it
    names: dict[str, int] = {}
    out_folder = out.resolve()  # (where results.csv goes)
    for i, item in enumerate(data["jobs"]):
        job = _parse_job(i, item, path, out)
        needs = job.needs  # as the file lists them
        if isinstance(job, (ReconstructJob, EvaluateJob)):
            key, maker_kind = ("scene", CaptureJob) if isinstance(job, ReconstructJob) else ("run", ReconstructJob)
            source = getattr(job, key)
            if isinstance(made.get(source.resolve()), maker_kind):
                needs = (*needs, made[source.resolve()].name)
            elif not source.is_dir():
                raise ConfigError(
                    f"jobs[{i}].{key}",
                    f"{source} is not a folder, nor the out of a "
                    f"{maker_kind.__name__.removesuffix('Job').lower()} job listed before this one",
                    path,
                )
        if isinstance(job, EvaluateJob):  # (two would evaluate it again in turn at every rerun)
            if (folder := job.run.resolve()) in evaluated:
                raise ConfigError(f"jobs[{i}].run", f"{job.run} is also evaluated by {evaluated[folder].name}", path)
            evaluated[folder] = job
        else:
            folder = job.out.resolve()
            if out_folder.is_relative_to(folder):  # --out itself, or `..`: results.csv and the other jobs' folders
                what = "is --out itself" if folder == out_folder else f"holds --out ({out})"
                raise ConfigError(f"jobs[{i}].out", f"{job.out} {what}; give a folder in it", path)
            if folder in made:
                raise ConfigError(f"jobs[{i}].out", f"{job.out} is also the out of {made[folder].name}", path)
            # nested outs: one job would write into the other's folder (looked up by folder: a batch may hold
            # thousands of jobs)
            inside = next((made[parent] for parent in folder.parents if parent in made), None)
            if (other := holding.get(folder) if inside is None else inside) is not None:
                raise ConfigError(
                    f"jobs[{i}].out",
                    f"{job.out} {'is inside' if inside else 'holds'} {other.out}, the out of {other.name} "
                    f"(jobs[{names[other.name]}]): give each job a folder outside the others'",
                    path,
                )
            made[folder] = job
            for parent in folder.parents:
                holding.setdefault(parent, job)
        if job.name in names:
            raise ConfigError(
                f"jobs[{i}].name", f"two jobs are named {job.name!r}: jobs[{names[job.name]}] and this one", path
            )
        names[job.name] = i
        try:
            job.check()
        except ConfigError as exc:
            raise ConfigError(f"jobs[{i}] ({job.name})", str(exc), path) from None
        jobs.append(replace(job, needs=tuple(dict.fromkeys(needs))))
    return _in_needs_order(jobs, path)


def _in_needs_order(jobs: list, path: Path) -> list:
    """``jobs`` in the file's order, but each after the jobs it needs; one ConfigError naming the file and the job
    for a need that is no job's name, or naming the jobs of a cycle of needs."""
    from graphlib import CycleError, TopologicalSorter

    index = {job.name: i for i, job in enumerate(jobs)}
    for i, job in enumerate(jobs):
        if unknown := [n for n in job.needs if n not in index]:
            raise ConfigError(
                f"jobs[{i}].needs",
                f"{job.name!r} needs {unknown[0]!r}, which is no job of this file "
                "(a job's name is its `name:`, else its kind and its out, or run, as written, as in "
                f"{jobs[0].name!r})",
                path,
            )
    sorter = TopologicalSorter({job.name: job.needs for job in jobs})
    try:
        sorter.prepare()
    except CycleError as exc:
        cycle = exc.args[1][:0:-1]  # (graphlib lists each job before the jobs that need it, the first twice)
        first = min(range(len(cycle)), key=lambda k: index[cycle[k]])
        cycle = [f"{n!r} (jobs[{index[n]}])" for n in (*cycle[first:], *cycle[:first], cycle[first])]
        raise ConfigError(
            "jobs",
            f"the needs form a cycle, so none of its jobs can run: {cycle[0]} needs {', which needs '.join(cycle[1:])}",
            path,
        ) from None
    # next: the first job of the file whose needs are all in order (a heap of the ready jobs' indices, not a scan
    # of the file per job: a batch may hold thousands of jobs)
    order: list = []
    ready: list[int] = []
    while sorter.is_active():
        for name in sorter.get_ready():
            heapq.heappush(ready, index[name])
        order.append(jobs[heapq.heappop(ready)])
        sorter.done(order[-1].name)
    return order


def _parse_job(i: int, item, path: Path, out: Path):
    """One job of the file: validated by pydantic (strictly, as JSON), paths resolved, named."""
    if not isinstance(item, dict):
        raise ConfigError(f"jobs[{i}]", f"expected a mapping with a kind ({', '.join(KINDS)}), got {item!r}", path)
    if item.get("kind") == "capture":  # a capture's slide_m, before the slide was removed: refused, saying why
        from tacsplat.acquisition.config import REMOVED_SLIDE, refuse_removed

        refuse_removed(item, {"slide_m": (None, REMOVED_SLIDE)}, f"jobs[{i}].", path)
    if isinstance(overrides := item.get("overrides"), dict):  # `init: {x: 1}` as `init.x: 1`, as the config files
        from tacsplat.reconstruction.config import flat_settings

        item = {**item, "overrides": flat_settings(overrides)}
    from pydantic import ValidationError

    try:
        job = _job_adapter().validate_json(json.dumps(item, default=str), strict=True)
    except ValidationError as exc:
        raise _job_error(i, item, exc, path) from None
    # relative paths: out, scene and run in --out, meshes in the file's folder (an absolute path as it is)
    resolved = {k: Path(out, getattr(job, k)) for k in ("out", "scene", "run") if hasattr(job, k)}
    resolved |= {k: str(Path(path.parent, v)) for k in ("mesh", "gt_mesh") if (v := getattr(job, k, None)) is not None}
    label = item.get("run" if job.kind == "evaluate" else "out")
    return replace(job, **resolved, name=job.name or f"{job.kind} {label}")


def _job_error(i: int, item: dict, exc, path: Path) -> ConfigError:
    """pydantic's first error as one ConfigError naming ``jobs[i].field``."""
    error = exc.errors(include_url=False)[0]
    if error["type"] in ("union_tag_not_found", "union_tag_invalid"):
        return ConfigError(f"jobs[{i}].kind", f"expected one of {', '.join(KINDS)}, got {item.get('kind')!r}", path)

    def unknown(loc: tuple) -> str:  # the keys a job of this kind takes
        cls = {"capture": CaptureJob, "reconstruct": ReconstructJob, "evaluate": EvaluateJob}[item["kind"]]
        return f"a {item['kind']} job takes {', '.join(sorted(f.name for f in fields(cls) if f.name != 'kind'))}"

    error = {**error, "loc": error["loc"][1:]}  # loc[0] is the kind's tag
    return ConfigError(*pydantic_problem(error, "key", f"jobs[{i}].", unknown), path)


# ---------------------------------------------------------------------- results


def result_rows(jobs: list, out: Path) -> list[dict]:
    """One row per run folder with a metrics.json, in the batch's order (of the first job on it), named after the
    last job on it whose output is complete (an evaluation of a run the batch trains, once done: the metrics are
    its), else the first: :data:`RESULT_COLUMNS` and every other scalar (number, bool, string or null) of its
    metrics.json (not the dicts: ``settings``, ``mechanisms``)."""
    rows: dict[Path, dict] = {}
    for job in jobs:
        run = run_folder(job)
        if run is None or not (run / METRICS).is_file() or (run.resolve() in rows and not job.complete()):
            continue
        m = json.loads((run / METRICS).read_text())
        rows[run.resolve()] = (
            {"job": job.name, "run": _relative(run, out), "scene": _scene_name(run, m, out)}
            | {"method": m.get("method"), "seed": m.get("settings", {}).get("seed")}
            | {k: m.get(k) for k in RUN_COLUMNS}
            | {k: v for k, v in m.items() if k not in RESULT_COLUMNS and not isinstance(v, (dict, list))}
        )
    return list(rows.values())


def result_columns(rows: list[dict]) -> list[str]:
    """results.csv's columns: :data:`RESULT_COLUMNS` (in that order, for readers of the earlier table), then every
    other key of any row, sorted (an order that does not depend on which runs have finished)."""
    return [*RESULT_COLUMNS, *sorted({k for row in rows for k in row} - set(RESULT_COLUMNS))]


def _relative(path: Path, base: Path) -> str:
    return str(path.relative_to(base)) if path.is_relative_to(base) else str(path)


def _scene_name(run: Path, metrics: dict, out: Path) -> str:
    """The scene of a run's metrics as results.csv names it: relative to ``out`` when in it, else absolute. Its
    config.json records it absolute; metrics.json has it absolute from an evaluation but as the trainer was given
    it from a reconstruction (relative to the cwd of the batch that trained it), so the record comes first."""
    from tacsplat.reconstruction.run_dir import recorded_scene

    record = recorded_scene(run)
    scene = record["path"] if record else metrics.get("scene")
    return _relative(Path(scene).resolve(), out.resolve()) if scene else ""


def run_batch(jobs: list, out: str | Path, progress: bool = True, **executor) -> list[dict]:
    """Run a batch (:func:`~tacsplat.apps.executors.run_jobs`), writing ``out/results.csv`` as runs finish;
    returns its rows. A :class:`~tacsplat.apps.executors.BatchError` at the end when jobs failed."""
    from tacsplat.apps.report import number, write_csv

    out = Path(out)
    kept = {
        ReconstructJob: "a run trained with other settings (%s); it is kept, or resumed, as it was trained (delete "
        "the folder to train it anew)",
        CaptureJob: "a capture made with other settings (%s); it is kept as it was captured (delete the folder to "
        "capture it anew)",
    }
    for job in jobs:  # kept, not refused: a batch file says what each job is, and a folder may be reused on purpose
        if type(job) in kept and (changes := job.changed_settings()):
            log.warning("%s: %s holds " + kept[type(job)], job.name, job.out, ", ".join(changes))

    def on_done(job, summary: dict) -> str | None:
        if run_folder(job) is None:
            return None
        rows = result_rows(jobs, out)  # (every run's of the batch: a finished one skipped this time included)
        write_csv(rows, out / "results.csv", result_columns(rows))
        return (
            f"{job.name}: CD {number(summary.get('cd'), 4, 'nan')}  PSNR {number(summary.get('psnr'), 2, 'nan')}  "
            f"{summary.get('train_seconds') or 0:.0f} s"
        )

    outcome = run_jobs(jobs, out, on_done=on_done, desc="batch", progress=progress, **executor)
    rows = result_rows(jobs, out)
    write_csv(rows, out / "results.csv", result_columns(rows))
    outcome.raise_if_failed(out)
    return rows


# ---------------------------------------------------------------------- command line


@dataclass
class BatchCommand:
    """run a list of captures, reconstructions and evaluations, here or on a Ray cluster

    Runs the jobs of JOBS.yaml (kind: capture | reconstruct | evaluate; docs/batches.md has an example), skipping those
    whose output is complete; writes DIR/results.csv and, if jobs fail, DIR/failures.csv. Rerun the same command to
    retry what failed or never ran."""

    jobs: tyro.conf.Positional[Path]
    """the batch file (YAML: jobs: [...])"""
    out: Path
    """folder the jobs' relative paths are in (on a cluster: shared storage)"""
    executors: Executors = field(default_factory=ExecutorOptions)


def register(cli) -> None:
    cli.typed("batch", BatchCommand, _run)


def _run(args: BatchCommand) -> int:
    from tacsplat.datasets.outputs import claim_output_dir

    executor, out = args.executors.run_jobs_args(), args.out
    jobs = load_batch(args.jobs, out)
    started = time.perf_counter()
    with claim_output_dir(out, "--out"):
        rows = run_batch(jobs, out, **executor)
    print(
        f"{len(jobs)} jobs, {len(rows)} runs with metrics in {out / 'results.csv'}; "
        f"this invocation took {(time.perf_counter() - started) / 60:.1f} min"
    )
    return 0
