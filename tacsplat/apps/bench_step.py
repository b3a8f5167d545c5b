"""`tacsplat bench step`: where the time of a training step goes, on the demo's scene.

Its options and what it does: :class:`BenchStep`.
"""

from __future__ import annotations

import contextlib
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from tacsplat.apps.report import machine, pyplot, save_figure

PHASES = (
    "projection + SH",
    "binning + sort",
    "composite forward",
    "composite backward",
    "shading",
    "SSIM",
    "other losses",
    "autograd (other)",
    "neighbour search",
    "optimiser",
    "densification",
    "rest",
)
WARMUP_STEPS = 10  # first steps left out of the statistics (kernel loading, first allocations)


class PhaseTimer:
    """Exclusive wall time per phase: entering a phase pauses the one it is nested in."""

    def __init__(self):
        self.totals: dict[str, float] = defaultdict(float)
        self._stack: list[list] = []  # [phase, resumed at]

    def enter(self, phase: str) -> None:
        now = time.perf_counter()
        if self._stack:
            self.totals[self._stack[-1][0]] += now - self._stack[-1][1]
        self._stack.append([phase, now])

    def leave(self) -> None:
        now = time.perf_counter()
        phase, resumed = self._stack.pop()
        self.totals[phase] += now - resumed
        if self._stack:
            self._stack[-1][1] = now

    @contextlib.contextmanager
    def phase(self, name: str):
        self.enter(name)
        try:
            yield
        finally:
            self.leave()

    def take(self) -> dict[str, float]:
        """The totals so far (seconds), then zero."""
        totals, self.totals = dict(self.totals), defaultdict(float)
        return totals


def _timed(timer: PhaseTimer, phase: str, function):
    def wrapper(*args, **kwargs):
        with timer.phase(phase):
            return function(*args, **kwargs)

    return wrapper


def _backward_marker():
    """An identity autograd Function whose backward calls ``ctx.callback`` (times a loss's backward)."""
    import torch

    class Marker(torch.autograd.Function):
        @staticmethod
        def forward(ctx, callback, x):
            ctx.callback = callback
            return x.view_as(x)

        @staticmethod
        def backward(ctx, grad):
            ctx.callback()
            return None, grad

    return Marker


@contextlib.contextmanager
def instrumented(timer: PhaseTimer):
    """Wrap, for the duration, the functions a training step calls with ``timer``'s phases; yields the list that
    receives one ``{phase: seconds}`` per ``Trainer.train_step`` call."""
    from unittest import mock

    import torch

    from tacsplat.reconstruction import fused_shading, losses
    from tacsplat.reconstruction.densification import DensifyStrategy
    from tacsplat.reconstruction.raster import cpu_composite, cpu_project
    from tacsplat.reconstruction.trainer import Trainer

    marker = _backward_marker()
    d_ssim = losses.d_ssim

    def timed_d_ssim(rendered, target, fused=True):  # forward, and backward between the two markers
        with timer.phase("SSIM"):
            if rendered.requires_grad:
                rendered = marker.apply(timer.leave, rendered)
            out = d_ssim(rendered, target, fused)
            return marker.apply(lambda: timer.enter("SSIM"), out) if out.requires_grad else out

    steps: list[dict[str, float]] = []
    step_function = Trainer.train_step

    def timed_step(self):
        timer.take()
        started = time.perf_counter()
        terms = step_function(self)
        totals = timer.take()
        totals["rest"] = time.perf_counter() - started - sum(totals.values())
        totals["n_gaussians"] = len(self.gaussians)
        steps.append(totals)
        return terms

    loss_functions = (
        "photometric_loss",
        "backdrop_alpha_loss",
        "transmittance_loss",
        "edge_aware_smoothness",
        "depth_normal_consistency",
        "flatten_loss",
        "visible_touch_pixels",
        "proximity_mask",
        "expected_depth",
        "image_edge_weights",
        "window_inside",
        "albedo_smoothness_loss",
    )
    both = ("forward", "backward")
    patches = [  # (owner, its functions, phase)
        (cpu_project._ProjectCPU, both, "projection + SH"),
        (cpu_project._SphericalHarmonicsCPU, both, "projection + SH"),
        (cpu_composite, ("bin_gaussians",), "binning + sort"),
        (cpu_composite._RasterizeCPU, ("forward",), "composite forward"),
        (cpu_composite._RasterizeCPU, ("backward",), "composite backward"),
        (fused_shading._ShadeCPU, both, "shading"),
        (losses, [name for name in loss_functions if hasattr(losses, name)], "other losses"),
        (Trainer, ("_smoothness_weights",), "other losses"),
        (losses.TouchNeighbours, ("candidates",), "neighbour search"),
        (torch.optim.Adam, ("step",), "optimiser"),
        (torch.optim.Optimizer, ("zero_grad",), "optimiser"),
        (DensifyStrategy, ("step_pre_backward", "step_post_backward"), "densification"),
        (torch.Tensor, ("backward",), "autograd (other)"),
    ]
    with contextlib.ExitStack() as patched:  # (each original is put back on the way out)
        for owner, names, phase in patches:
            for name in names:
                original = owner.__dict__[name]
                static = isinstance(original, staticmethod)  # (an autograd Function's forward and backward)
                wrapped = _timed(timer, phase, original.__func__ if static else original)
                patched.enter_context(mock.patch.object(owner, name, staticmethod(wrapped) if static else wrapped))
        patched.enter_context(mock.patch.object(losses, "d_ssim", timed_d_ssim))
        patched.enter_context(mock.patch.object(Trainer, "train_step", timed_step))
        yield steps


