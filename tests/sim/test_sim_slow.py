"""Longer simulator runs (marked slow: `make bench-quick` runs it; many grasps per object: tests/acquisition)."""

import json  # noqa: E402

import pytest  # noqa: E402

from tacsplat.apps.bench_sim import run_bench  # noqa: E402


@pytest.mark.slow
def test_bench_sim_quick(tmp_path):
    report = run_bench(tmp_path, quick=True)
    data = json.loads((tmp_path / "sim.json").read_text())
    assert (tmp_path / "sim.png").stat().st_size > 0 and "Penetration" in report
    plane = [r for r in data["tactile"] if r["surface"] == "plane"]
    assert all(r["max_depth_error_um"] < 0.01 for r in plane)
    sphere = [r for r in data["tactile"] if r["surface"] == "sphere"]
    assert all(r["max_depth_error_um"] < 1.0 for r in sphere)
    assert all(r["max_penetration_mm"] < 1.0 for r in data["physics"])
