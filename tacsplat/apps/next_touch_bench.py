"""`tacsplat bench next-touch`: next-best against random grasps at equal grasp budgets, views and training steps.

Per object, seed and strategy one simulated capture with 5 train views and the largest grasp budget
(``sim-capture --grasp-strategy random|next-best``); both strategies of an object and seed see the same views
(the views do not depend on the strategy). Choices are sequential, so the first ``k`` grasps of a capture are the
``k``-grasp capture: per budget ``k`` a copy of the scene keeps every frame and the touches of its first ``k``
recorded grasps, and is reconstructed with the trainer's defaults for the same ``--iterations`` whatever the
strategy. The training next-best spends choosing (``selection_steps`` per grasp) is not in these steps; it is
reported as ``selection_seconds``.

Beside the table, for each object's first seed: how well the two uncertainty scores of the views-only
reconstruction that chose the first grasp predict its real error: each score rendered on the test views beside
the depth error against the ground truth, and the Spearman rank correlation of the two over the test pixels.

Output (resumable: finished captures, copies and runs are kept)::

    OUT/scenes/<object>-s<seed>-<strategy>/        the captures (next-best's decisions in their scene.json)
    OUT/scenes/<object>-s<seed>-<strategy>-g<k>/   their first k grasps
    OUT/runs/<object>-s<seed>-<strategy>-g<k>/     `tacsplat reconstruct` run folders
    OUT/results.csv  OUT/report.md  OUT/cd_vs_grasps.png  OUT/uncertainty_<object>.png
"""

from __future__ import annotations

import csv
import json
import logging
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tacsplat.apps.options import comma_separated_ints
from tacsplat.errors import ConfigError

log = logging.getLogger(__name__)

STRATEGIES = ("random", "next-best")
RESULT_COLUMNS = ("object", "strategy", "grasps", "seed", "cd", "cd_paper", "psnr", "seconds", "selection_seconds",
                  "touches")


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
    candidates: int = 16  # next-best: approaches scored per grasp
    selection_steps: int = 300  # next-best: steps of the reconstruction that chooses each grasp
    uncertainty: str = "depth-variance"  # next-best: the score

    def validate(self) -> None:
        from tacsplat.reconstruction.uncertainty import SCORES
        from tacsplat.sim.objects import OBJECT_NAMES

        unknown = [o for o in self.objects if o not in OBJECT_NAMES]
        if unknown:
            raise ConfigError("--objects", f"unknown object(s) {', '.join(unknown)}; choose from "
                              f"{', '.join(OBJECT_NAMES)} (or all)")
        if self.mesh is not None and not Path(self.mesh).is_file():
            raise ConfigError("--mesh", f"file not found: {self.mesh}")
        if not self.seeds or min(self.seeds) < 0:
            raise ConfigError("--seeds", f"need at least one seed, each >= 0, got {self.seeds}")
        if not self.grasps or min(self.grasps) < 0:
            raise ConfigError("--grasps", f"need at least one grasp budget, each >= 0, got {self.grasps}")
        for key in ("views", "test_views", "resolution", "iterations", "candidates", "selection_steps"):
            if getattr(self, key) < 1:
                raise ConfigError(f"--{key.replace('_', '-')}", f"must be >= 1, got {getattr(self, key)}")
        if self.uncertainty not in SCORES:
            raise ConfigError("--uncertainty", f"must be one of {', '.join(SCORES)}, got {self.uncertainty!r}")

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
    from tacsplat.datasets import Scene, SceneMeta, copy_scene

    scene = Scene.load(scene_path)
    kept = sorted({t.grasp for t in scene.touches})[:count]
    touches = [t for t in scene.touches if t.grasp in kept]
    meta = SceneMeta(scene.meta.source, scene.meta.object, dict(scene.meta.capture_plan),
                     {**scene.meta.extra, "first_grasps": {"from": str(scene.path), "grasps": len(kept)}})
    copy_scene(scene, out, touches=touches, meta=meta)
    return len(kept), sum(t.in_contact for t in touches)


