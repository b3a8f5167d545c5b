"""`tacsplat demo` and `bench paper` into an --out that is not new: runs trained with another --iterations and a
folder of other files are refused before anything runs; a mesh file's renders are named by its stem; the no-touch
row reads as what it is (and its runs under its former name are still read); an interruption says how to go on."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tacsplat.apps import batch, paper_bench
from tacsplat.apps.demo import COLUMNS, NO_TOUCH, demo_config
from tacsplat.apps.paper_bench import PaperBench, PaperBenchConfig
from tacsplat.cli import main
from tacsplat.errors import ConfigError

PAPER = ["--objects", "teapot", "--settings", "minimal", "--methods", "3dgs", "--resolution", "32", "--test-views", "2"]


def _trained(bench: PaperBench, run, cd: float = 0.03) -> None:
    """What a finished run of ``bench`` leaves: its config.json (the settings it trained with) and metrics.json."""
    run.out.mkdir(parents=True, exist_ok=True)
    (run.out / "config.json").write_text(json.dumps(bench.reconstruct_job(run).config().to_json()))
    metrics = {"cd": cd, "psnr": 20.0, "ssim": 0.8, "train_seconds": 5.0, "cd_unseen": cd, "cd_seen": cd}
    (run.out / "metrics.json").write_text(json.dumps(metrics))
    (run.out / "checkpoint.pt").write_bytes(b"")  # (what the render grid draws from: these tests render none)


@pytest.fixture
def nothing_runs(monkeypatch) -> list:
    """Captures and trainings that only record that they were called (none should be)."""
    called = []
    monkeypatch.setattr(batch.CaptureJob, "__call__", lambda job: called.append(job.name))
    monkeypatch.setattr(batch.ReconstructJob, "__call__", lambda job: called.append(job.name))
    return called


def _tree(folder, lock: bool = False) -> dict:
    """Every path under ``folder`` with its content (the lock file of the command that claimed it, if ``lock``)."""
    paths = [p for p in sorted(folder.rglob("*")) if lock or p.name != ".tacsplat.lock"]
    return {str(p.relative_to(folder)): p.read_bytes() if p.is_file() else None for p in paths}


# ---------------------------------------------------------------------- 1. another --iterations


def test_a_demo_rerun_with_other_iterations_is_refused_not_shown_under_the_new_count(tmp_path, capsys, nothing_runs):
    out = tmp_path / "demo"
    earlier = PaperBench(out, demo_config(iterations=50))
    for run in earlier.runs():
        _trained(earlier, run)
    before = _tree(out)
    assert main(["demo", "--out", str(out), "--iterations", "400"]) == 1
    err = capsys.readouterr().err
    assert f"error: --out: {out / 'runs'}" in err and "and 3 other run(s) were trained with other settings" in err
    assert "(iterations 50 -> 400): rerun with --iterations 50, or choose a new --out" in err, err
    assert nothing_runs == [] and _tree(out) == before  # (no results.csv, no report.md written)


def test_bench_paper_refuses_an_interrupted_run_of_other_iterations_and_keeps_one_of_a_changed_default(
    tmp_path, nothing_runs
):
    config = PaperBenchConfig(objects=("teapot",), settings=("minimal",), methods=("3dgs",), iterations=50)
    earlier = PaperBench(tmp_path, config)
    (run,) = earlier.runs()
    run.out.mkdir(parents=True)
    (run.out / "config.json").write_text(json.dumps(earlier.reconstruct_job(run).config().to_json()))
    (run.out / "checkpoint.pt").write_bytes(b"")  # interrupted: it would be continued with 50 steps
    now = PaperBench(tmp_path, PaperBenchConfig(**{**config.__dict__, "iterations": 60}))
    with pytest.raises(ConfigError, match=r"--out: .*3dgs-s0 were trained with other settings \(iterations 50 -> 60"):
        now.run(progress=False)
    assert nothing_runs == []
    assert [changes for _, changes in PaperBench(tmp_path, config).stale_runs()] == []  # (the same: no refusal)
    other = earlier.reconstruct_job(run).config().to_json() | {"ssim_weight": 0.3}  # a default changed since
    (run.out / "config.json").write_text(json.dumps(other))
    bench = PaperBench(tmp_path, config)
    bench.refuse_changed_options(bench.stale_runs())  # kept, not refused, and named as stale
    assert [changes for _, changes in bench.stale_runs()] == [["ssim_weight 0.3 -> 0.2"]]


# ---------------------------------------------------------------------- 2. a folder of the user's


@pytest.mark.parametrize("layout", [[], ["runs"]])
def test_a_folder_of_other_files_is_refused_before_anything_is_written(tmp_path, capsys, nothing_runs, layout):
    out = tmp_path / "myresults"
    out.mkdir()
    (out / "results.csv").write_text("my,own,results\n")
    (out / "report.md").write_text("# my thesis notes\n")
    for name in layout:  # (a folder of that name, but the results.csv is not a bench's)
        (out / name).mkdir()
    before = _tree(out, lock=True)
    assert main(["demo", "--out", str(out), "--iterations", "50", "--resolution", "64"]) == 1
    err = capsys.readouterr().err
    assert f"error: --out: {out} holds other files and no bench" in err and "choose an empty or new folder" in err
    assert nothing_runs == [] and _tree(out, lock=True) == before  # (not even a lock file)
    assert main(["bench", "paper", "--out", str(out), *PAPER]) == 1
    assert "holds other files and no bench" in capsys.readouterr().err and _tree(out, lock=True) == before


def test_an_earlier_bench_folder_is_continued(tmp_path, monkeypatch):
    config = PaperBenchConfig(objects=("teapot",), settings=("minimal",), methods=("3dgs",), iterations=50)
    bench = PaperBench(tmp_path, config)
    (run,) = bench.runs()
    _trained(bench, run)
    monkeypatch.setattr(paper_bench, "render_first_test_view", _no_render)
    assert [r["cd"] for r in bench.run(progress=False)] == [0.03]
    assert [r["cd"] for r in PaperBench(tmp_path, config).run(progress=False)] == [0.03]  # (its results.csv: a bench's)


def _no_render(runs, cache=None):
    depth = np.full((8, 8), 0.3, np.float32)
    normal = np.broadcast_to(np.array([0.0, 0.0, -1.0], np.float32), (8, 8, 3))
    panels = {r.method: (np.zeros((8, 8, 3)), depth, normal) for r in runs}
    return panels, np.ones((8, 8, 3)), depth, normal, np.ones((8, 8), bool)


# ---------------------------------------------------------------------- 3. a mesh file's picture


def _fake_rows(monkeypatch) -> None:
    """PaperBench.run made instant: a row of numbers per demo column."""
    row = {"cd": 0.03, "cd_unseen": 0.04, "psnr": 25.0, "ssim": 0.9, "train_seconds": 10.0}
    monkeypatch.setattr(PaperBench, "run", lambda self, **kw: [{"method": m, **row} for m in COLUMNS])


def test_the_demo_of_a_mesh_file_names_the_picture_the_bench_writes(tmp_path, capsys, monkeypatch):
    import trimesh

    mesh = tmp_path / "meshes" / "cup.ply"
    mesh.parent.mkdir()
    trimesh.creation.icosphere(subdivisions=2).export(mesh)
    _fake_rows(monkeypatch)
    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--out", "dm", "--object", "meshes/cup.ply", "--iterations", "30"]) == 0
    out = capsys.readouterr().out
    assert f"open first: {tmp_path / 'dm' / 'renders_cup_minimal.png'} (" in out, out
    assert "\ncup, 5 views + 5 grasps" in out
    assert PaperBench(tmp_path / "dm", demo_config("meshes/cup.ply")).runs()[0].object == "cup"  # (the bench's name)


# ---------------------------------------------------------------------- 4. the no-touch row


def test_the_no_touch_row_says_what_it_is_and_reads_runs_of_its_former_name(tmp_path, monkeypatch):
    from tacsplat.apps.report import markdown_table

    assert NO_TOUCH == "default-no-touch" and COLUMNS[NO_TOUCH] == "default, no touch"
    assert (
        paper_bench.bench_row("default-touch") == paper_bench.bench_row(NO_TOUCH) == ("default", {"use_touch": False})
    )
    config = PaperBenchConfig(objects=("teapot",), settings=("minimal",), methods=("default", "default-touch"))
    config.validate()
    assert config.methods == ("default", NO_TOUCH)
    with pytest.raises(ConfigError, match="given twice"):
        PaperBenchConfig(objects=("teapot",), methods=("default-touch", NO_TOUCH)).validate()
    # an earlier demo's no-touch run, in its folder of the former name, is the row's run (not trained again)
    bench = PaperBench(tmp_path, config)
    former = tmp_path / "runs" / "teapot" / "minimal" / "default-touch-s0"
    former.mkdir(parents=True)
    assert [r.out.name for r in bench.runs()] == ["default-s0", "default-touch-s0"]
    for run in bench.runs():
        _trained(bench, run, 0.02 if run.method == "default" else 0.03)
    monkeypatch.setattr(paper_bench, "render_first_test_view", _no_render)
    rows = bench.run(progress=False)
    assert {r["method"]: r["cd"] for r in rows} == {"default": 0.02, NO_TOUCH: 0.03}
    assert "| Default, no touch | 0.0300 | 0.0300 |" in markdown_table(rows, "cd", "minimal")
    report = (tmp_path / "report.md").read_text()
    assert "`default-no-touch` (Default, no touch): the default with `--no-use-touch`: no touch Gaussians" in report
    assert "| Default, no touch |" in report and "default-touch" not in report
    assert [r.out.name for r in PaperBench(tmp_path / "new", config).runs()] == ["default-s0", "default-no-touch-s0"]


# ---------------------------------------------------------------------- 5. an interruption


@pytest.mark.parametrize("command", [["demo"], ["bench", "paper", *PAPER]])
def test_an_interruption_says_that_the_same_command_continues(tmp_path, capsys, monkeypatch, command):
    def interrupted(self, **kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(PaperBench, "run", interrupted)
    assert main([*command, "--out", str(tmp_path / "out")]) == 130
    err = capsys.readouterr().err
    assert f"to continue, run the same command again: only the unfinished jobs run (what finished in {tmp_path}" in err
    assert err.rstrip().endswith("interrupted")
