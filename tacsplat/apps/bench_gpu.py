"""`tacsplat bench gpu` (what `make gpu-check` runs on a CUDA machine): the trainer on CUDA at the paper's scale,
measured in minutes.

Its options and what it does: :class:`BenchGpu`.
"""

from __future__ import annotations

import hashlib
import json
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from tacsplat.errors import ConfigError, UsageError
from tacsplat.options import comma_separated_ints

PARITY_FILE = "cpu.json"  # in a --prepare folder, beside its scene/


@dataclass
class BenchGpu:
    """train on CUDA at the paper's scale: seconds per 1k steps, peak GPU memory, CPU/CUDA parity

    One twin capture (default: the teapot, 100 train views at 800x800 px, 24 test views, 5 grasps). The
    default and the paper's method each train the first '--steps' steps of the paper's 30k-step schedule
    (reconstruction/paper_schedule.yaml) after a short warm-up run that builds gsplat's kernels: seconds per
    1000 steps, peak GPU memory, and 30k steps at that rate (a lower bound: the Gaussians multiply until
    densification stops at step 15k). With '--parity DIR', written beforehand on a CPU machine by '--prepare
    DIR', DIR's small scene trains on this device with the seeds and steps of DIR's CPU runs: CD and PSNR beside
    the CPU's mean and spread. Only 'gpu.json' and 'gpu.md' go to '--out'; the capture and the runs go to
    '--work'. Without CUDA it says so in one line and measures nothing."""

    out: Path = Path("bench-output/gpu")
    """folder of gpu.json and gpu.md"""
    work: Annotated[Path | None, tyro.conf.arg(metavar="PATH", help_behavior_hint="(default: --out/work)")] = None
    """folder of the capture and the runs"""
    object: str = "teapot"
    """library object to capture"""
    resolution: int = 800
    """image size of the capture (px)"""
    views: int = 100
    """train views of the capture"""
    test_views: int = 24
    """held-out test views of the capture"""
    grasps: int = 5
    """grasps of 4 touches"""
    steps: int = 1000
    """steps of the paper's schedule each method trains"""
    methods: str = "default,paper"
    """comma-separated methods (or bench paper rows)"""
    parity: Annotated[Path | None, tyro.conf.arg(metavar="DIR")] = None
    """a folder written by --prepare: its scene on CUDA"""
    prepare: Annotated[Path | None, tyro.conf.arg(metavar="DIR")] = None
    """on this machine's CPU, write DIR: a 128 px twin scene and its runs (--parity-steps, --parity-seeds)"""
    parity_steps: int = 1500
    """steps of each parity run"""
    parity_seeds: str = "0,1,2"
    """comma-separated seeds of the parity runs"""
    parity_resolution: int = 128
    """image size of the parity scene (px)"""
    device: Literal["cuda", "cpu"] = "cuda"
    """cpu: the whole device path on this machine's CPU (what the tests run)"""


def register(cli) -> None:
    cli.typed("bench gpu", BenchGpu, _run)


def _run(args: BenchGpu) -> int:
    import torch

    from tacsplat.apps.paper_bench import bench_row

    seeds = comma_separated_ints(args.parity_seeds, "--parity-seeds")
    methods = [name.strip() for name in args.methods.split(",") if name.strip()]
    for option, empty in (("--parity-seeds", not seeds), ("--methods", not methods)):
        if empty:
            raise UsageError(option, "needs at least one value")
    for option in ("steps", "parity_steps"):
        if getattr(args, option) < 1:
            raise UsageError(f"--{option.replace('_', '-')}", f"must be >= 1, got {getattr(args, option)}")
    if args.prepare is not None and args.prepare.exists() and not args.prepare.is_dir():
        raise UsageError("--prepare", f"{args.prepare} is a file; give a folder")
    if args.parity is not None and not args.parity.is_dir():
        raise UsageError("--parity", f"{args.parity}: no such folder (one `tacsplat bench gpu --prepare` wrote)")
    if args.prepare is not None:
        _prepare(args.prepare, args, seeds)
        return 0
    if args.device == "cuda" and not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else f"CUDA {torch.version.cuda}, no device visible"
        print(f"bench gpu: skipped: torch {torch.__version__} ({build}) sees no CUDA device; nothing was measured")
        return 0
    for name in methods:
        bench_row(name, "--methods")
    source = source_hash()
    parity = _read_parity(args.parity, source) if args.parity else None
    out, work = args.out, args.work or args.out / "work"
    started = time.perf_counter()
    scene = _capture(args, work / "scene", args.resolution, args.views, args.test_views)
    report = {
        "device": _device(args.device),
        "scene": _scene_facts(scene),
        "capture_seconds": time.perf_counter() - started,
        "runs": [],
        "source": source,
        "parity": None if parity is None else {"cpu": parity, "device_runs": []},
    }
    warm_up = _attempt(scene, work / "warm-up", methods[0], 20, 0, args.device)  # gsplat's kernels build here
    if "error" in warm_up:  # (a kernel build or memory failure): a row of the report; the runs still try
        report["runs"].append(warm_up | {"method": "warm-up"})
        _write_report(out, report, started)
    for method in methods:  # the report is written after each run: a lease that ends early keeps what was measured
        report["runs"].append(_attempt(scene, work / "runs" / method, method, args.steps, 0, args.device, True))
        _write_report(out, report, started)
    if parity is not None:
        for seed in parity["seeds"]:
            folder, method = work / "parity" / f"seed{seed}", parity["method"]
            run = _attempt(args.parity / "scene", folder, method, parity["steps"], seed, args.device)
            report["parity"]["device_runs"].append(run)
            _write_report(out, report, started)
    print((out / "gpu.md").read_text())
    return 0


