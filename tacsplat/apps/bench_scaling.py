"""`tacsplat bench scaling`: error against cost for the whole job, at several resolutions and step counts.

Its options and what it does: :class:`BenchScaling`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from tacsplat.options import comma_separated_ints

COLUMNS = ("resolution", "iterations", "method", "cd", "cd_paper", "psnr", "ssim", "train_seconds", "num_gaussians")


def run_scaling(out: Path, obj: str, resolutions, step_counts, seed: int = 0) -> list[dict]:
    from tacsplat.apps.paper_bench import PaperBench, PaperBenchConfig

    rows = []
    for resolution in resolutions:
        for iterations in step_counts:
            config = PaperBenchConfig(
                objects=(obj,),
                settings=("minimal",),
                methods=("3dgs", "paper"),
                resolution=resolution,
                iterations=iterations,
                seeds=(seed,),
            )
            bench = PaperBench(out / f"{resolution}px-{iterations}steps", config)
            for row in bench.run(progress=False):
                rows.append(
                    {"resolution": resolution, "iterations": iterations, **{k: row[k] for k in COLUMNS if k in row}}
                )
                print(
                    f"{resolution:4d} px {iterations:5d} steps {row['method']:5s}: cd_paper {row['cd_paper']:.5f} "
                    f"PSNR {row['psnr']:.2f} train {row['train_seconds']:.0f} s",
                    flush=True,
                )
    return rows


def write_scaling_report(out: Path, rows: list[dict], obj: str) -> Path:
    from tacsplat.apps.report import md_table, pyplot, save_figure, write_csv
    from tacsplat.reconstruction.methods import method_label

    write_csv(rows, out / "scaling.csv", COLUMNS)
    plt = pyplot()
    fig, (ax_cd, ax_psnr) = plt.subplots(1, 2, figsize=(11, 4.2))
    for resolution in sorted({r["resolution"] for r in rows}):
        for method, style in (("paper", "o-"), ("3dgs", "s--")):
            points = sorted(
                (r["train_seconds"], r["cd_paper"], r["psnr"])
                for r in rows
                if r["resolution"] == resolution and r["method"] == method
            )
            if not points:
                continue
            seconds, cd_paper, psnr = zip(*points)
            label = f"{resolution} px, {method_label(method)}"
            ax_cd.plot(seconds, cd_paper, style, label=label)
            ax_psnr.plot(seconds, psnr, style, label=label)
    ax_cd.set_yscale("log")
    ax_cd.set_ylabel("cd_paper [x GT radius^2] (lower is better)")
    ax_psnr.set_ylabel("held-out PSNR [dB]")
    for ax in (ax_cd, ax_psnr):
        ax.set_xlabel("train seconds (2 CPU cores)")
        ax.grid(alpha=0.3)
    ax_cd.legend(fontsize=7)
    fig.suptitle(f"{obj}, 5 views + 5 grasps: error against cost (a point per step count)")
    fig.tight_layout()
    save_figure(fig, out / "scaling.png")
    rows = sorted(rows, key=lambda r: (r["resolution"], r["iterations"], r["method"]))
    lines = [f"# Error against cost: {obj}, minimal views", ""] + md_table(
        ["px", "steps", "method", "train s", "cd_paper", "CD", "PSNR"],
        [
            [r["resolution"], r["iterations"], r["method"], f"{r['train_seconds']:.0f}", f"{r['cd_paper']:.5f}"]
            + [f"{r['cd']:.4f}", f"{r['psnr']:.2f}"]
            for r in rows
        ],
        "rrlrrrr",
    )
    lines += ["", "![error against cost](scaling.png)", ""]
    (out / "report.md").write_text("\n".join(lines))
    return out / "report.md"


@dataclass
class BenchScaling:
    """error against cost: resolutions x step counts, the paper method and 3DGS, one object

    One object in the minimal-views setting, reconstructed by the full method and by vanilla 3DGS at each
    resolution (default 128, 256 and 400 px) and step count (default 750 and 1500), each a `tacsplat bench
    paper` slice in its own folder (so it resumes the same way). Writes 'scaling.csv', 'report.md' and
    'scaling.png': the paper's CD and PSNR against train seconds, one curve per resolution and method, a point
    per step count."""

    out: Path = Path("bench-output/scaling")
    """output folder"""
    object: str = "teapot"
    """library object"""
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
    rows = run_scaling(args.out, args.object, resolutions, steps, args.seed)
    report = write_scaling_report(args.out, rows, args.object)
    print(report.read_text())
    print(f"{len(rows)} runs in {(time.perf_counter() - started) / 60:.1f} min; report: {report}")
    return 0
