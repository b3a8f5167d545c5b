"""Fast tests of the benchmark writers (results.csv, report.md tables, plots), the resumability of
`bench paper` and the touch subsampling of `bench touches`, on small synthetic results."""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace

import cv2
import numpy as np
import pytest

from tacsplat.apps import batch, paper_bench
from tacsplat.apps.paper_bench import PaperBench, PaperBenchConfig, step_work
from tacsplat.apps.report import (
    RESULT_COLUMNS,
    best_rows,
    markdown_table,
    metric_table,
    plot_cd_bars,
    render_grid,
    write_csv,
)
from tacsplat.apps.touch_bench import subsample_touches, summarise, write_touch_report
from tacsplat.errors import ConfigError
from tacsplat.reconstruction.methods import DEFAULT_METHOD


def synthetic_rows() -> list[dict]:
    """Two objects; 'paper' has the lowest CD on the teapot, '3dgs+t' on the bell; '3dgs' the best PSNR on the bell."""
    cd = {
        ("teapot", "3dgs"): 0.02,
        ("teapot", "3dgs+s"): 0.015,
        ("teapot", "3dgs+t"): 0.01,
        ("teapot", "paper"): 0.005,
        ("bell", "3dgs"): 0.03,
        ("bell", "3dgs+s"): 0.02,
        ("bell", "3dgs+t"): 0.004,
        ("bell", "paper"): 0.006,
    }
    psnr = {
        ("teapot", "3dgs"): 20.0,
        ("teapot", "3dgs+s"): 21.0,
        ("teapot", "3dgs+t"): 22.0,
        ("teapot", "paper"): 23.0,
        ("bell", "3dgs"): 25.0,
        ("bell", "3dgs+s"): 24.0,
        ("bell", "3dgs+t"): 23.0,
        ("bell", "paper"): 22.0,
    }
    return [
        {
            "object": o,
            "setting": "minimal",
            "method": v,
            "seed": 0,
            "cd": cd[o, v],
            "cd_paper": cd[o, v] ** 2,
            "psnr": psnr[o, v],
            "ssim": 0.9,
            "train_seconds": 10.0,
            "num_gaussians": 1000,
        }
        for (o, v) in cd
    ]


def test_metric_table_layout_and_average():
    objects, methods, values = metric_table(synthetic_rows(), "cd", "minimal")
    assert objects == ["teapot", "bell"]
    assert methods == ["3dgs", "3dgs+s", "3dgs+t", "paper"]
    assert values.shape == (4, 3)
    np.testing.assert_allclose(values[3], [0.005, 0.006, 0.0055])
    np.testing.assert_allclose(values[:, -1], values[:, :2].mean(axis=1))


def test_best_per_column_bold_lower_and_higher():
    rows = synthetic_rows()
    cd_lines = markdown_table(rows, "cd", "minimal").splitlines()
    header = next(line for line in cd_lines if line.startswith("| Method"))
    assert header == "| Method | teapot | bell | Avg. |"
    full = next(line for line in cd_lines if line.startswith("| Paper"))
    plus_t = next(line for line in cd_lines if line.startswith("| 3DGS + T"))
    assert full == "| Paper (T + S) | **0.0050** | 0.0060 | **0.0055** |"
    assert plus_t == "| 3DGS + T | 0.0100 | **0.0040** | 0.0070 |"
    psnr_lines = markdown_table(rows, "psnr", "minimal").splitlines()
    vanilla = next(line for line in psnr_lines if line.startswith("| 3DGS |"))
    # every method averages 22.5 dB: a tie marks them all
    assert vanilla == "| 3DGS | 20.00 | **25.00** | **22.50** |"
    full_psnr = next(line for line in psnr_lines if line.startswith("| Paper"))
    assert full_psnr == "| Paper (T + S) | **23.00** | 22.00 | **22.50** |"


def test_best_rows_ties_and_missing():
    values = np.array([[1.0, np.nan, 2.0], [1.0, np.nan, 3.0]])
    assert best_rows(values, "lower") == [{0, 1}, set(), {0}]
    assert best_rows(values, "higher") == [{0, 1}, set(), {1}]


def test_best_signed_value_is_the_one_nearest_zero():
    values = np.array([[0.03, -0.01, np.nan], [-0.02, 0.01, 0.5], [0.05, 0.2, np.nan]])
    assert best_rows(values, "zero") == [{1}, {0, 1}, {1}]


def test_values_equal_as_printed_are_both_bold():
    rows = synthetic_rows()
    rows[0]["cd"], rows[3]["cd"] = 0.00501, 0.00499  # teapot 3dgs and full both print as 0.0050
    lines = markdown_table(rows, "cd", "minimal").splitlines()
    assert next(line for line in lines if line.startswith("| 3DGS |")).startswith("| 3DGS | **0.0050** |")
    assert next(line for line in lines if line.startswith("| Paper")).startswith("| Paper (T + S) | **0.0050** |")


def test_missing_run_shows_dash_and_is_not_best():
    rows = [r for r in synthetic_rows() if not (r["object"] == "teapot" and r["method"] == "paper")]
    lines = markdown_table(rows, "cd", "minimal").splitlines()
    full = next(line for line in lines if line.startswith("| Paper"))
    assert full.startswith("| Paper (T + S) | – |")
    assert "**0.0100**" in next(line for line in lines if line.startswith("| 3DGS + T"))


