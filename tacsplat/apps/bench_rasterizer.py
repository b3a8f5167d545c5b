"""`tacsplat bench rasterizer`: the ``cpu`` backend against the ``torch`` reference.

Also home of :func:`random_scene`, the random Gaussian scenes used by the
benchmark and by the rasterizer tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from tacsplat.errors import UsageError


def random_scene(
    n: int,
    width: int,
    height: int,
    n_cams: int = 1,
    sh_degree: int | None = 3,
    radius_px: tuple[float, float] = (1.0, 8.0),
    seed: int = 0,
    dtype=None,
) -> dict:
    """N random Gaussians filling the frustum of C cameras; 3-sigma radii roughly uniform in ``radius_px``.

    Returns the keyword arguments of ``rasterization`` (means, quats, scales,
    opacities, colors, viewmats, Ks, width, height, sh_degree). Camera 0 is at
    the origin looking down +z; the others are turned about the y axis around
    the cloud's centre (3 m ahead).
    """
    import torch

    dtype = dtype or torch.float32
    f64 = torch.float64
    g = torch.Generator().manual_seed(seed)
    focal = 0.9 * max(width, height)
    depth = 2.5 + torch.rand(n, generator=g, dtype=f64)  # [N]
    px = torch.rand(n, generator=g, dtype=f64) * width
    py = torch.rand(n, generator=g, dtype=f64) * height
    means = torch.stack([(px - width / 2) / focal * depth, (py - height / 2) / focal * depth, depth], dim=-1)
    radius = radius_px[0] + torch.rand(n, generator=g, dtype=f64) * (radius_px[1] - radius_px[0])
    base = radius / 3.0 * depth / focal  # world-space standard deviation giving that pixel size (sigma: radius / 3)
    scales = base[:, None] * torch.exp((torch.rand(n, 3, generator=g, dtype=f64) - 0.5) * 0.8)
    quats = torch.randn(n, 4, generator=g, dtype=f64)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g, dtype=f64)
    if sh_degree is None:
        colors = torch.rand(n, 3, generator=g, dtype=f64)
    else:
        colors = torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g, dtype=f64) * 0.3
    viewmats = torch.eye(4, dtype=f64).repeat(n_cams, 1, 1)
    centre = torch.tensor([0.0, 0.0, 3.0], dtype=f64)
    for c in range(1, n_cams):
        ang = 0.12 * c
        rot = torch.tensor(
            [[math.cos(ang), 0.0, math.sin(ang)], [0.0, 1.0, 0.0], [-math.sin(ang), 0.0, math.cos(ang)]], dtype=f64
        )
        viewmats[c, :3, :3] = rot
        viewmats[c, :3, 3] = centre - rot @ centre
    Ks = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=f64).repeat(n_cams, 1, 1)
    scene = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmats=viewmats, Ks=Ks)
    scene = {k: v.to(dtype).contiguous() for k, v in scene.items()}
    return scene | dict(width=width, height=height, sh_degree=sh_degree)


DEFAULT_SIZES = ("128x128:5000", "256x256:20000", "256x256:100000", "512x512:100000")
PARAMS = ("means", "quats", "scales", "opacities", "colors")


def parse_size(text: str) -> tuple[int, int, int]:
    """'WxH:N' -> (width, height, n_gaussians)."""
    try:
        res, n = text.split(":")
        width, height = res.lower().split("x")
        size = int(width), int(height), int(n)
    except ValueError:
        size = ()
    if len(size) != 3 or min(size) < 1:
        raise UsageError("--sizes", f"expected WxH:N of positive integers such as 256x256:20000, got {text!r}")
    return size


def _time_backend(scene: dict, backend: str, repeats: int) -> dict:
    """Median wall times (ms) of forward and forward+backward after one warm-up run (none when repeats=0)."""
    import time
    from statistics import median_high

    from tacsplat.reconstruction.raster import rasterization

    params = {k: scene[k].detach().clone().requires_grad_(True) for k in PARAMS}
    others = {k: v for k, v in scene.items() if k not in PARAMS}

    def forward():
        return rasterization(**params, **others, backend=backend)

    def forward_backward():
        img, alpha, meta = forward()
        (img.sum() + alpha.sum()).backward()
        return meta

    meta = forward_backward()  # warm-up (and compile)
    fwd, fwd_bwd = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        forward()
        fwd.append(time.perf_counter() - start)
        for p in params.values():
            p.grad = None
        start = time.perf_counter()
        forward_backward()
        fwd_bwd.append(time.perf_counter() - start)
    out = {"visible_gaussians": int((meta["radii"] > 0).all(-1).sum())}
    if repeats:  # (median_high: the middle one, or the upper of the two in the middle)
        out |= {"forward_ms": 1e3 * median_high(fwd), "forward_backward_ms": 1e3 * median_high(fwd_bwd)}
    return out | {key: meta[key] for key in ("n_intersections", "n_pairs") if key in meta}


def _vm_kib(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def memory_worker(width: int, height: int, n: int) -> dict:
    """Run in a fresh process: peak resident memory (VmHWM) around a first and a second cpu forward+backward.

    ``peak_over_baseline_mb`` is the peak minus the resident memory after the imports and the
    scene were made (it includes loading the cached kernels).
    """
    import tacsplat.reconstruction.raster.cpu_composite  # noqa: F401  (imports numba and torch before the baseline)

    scene = random_scene(n, width, height, sh_degree=3, seed=0)
    baseline = _vm_kib("VmRSS")
    _time_backend(scene, "cpu", repeats=1)
    peak = _vm_kib("VmHWM")
    return {"peak_rss_mb": peak / 1024, "peak_over_baseline_mb": (peak - baseline) / 1024}


def compile_worker() -> dict:
    """Run in a fresh process: time of the first cpu forward+backward minus a second one, on a tiny scene."""
    import time

    start = time.perf_counter()
    scene = random_scene(200, 32, 32, sh_degree=3, seed=0)
    setup = time.perf_counter() - start
    times = []
    for _ in range(2):
        start = time.perf_counter()
        _time_backend(scene, "cpu", repeats=0)
        times.append(time.perf_counter() - start)
    return {"first_call_s": times[0] - times[1], "setup_s": setup}


def _in_subprocess(call: str, env_extra: dict | None = None) -> dict:
    import json
    import os
    import subprocess
    import sys

    code = f"import json; from tacsplat.apps import bench_rasterizer as b; print(json.dumps(b.{call}))"
    env = dict(os.environ, **(env_extra or {}))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"benchmark worker {call} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_benchmark(sizes: list[str], repeats: int, torch_repeats: int, skip_torch: bool = False) -> dict:
    """Time the cpu backend against the torch reference at each size; compile times; peak memory."""
    import os
    import tempfile

    import torch

    from tacsplat.apps.report import machine
    from tacsplat.progress import progress_bar

    results = {
        "machine": machine(torch_threads=torch.get_num_threads()),
        "settings": {"repeats": repeats, "torch_repeats": torch_repeats, "sh_degree": 3, "radius_px": [1, 8]},
        "sizes": [],
    }
    with tempfile.TemporaryDirectory() as cache_dir:  # cold, then cached by the first in a process of its own
        cold, warm = (_in_subprocess("compile_worker()", {"NUMBA_CACHE_DIR": cache_dir}) for _ in range(2))
    results["compile"] = {"cold_first_call_s": cold["first_call_s"], "cached_first_call_s": warm["first_call_s"]}
    for text in progress_bar(sizes, desc="bench rasterizer", unit="size"):
        width, height, n = parse_size(text)
        scene = random_scene(n, width, height, sh_degree=3, seed=0)
        row = {"width": width, "height": height, "n_gaussians": n}
        cpu = row["cpu"] = _time_backend(scene, "cpu", repeats)
        if not skip_torch:
            row["torch"] = _time_backend(scene, "torch", torch_repeats)
            for key in ("forward_ms", "forward_backward_ms"):
                row[f"speedup_{key[:-3]}"] = row["torch"][key] / row["cpu"][key]
        for key in ("forward", "forward_backward"):
            cpu[f"ns_per_pair_{key}"] = 1e6 * cpu[f"{key}_ms"] / max(cpu["n_pairs"], 1)
        cpu.update(_in_subprocess(f"memory_worker({width}, {height}, {n})"))
        results["sizes"].append(row)
    results["machine"]["load_average_at_end"] = list(os.getloadavg())
    return results


def format_table(results: dict) -> str:
    """The benchmark as a plain-text table."""
    head = (
        f"{'size':>9} {'N':>7} | {'torch fwd':>9} {'torch f+b':>9} | {'cpu fwd':>8} {'cpu f+b':>8} | "
        f"{'x fwd':>6} {'x f+b':>6} | {'isects':>8} {'pairs':>10} {'ns/pair f+b':>11} | {'peak MB':>7} {'+MB':>6}"
    )
    lines = [head, "-" * len(head)]
    for row in results["sizes"]:
        cpu, ref = row["cpu"], row.get("torch")

        def ms(v):
            return f"{v:9.1f}" if v is not None else f"{'-':>9}"

        lines.append(
            f"{row['width']:>4}x{row['height']:<4} {row['n_gaussians']:>7} | "
            f"{ms(ref and ref['forward_ms'])} {ms(ref and ref['forward_backward_ms'])} | "
            f"{cpu['forward_ms']:8.1f} {cpu['forward_backward_ms']:8.1f} | "
            f"{row.get('speedup_forward', float('nan')):6.1f} {row.get('speedup_forward_backward', float('nan')):6.1f} | "
            f"{cpu['n_intersections']:>8} {cpu['n_pairs']:>10} {cpu['ns_per_pair_forward_backward']:11.1f} | "
            f"{cpu['peak_rss_mb']:7.0f} {cpu['peak_over_baseline_mb']:6.0f}"
        )
    comp, mach = results["compile"], results["machine"]
    lines += [
        f"numba first call: cold {comp['cold_first_call_s']:.1f} s, cached (second process) "
        f"{comp['cached_first_call_s']:.1f} s",
        f"times: median ms of the whole rasterization() call (projection, SH degree 3, compositing); "
        f"{mach['cpu_count']} cores, numba threads {mach['numba_threads']}, torch threads {mach['torch_threads']}, "
        f"load average {mach['load_average_at_start'][0]:.1f} at start, {mach['load_average_at_end'][0]:.1f} at end",
        "pairs: pixel-Gaussian pairs the cpu forward evaluated; peak MB: VmHWM of a fresh process running the cpu "
        "backend at that size, +MB: that peak over its resident memory after imports and scene set-up",
    ]
    return "\n".join(lines)


@dataclass
class BenchRasterizer:
    """time the cpu rasterizer against the torch reference (forward, forward+backward, memory, compile)"""

    json: Path | None = None
    """also write the results to this JSON file"""
    sizes: Annotated[
        tuple[str, ...] | None,
        tyro.conf.arg(metavar="WxH:N", help_behavior_hint=f"(default: {' '.join(DEFAULT_SIZES)})"),
    ] = None
    """image sizes and Gaussian counts"""
    repeats: int = 7
    """timed runs of the cpu backend per size (median)"""
    torch_repeats: int = 3
    """timed runs of the torch reference per size"""
    skip_torch: bool = False
    """do not time the (slow) torch reference"""


def _handler(args: BenchRasterizer) -> int:
    import json

    sizes = list(args.sizes or DEFAULT_SIZES)
    for text in sizes:
        parse_size(text)
    for option, value in (("--repeats", args.repeats), ("--torch-repeats", args.torch_repeats)):
        if value < 1:
            raise UsageError(option, f"must be >= 1, got {value}")
    if args.json is not None and args.json.is_dir():
        raise UsageError("--json", f"{args.json} is a folder; give a .json file")
    results = run_benchmark(sizes, args.repeats, args.torch_repeats, skip_torch=args.skip_torch)
    print(format_table(results))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2))
        print(f"wrote {args.json}")
    return 0


def register(cli) -> None:
    """Add `tacsplat bench rasterizer`."""
    cli.typed("bench rasterizer", BenchRasterizer, _handler)
