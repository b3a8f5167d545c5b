"""`tacsplat bench step` (phase profile of a training step) and `tacsplat bench compare` (no timings asserted)."""

from __future__ import annotations

import json
import time

import pytest

from tacsplat.apps.bench_compare import compare, flatten, format_comparison, read_results
from tacsplat.apps.bench_step import PHASES, PhaseTimer, summarize
from tacsplat.cli import main
from tacsplat.errors import InvalidInputError


def test_phase_timer_counts_a_nested_phase_once():
    timer = PhaseTimer()
    with timer.phase("outer"):
        time.sleep(0.02)
        with timer.phase("inner"):
            time.sleep(0.2)
    totals = timer.take()
    assert 0.02 <= totals["outer"] < 0.2  # the inner phase's 200 ms paused the outer one
    assert totals["inner"] >= 0.2
    assert timer.take() == {}


def test_summarize_leaves_out_the_warm_up_and_sums_the_phases():
    steps = [{"SSIM": 1.0, "optimiser": 1.0, "n_gaussians": 10}] * 2 + [
        {"SSIM": 0.002, "optimiser": 0.001, "rest": 0.001, "n_gaussians": 100 + i} for i in range(5)
    ]
    s = summarize(steps, warmup=2)
    assert s["steps_timed"] == 5
    assert s["step_median_ms"] == pytest.approx(4.0)
    assert s["phases"]["SSIM"]["median_ms"] == pytest.approx(2.0)
    assert s["phases"]["composite forward"]["median_ms"] == 0.0
    assert s["n_gaussians_final"] == 104 and set(s["phases"]) == set(PHASES)


def test_compare_matches_list_rows_by_label_and_gives_ratios():
    a = {
        "sizes": [
            {"width": 64, "height": 64, "n_gaussians": 10, "cpu": {"forward_ms": 2.0}},
            {"width": 128, "height": 64, "n_gaussians": 10, "cpu": {"forward_ms": 8.0}},
        ],
        "per_step": [1.0, 2.0],
        "ok": True,
    }
    b = {"sizes": [{"width": 128, "height": 64, "n_gaussians": 10, "cpu": {"forward_ms": 4.0}}]}
    assert flatten(a) == {
        "sizes.64x64:10.width": 64.0,
        "sizes.64x64:10.height": 64.0,
        "sizes.64x64:10.n_gaussians": 10.0,
        "sizes.64x64:10.cpu.forward_ms": 2.0,
        "sizes.128x64:10.width": 128.0,
        "sizes.128x64:10.height": 64.0,
        "sizes.128x64:10.n_gaussians": 10.0,
        "sizes.128x64:10.cpu.forward_ms": 8.0,
    }
    rows = {key: (va, vb, r) for key, va, vb, r in compare(a, b, match="_ms")}
    assert rows == {
        "sizes.64x64:10.cpu.forward_ms": (2.0, None, None),
        "sizes.128x64:10.cpu.forward_ms": (8.0, 4.0, 0.5),
    }
    assert "0.500" in format_comparison(compare(a, b, match="_ms"), "a.json", "b.json")


def test_compare_refuses_a_missing_or_broken_file(tmp_path):
    with pytest.raises(InvalidInputError, match="no such file"):
        read_results(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(InvalidInputError, match="bad.json"):
        read_results(tmp_path / "bad.json")


def test_bench_step_writes_its_table_json_and_png_and_compare_reads_them(tmp_path, capsys):
    out = tmp_path / "step"
    assert main(["bench", "step", "--out", str(out), "--resolutions", "16", "--iterations", "12"]) == 0
    results = json.loads((out / "step.json").read_text())
    assert (out / "step.png").stat().st_size > 0
    (row,) = results["resolutions"]
    assert row["label"] == "16px" and row["steps_timed"] == 2 and len(row["per_step"]) == 12
    assert row["phases"]["composite forward"]["median_ms"] > 0 and row["phases"]["optimiser"]["median_ms"] > 0
    assert row["step_median_ms"] > 0
    table = capsys.readouterr().out
    assert "composite backward" in table and "step.json" in table
    assert main(["bench", "compare", str(out / "step.json"), str(out / "step.json"), "--match", "step_median"]) == 0
    assert "resolutions.16px.step_median_ms" in capsys.readouterr().out


def test_bench_step_refuses_too_few_iterations(tmp_path):
    assert main(["bench", "step", "--out", str(tmp_path), "--iterations", "5"]) == 2


def test_bench_step_with_a_reference_profiles_both_back_to_back_and_prints_their_ratio(tmp_path, capsys):
    out = tmp_path / "step"
    assert (
        main(
            [
                "bench",
                "step",
                "--out",
                str(out),
                "--resolutions",
                "16",
                "--iterations",
                "12",
                "--method",
                "paper+n",
                "--reference",
                "paper",
                "--rounds",
                "3",
            ]
        )
        == 0
    )
    results = json.loads((out / "step.json").read_text())
    (row,), (ref,) = results["resolutions"], results["reference"]
    assert results["settings"]["reference"] == "paper" and results["settings"]["method"] == "paper+n"
    ratio = row["ratio_to_reference"]
    assert (
        len(ratio["rounds"]) == 3 and ratio["rounds"][0]["step_median"] == row["step_median_ms"] / ref["step_median_ms"]
    )
    assert ratio["step_median"] == sorted(r["step_median"] for r in ratio["rounds"])[1]
    assert "paper+n / paper (each run next to its reference): step median" in capsys.readouterr().out
    assert main(["bench", "step", "--out", str(out), "--rounds", "2"]) == 2  # rounds without a reference
    assert main(["bench", "step", "--out", str(out), "--reference", "nonsense"]) != 0
    assert "--reference" in capsys.readouterr().err