def _attempt(scene: Path, out: Path, method: str, steps: int, seed: int, device: str, show_progress: bool = False):
    """:func:`_train`'s row, or a row saying why it failed (the other runs of the check still run)."""
    try:
        return _train(scene, out, method, steps, seed, device, show_progress)
    except Exception as exc:  # one run's failure is a row of the table, not the end of the check
        return {"method": method, "seed": seed, "error": f"{type(exc).__name__}: {exc}"}


def _write_report(out: Path, report: dict, started: float) -> None:
    report["wall_seconds"] = time.perf_counter() - started
    out.mkdir(parents=True, exist_ok=True)
    (out / "gpu.json").write_text(json.dumps(report, indent=2))
    (out / "gpu.md").write_text(gpu_table(report))


def _capture(args, scene: Path, resolution: int, views: int, test_views: int) -> Path:
    from tacsplat.apps.batch import CaptureJob

    CaptureJob(
        out=scene, object=args.object, views=views, test_views=test_views, grasps=args.grasps, resolution=resolution
    )()
    return scene


def _train(
    scene: Path, out: Path, method: str, steps: int, seed: int, device: str, show_progress: bool = False
) -> dict:
    """Train ``method`` for the first ``steps`` steps of the paper's schedule (one evaluation, at the end)."""
    import torch

    from tacsplat.apps.paper_bench import row_config
    from tacsplat.reconstruction.trainer import reconstruct

    config = row_config(method, "paper")
    config.iterations, config.seed, config.device = steps, seed, device
    config.eval_every_iters, config.eval_every_seconds = steps, 1e9
    config.init.use_sfm = False  # the visual hull: no pycolmap on the device
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    metrics = reconstruct(scene, out, config, overwrite=True, show_progress=show_progress)
    peak = torch.cuda.max_memory_allocated() / 2**30 if device == "cuda" else None
    per_1k = 1000.0 * metrics["train_seconds"] / max(metrics["iterations"], 1)
    row = dict(method=method, seed=seed, steps=metrics["iterations"], train_seconds=metrics["train_seconds"])
    row |= dict(seconds_per_1k_steps=per_1k, projected_30k_minutes=30 * per_1k / 60, peak_gpu_memory_gib=peak)
    return row | {key: metrics[key] for key in ("num_gaussians", "cd", "psnr")}


def _prepare(folder: Path, args, seeds: tuple[int, ...]) -> None:
    """The CPU side of the parity check: a small twin scene and its runs, one per seed, on this machine's CPU (the
    runs' folders are dropped: their numbers are what travels)."""
    import tempfile

    from tacsplat.reconstruction.methods import DEFAULT_METHOD

    scene = _capture(args, folder / "scene", args.parity_resolution, 5, 4)
    with tempfile.TemporaryDirectory(prefix="parity-runs-") as runs_dir:
        runs = [_train(scene, Path(runs_dir) / f"seed{s}", DEFAULT_METHOD, args.parity_steps, s, "cpu") for s in seeds]
    record = {"method": DEFAULT_METHOD, "steps": args.parity_steps, "seeds": list(seeds), "source": source_hash()}
    record["runs"] = [{k: r[k] for k in ("seed", "cd", "psnr", "train_seconds")} for r in runs]
    (folder / PARITY_FILE).write_text(json.dumps(record, indent=2))
    print(
        f"bench gpu: {folder} holds the parity scene and {len(runs)} CPU runs of {DEFAULT_METHOD} (source "
        f"{record['source']}); carry it to the device and give it to --parity"
    )


