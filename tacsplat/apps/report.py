"""Tables and plots shared by the benchmarks (`tacsplat bench paper`, `bench touches`, `demo`).

A result is a dict with the keys of :data:`RESULT_COLUMNS` (one reconstruction run).
Tables follow the paper's layout (Tables 1-3): objects as columns plus ``Avg.``,
methods as rows, the best value of each column in bold.
"""

from __future__ import annotations

import csv
import math
import textwrap
from pathlib import Path
from typing import Literal

import numpy as np

from tacsplat.reconstruction.methods import METHODS, method_label

Better = Literal["lower", "higher", "zero"]  # which value of a metric is best: "zero" the one nearest 0
# metric -> (heading, which is better, decimals)
METRICS: dict[str, tuple[str, Better, int]] = {
    "cd": ("CD (↓)", "lower", 4),
    "cd_seen": ("CD on the surface a training view sees (↓)", "lower", 4),
    "cd_unseen": ("CD on the surface no training view sees (↓)", "lower", 4),
    "cd_paper": ("CD as the paper measures it (↓)", "lower", 5),
    "psnr": ("PSNR (↑)", "higher", 2),
    "ssim": ("SSIM (↑)", "higher", 3),
    "normal_error_deg": ("Normal error, degrees (↓)", "lower", 1),
    "depth_bias": ("Depth bias: median rendered minus true depth, + behind the truth (→ 0)", "zero", 4),
    "mesh_fscore_1": ("Mesh F-score at 1 % of the radius (↑)", "higher", 3),
    "mesh_fscore_2": ("Mesh F-score at 2 % of the radius (↑)", "higher", 3),
    "mesh_fscore_5": ("Mesh F-score at 5 % of the radius (↑)", "higher", 3),
    "mesh_fscore_5_seen": ("Mesh F-score at 5 % on the surface a training view sees (↑)", "higher", 3),
    "mesh_fscore_5_unseen": ("Mesh F-score at 5 % on the surface no training view sees (↑)", "higher", 3),
    "mesh_cd": ("Mesh CD, radii (↓)", "lower", 4),
    "mesh_untouched_fscore_5": ("Mesh F-score at 5 %, touches not fused into the mesh (↑)", "higher", 3),
    "mesh_untouched_cd": ("Mesh CD, touches not fused into the mesh (↓)", "lower", 4),
}
# a run's numbers in results.csv
NUMBER_COLUMNS = (
    *METRICS,
    "cd_paper_accuracy",
    "cd_paper_completeness",
    "unseen_fraction",
    "train_seconds",
    "num_gaussians",
    "psnr_splat",
)  # psnr_splat: what splat.ply shows a plain 3DGS renderer
RESULT_COLUMNS = ("object", "setting", "method", *NUMBER_COLUMNS, "seed")


ROW_LABELS = {"default-no-touch": "Default, no touch"}  # bench rows beyond the methods that tables name otherwise


def row_label(name: str) -> str:
    """The label the tables and plots print for a bench row: a method's label, :data:`ROW_LABELS`', or the name."""
    return ROW_LABELS.get(name) or method_label(name)


def number(value, decimals: int, missing: str = "–") -> str:
    """``value`` with ``decimals`` decimals; ``missing`` for None, NaN or infinity."""
    return missing if value is None or not math.isfinite(value) else f"{value:.{decimals}f}"


def write_csv(rows: list[dict], path: str | Path, columns) -> Path:
    """One line per row with ``columns`` (missing or None values empty, other keys left out); parent folders
    created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows({k: "" if row.get(k) is None else row[k] for k in columns} for row in rows)
    return path


def read_csv(path: str | Path) -> list[dict]:
    """The rows of a CSV file :func:`write_csv` wrote, as dicts of strings (none when there is no file)."""
    path = Path(path)
    if not path.is_file():
        return []
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


def md_table(header, rows, align: str = "") -> list[str]:
    """The lines of a Markdown table: ``header`` and ``rows`` of cells; ``align`` a letter per column, ``l``
    (left, ``---``) or ``r`` (right, ``---:``), by default the first column left and the others right."""
    align = align or "l" + "r" * (len(header) - 1)
    lines = [
        "| " + " | ".join(map(str, header)) + " |",
        "|" + "".join(" ---: |" if a == "r" else " --- |" for a in align),
    ]
    return lines + ["| " + " | ".join(map(str, row)) + " |" for row in rows]


def machine(**extra) -> dict:
    """What a benchmark's timings depend on: cores, numba's threads (``extra`` after them), the load average, the
    platform and the versions of numba and torch."""
    import os
    import platform

    import numba
    import torch

    return {
        "cpu_count": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        **extra,
        "load_average_at_start": list(os.getloadavg()),
        "platform": platform.platform(),
        "numba": numba.__version__,
        "torch": torch.__version__,
    }


def finite_mean(values: list[float | None]) -> float:
    """The mean of the values that are finite numbers (NaN without any)."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def metric_table(rows: list[dict], metric: str, setting: str) -> tuple[list[str], list[str], np.ndarray]:
    """``(objects, methods, values [V, O + 1])``: the mean over seeds of ``metric`` per method and object (NaN
    where a run is missing), last column the average over objects: NaN unless the method has every object's value,
    so that no two averages over different objects are compared."""
    selected = [r for r in rows if r["setting"] == setting]
    objects = list(dict.fromkeys(r["object"] for r in selected))
    present = {r["method"] for r in selected}
    methods = [v for v in METHODS if v in present] + sorted(present - set(METHODS))
    values = np.full((len(methods), len(objects) + 1), np.nan)
    for i, method in enumerate(methods):
        for j, obj in enumerate(objects):
            values[i, j] = finite_mean(
                [r.get(metric) for r in selected if r["method"] == method and r["object"] == obj]
            )
        values[i, -1] = np.mean(values[i, :-1]) if np.isfinite(values[i, :-1]).all() else np.nan
    return objects, methods, values


