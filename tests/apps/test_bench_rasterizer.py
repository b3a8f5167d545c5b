"""`tacsplat bench rasterizer`: argument parsing and one timing row (no timings asserted)."""

from __future__ import annotations

import pytest

from tacsplat.apps.bench_rasterizer import _time_backend, parse_size, random_scene
from tacsplat.errors import ConfigError


def test_parse_size():
    assert parse_size("256x128:20000") == (256, 128, 20000)
    with pytest.raises(ConfigError, match="--sizes"):
        parse_size("256:20000")


def test_random_scene_radii_and_timing_row():
    scene = random_scene(300, 64, 48, sh_degree=3, radius_px=(1.0, 8.0), seed=0)
    row = _time_backend(scene, "cpu", repeats=1)
    assert row["visible_gaussians"] > 250
    assert row["n_pairs"] > row["n_intersections"] > 0
    assert row["forward_ms"] > 0 and row["forward_backward_ms"] > 0


def test_cli_registers_bench_rasterizer():
    from tacsplat.apps.bench_rasterizer import BenchRasterizer
    from tacsplat.cli import build_parser
    from tacsplat.options import parse_options

    assert callable(build_parser().parse_args(["bench", "rasterizer"]).func)
    args = parse_options(BenchRasterizer, ["--sizes", "64x64:100", "--repeats", "2"], "tacsplat bench rasterizer")
    assert args.sizes == ("64x64:100",) and args.repeats == 2
