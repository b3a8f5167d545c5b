"""`tacsplat bench gpu`: the whole trainer on CUDA with gsplat, at the paper's scale.

One simulated object (default: the teapot at 800x800, 100 train views, 5 grasps, the paper's
preset), reconstructed with the full method and with vanilla 3DGS on the GPU. Writes, into
``--out``: ``gpu.json`` and ``gpu.md`` (seconds per 1k steps, total train seconds, peak GPU
memory, CD, cd_paper and PSNR of each run, the device and library versions) and
``error_vs_time.png`` (held-out CD and PSNR against train seconds). Without CUDA it says so and
measures nothing. ``--scene`` reconstructs an existing scene instead of capturing one (a machine
with a GPU but no simulator).
"""

from __future__ import annotations

import json
import time
from pathlib import Path


def register(cli) -> None:
    p = cli.command(
        "bench gpu",
        help="train on CUDA with gsplat at the paper's scale: seconds per 1k steps, peak GPU memory, error vs time",
        description=__doc__.split("\n\n", 1)[1].replace("``", "'"),
    )
    p.add_argument("--out", default="bench-output/gpu", help="output folder (capture, runs, gpu.json, gpu.md, plot)")
    p.add_argument("--scene", default=None, help="reconstruct this scene instead of capturing one")
    p.add_argument("--object", default="teapot", help="library object to capture")
    p.add_argument("--resolution", type=int, default=800, help="image size of the capture (px)")
    p.add_argument("--views", type=int, default=100, help="train views of the capture")
    p.add_argument("--test-views", type=int, default=24, help="held-out test views of the capture")
    p.add_argument("--grasps", type=int, default=5, help="grasps of 4 touches")
    p.add_argument("--preset", default="paper", choices=("default", "paper"), help="training preset")
    p.add_argument("--iterations", type=int, default=None, help="steps per run (default: the preset's)")
    p.add_argument(
        "--methods", default="paper,3dgs", help="comma-separated methods (or rows of `bench paper`'s ablations.yaml)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--no-sfm",
        action="store_true",
        help="initialise without pycolmap (visual hull), e.g. on a GPU machine without pycolmap",
    )
    p.set_defaults(func=_run)


def _run(args) -> int:
    import torch

    if not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else f"CUDA {torch.version.cuda}, no device visible"
        print(f"bench gpu: skipped: torch {torch.__version__} ({build}) sees no CUDA device; nothing was measured")
        return 0
    from tacsplat.apps.paper_bench import bench_row

    methods = [name.strip() for name in args.methods.split(",") if name.strip()]
    for name in methods:
        bench_row(name, "--methods")
    out = Path(args.out)
    scene = Path(args.scene) if args.scene else _capture(args, out / "scene")
    rows = [_train(scene, out / "runs" / method, method, args) for method in methods]
    _write_report(out, rows, scene)
    print((out / "gpu.md").read_text())
    return 0


def _capture(args, scene: Path) -> Path:
    from tacsplat.acquisition.sim_capture import sim_rig_config
    from tacsplat.apps.batch import capture_once

    rig = sim_rig_config(
        object=args.object,
        views=args.views,
        test_views=args.test_views,
        grasps=args.grasps,
        resolution=args.resolution,
        seed=args.seed,
    )
    return capture_once(rig, scene)


def _train(scene: Path, out: Path, method: str, args) -> dict:
    import torch

    from tacsplat.apps.paper_bench import row_config
    from tacsplat.reconstruction.trainer import reconstruct

    config = row_config(method, args.preset, args.iterations)
    config.seed, config.device = args.seed, "cuda"
    config.init.use_sfm = not args.no_sfm
    torch.cuda.reset_peak_memory_stats()
    started = time.perf_counter()
    resume = (out / "checkpoint.pt").is_file()
    metrics = reconstruct(scene, out, config, resume=resume, overwrite=not resume, show_progress=True)
    wall = time.perf_counter() - started
    return {
        "method": method,
        "preset": args.preset,
        "iterations": metrics["iterations"],
        "train_seconds": metrics["train_seconds"],
        "wall_seconds": wall,
        "seconds_per_1k_steps": 1000.0 * metrics["train_seconds"] / max(metrics["iterations"], 1),
        "peak_gpu_memory_gib": torch.cuda.max_memory_allocated() / 2**30,
        "num_gaussians": metrics["num_gaussians"],
        "cd": metrics["cd"],
        "cd_paper": metrics["cd_paper"],
        "psnr": metrics["psnr"],
        "ssim": metrics["ssim"],
        "run": str(out),
    }


def _write_report(out: Path, rows: list[dict], scene: Path) -> None:
    import torch

    from tacsplat.apps.report import plot_error_vs_time
    from tacsplat.datasets import Scene
    from tacsplat.reconstruction.run_dir import read_progress

    loaded = Scene.load(scene)
    train = loaded.split("train")
    device = {
        "gpu": torch.cuda.get_device_name(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "gsplat": _version("gsplat"),
        "scene": str(scene),
        "train_views": len(train),
        "test_views": len(loaded.split("test")),
        "touches": len(loaded.touches),
        "resolution": f"{train[0].intrinsics.width}x{train[0].intrinsics.height}",
    }
    (out / "gpu.json").write_text(json.dumps({"device": device, "runs": rows}, indent=2))
    curves = {"": {r["method"]: read_progress(Path(r["run"]) / "progress.csv") for r in rows}}
    plot_error_vs_time(curves, out / "error_vs_time.png", f"{device['gpu']}: held-out error vs train time")
    lines = [
        f"# Training on {device['gpu']}",
        "",
        f"Scene: {device['train_views']} train views at {device['resolution']} px, {device['test_views']} test views, "
        f"{device['touches']} touches. torch {device['torch']} (CUDA {device['cuda']}), gsplat {device['gsplat']}.",
        "",
        "| method | preset | steps | s / 1k steps | train s | wall s | peak GPU GiB | Gaussians | CD | cd_paper | PSNR |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['preset']} | {r['iterations']} | {r['seconds_per_1k_steps']:.1f} | "
            f"{r['train_seconds']:.0f} | {r['wall_seconds']:.0f} | {r['peak_gpu_memory_gib']:.2f} | "
            f"{r['num_gaussians']} | {_fmt(r['cd'], 4)} | {_fmt(r['cd_paper'], 5)} | {_fmt(r['psnr'], 2)} |"
        )
    lines += ["", "![error vs time](error_vs_time.png)", ""]
    (out / "gpu.md").write_text("\n".join(lines))


def _fmt(value, decimals: int) -> str:
    return "n/a" if value is None else f"{value:.{decimals}f}"


def _version(package: str) -> str | None:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return None