def _read_parity(folder: Path, here: str) -> dict:
    """The record of a ``--prepare`` folder (a warning when its CPU runs ran other source than ``here``)."""
    path = folder / PARITY_FILE
    try:
        record = json.loads(path.read_text())
        if not (folder / "scene").is_dir() or not record["runs"]:
            raise ValueError("no scene/ or no runs")
    except (OSError, ValueError, KeyError) as exc:
        raise ConfigError("--parity", f"not a folder written by `tacsplat bench gpu --prepare` ({exc})", path) from None
    if record.get("source") != here:
        print(f"bench gpu: warning: the CPU runs are of source {record.get('source')}, this is {here}")
    return record


def parity_verdict(cpu: list[float], device: list[float]) -> tuple[float, float, float, bool]:
    """``(CPU mean, CPU spread (max - min), device mean, whether the device mean lies within the CPU's range)``."""
    mean = statistics.fmean(device)
    return statistics.fmean(cpu), max(cpu) - min(cpu), mean, min(cpu) <= mean <= max(cpu)


def gpu_table(report: dict) -> str:
    """The check's one table (Markdown): a row per method, then the parity rows."""
    from tacsplat.apps.report import md_table, number

    dev, scene = report["device"], report["scene"]
    lines = [
        f"# {dev['name']}: torch {dev['torch']}, CUDA {dev['cuda']}, gsplat {dev['gsplat']}",
        "",
        f"Scene: {scene['train_views']} train views at {scene['resolution']} px, {scene['test_views']} test views, "
        f"{scene['touches']} touches (captured in {report['capture_seconds']:.0f} s). "
        f"Whole check: {report['wall_seconds']:.0f} s.",
        "",
    ]
    table = []
    for r in report["runs"]:
        if "error" in r:
            table.append([r["method"], f"failed: {r['error']}", *[""] * 6])
            continue
        peak = number(r["peak_gpu_memory_gib"], 2, "n/a")
        table.append(
            [r["method"], r["steps"], f"{r['seconds_per_1k_steps']:.1f}", f"{r['projected_30k_minutes']:.1f}", peak]
            + [r["num_gaussians"], number(r["cd"], 4, "n/a"), number(r["psnr"], 2, "n/a")]
        )
    lines += md_table(
        ["run", "steps", "s / 1k steps", "30k steps [min]", "peak GPU [GiB]", "Gaussians", "CD", "PSNR"], table
    )
    parity = report["parity"]
    if parity is not None:
        cpu, failed = parity["cpu"], [r for r in parity["device_runs"] if "error" in r]
        runs = [r for r in parity["device_runs"] if "error" not in r]
        lines += [
            "",
            f"Parity: {cpu['method']}, {cpu['steps']} steps, seeds {cpu['seeds']}; the CPU runs' source "
            f"{cpu['source']}, this one {report['source']}.",
            "",
        ]
        table = []
        for key, decimals in (("cd", 4), ("psnr", 2)) if runs else ():
            verdict = parity_verdict([r[key] for r in cpu["runs"]], [r[key] for r in runs])
            table.append([key, *(f"{v:.{decimals}f}" for v in verdict[:3]), "yes" if verdict[3] else "NO"])
        lines += md_table(["metric", "CPU mean", "CPU spread", "device mean", "within the CPU's range"], table, "lrrrl")
        lines += ["", *(f"Parity run of seed {r['seed']} failed: {r['error']}" for r in failed)] if failed else []
    return "\n".join(lines) + "\n"


def _device(device: str) -> dict:
    import torch

    name = torch.cuda.get_device_name() if device == "cuda" else "CPU (--device cpu)"
    return {"name": name, "torch": torch.__version__, "cuda": torch.version.cuda, "gsplat": _version("gsplat")}


def _scene_facts(scene: Path) -> dict:
    from tacsplat.datasets import Scene

    loaded = Scene.load(scene)
    train = loaded.split("train")
    return {
        "path": str(scene),
        "train_views": len(train),
        "test_views": len(loaded.split("test")),
        "touches": len(loaded.touches),
        "resolution": f"{train[0].intrinsics.width}x{train[0].intrinsics.height}",
    }


def source_hash() -> str:
    """12 hex digits of a hash of the package's source (its .py and .yaml files by module path): the same for the
    same code whether it is installed, editable or linked, with or without git."""
    import tacsplat
    from tacsplat import acquisition, datasets, drivers, reconstruction, sim

    files = {}
    for package in (tacsplat, acquisition, datasets, drivers, reconstruction, sim):
        root = Path(package.__file__).resolve().parent
        prefix = Path(*package.__name__.split("."))
        for path in root.rglob("*"):
            if path.suffix in (".py", ".yaml") and "__pycache__" not in path.parts:
                files[(prefix / path.relative_to(root)).as_posix()] = path
    digest = hashlib.sha256()
    for key in sorted(files):
        digest.update(key.encode() + b"\0" + files[key].read_bytes() + b"\0")
    return digest.hexdigest()[:12]


def _version(package: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return None