def seed_spread(rows: list[dict], metric: str, setting: str) -> dict[str, float]:
    """Per method, the standard deviation over seeds of each seed's average of ``metric`` over the objects
    (:func:`metric_table`'s ``Avg.`` on that seed's rows): how far the tables' ``Avg.`` moves from one seed to the
    next. A seed counts where the method has a finite value on every object of the setting; NaN with fewer than
    two such seeds."""
    objects, methods, _ = metric_table(rows, metric, setting)
    averages = {method: [] for method in methods}
    for seed in dict.fromkeys(r.get("seed") for r in rows if r["setting"] == setting):
        seed_objects, seed_methods, values = metric_table([r for r in rows if r.get("seed") == seed], metric, setting)
        if set(seed_objects) != set(objects):
            continue
        for method, row in zip(seed_methods, values):
            if np.isfinite(row[:-1]).all():
                averages[method].append(float(row[-1]))
    return {method: float(np.std(a, ddof=1)) if len(a) >= 2 else float("nan") for method, a in averages.items()}


def best_rows(values: np.ndarray, better: Better) -> list[set[int]]:
    """Per column, the row indices holding the best finite value (ties all count)."""
    score = {"lower": values, "higher": -values, "zero": np.abs(values)}[better]
    return [{i for i in np.flatnonzero(np.isfinite(column)) if column[i] == np.nanmin(column)} for column in score.T]


SPREAD_NOTE = (  # under a table with a "Seed s.d." column
    "\n*Seed s.d.: the standard deviation over the seeds of each seed's average over the objects; a "
    "difference in Avg. smaller than it may be the seeds' luck.*\n"
)