class NextTouchBench:
    """The sweep in a folder; :meth:`run` does whatever is not done yet."""

    def __init__(self, out: str | Path, config: NextTouchBenchConfig | None = None):
        self.out = Path(out)
        self.config = config or NextTouchBenchConfig()
        self.config.validate()

    def rig(self, subject: str, seed: int, strategy: str):
        """The sim capture's config of one object, seed and strategy."""
        from tacsplat.acquisition.sim_capture import sim_rig_config

        c = self.config
        return sim_rig_config(object=subject if c.mesh is None else "teapot", mesh=c.mesh, views=c.views,
                              test_views=c.test_views, grasps=max(c.grasps), resolution=c.resolution, seed=seed,
                              grasp_strategy=strategy, candidates=c.candidates, selection_steps=c.selection_steps,
                              uncertainty=c.uncertainty)

    def scene_dir(self, subject: str, seed: int, strategy: str) -> Path:
        return self.out / "scenes" / f"{subject}-s{seed}-{strategy}"

    def check_captures(self) -> None:
        """Refuse a folder whose finished captures were made with another plan, before anything runs."""
        from tacsplat.apps.batch import CAPTURE_MARKER

        c = self.config
        for subject in c.subjects:
            for seed in c.seeds:
                for strategy in STRATEGIES:
                    marker = self.scene_dir(subject, seed, strategy) / CAPTURE_MARKER
                    plan = self.rig(subject, seed, strategy).plan.to_json()
                    if marker.is_file() and json.loads(marker.read_text())["plan"] != plan:
                        raise ConfigError("--out", f"{marker.parent} was captured with another plan ({marker}); "
                                          "use the same options or a new --out")

    def capture(self, subject: str, seed: int, strategy: str) -> Path:
        from tacsplat.apps.batch import capture_once

        return capture_once(self.rig(subject, seed, strategy), self.scene_dir(subject, seed, strategy))

    def budget_scene(self, subject: str, seed: int, strategy: str, count: int) -> tuple[Path, dict]:
        """The copy of a capture with its first ``count`` grasps, and what it holds (marker ``<copy>.json``)."""
        path = self.out / "scenes" / f"{subject}-s{seed}-{strategy}-g{count}"
        marker = path.with_name(path.name + ".json")
        if marker.is_file():
            return path, json.loads(marker.read_text())
        if path.exists():  # a copy interrupted before its marker: ours to redo
            shutil.rmtree(path)
        source = self.capture(subject, seed, strategy)
        grasps, touches = first_grasps(source, path, count)
        info = {"grasps": grasps, "touches": touches, "selection_seconds": selection_seconds(source, count)}
        marker.write_text(json.dumps(info))
        return path, info

    def run(self, progress: bool = True) -> list[dict]:
        from tacsplat.progress import progress_bar
        from tacsplat.reconstruction.config import TrainConfig
        from tacsplat.reconstruction.trainer import reconstruct

        c = self.config
        self.check_captures()
        jobs = [(subject, seed, strategy, k) for subject in c.subjects for seed in c.seeds for strategy in STRATEGIES
                for k in c.grasps]
        rows = []
        bar = progress_bar(jobs, desc="bench next-touch", unit="run", enabled=progress)
        for subject, seed, strategy, k in bar:
            bar.set_postfix_str(f"{subject} seed {seed}, {strategy}, {k} grasps")
            scene, info = self.budget_scene(subject, seed, strategy, k)
            out = self.out / "runs" / scene.name
            if (out / "metrics.json").is_file():
                metrics = json.loads((out / "metrics.json").read_text())
                if metrics["iterations"] != c.iterations:
                    raise ConfigError("--out", f"{out} was trained for {metrics['iterations']} steps, this run asks "
                                      f"for {c.iterations}: use the same --iterations or a new --out")
            else:
                resume = (out / "checkpoint.pt").is_file()
                metrics = reconstruct(scene, out, TrainConfig(iterations=c.iterations, seed=seed), resume=resume,
                                      overwrite=not resume, show_progress=False)
            rows.append({"object": subject, "strategy": strategy, "grasps": k, "seed": seed, "cd": metrics["cd"],
                         "cd_paper": metrics.get("cd_paper"), "psnr": metrics["psnr"],
                         "seconds": metrics["train_seconds"], "selection_seconds": info["selection_seconds"],
                         "touches": info["touches"]})
            bar.write(f"{subject} s{seed} {strategy:9s} {k} grasps ({info['touches']} touches): CD {metrics['cd']:.4f}")
        bar.close()
        correlations = {subject: self.uncertainty_picture(subject, c.seeds[0]) for subject in c.subjects}
        write_report(self.out, rows, correlations, c)
        return rows

    def uncertainty_picture(self, subject: str, seed: int) -> dict[str, float]:
        """``uncertainty_<subject>.png`` and the Spearman correlation of each score with the depth error."""
        scene, _ = self.budget_scene(subject, seed, "next-best", 0)
        return uncertainty_vs_error(scene, self.config.selection_steps, seed, self.out / f"uncertainty_{subject}.png")


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
    from tacsplat.reconstruction.uncertainty import SCORES, Views, brief_reconstruction, gaussian_uncertainty, \
        render_uncertainty
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
    fig, axes = plt.subplots(len(shown) or 1, 2 + len(SCORES), figsize=(3.0 * (2 + len(SCORES)), 3.0 * max(len(shown), 1)),
                             squeeze=False)
    scale = np.nanpercentile(np.stack(errors), 95) if errors and pixels.any() else 1.0
    limits = {name: tuple(np.percentile(np.stack(maps[name])[pixels], [2, 98])) if errors and pixels.any() else (0, 1)
              for name in SCORES}  # each score on its own scale over the surface: its order is what counts
    for row, i in enumerate(shown):
        axes[row, 0].imshow(scene.load_image(tests[i]))
        axes[row, 0].set_title("test view" if row == 0 else "")
        for col, name in enumerate(SCORES, start=1):
            axes[row, col].imshow(np.where(pixels[i], maps[name][i], np.nan), cmap="magma", vmin=limits[name][0],
                                  vmax=limits[name][1])
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
            summary[strategy, k] = {"cd": float(np.mean([r["cd"] for r in group])), "spread": float(np.std(per_seed)),
                                    "runs": len(group)}
    return summary