def summarize(steps: list[dict[str, float]], warmup: int = WARMUP_STEPS) -> dict:
    """Median and mean milliseconds per phase and per step over the steps after ``warmup``."""
    import numpy as np

    kept = steps[warmup:] if len(steps) > warmup else steps
    ms = {phase: np.array([s.get(phase, 0.0) for s in kept]) * 1e3 for phase in PHASES}
    phases = {phase: {"median_ms": float(np.median(v)), "mean_ms": float(v.mean())} for phase, v in ms.items()}
    totals = np.array([sum(s.get(p, 0.0) for p in PHASES) for s in kept]) * 1e3
    return {
        "steps_timed": len(kept),
        "step_median_ms": float(np.median(totals)),
        "step_mean_ms": float(totals.mean()),
        "steps_per_second": float(1e3 / totals.mean()),
        "n_gaussians_mean": float(np.mean([s["n_gaussians"] for s in kept])),
        "n_gaussians_final": int(kept[-1]["n_gaussians"]),
        "phases": phases,
    }


def profile_resolution(out: Path, resolution: int, iterations: int, method: str, obj: str, seed: int) -> dict:
    """Capture (once) the demo scene at ``resolution`` px and time a full reconstruction of it."""
    import tempfile

    from tacsplat.apps.demo import demo_config
    from tacsplat.apps.paper_bench import PaperBench, row_config
    from tacsplat.datasets import Scene
    from tacsplat.reconstruction.trainer import Trainer
    from tacsplat.reconstruction.views import scene_at

    bench = PaperBench(out / f"{resolution}px", demo_config(obj, resolution, iterations))
    capture = bench.capture_job(obj, "minimal", seed)
    capture()  # (once: a finished capture is kept)
    config = row_config(method, bench.config.preset, iterations)
    config.seed, config.device = seed, "cpu"
    with tempfile.TemporaryDirectory() as run_dir, instrumented(PhaseTimer()) as steps:
        trainer = Trainer(scene_at(Scene.load(capture.out), config.downscale), run_dir, config)
        trainer.run(show_progress=False)
    run = dict(
        resolution=resolution, label=f"{resolution}px", iterations=iterations, train_seconds=trainer.train_seconds
    )
    per_step = [{k: round(v * 1e3, 4) if k != "n_gaussians" else v for k, v in s.items()} for s in steps]
    return run | {"torch_threads": config.torch_threads, **summarize(steps), "per_step": per_step}


