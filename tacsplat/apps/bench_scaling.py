"""`tacsplat bench scaling`: error against cost for the whole job, at several resolutions and step counts.

Its options and what it does: :class:`BenchScaling`.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from pathlib import Path

from tacsplat.errors import ConfigError, UsageError
from tacsplat.options import comma_separated_ints, first_repeat, options_error

COLUMNS = ("resolution", "iterations", "method", "cd", "cd_paper", "psnr", "ssim", "train_seconds", "num_gaussians")
OPTIONS = {  # PaperBenchConfig's fields -> this command's options
    "objects": "--object",
    "methods": "--methods",
    "resolution": "--resolutions",
    "iterations": "--steps",
    "seeds": "--seed",
}
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*")  # a method's marker and line style, in the order given
LINESTYLES = ("-", "--", ":", "-.")


def scaling_methods(text: str) -> tuple[str, ...]:
    """The rows of ``--methods``: methods or ablation rows, as `tacsplat bench paper --methods` takes them; a
    UsageError (exit 2) naming ``--methods`` otherwise."""
    from tacsplat.apps.paper_bench import bench_row

    methods = tuple(v.strip() for v in text.split(",") if v.strip())
    if not methods:
        raise UsageError("--methods", f"need at least one method, got {text!r}")
    if (name := first_repeat(methods)) is not None:
        raise UsageError("--methods", f"{name!r} is given twice")
    for name in methods:
        try:
            bench_row(name, "--methods")
        except ConfigError as exc:
            raise UsageError(exc.key, str(exc).removeprefix(f"{exc.key}: ")) from None
    return methods


def scaling_benches(out: Path, obj: str, resolutions, step_counts, methods, seed: int = 0) -> list:
    """``(resolution, steps, bench)``: the `bench paper` slice of each resolution and step count, all validated
    before any runs; a UsageError naming the option at fault otherwise."""
    from tacsplat.apps.paper_bench import PaperBench, PaperBenchConfig

    for option, values in (("--resolutions", resolutions), ("--steps", step_counts)):
        if (value := first_repeat(values)) is not None:  # (a slice's folder)
            raise UsageError(option, f"{value!r} is given twice")
    suite = dict(objects=(obj,), settings=("minimal",), methods=tuple(methods), seeds=(seed,))
    slices = []
    for resolution, iterations in itertools.product(resolutions, step_counts):
        config = PaperBenchConfig(**suite, resolution=resolution, iterations=iterations)
        # one capture per resolution (it does not depend on the step count): its first slice's
        scenes = out / f"{resolution}px-{step_counts[0]}steps" / "scenes"
        try:
            slices.append(
                (resolution, iterations, PaperBench(out / f"{resolution}px-{iterations}steps", config, scenes))
            )
        except ConfigError as exc:
            raise options_error(exc, OPTIONS) from None
    return slices


def run_scaling(out: Path, obj: str, resolutions, step_counts, methods, seed: int = 0) -> list[dict]:
    from tacsplat.apps.report import number

    width = max(map(len, methods))
    rows = []
    for resolution, iterations, bench in scaling_benches(out, obj, resolutions, step_counts, methods, seed):
        for row in bench.run(progress=False):
            rows.append({"resolution": resolution, "iterations": iterations} | {k: row[k] for k in COLUMNS if k in row})
            print(
                f"{resolution:4d} px {iterations:5d} steps {row['method']:{width}s}: "
                f"CD {number(row['cd'], 4, 'nan')} cd_paper {number(row['cd_paper'], 5, 'nan')} "
                f"PSNR {number(row['psnr'], 2, 'nan')} train {row['train_seconds']:.0f} s",
                flush=True,
            )
    return rows


def write_scaling_report(out: Path, rows: list[dict], obj: str) -> Path:
    """'scaling.csv', 'scaling.png' (CD and PSNR against train seconds: a curve per resolution and method, a point
    per step count) and 'report.md' in ``out``."""
    import numpy as np
    from matplotlib.lines import Line2D

    from tacsplat.apps.report import md_table, number, pyplot, save_figure, write_csv
    from tacsplat.reconstruction.methods import method_label

    write_csv(rows, out / "scaling.csv", COLUMNS)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    resolutions = sorted({r["resolution"] for r in rows})
    plt = pyplot()
    colors = plt.get_cmap("viridis")(np.linspace(0.0, 0.8, len(resolutions)))
    styles = {m: (MARKERS[i % len(MARKERS)], LINESTYLES[i % len(LINESTYLES)]) for i, m in enumerate(methods)}
    fig, (ax_cd, ax_psnr) = plt.subplots(1, 2, figsize=(11, 4.5))
    for resolution, color in zip(resolutions, colors):
        for method, (marker, linestyle) in styles.items():
            points = sorted(
                (r["iterations"], r["train_seconds"], r["cd"], r["psnr"])
                for r in rows
                if r["resolution"] == resolution and r["method"] == method
            )
            if not points:
                continue
            steps, seconds, cd, psnr = zip(*points)
            for ax, values in ((ax_cd, cd), (ax_psnr, psnr)):
                ax.plot(seconds, values, marker=marker, linestyle=linestyle, color=color)
                for n, x, y in zip(steps, seconds, values):
                    ax.annotate(f"{n}", (x, y), xytext=(3, 3), textcoords="offset points", fontsize=6)
    ax_cd.set(yscale="log", ylabel="CD [x GT radius] (lower is better)")
    ax_psnr.set(ylabel="held-out PSNR [dB] (higher is better)")
    for ax in (ax_cd, ax_psnr):
        ax.set_xlabel("train seconds")
        ax.grid(alpha=0.3)
    method_keys = [
        Line2D([], [], color="0.3", marker=marker, linestyle=linestyle, label=method_label(method))
        for method, (marker, linestyle) in styles.items()
    ]
    size_keys = [Line2D([], [], color=c, linewidth=3, label=f"{r} px") for r, c in zip(resolutions, colors)]
    ax_cd.legend(handles=method_keys, title="method", fontsize=7, title_fontsize=8)
    ax_psnr.legend(handles=size_keys, title="image size", fontsize=7, title_fontsize=8)
    fig.suptitle(f"{obj}, 5 views + 5 grasps: error against cost (a point per step count, labelled)")
    fig.tight_layout()
    save_figure(fig, out / "scaling.png")
    rows = sorted(rows, key=lambda r: (r["resolution"], r["iterations"], methods.index(r["method"])))
    lines = [f"# Error against cost: {obj}, minimal views", ""] + md_table(
        ["px", "steps", "method", "train s", "CD", "PSNR"],
        [
            [r["resolution"], r["iterations"], r["method"], number(r["train_seconds"], 0)]
            + [number(r["cd"], 4), number(r["psnr"], 2)]
            for r in rows
        ],
        "rrlrrr",
    )
    lines += ["", "![error against cost](scaling.png)", ""]
    (out / "report.md").write_text("\n".join(lines))
    return out / "report.md"


@dataclass
class BenchScaling:
    """error against cost: resolutions x step counts, any methods, one object

    One object in the minimal-views setting, reconstructed by each of --methods (methods or rows of
    ablations.yaml, as `tacsplat bench paper --methods` takes them: default+c2f75 is the default trained coarse to
    fine) at each resolution (default 128, 256 and 400 px) and step count (default 750 and 1500), each a `tacsplat
    bench paper` slice in its own folder (so it resumes the same way; the slices of a resolution train on the
    capture of its first step count's). Writes scaling.csv, report.md and one figure,
    scaling.png: CD (log) and PSNR against train seconds, one curve per resolution (color) and method (marker and
    line style), a point per step count, to pick a point on the curve."""

    out: Path = Path("bench-output/scaling")
    """output folder"""
    object: str = "teapot"
    """library object"""
    methods: str = "paper,default"
    """comma-separated methods or rows of ablations.yaml (bench paper --help lists them); paper: the paper's method,
    default: what reconstruct runs"""
    resolutions: str = "128,256,400"
    """comma-separated image sizes in pixels"""
    steps: str = "750,1500"
    """comma-separated step counts"""
    seed: int = 0


def register(cli) -> None:
    cli.typed("bench scaling", BenchScaling, _run)


def _run(args: BenchScaling) -> int:
    started = time.perf_counter()
    resolutions, steps = (comma_separated_ints(getattr(args, key), f"--{key}") for key in ("resolutions", "steps"))
    for option, values in (("--resolutions", resolutions), ("--steps", steps)):
        if not values or min(values) < 1:
            raise UsageError(option, f"needs positive integers, got {getattr(args, option[2:])!r}")
    rows = run_scaling(args.out, args.object, resolutions, steps, scaling_methods(args.methods), args.seed)
    report = write_scaling_report(args.out, rows, args.object)
    print(report.read_text())
    print(f"{len(rows)} runs in {(time.perf_counter() - started) / 60:.1f} min; report: {report}")
    return 0
