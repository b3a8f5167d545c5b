"""`tacsplat demo`: the README's main job (see `make demo`).

Simulated capture of one glossy object (5 train views, 5 grasps of 4 touches),
reconstruction without touch (vanilla 3DGS), with it (the paper's full method)
and with what `tacsplat reconstruct` does by default (the full method plus
surface normals from views and touch, and colour shaded at those normals), that
default once more with every tactile and hand signal off (what touching did),
the results side by side and a small
report (report.md, CD bars, error against run time, renders next to ground
truth) in the output folder. It is the
minimal-views slice of `tacsplat bench paper` for one object, so it is
resumable the same way and its numbers are the benchmark's own.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

from tacsplat.reconstruction.methods import DEFAULT_METHOD

DEMO_OBJECT = "teapot"
NO_TOUCH = "default-no-touch"  # the default with --no-use-touch: no touch Gaussians, no L_T (ablations.yaml)
COLUMNS = {
    "3dgs": "3DGS (no touch)",
    "paper": "paper (touch)",
    NO_TOUCH: "default, no touch",
    DEFAULT_METHOD: "default (touch)",
}  # method: heading


def demo_config(object_name: str = DEMO_OBJECT, resolution: int = 128, iterations: int = 1200):
    """The :class:`PaperBenchConfig` of the demo: one object, minimal views, :data:`COLUMNS`' methods."""
    from tacsplat.apps.paper_bench import PaperBenchConfig

    return PaperBenchConfig(
        objects=(object_name,),
        settings=("minimal",),
        methods=tuple(COLUMNS),
        resolution=resolution,
        iterations=iterations,
        test_views=8,
    )


@dataclass
class DemoCommand:
    """the main job: simulated capture of a glossy object, reconstruction without and with touch, report"""

    out: Path = Path("demo-output")
    """output folder"""
    object: str = DEMO_OBJECT
    """library object (all are glossy)"""
    resolution: int = 128
    """image size in pixels"""
    iterations: int = 1200
    """steps per reconstruction"""


def register(cli) -> None:
    cli.typed("demo", DemoCommand, run)


def _change(without: float, with_touch: float) -> str:
    """A Chamfer distance without touch against with it, said the way it went: ``1.07x lower (0.0300 -> 0.0280)``
    when touch helped, ``higher`` when it hurt."""
    lower = with_touch <= without
    ratio = without / with_touch if lower else with_touch / without
    return f"{ratio:.2f}x {'lower' if lower else 'higher'} ({without:.4f} -> {with_touch:.4f})"


def run(args: DemoCommand) -> int:
    from tacsplat.apps.paper_bench import PaperBench, continue_hint
    from tacsplat.errors import ConfigError
    from tacsplat.options import options_error

    started = time.perf_counter()
    try:
        bench = PaperBench(Path(args.out), demo_config(args.object, args.resolution, args.iterations))
    except ConfigError as exc:  # an option's value, refused before anything is made
        raise options_error(exc, {"objects": "--object"}) from None
    try:
        rows = {r["method"]: r for r in bench.run(executor="auto")}  # the trainings side by side on 2+ cores
    except KeyboardInterrupt:
        print(continue_hint("demo", bench.out), file=sys.stderr)
        raise
    name = bench.config.object_list()[0]  # the object's name in the bench's files (a mesh file: its stem)
    print()
    print(f"{name}, 5 views + 5 grasps (20 touches), {args.resolution} px, {args.iterations} steps:")
    width = 2 + max(len(heading) for heading in COLUMNS.values())
    print(f"{'':22s}" + "".join(f"{heading:>{width}s}" for heading in COLUMNS.values()))
    for key, label, decimals in (
        ("cd", "Chamfer distance (↓)", 4),
        ("psnr", "PSNR dB (↑)", 2),
        ("ssim", "SSIM (↑)", 3),
        ("train_seconds", "train seconds", 0),
    ):
        print(f"{label:22s}" + "".join(f"{rows[v][key]:>{width}.{decimals}f}" for v in COLUMNS))
    touch, none = rows[DEFAULT_METHOD], rows[NO_TOUCH]
    print(
        f"what touching did to the default (one seed; the spread over seeds and objects: docs/results.md): CD "
        f"{_change(none['cd'], touch['cd'])}, on the surface no training view sees "
        f"{_change(none['cd_unseen'], touch['cd_unseen'])}, PSNR {touch['psnr'] - none['psnr']:+.2f} dB"
    )
    report = bench.out.resolve()
    print(f"report: {report / 'report.md'} (tables, plots and renders)")
    print(
        f"open first: {report / f'renders_{name}_minimal.png'} "
        "(a test view: ground truth and the four runs; RGB, depth, normals, and the depth error beside "
        "what the training views see)"
    )
    print(f"total {(time.perf_counter() - started) / 60:.1f} min")
    return 0