def run_profile(
    out: Path,
    resolutions,
    iterations: int,
    method: str,
    obj: str,
    seed: int,
    reference: str | None = None,
    rounds: int = 1,
) -> dict:
    """The profile of ``method`` at each resolution; with ``reference``, that method's profile is taken next to
    each (back to back: this machine's speed drifts by 10-30% between runs minutes apart) and the ratios reported,
    ``rounds`` times, the reference first in even rounds and second in odd ones: the ratios are the medians over the
    rounds (each round's are kept too), the profiles those of the first round."""
    import os
    import statistics

    results = {
        "benchmark": "step",
        "machine": machine(),
        "settings": dict(object=obj, method=method, iterations=iterations, seed=seed, warmup_steps=WARMUP_STEPS),
        "resolutions": [],
    }
    if reference is not None:
        results["settings"].update(reference=reference, rounds=rounds)
        results["reference"] = []
    for r in resolutions:
        if reference is None:
            results["resolutions"].append(profile_resolution(out, r, iterations, method, obj, seed))
            continue
        per_round = []
        for k in range(rounds):  # ABAB..., then BABA...: a machine slowing down or speeding up favours neither
            order = (reference, method) if k % 2 == 0 else (method, reference)
            first, second = (profile_resolution(out, r, iterations, m, obj, seed) for m in order)
            ref, row = (first, second) if k % 2 == 0 else (second, first)
            keys = {"step_median": "step_median_ms", "step_mean": "step_mean_ms", "train_seconds": "train_seconds"}
            per_round.append({key: row[field] / ref[field] for key, field in keys.items()})
            if k == 0:
                results["reference"].append(ref)
                results["resolutions"].append(row)
        ratios = {key: statistics.median(p[key] for p in per_round) for key in per_round[0]}
        results["resolutions"][-1]["ratio_to_reference"] = {**ratios, "rounds": per_round}
    results["machine"]["load_average_at_end"] = list(os.getloadavg())
    return results


def format_table(results: dict) -> str:
    rows = results["resolutions"]
    head = f"{'phase':20s}" + "".join(f" | {r['label'] + ' median':>12s} {'mean':>7s} {'share':>6s}" for r in rows)
    lines = [head, "-" * len(head)]
    for phase in PHASES:
        cells = [(r["phases"][phase], r["step_mean_ms"]) for r in rows]
        share = " | {0[median_ms]:12.2f} {0[mean_ms]:7.2f} {1:5.1f}%"
        lines.append(f"{phase:20s}" + "".join(share.format(p, 100 * p["mean_ms"] / mean) for p, mean in cells))
    s, m = results["settings"], results["machine"]
    lines += [
        "-" * len(head),
        f"{'step':20s}" + "".join(f" | {r['step_median_ms']:12.2f} {r['step_mean_ms']:7.2f} {'':6s}" for r in rows),
        f"ms per step (median and mean over steps {s['warmup_steps'] + 1}..{s['iterations']}); "
        + "; ".join(
            f"{r['label']}: {r['steps_per_second']:.1f} steps/s, {r['n_gaussians_mean']:.0f} Gaussians on "
            f"average, train {r['train_seconds']:.1f} s"
            for r in rows
        ),
    ]
    for r in filter(lambda r: "ratio_to_reference" in r, rows):
        ratio = r["ratio_to_reference"]
        each = ", ".join(f"{p['step_median']:.2f}x" for p in ratio["rounds"])
        lines.append(
            f"{r['label']}: {s['method']} / {s['reference']} (each run next to its reference): step "
            f"median {ratio['step_median']:.2f}x, mean {ratio['step_mean']:.2f}x, train time "
            f"{ratio['train_seconds']:.2f}x (medians over {len(ratio['rounds'])} rounds; step median by "
            f"round: {each})"
        )
    lines.append(
        f"{s['object']}, method {s['method']}, seed {s['seed']}; {m['cpu_count']} cores, numba threads "
        f"{m['numba_threads']}, load average {m['load_average_at_start'][0]:.1f} at start, "
        f"{m['load_average_at_end'][0]:.1f} at end"
    )
    return "\n".join(lines)