def write_report(out: Path, rows: list[dict], correlations: dict[str, dict], config: NextTouchBenchConfig) -> None:
    """``results.csv``, ``cd_vs_grasps.png`` and ``report.md``."""
    from tacsplat.apps.report import pyplot, save_figure

    out.mkdir(parents=True, exist_ok=True)
    with (out / "results.csv").open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=RESULT_COLUMNS)
        writer.writeheader()
        writer.writerows({k: "" if r.get(k) is None else r[k] for k in RESULT_COLUMNS} for r in rows)
    summary = summarise(rows)
    budgets = sorted({r["grasps"] for r in rows})
    fig, ax = pyplot().subplots(figsize=(5.5, 4))
    for strategy, colour in zip(STRATEGIES, ("tab:blue", "tab:red")):
        ks = [k for k in budgets if (strategy, k) in summary]
        mean = np.array([summary[strategy, k]["cd"] for k in ks])
        spread = np.array([summary[strategy, k]["spread"] for k in ks])
        ax.plot(ks, mean, "o-", color=colour, label=strategy)
        ax.fill_between(ks, mean - spread, mean + spread, color=colour, alpha=0.2)
    ax.set_xlabel("grasps (4 fingertips each)")
    ax.set_ylabel("Chamfer distance [x GT radius]")
    ax.set_title("CD against grasps (mean; band: spread over seeds)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, out / "cd_vs_grasps.png")

    subjects = list(dict.fromkeys(r["object"] for r in rows))
    lines = ["# Next-best touch against random grasps", "",
             f"{len(subjects)} object(s), seeds {', '.join(map(str, config.seeds))}; {config.views} train views, "
             f"{config.test_views} test views, {config.resolution} px; every reconstruction {config.iterations} "
             f"steps. Next-best: {config.candidates} candidate approaches per grasp, scored on a "
             f"{config.selection_steps}-step reconstruction of the scene so far with the {config.uncertainty} score.",
             "", "## Mean CD (x GT radius, lower is better) over seeds", "",
             "| object | strategy | " + " | ".join(f"{k} grasps" for k in budgets) + " |",
             "| --- | --- |" + " ---: |" * len(budgets)]
    for subject in subjects:
        for strategy in STRATEGIES:
            cells = []
            for k in budgets:
                cds = [r["cd"] for r in rows if (r["object"], r["strategy"], r["grasps"]) == (subject, strategy, k)]
                cells.append(f"{np.mean(cds):.4f}" if cds else "–")
            lines.append(f"| {subject} | {strategy} | " + " | ".join(cells) + " |")
    lines += ["", "## Over every object and seed", "",
              "| grasps | random CD | next-best CD | change | next-best choosing (s, mean per capture) |",
              "| ---: | ---: | ---: | ---: | ---: |"]
    for k in budgets:
        if ("random", k) in summary and ("next-best", k) in summary:
            r, n = summary["random", k]["cd"], summary["next-best", k]["cd"]
            choosing = np.mean([x["selection_seconds"] for x in rows if x["strategy"] == "next-best" and x["grasps"] == k])
            lines.append(f"| {k} | {r:.4f} ± {summary['random', k]['spread']:.4f} | {n:.4f} ± "
                         f"{summary['next-best', k]['spread']:.4f} | {100 * (n - r) / r:+.1f} % | {choosing:.0f} |")
    lines += ["", "![CD against grasps](cd_vs_grasps.png)", "",
              "## Does the uncertainty predict the error?", "",
              "Spearman rank correlation, over the test pixels, of each score of the views-only reconstruction that "
              "chose the first grasp with its depth error against the ground truth (1: perfectly ordered).", "",
              "| object | " + " | ".join(next(iter(correlations.values()), {})) + " |",
              "| --- |" + " ---: |" * len(next(iter(correlations.values()), {}))]
    for subject, rho in correlations.items():
        lines.append(f"| {subject} | " + " | ".join(f"{v:+.3f}" for v in rho.values()) + " |")
    lines += [""] + [f"![uncertainty {s}](uncertainty_{s}.png)" for s in correlations] + [""]
    (out / "report.md").write_text("\n".join(lines))


def register(cli) -> None:
    p = cli.command(
        "bench next-touch",
        help="next-best against random grasps: CD against the number of grasps, both strategies",
        description="Per object, seed and strategy one sim capture (5 views, the largest grasp budget); per budget "
        "k a copy with the first k grasps, reconstructed with --iterations steps whatever the strategy. Writes "
        "OUT/results.csv, OUT/report.md (tables, uncertainty against error), OUT/cd_vs_grasps.png. Resumable.",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--objects", default="all", help="'all' or comma-separated library objects")
    p.add_argument("--mesh", default=None, help="any .obj/.ply/.stl mesh instead of the library objects")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (capture and training)")
    p.add_argument("--grasps", default="1,2,3,5,8", help="comma-separated grasp budgets")
    p.add_argument("--resolution", type=int, default=128, help="image size in pixels")
    p.add_argument("--test-views", type=int, default=12, help="held-out test views")
    p.add_argument("--iterations", type=int, default=1500, help="steps of every final reconstruction")
    p.add_argument("--candidates", type=int, default=16, help="next-best: approaches scored per grasp")
    p.add_argument("--selection-steps", type=int, default=300,
                   help="next-best: steps of the reconstruction that chooses each grasp")
    p.add_argument("--uncertainty", default="depth-variance", help="next-best: the score (depth-variance or fisher)")
    p.set_defaults(func=_run)


def _run(args) -> int:
    config = NextTouchBenchConfig(
        objects=() if args.objects == "all" else tuple(o.strip() for o in args.objects.split(",") if o.strip()),
        mesh=args.mesh, seeds=comma_separated_ints(args.seeds, "--seeds"),
        grasps=comma_separated_ints(args.grasps, "--grasps"), resolution=args.resolution, test_views=args.test_views,
        iterations=args.iterations, candidates=args.candidates, selection_steps=args.selection_steps,
        uncertainty=args.uncertainty,
    )  # fmt: skip
    started = time.perf_counter()
    bench = NextTouchBench(args.out, config)
    bench.run()
    print((bench.out / "report.md").read_text())
    print(f"done in {(time.perf_counter() - started) / 60:.1f} min; report: {bench.out / 'report.md'}")
    return 0