def test_seed_spread_column_with_several_seeds():
    """With two seeds the table gains the standard deviation of the per-seed averages over objects; a method
    missing an object on one seed has too few complete seeds and shows a dash."""
    rows = []
    for seed, shift in ((0, 0.0), (1, 0.002)):
        for row in synthetic_rows():
            rows.append({**row, "seed": seed, "cd": row["cd"] + shift})
    rows = [r for r in rows if not (r["method"] == "3dgs" and r["object"] == "bell" and r["seed"] == 1)]
    assert "Seed s.d." not in markdown_table(synthetic_rows(), "cd", "minimal")  # one seed: no column
    lines = markdown_table(rows, "cd", "minimal").splitlines()
    assert (
        next(line for line in lines if line.startswith("| Method")) == "| Method | teapot | bell | Avg. | Seed s.d. |"
    )
    # full's averages over objects are 0.0055 and 0.0075: s.d. (ddof 1) 0.0014142
    assert next(line for line in lines if line.startswith("| Paper")).endswith("| 0.0014 |")
    assert next(line for line in lines if line.startswith("| 3DGS |")).endswith("| – |")
    assert any(line.startswith("*Seed s.d.:") for line in lines)


def test_results_csv_roundtrip(tmp_path):
    rows = synthetic_rows()
    rows[0]["cd"] = None  # a run without ground truth
    path = write_csv(rows, tmp_path / "results.csv", RESULT_COLUMNS)
    with path.open() as fh:
        assert next(csv.reader(fh)) == list(RESULT_COLUMNS)
    with path.open() as fh:
        back = list(csv.DictReader(fh))
    assert len(back) == len(rows) and back[0]["cd"] == ""
    assert [(r["object"], r["method"], float(r["psnr"])) for r in back[1:]] == [
        (r["object"], r["method"], r["psnr"]) for r in rows[1:]
    ]


def test_plots_are_written(tmp_path):
    png = plot_cd_bars(synthetic_rows(), "minimal", tmp_path / "cd.png")
    assert cv2.imread(str(png)) is not None
    gt_depth = np.zeros((8, 10), np.float32)
    gt_depth[2:6, 3:7] = 0.3
    panels = {"3dgs": (np.full((8, 10, 3), 0.5), gt_depth + 0.01), "paper": (np.zeros((8, 10, 3)), gt_depth)}
    grid = render_grid(panels, np.ones((8, 10, 3)), gt_depth, tmp_path / "grid.png")
    assert cv2.imread(str(grid)) is not None
    grid = render_grid(panels, np.ones((8, 10, 3)), np.zeros((8, 10), np.float32), tmp_path / "no_gt.png")
    assert cv2.imread(str(grid)) is not None


def test_bench_rows_and_config_errors():
    from tacsplat.apps.paper_bench import ablation_rows, bench_row, row_config
    from tacsplat.reconstruction.methods import METHODS, get_method, mechanisms, method_config, method_of

    for name in METHODS:  # a method is a row without overrides
        assert bench_row(name) == (name, {}) and method_of(row_config(name)) == name
    for name, (method, overrides) in ablation_rows().items():  # each row changes its method's mechanisms or pixels
        assert method in METHODS and overrides and row_config(name) != method_config(method)
        config = row_config(name)
        assert mechanisms(config) != mechanisms(method_config(method)) or config.coarse_factors or config.crop_margin
    assert not row_config("default-touch").use_touch and row_config("paper+n").lambda_flatten == 10.0
    with pytest.raises(ConfigError, match="--methods: unknown method 'ours'; choose one of .* or a row of ablations"):
        bench_row("ours")
    assert get_method("3dgs").overrides == {
        "use_touch": False,
        "lambda_s": 0.0,
        "lambda_flatten": 0.0,
        "lambda_depth_normal": 0.0,
        "appearance": "sh",
        "lambda_albedo_smoothness": 0.0,
        "init.colors_from_views": False,
    }
    with pytest.raises(ConfigError, match="method"):
        get_method("ours")
    with pytest.raises(ConfigError, match="methods"):
        PaperBench("x", PaperBenchConfig(methods=("3dgs", "ours")))
    with pytest.raises(ConfigError, match="full_views"):
        PaperBench("x", PaperBenchConfig(full_views=10))
    with pytest.raises(ConfigError, match="objects"):
        PaperBench("x", PaperBenchConfig(objects=("sphere",)))
    with pytest.raises(ConfigError, match="texture"):
        PaperBench("x", PaperBenchConfig(texture="plaid"))


def test_finished_runs_trained_with_other_settings_are_named_in_the_report(tmp_path, monkeypatch):
    """A finished run whose config.json differs from what the bench trains its method with now (a default
    changed since) is listed with what differs, and report.md says so; a setting that the method's config does not
    use, then or now, does not count (the albedo smoothness's weights, from before they existed, and the start of
    the depth-normal consistency of a `full` run, which has none)."""
    config = PaperBenchConfig(
        objects=("teapot",), settings=("minimal",), seeds=(0, 1), methods=("paper", DEFAULT_METHOD)
    )
    bench = PaperBench(tmp_path, config)
    for run in bench.runs():
        _finish(run, 0.03)
        recorded = bench.reconstruct_job(run).config().to_json()
        del recorded["albedo_smoothness_beta"]  # written before the setting existed
        recorded["depth_normal_start_iter"] = 300  # the default until 2026-11-25
        (run.out / "config.json").write_text(json.dumps(recorded))
    stale = bench.stale_runs()
    assert [(run.method, run.seed, changes) for run, changes in stale] == [
        (DEFAULT_METHOD, seed, ["depth_normal_start_iter 300 -> 700", "albedo_smoothness_beta 0.0 -> 10.0"])
        for seed in (0, 1)
    ]
    depth = np.full((8, 8), 0.3, np.float32)
    normal = np.broadcast_to(np.array([0.0, 0.0, -1.0], np.float32), (8, 8, 3))
    monkeypatch.setattr(
        paper_bench,
        "render_first_test_view",
        lambda runs, cache=None: (
            {r.method: (np.zeros((8, 8, 3)), depth, normal) for r in runs},
            np.ones((8, 8, 3)),
            depth,
            normal,
            np.ones((8, 8), bool),
        ),
    )
    bench.run(progress=False)
    report = (tmp_path / "report.md").read_text()
    assert "2 run(s) were trained with other settings" in report  # one group: same method, same change
    assert (
        f"{DEFAULT_METHOD} (depth_normal_start_iter 300 -> 700, albedo_smoothness_beta 0.0 -> 10.0), 2 run(s): "
        f"runs/teapot/minimal/{DEFAULT_METHOD}-s0, runs/teapot/minimal/{DEFAULT_METHOD}-s1"
    ) in report