def markdown_table(rows: list[dict], metric: str, setting: str) -> str:
    """A paper-style Markdown table of one metric in one setting; the best value per column in bold."""
    heading, better, decimals = METRICS[metric]
    objects, methods, values = metric_table(rows, metric, setting)
    best = best_rows(np.round(values, decimals), better)  # values equal as printed are equally best
    spread = seed_spread(rows, metric, setting)
    with_spread = any(math.isfinite(v) for v in spread.values())
    table = []
    for i, method in enumerate(methods):
        cells = [number(v, decimals) for v in values[i]]
        cells = [f"**{text}**" if i in best[j] else text for j, text in enumerate(cells)]
        table.append([row_label(method), *cells] + ([number(spread[method], decimals)] if with_spread else []))
    lines = md_table(["Method", *objects, "Avg.", *(["Seed s.d."] if with_spread else [])], table)
    return f"**{heading}, {setting}**\n\n" + "\n".join(lines) + "\n" + (SPREAD_NOTE if with_spread else "")


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 100, **savefig_kwargs) -> Path:
    """Save ``fig`` as ``path`` (parent folders created) and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, **savefig_kwargs)
    pyplot().close(fig)
    return path


def plot_cd_bars(rows: list[dict], setting: str, path: str | Path) -> Path:
    """Grouped bar chart: CD per method (bars) per object (groups), log scale, mean over seeds."""
    plt = pyplot()
    objects, methods, values = metric_table(rows, "cd", setting)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.3 * (len(objects) + 1)), 4))
    width = 0.8 / max(len(methods), 1)
    x = np.arange(len(objects) + 1)
    for i, method in enumerate(methods):
        offset = (i - (len(methods) - 1) / 2) * width
        ax.bar(x + offset, np.nan_to_num(values[i], nan=0.0), width, label=row_label(method))
    ax.set_xticks(x, objects + ["Avg."])
    ax.set_ylabel("Chamfer distance [x GT radius]")
    if np.nanmin(np.where(values > 0, values, np.nan), initial=np.inf) < np.inf:
        ax.set_yscale("log")
    ax.set_title(f"Chamfer distance per object ({setting})")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_error_vs_time(curves: dict[str, dict[str, dict[str, np.ndarray]]], path: str | Path, title: str = "") -> Path:
    """CD (top) and PSNR (bottom) against run time, one column per object, one line per method.

    ``curves[object][method]`` holds a run's ``seconds``, ``cd`` and ``psnr`` arrays
    (:func:`tacsplat.reconstruction.run_dir.read_progress`).
    """
    plt = pyplot()
    objects = list(curves)
    fig, axes = plt.subplots(2, max(len(objects), 1), figsize=(4 * max(len(objects), 1), 6.5), squeeze=False)
    from tacsplat.reconstruction.run_dir import draw_error_vs_time

    for j, obj in enumerate(objects):
        draw_error_vs_time(axes[0, j], axes[1, j], {row_label(v): c for v, c in curves[obj].items()})
        axes[0, j].set_title(obj)
        axes[0, j].set_yscale("log")
    axes[0, 0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


UNSEEN_COLOR = (0.9, 0.0, 0.8)  # magenta: ground-truth surface no training camera sees


def render_grid(
    panels: dict[str, tuple],
    gt_rgb: np.ndarray,
    gt_depth: np.ndarray,
    path: str | Path,
    title: str = "",
    gt_normal: np.ndarray | None = None,
    gt_seen: np.ndarray | None = None,
) -> Path:
    """Ground truth then one column per method; RGB on top, depth below on ONE colour scale (the ground
    truth's depth range), so that a surface behind or in front of the true one shows as a colour shift; a third
    row of camera-frame normals (as RGB, (n + 1) / 2; black where empty) when the panels carry them; with
    ``gt_seen`` [H, W] bool (which ground-truth pixels a training camera sees), a last row: under the ground
    truth that coverage (grey seen, magenta unseen), under each method its depth minus the truth's (red
    behind, blue in front, on one symmetric scale of a quarter of the truth's depth range).

    ``panels[method] = (rgb [H, W, 3] in [0, 1], depth [H, W] metres, 0 = empty)`` of the same test view, or
    ``(rgb, depth, normal [H, W, 3])``; ``gt_normal`` the ground truth's (e.g. from its depth map).
    """
    plt = pyplot()
    valid = gt_depth[gt_depth > 0]
    lo, hi = (float(valid.min()), float(valid.max())) if valid.size else (0.0, 1.0)
    pad = 0.1 * max(hi - lo, 1e-6)
    columns = [("ground truth", gt_rgb, gt_depth, gt_normal)] + [
        (row_label(v), p[0], p[1], p[2] if len(p) > 2 else None) for v, p in panels.items()
    ]
    with_normals = any(c[3] is not None for c in columns)
    with_error = gt_seen is not None and valid.size > 0
    rows = 2 + with_normals + with_error
    fig, axes = plt.subplots(rows, len(columns), figsize=(2.6 * len(columns) + 0.8, 2.7 * rows), squeeze=False)
    cmap = plt.get_cmap("turbo").with_extremes(bad="black")
    error_cmap = plt.get_cmap("RdBu_r").with_extremes(bad="black")
    error_range = 0.25 * max(hi - lo, 1e-6)
    image = error_image = None
    for j, (label, rgb, depth, normal) in enumerate(columns):
        axes[0, j].imshow(np.clip(rgb, 0, 1))
        image = axes[1, j].imshow(np.ma.masked_less_equal(depth, 0), cmap=cmap, vmin=lo - pad, vmax=hi + pad)
        if with_normals:
            shown = np.zeros(rgb.shape[:2] + (3,)) if normal is None else normal
            empty = ~np.any(shown != 0, axis=-1, keepdims=True)
            axes[2, j].imshow(np.where(empty, 0.0, np.clip((shown + 1.0) / 2.0, 0, 1)))
        if with_error and j == 0:
            coverage = np.zeros(gt_depth.shape + (3,))
            coverage[(gt_depth > 0) & gt_seen] = 0.8
            coverage[(gt_depth > 0) & ~gt_seen] = UNSEEN_COLOR
            axes[-1, j].imshow(coverage)
        elif with_error:
            both = (depth > 0) & (gt_depth > 0)
            error_image = axes[-1, j].imshow(
                np.ma.masked_array(depth - gt_depth, ~both), cmap=error_cmap, vmin=-error_range, vmax=error_range
            )
        axes[0, j].set_title(textwrap.fill(label, 28), fontsize=10)  # long method labels on two lines
    for ax in axes.flat:
        ax.set(xticks=[], yticks=[])
    for ax, label in zip(axes[:, 0], ["RGB", "depth", *(["normals (camera frame)"] if with_normals else [])]):
        ax.set_ylabel(label)
    fig.colorbar(image, ax=list(axes[1]), fraction=0.02, label="depth [m]")
    if with_error:
        axes[-1, 0].set_ylabel("seen by training views\n(magenta: not) | depth error")
        if error_image is not None:
            fig.colorbar(error_image, ax=list(axes[-1]), fraction=0.02, label="depth - true depth [m]")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path, bbox_inches="tight")