def plot_phases(results_list: list[tuple[str, dict]], path: Path) -> Path:
    """Stacked bars of the mean ms per step by phase, one bar per (results, resolution)."""
    plt = pyplot()
    bars = [
        (f"{name} {r['label']}" if name else r["label"], r)
        for name, results in results_list
        for r in results["resolutions"]
    ]
    fig, ax = plt.subplots(figsize=(max(4.0, 1.4 * len(bars) + 3.0), 4.5))
    colors = plt.get_cmap("tab20").colors
    bottoms = [0.0] * len(bars)
    for i, phase in enumerate(PHASES):
        heights = [r["phases"].get(phase, {}).get("mean_ms", 0.0) for _, r in bars]  # (a phase added later: 0)
        ax.bar(range(len(bars)), heights, bottom=bottoms, color=colors[i % len(colors)], label=phase)
        bottoms = [b + h for b, h in zip(bottoms, heights)]
    ax.set_xticks(range(len(bars)), [label for label, _ in bars])
    ax.set_ylabel("ms per training step (mean)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


@dataclass
class BenchStep:
    """profile of a training step on the demo scene: time per phase, table + PNG

    The demo's capture (one glossy object, 5 views, 5 grasps; made once per resolution and reused) is
    reconstructed by the trainer itself ('Trainer.run', the demo's settings), while the functions a step calls
    are timed in place: projection and SH, binning and depth sort, compositing forward and backward, the
    deferred shading of the sh-lit appearance (forward and backward), SSIM (forward and backward), the other
    losses, the transmittance neighbour search, the optimiser and densification. Each phase is timed exclusively
    (a phase nested in another is not counted twice); 'autograd (other)' is what 'loss.backward()' spends
    outside the timed backward passes, 'rest' what a step spends outside every timed phase. Writes 'step.json'
    (the compare command reads it), 'step.png' (stacked bars) and prints a table."""

    out: Path = Path("bench-output/step")
    """output folder (scenes are captured here once)"""
    resolutions: str = "128,256"
    """comma-separated image sizes in pixels"""
    iterations: int = 1200
    """training steps per resolution (the demo's 1200)"""
    method: str = "paper"
    """a method (3dgs, 3dgs+s, 3dgs+t, paper, default) or a row of `bench paper`'s ablations.yaml"""
    reference: str | None = None
    """also profile this method next to it, and print the ratios"""
    rounds: int = 1
    """with --reference: profile the pair this many times, the reference first, then second, ... (ratios: medians
    over the rounds)"""
    object: str = "teapot"
    """library object"""
    seed: int = 0


def register(cli) -> None:
    """Add `tacsplat bench step`."""
    cli.typed("bench step", BenchStep, _handler)


def _handler(args: BenchStep) -> int:
    import json

    from tacsplat.apps.demo import demo_config
    from tacsplat.apps.paper_bench import bench_row
    from tacsplat.errors import ConfigError, UsageError
    from tacsplat.options import comma_separated_ints, options_error

    resolutions = comma_separated_ints(args.resolutions, "--resolutions")
    if not resolutions or min(resolutions) < 16:
        raise UsageError("--resolutions", f"need image sizes of at least 16 px, got {args.resolutions!r}")
    if args.iterations <= WARMUP_STEPS:
        raise UsageError("--iterations", f"must be more than the {WARMUP_STEPS} warm-up steps, got {args.iterations}")
    bench_row(args.method, "--method")
    if args.reference is not None:
        bench_row(args.reference, "--reference")
    if args.rounds < 1 or (args.rounds > 1 and args.reference is None):
        raise UsageError("--rounds", f"needs --reference and a count of at least 1, got {args.rounds}")
    try:  # (the object, as bench scaling checks it: before any capture)
        demo_config(args.object, resolutions[0], args.iterations).validate()
    except ConfigError as exc:
        raise options_error(exc, {"objects": "--object"}) from None
    out = args.out
    results = run_profile(
        out, resolutions, args.iterations, args.method, args.object, args.seed, args.reference, args.rounds
    )
    print(format_table(results))
    out.mkdir(parents=True, exist_ok=True)
    (out / "step.json").write_text(json.dumps(results, indent=1))
    bars = [("", results)]
    if args.reference is not None:
        bars = [(args.reference, {"resolutions": results["reference"]}), (args.method, results)]
    plot_phases(bars, out / "step.png")
    print(f"wrote {out / 'step.json'} and {out / 'step.png'}")
    return 0