def test_textured_objects_get_their_own_scenes_and_runs(tmp_path):
    """--texture checker captures textured scenes in their own folders and its runs never mix with the glossy
    ones in one report folder; the batch job's choices are the twin's."""
    from typing import get_args, get_type_hints

    from tacsplat.sim.objects import TEXTURES

    plain, textured = (
        PaperBench(tmp_path, PaperBenchConfig(objects=("torus",), settings=("minimal",), methods=("paper",), texture=t))
        for t in TEXTURES
    )
    assert [r.scene.name for r in plain.runs()] == ["minimal-s0"]
    assert [r.scene.name for r in textured.runs()] == ["minimal-s0-checker"]
    assert [r.out.name for r in textured.runs()] == ["paper-s0-checker"]
    job = textured.capture_job("torus", "minimal", 0)
    assert job.texture == "checker" and job.rig().sim.texture == "checker"
    assert get_args(get_type_hints(batch.CaptureJob)["texture"]) == TEXTURES


def _finish(run, cd: float) -> None:
    """What a finished run leaves behind (for the report): metrics.json and progress.csv."""
    run.out.mkdir(parents=True, exist_ok=True)
    (run.out / "metrics.json").write_text(
        json.dumps(
            {
                "cd": cd,
                "psnr": 20.0,
                "ssim": 0.8,
                "normal_error_deg": 1000 * cd,
                "train_seconds": 5.0,
                "num_gaussians": 100,
            }
        )
    )
    from tacsplat.reconstruction.run_dir import PROGRESS_COLUMNS

    rows = [
        {"iteration": 0, "seconds": 0.0, "psnr": 10, "cd": 0.1},
        {"iteration": 100, "seconds": 5.0, "psnr": 20, "cd": cd},
    ]
    lines = [",".join(PROGRESS_COLUMNS)] + [",".join(str(r.get(k, 0)) for k in PROGRESS_COLUMNS) for r in rows]
    (run.out / "progress.csv").write_text("\n".join(lines) + "\n")
    (run.out / "checkpoint.pt").write_bytes(b"")  # (what the render grid draws from: the tests render no checkpoint)


def test_resume_skips_finished_runs(tmp_path, monkeypatch):
    config = PaperBenchConfig(objects=("teapot",), settings=("minimal",), methods=("3dgs", "paper"))
    bench = PaperBench(tmp_path, config)
    first, second = bench.runs()
    _finish(first, 0.02)
    trained = []

    def capture(job):
        return {"scene": str(job.out)}

    def train(job):
        run = next(r for r in bench.runs() if r.out == job.out)
        trained.append(run.method)
        _finish(run, 0.01)
        return json.loads((run.out / "metrics.json").read_text())

    rendered, drawn = [], []  # the runs of each call; the runs each call had to render (not in its cache)

    def render_first_test_view(runs, cache=None):
        rendered.append([r.method for r in runs])
        cache = {} if cache is None else cache
        drawn.extend(r.method for r in runs if r.out not in cache)
        cache.update({r.out: None for r in runs})
        depth = np.full((8, 8), 0.3, np.float32)
        normal = np.broadcast_to(np.array([0.0, 0.0, -1.0], np.float32), (8, 8, 3))
        seen = np.ones((8, 8), bool)
        return {r.method: (np.zeros((8, 8, 3)), depth, normal) for r in runs}, np.ones((8, 8, 3)), depth, normal, seen

    monkeypatch.setattr(batch.CaptureJob, "__call__", capture)
    monkeypatch.setattr(batch.ReconstructJob, "__call__", train)
    monkeypatch.setattr(paper_bench, "render_first_test_view", render_first_test_view)
    rows = bench.run(progress=False)
    assert trained == ["paper"]  # the 3dgs run had its metrics.json
    assert {r["method"]: r["cd"] for r in rows} == {"3dgs": 0.02, "paper": 0.01}
    report = (tmp_path / "report.md").read_text()
    assert "| Paper (T + S) | **0.0100** | **0.0100** |" in report
    assert "Normal error, degrees (↓)" in report and "| Paper (T + S) | **10.0** | **10.0** |" in report
    for name in ("results.csv", "cd_minimal.png", "error_vs_time_minimal.png", "renders_teapot_minimal.png"):
        assert (tmp_path / name).is_file(), name
    assert rendered[-1] == ["3dgs", "paper"]  # the grid shows every finished run
    assert drawn == ["paper", "3dgs"]  # full while the batch ran (pictures prepared), 3dgs (finished before) at the end
    trained.clear()
    bench.run(progress=False)
    assert trained == []  # everything finished: nothing retrained


def test_each_capture_starts_its_costliest_methods_first(tmp_path):
    """Runs of one capture are started most work per step first (the longest no longer starts last on few
    cores); captures and settings keep the order of runs()."""
    config = PaperBenchConfig(
        objects=("teapot", "bell"), settings=("minimal",), methods=("3dgs", "paper", "paper+n", "3dgs+t")
    )
    names = [job.name.split("/")[-1] if run else job.name for run, job in PaperBench(tmp_path, config).jobs()]
    assert names == [
        "capture scenes/teapot/minimal-s0",
        "paper+n-s0",
        "paper-s0",
        "3dgs+t-s0",
        "3dgs-s0",
        "capture scenes/bell/minimal-s0",
        "paper+n-s0",
        "paper-s0",
        "3dgs+t-s0",
        "3dgs-s0",
    ]
    assert step_work("3dgs") < step_work("3dgs+s") == step_work("3dgs+t") < step_work("paper") < step_work("paper+n")
    assert step_work("paper+n") < step_work("default-vc")


def _small_scene(path, meta=None):
    from tacsplat.datasets import SceneMeta, SceneWriter, SensorModel
    from tacsplat.geometry import look_at
    from tacsplat.types import CameraIntrinsics

    sensor = SensorModel(name="gel", width_px=6, height_px=5, pixel_size_m=5e-4, gel_thickness_m=2e-3)
    intr = CameraIntrinsics(np.array([[10.0, 0, 6], [0, 10.0, 4], [0, 0, 1]]), 12, 8)
    with SceneWriter.create(path, intr, meta or SceneMeta(source="sim", object="cube"), sensor) as writer:
        for i, split in enumerate(("train", "train", "test")):
            image = np.full((8, 12, 3), 40 * i, np.uint8)
            writer.add_frame(
                image,
                look_at([0.3, 0.1 * i, 0.2], [0, 0, 0]),
                split,
                gt_depth=np.full((8, 12), 0.3, np.float32) if split == "test" else None,
            )
        for t in range(6):  # touches 1 and 4 miss
            depth = np.zeros((5, 6), np.float32)
            if t not in (1, 4):
                depth[2, 3] = 1e-3 * (t + 1)
            writer.add_touch(depth, np.eye(4), grasp=t // 3, finger=f"f{t % 3}")


def test_subsample_keeps_first_touches_in_contact(tmp_path):
    from tacsplat.datasets import Scene

    _small_scene(tmp_path / "base")
    assert subsample_touches(tmp_path / "base", tmp_path / "t3", 3) == 3
    copy = Scene.load(tmp_path / "t3")
    base = Scene.load(tmp_path / "base")
    assert [t.in_contact for t in copy.touches] == [True] * 3
    assert [copy.load_touch_depth(t).max() for t in copy.touches] == pytest.approx([1e-3, 3e-3, 4e-3])
    assert [(f.split, f.id) for f in copy.frames] == [(f.split, f.id) for f in base.frames]
    np.testing.assert_array_equal(copy.load_image(copy.frames[1]), base.load_image(base.frames[1]))
    assert copy.gt_depth(copy.frames[2]) is not None
    assert subsample_touches(tmp_path / "base", tmp_path / "t10", 10) == 4  # only 4 in contact
    assert subsample_touches(tmp_path / "base", tmp_path / "t0", 0) == 0
    assert Scene.load(tmp_path / "t0").touches == []


def test_touch_bench_trains_the_method_it_is_asked_for(tmp_path):
    from tacsplat.apps.touch_bench import TouchBench, TouchBenchConfig

    for config, method in ((TouchBenchConfig(), "paper"), (TouchBenchConfig(method=DEFAULT_METHOD), DEFAULT_METHOD)):
        runs = [job for job in TouchBench(tmp_path, config).jobs() if isinstance(job, batch.ReconstructJob)]
        assert len(runs) == 18 and {job.method for job in runs} == {method}
    with pytest.raises(ConfigError, match="method: unknown method 'ours'"):
        TouchBench(tmp_path, TouchBenchConfig(method="ours"))


def test_touch_bench_runs_its_jobs_and_resumes(tmp_path, monkeypatch):
    from tacsplat.apps.touch_bench import TouchBench, TouchBenchConfig

    captured, trained = _fake_touch_jobs(monkeypatch)
    bench = TouchBench(tmp_path, TouchBenchConfig(object="teapot", touch_counts=(0, 3, 10), seeds=(0, 1)))
    rows = bench.run(progress=False)
    assert captured == ["teapot-s0", "teapot-s1"]
    assert trained == [f"teapot/t{n:03d}-s{s}" for s in (0, 1) for n in (0, 3, 10)]
    assert [(r["seed"], r["requested_touches"], r["touches"], r["cd"]) for r in rows] == [
        (s, n, k, 0.01 * (1 + s)) for s in (0, 1) for n, k in ((0, 0), (3, 3), (10, 4))
    ]  # 4 touches in contact
    assert (tmp_path / "touches.csv").is_file() and (tmp_path / "summary.csv").is_file()

    shutil.rmtree(tmp_path / "runs" / "teapot" / "t003-s1")  # a run to do again; its copy is there
    captured.clear(), trained.clear()
    assert len(bench.run(progress=False)) == 6
    assert captured == [] and trained == ["teapot/t003-s1"]

    runs = [job for job in bench.jobs() if isinstance(job, batch.ReconstructJob)]
    assert {job.method for job in runs} == {"paper"}  # the paper's method, as its Fig. 6
    stale = replace(runs[0], method=DEFAULT_METHOD).config()  # a run trained with other settings ...
    (runs[0].out / "config.json").write_text(json.dumps(stale.to_json()))
    (runs[-1].out / "metrics.json").unlink()  # a run still to do, which the refusal must come before
    trained.clear()
    with pytest.raises(ConfigError, match="--out.*teapot/t000-s0 was trained with other settings"):
        bench.run(progress=False)  # ... is refused before any job runs
    assert trained == []


def test_touch_summary_and_plot(tmp_path):
    rows = [
        {
            "seed": s,
            "requested_touches": n,
            "touches": n,
            "cd": 0.01 / (1 + n) + 0.001 * s,
            "psnr": 20.0 + s,
            "ssim": 0.9,
            "train_seconds": 1.0,
            "num_gaussians": 10,
        }
        for s in (0, 1)
        for n in (0, 4, 8)
    ]
    summary = summarise(rows)
    assert [s["requested_touches"] for s in summary] == [0, 4, 8]
    assert summary[0]["cd_mean"] == pytest.approx(0.0105)
    assert summary[0]["cd_std"] == pytest.approx(0.0005 * 2**0.5)  # over seeds, as report.seed_spread (ddof 1)
    paths = write_touch_report(tmp_path, rows, "paper")
    assert cv2.imread(str(paths["plot"])) is not None
    with paths["summary"].open() as fh:
        assert len(list(csv.DictReader(fh))) == 3


def test_full_vs_vanilla_sentence():
    from tacsplat.apps.paper_bench import full_vs_vanilla

    text = full_vs_vanilla(synthetic_rows(), "minimal")
    assert "lower CD on 2 of 2 objects" in text and "0.0055 vs 0.0250" in text
    assert full_vs_vanilla([r for r in synthetic_rows() if r["method"] != "paper"], "minimal") == ""


def test_default_vs_full_sentence():
    from tacsplat.apps.paper_bench import default_vs_full
    from tacsplat.reconstruction.methods import DEFAULT_METHOD

    rows = synthetic_rows()
    assert default_vs_full(rows, "minimal") == ""  # no default-method runs
    rows += [
        {**r, "method": DEFAULT_METHOD, "cd": r["cd"] * (0.5 if r["object"] == "teapot" else 1.5)}
        for r in synthetic_rows()
        if r["method"] == "paper"
    ]
    text = default_vs_full(rows, "minimal")  # teapot 0.0025 (< 0.005), bell 0.009 (> 0.006)
    assert "lower CD on 1 of 2 objects" in text and "0.0058 vs 0.0055 (+5%)" in text


def test_coverage_sentence():
    from tacsplat.apps.paper_bench import coverage_sentence

    assert coverage_sentence(synthetic_rows(), "minimal") == ""  # no ground-truth mesh: no split
    rows = [
        {**r, "unseen_fraction": 0.1 if r["object"] == "teapot" else 0.3, "cd_seen": r["cd"], "cd_unseen": 2 * r["cd"]}
        for r in synthetic_rows()
    ]
    text = coverage_sentence(rows, "minimal")
    assert "20% of the test views' surface" in text and "teapot 10%, bell 30%" in text
    assert "Paper (T + S) 0.0110 vs 0.0055" in text


def test_where_we_stand_puts_the_papers_numbers_beside_ours_and_lists_departures():
    from tacsplat.apps.paper_bench import where_we_stand

    text = where_we_stand(synthetic_rows(), PaperBenchConfig(iterations=1500, resolution=128))
    table = {
        line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
        for line in text.splitlines()
        if line.startswith("| ") and "---" not in line
    }
    assert table["3DGS (ours)"] == ["0.00040", "0.00090", "0.00065"]  # cd_paper = cd^2 in the synthetic rows
    assert table["full (paper)"] == ["0.0022", "0.0082", "0.0026"] and table["3DGS (paper)"][2] == "0.0111"
    # 3DGS/full: our CD 0.025/0.0055 = 4.55x, cd_paper 0.00065/0.0000305 = 21.31x, the paper's 4.3x
    assert "4.55x in our CD, 21.31x in the paper's CD (the paper: 4.3x)" in text
    assert "touches: gel contact patches" in text and "resolution 128 px" in text
    assert "surface normals" not in text  # the departures of the paper's full method, not of the default method
    paper = where_we_stand(
        synthetic_rows(), PaperBenchConfig(preset="paper", touch_model="paper", iterations=30000, resolution=800)
    )
    assert "touches:" not in paper and "resolution" not in paper and "steps" not in paper.split("in force")[1]


def test_scaling_report_draws_any_methods_on_one_figure(tmp_path, monkeypatch):
    from tacsplat.apps import report
    from tacsplat.apps.bench_scaling import write_scaling_report

    rows = [
        {
            "resolution": r,
            "iterations": n,
            "method": v,
            "cd": 0.04 / k,
            "cd_paper": 0.004 / k,
            "psnr": 20.0 + k,
            "ssim": 0.8,
            "train_seconds": 10.0 * k * r / 128,
            "num_gaussians": 1000,
        }
        for r in (128, 256)
        for k, n in ((1, 750), (2, 1500))
        for v in ("default", "default+c2f75")
    ]
    figures = []
    save = report.save_figure
    monkeypatch.setattr(report, "save_figure", lambda fig, path: figures.append(fig) or save(fig, path))
    text = write_scaling_report(tmp_path, rows, "teapot").read_text()
    assert "| px | steps | method | train s | CD | PSNR |" in text and "scaling.png" in text
    assert "| 128 | 750 | default+c2f75 | 10 | 0.0400 | 21.00 |" in text and text.count("\n| 256 |") == 4
    csv_rows = read_results_rows(tmp_path / "scaling.csv")
    assert len(csv_rows) == 8 and {"cd", "cd_paper", "psnr", "train_seconds"} <= set(csv_rows[0])
    assert cv2.imread(str(tmp_path / "scaling.png")) is not None
    ((ax_cd, ax_psnr),) = [fig.axes for fig in figures]  # one figure, two panels
    assert ax_cd.get_yscale() == "log" and len(ax_cd.lines) == len(ax_psnr.lines) == 4  # (px, method) curves
    assert [len(line.get_xdata()) for line in ax_cd.lines] == [2] * 4  # a point per step count
    assert [t.get_text() for t in ax_cd.get_legend().get_texts()] == ["Default (ours)", "default+c2f75"]
    assert [t.get_text() for t in ax_psnr.get_legend().get_texts()] == ["128 px", "256 px"]
    styles = {(line.get_marker(), line.get_linestyle(), tuple(line.get_color())) for line in ax_cd.lines}
    assert len(styles) == 4


def test_bench_scaling_refuses_an_unknown_method_before_it_runs(tmp_path, capsys):
    from tacsplat.cli import main

    out = tmp_path / "scaling"
    assert main(["bench", "scaling", "--out", str(out), "--methods", "default,nope", "--resolutions", "16"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("tacsplat bench scaling: error: --methods: unknown method 'nope'; choose one of ")
    assert "default+c2f75" in err and len(err.splitlines()) == 1 and not out.exists()
    assert main(["bench", "scaling", "--out", str(out), "--methods", " , "]) == 2
    assert "--methods: need at least one method" in capsys.readouterr().err and not out.exists()


def test_bench_scaling_captures_each_resolution_once(tmp_path):
    """Before: each step count's slice captured the same scene again into its own scenes/."""
    from tacsplat.apps.bench_scaling import scaling_benches

    slices = scaling_benches(tmp_path, "teapot", (32, 48), (20, 30), ("3dgs",))
    jobs = {(r, n): [job for _, job in bench.jobs()] for r, n, bench in slices}
    for (r, n), (capture, train) in jobs.items():
        assert capture.out == train.scene == tmp_path / f"{r}px-20steps" / "scenes" / "teapot" / "minimal-s0"
        assert train.out == tmp_path / f"{r}px-{n}steps" / "runs" / "teapot" / "minimal" / "3dgs-s0"
        assert train.needs == (capture.name,)
    assert jobs[32, 30][0].name == "capture ../32px-20steps/scenes/teapot/minimal-s0"


def read_results_rows(path):
    import csv

    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_the_report_says_how_its_jobs_ran(tmp_path):
    from tacsplat.apps.paper_bench import PaperBenchConfig, write_paper_report

    note = (
        " (jobs side by side as up to 2 worker processes: a run's train seconds include the time it shared the cores)"
    )
    write_paper_report(tmp_path, [], [], PaperBenchConfig(), wall_seconds=90.0, figures=False, wall_note=note)
    assert (
        f"Wall time of the last invocation: 1.5 min{note}; 0 of 0 runs finished."
        in (tmp_path / "report.md").read_text()
    )


def test_prepared_pictures_keep_only_the_latest_scene(tmp_path, monkeypatch):
    """The views rendered as runs finish are kept for one scene at a time (one grid's worth of images)."""
    config = PaperBenchConfig(objects=("teapot", "bell"), settings=("minimal",), methods=("3dgs", "paper"))
    bench = PaperBench(tmp_path, config)

    def render_first_test_view(runs, cache):
        cache.update({key: None for r in runs for key in (r.out, r.scene)})

    monkeypatch.setattr(paper_bench, "render_first_test_view", render_first_test_view)
    runs = {(r.object, r.method): r for r in bench.runs()}
    bench.prepare_pictures(runs["teapot", "paper"])
    bench.prepare_pictures(runs["teapot", "3dgs"])
    assert set(bench.first_views) == {
        runs["teapot", "paper"].out,
        runs["teapot", "3dgs"].out,
        runs["teapot", "paper"].scene,
    }
    bench.prepare_pictures(runs["bell", "3dgs"])  # another scene: the teapot's views go
    assert set(bench.first_views) == {runs["bell", "3dgs"].out, runs["bell", "3dgs"].scene}


def test_one_run_per_count_has_no_spread():
    rows = [{"seed": 0, "requested_touches": 4, "touches": 4, "cd": 0.01, "psnr": 20.0}]
    (line,) = summarise(rows)
    assert line["runs"] == 1 and np.isnan(line["cd_std"]) and np.isnan(line["psnr_std"])


def test_avg_is_over_every_object_or_none():
    """A method missing an object (a run still training, or failed) has no Avg.: averages over different objects
    are not compared, bolded or put in a sentence."""
    from tacsplat.apps.paper_bench import full_vs_vanilla

    rows = [r for r in synthetic_rows() if not (r["object"] == "bell" and r["method"] == "paper")]
    objects, methods, values = metric_table(rows, "cd", "minimal")
    assert np.isnan(values[methods.index("paper"), -1])
    assert values[methods.index("3dgs"), -1] == pytest.approx(0.025)
    lines = markdown_table(rows, "cd", "minimal").splitlines()
    assert next(line for line in lines if line.startswith("| Paper")) == "| Paper (T + S) | **0.0050** | – | – |"
    assert next(line for line in lines if line.startswith("| 3DGS + T")).endswith("| **0.0070** |")
    text = full_vs_vanilla(rows, "minimal")
    assert "lower CD on 1 of 1 objects" in text and "0.0050 vs" not in text and "nan" not in text


def _recorded_capture(job) -> None:
    """What a finished capture ``job`` leaves, without simulating: a small scene recording the job's settings
    (scene.json, as sim_capture records them) and its capture.json."""
    from tacsplat.acquisition.capture_scene import capture_settings, scene_meta

    _small_scene(job.out, scene_meta(capture_settings(job.rig()), {}))
    (job.out / batch.CAPTURE_MARKER).write_text("{}")


def _fake_touch_jobs(monkeypatch) -> tuple[list, list]:
    """The touch bench's captures and trainings made instant; the lists of the captures' and the runs' folders
    (relative to the bench's runs/ or scenes/) they were called for."""
    captured, trained = [], []

    def capture(job):
        captured.append(job.out.name)
        _recorded_capture(job)
        return {"scene": str(job.out)}

    def train(job):
        trained.append(f"{job.out.parent.name}/{job.out.name}")
        _finish(job, 0.01 * (1 + job.seed))
        return json.loads((job.out / "metrics.json").read_text())

    monkeypatch.setattr(batch.CaptureJob, "__call__", capture)
    monkeypatch.setattr(batch.ReconstructJob, "__call__", train)
    return captured, trained


def test_touch_bench_of_another_object_in_one_folder_trains_its_own_runs(tmp_path, monkeypatch):
    from tacsplat.apps.touch_bench import TouchBench, TouchBenchConfig

    captured, trained = _fake_touch_jobs(monkeypatch)
    for obj in ("teapot", "bell"):
        TouchBench(tmp_path, TouchBenchConfig(object=obj, touch_counts=(0, 4), seeds=(0,))).run(progress=False)
    assert captured == ["teapot-s0", "bell-s0"]
    assert trained == ["teapot/t000-s0", "teapot/t004-s0", "bell/t000-s0", "bell/t004-s0"]
    with (tmp_path / "touches.csv").open() as fh:
        assert [(r["object"], r["requested_touches"]) for r in csv.DictReader(fh)] == [("bell", "0"), ("bell", "4")]


def test_a_run_folder_names_a_scene_that_is_not_the_one_it_trained_on(tmp_path):
    """config.json records the scene's content; a job on other content (another scene, or the same changed) names
    it as a change; the same content moved elsewhere is none."""
    from tacsplat.datasets import Scene
    from tacsplat.reconstruction.run_dir import scene_record

    _small_scene(tmp_path / "a")
    _small_scene(tmp_path / "b")
    subsample_touches(tmp_path / "a", tmp_path / "fewer", 1)
    shutil.copytree(tmp_path / "a", tmp_path / "moved")
    job = batch.ReconstructJob(out=tmp_path / "r", scene=tmp_path / "a", iterations=20)
    job.out.mkdir()
    recorded = {**job.config().to_json(), "scene": scene_record(Scene.load(job.scene))}
    (job.out / "config.json").write_text(json.dumps(recorded))
    (job.out / "metrics.json").write_text("{}")
    assert job.changed_settings() == []
    assert replace(job, scene=tmp_path / "moved").changed_settings() == []
    assert replace(job, scene=tmp_path / "b").changed_settings() == []  # (the same frames and touches)
    (changed,) = replace(job, scene=tmp_path / "fewer").changed_settings()
    assert changed.startswith(f"scene: it was trained on the scene {tmp_path / 'a'} (content ")
    assert f"not on {tmp_path / 'fewer'} (content " in changed
    with pytest.raises(ConfigError, match=r"--out: .*r was trained with other settings \(scene: it was trained on "):
        replace(job, scene=tmp_path / "fewer").refuse_changed_settings()
    assert replace(job, scene=tmp_path / "nowhere").changed_settings() == []  # (no scene to compare)


def test_a_capture_folder_names_the_settings_that_changed_since(tmp_path):
    job = batch.CaptureJob(out=tmp_path / "s", resolution=32, test_views=2, seed=1)
    assert job.changed_settings() == []  # nothing captured yet
    _recorded_capture(job)
    assert job.changed_settings() == []
    assert set(replace(job, resolution=48, test_views=3).changed_settings()) == {
        "resolution 32 -> 48",
        "test_views 2 -> 3",
    }
    assert replace(job, object="bell").changed_settings() == ["object 'teapot' -> 'bell'"]
    assert replace(job, grasps=2).changed_settings() == ["grasps 5 -> 2"]
    assert replace(job, grasps=2).changed_settings(more_grasps_ok=True) == []  # (its first grasps are the same)
    assert replace(job, grasps=6).changed_settings(more_grasps_ok=True) == ["grasps 5 -> 6"]
    with pytest.raises(ConfigError, match=r"--out: .*s was captured with other settings \(resolution 32 -> 48\)"):
        replace(job, resolution=48).refuse_changed_settings()


def test_bench_paper_refuses_a_capture_made_with_other_settings(tmp_path, monkeypatch):
    """A rerun with another --resolution into the same folder is refused, not reported as if at the new size."""
    config = PaperBenchConfig(objects=("teapot",), settings=("minimal",), methods=("3dgs",), resolution=32)
    bench = PaperBench(tmp_path, config)
    (run,) = bench.runs()
    _recorded_capture(bench.capture_job(run.object, run.setting, run.seed))
    _finish(run, 0.02)
    monkeypatch.setattr(paper_bench, "render_first_test_view", _no_render)
    bench.run(progress=False)
    config.resolution = 48
    with pytest.raises(ConfigError, match=r"--out: .*minimal-s0 was captured with other settings \(resolution 32 "):
        PaperBench(tmp_path, config).run(progress=False)


def test_bench_touches_refuses_a_capture_with_too_few_grasps(tmp_path, monkeypatch):
    """The capture of a smaller largest count has too few grasps for a larger one: refused; one with more grasps
    than a smaller sweep needs serves it (its first grasps are the same)."""
    from tacsplat.apps.touch_bench import TouchBench, TouchBenchConfig

    captured, trained = _fake_touch_jobs(monkeypatch)
    TouchBench(tmp_path, TouchBenchConfig(touch_counts=(0, 4), seeds=(0,))).run(progress=False)
    bigger = TouchBench(tmp_path, TouchBenchConfig(touch_counts=(0, 4, 32), seeds=(0,)))
    with pytest.raises(ConfigError, match=r"--out: .*teapot-s0 was captured with other settings \(grasps 2 -> 12\)"):
        bigger.run(progress=False)
    captured.clear(), trained.clear()
    assert len(TouchBench(tmp_path, TouchBenchConfig(touch_counts=(4,), seeds=(0,))).run(progress=False)) == 1
    assert captured == trained == []


def _no_render(runs, cache=None):
    """render_first_test_view without a checkpoint to render."""
    depth = np.full((8, 8), 0.3, np.float32)
    return {r.method: (np.zeros((8, 8, 3)), depth) for r in runs}, np.ones((8, 8, 3)), depth, None, None


def test_an_interrupted_run_rerun_with_another_iterations_is_refused(tmp_path, monkeypatch):
    """A run interrupted, then rerun with another --iterations, is an error on --out naming the step counts (it
    would continue with the settings it started with, under the new count's heading), before anything runs."""
    config = PaperBenchConfig(objects=("teapot",), settings=("minimal",), methods=("3dgs",), iterations=40)
    bench = PaperBench(tmp_path, config)
    (run,) = bench.runs()
    run.out.mkdir(parents=True)
    started = replace(bench.reconstruct_job(run), iterations=400).config()
    (run.out / "config.json").write_text(json.dumps(started.to_json()))
    (run.out / "checkpoint.pt").write_bytes(b"")  # interrupted
    called = []
    monkeypatch.setattr(batch.CaptureJob, "__call__", lambda job: called.append(job.name))
    monkeypatch.setattr(batch.ReconstructJob, "__call__", lambda job: called.append(job.name))
    with pytest.raises(
        ConfigError, match=r"--out: .*3dgs-s0 were trained with other settings \(iterations 400 -> 40\)"
    ):
        bench.run(progress=False)
    assert called == [] and not (tmp_path / "report.md").exists()


def test_benches_refuse_a_folder_another_process_writes(tmp_path, monkeypatch):
    from tacsplat.apps.touch_bench import TouchBench, TouchBenchConfig
    from tacsplat.datasets.outputs import claim_output_dir

    _fake_touch_jobs(monkeypatch)
    monkeypatch.setattr(paper_bench, "render_first_test_view", _no_render)
    with claim_output_dir(tmp_path, "--out"):
        with pytest.raises(ConfigError, match="--out: .* is being written by another tacsplat process"):
            PaperBench(tmp_path, PaperBenchConfig(objects=("teapot",), settings=("minimal",))).run(progress=False)
        with pytest.raises(ConfigError, match="--out: .* is being written by another tacsplat process"):
            TouchBench(tmp_path, TouchBenchConfig(touch_counts=(0,), seeds=(0,))).run(progress=False)
    assert not (tmp_path / "scenes").exists()


def test_bench_touches_makes_no_scene_for_finished_runs(tmp_path, monkeypatch):
    """Every run finished and the scenes deleted (the large part): the rerun captures and copies nothing, and
    the report keeps the touches each run had."""
    from tacsplat.apps.touch_bench import TouchBench, TouchBenchConfig

    captured, trained = _fake_touch_jobs(monkeypatch)
    bench = TouchBench(tmp_path, TouchBenchConfig(touch_counts=(0, 3, 10), seeds=(0,)))
    first = bench.run(progress=False)
    shutil.rmtree(tmp_path / "scenes")
    captured.clear(), trained.clear()
    assert bench.run(progress=False) == first and [r["touches"] for r in first] == [0, 3, 4]
    assert captured == trained == [] and not (tmp_path / "scenes").exists()
    shutil.rmtree(tmp_path / "runs" / "teapot" / "t003-s0")  # a run to do again: its copy is made
    bench.run(progress=False)
    assert captured == ["teapot-s0"] and trained == ["teapot/t003-s0"]


def test_a_finished_run_without_a_checkpoint_is_left_out_of_the_render_grid(tmp_path):
    config = PaperBenchConfig(objects=("teapot",), settings=("minimal",), methods=("3dgs",))
    bench = PaperBench(tmp_path, config)
    (run,) = bench.runs()
    _finish(run, 0.02)
    (run.out / "checkpoint.pt").unlink()  # deleted to save space, or evaluated here after training elsewhere
    bench.run(progress=False)
    report = (tmp_path / "report.md").read_text()
    assert "Not in the render grid (no checkpoint.pt to render): runs/teapot/minimal/3dgs-s0." in report
    assert not (tmp_path / "renders_teapot_minimal.png").exists()
