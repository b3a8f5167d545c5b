"""`tacsplat bench paper --dataset`: the paper's settings on scenes imported from miniature copies of its datasets
(Glossy Synthetic through `import nero`, Shiny Blender through `import blender`), end to end in a few steps."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import pytest

from tacsplat.apps.paper_bench import paper_views
from tacsplat.cli import main
from tacsplat.datasets import Scene

sys.path.insert(0, str(Path(__file__).parents[1] / "datasets"))  # pytest's importlib mode does not add test folders

from paper_datasets import make_glossy_synthetic, make_shiny_blender  # noqa: E402

pytestmark = pytest.mark.timeout(600)


def test_the_paper_keeps_every_int_n_over_5th_train_view_from_the_first():
    assert paper_views(list(range(100)), 5) == [0, 20, 40, 60, 80]  # Shiny Blender's 100 train views
    assert paper_views(list(range(96)), 5) == [0, 19, 38, 57, 76]  # Glossy Synthetic's 96
    assert paper_views(list(range(8)), 5) == [0, 1, 2, 3, 4]
    assert paper_views(list(range(3)), 5) == [0, 1, 2] and paper_views(list(range(7)), 0) == list(range(7))


def test_bench_paper_on_imported_datasets_runs_end_to_end(tmp_path, capsys):
    dataset = tmp_path / "dataset"
    glossy, shiny = make_glossy_synthetic(tmp_path / "nero"), make_shiny_blender(tmp_path / "shiny")
    assert main(["import", "nero", str(glossy), "--out", str(dataset / "bell"), "--scale", "0.05"]) == 0
    assert main(["import", "blender", str(shiny), "--out", str(dataset / "toaster"), "--background", "black"]) == 0
    out = tmp_path / "report"
    command = ["bench", "paper", "--dataset", str(dataset), "--out", str(out), "--iterations", "3"]
    assert main([*command, "--methods", "paper", "--settings", "minimal,full-views"]) == 0
    capsys.readouterr()

    with (out / "results.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert {(r["object"], r["setting"], r["method"]) for r in rows} == {
        (o, s, m) for o in ("bell", "toaster") for s in ("minimal", "full-views") for m in ("paper",)
    }
    for row in rows:
        assert math.isfinite(float(row["cd"])) and math.isfinite(float(row["cd_paper"])), row

    for obj, train in (("bell", 8), ("toaster", 10)):
        imported = Scene.load(dataset / obj)
        for setting, views in (("minimal", paper_views(imported.split("train"), 5)), ("full-views", None)):
            scene = Scene.load(out / "scenes" / obj / f"{setting}-s0-paper-touches")
            kept = len(views) if views else train
            assert len(scene.split("train")) == kept and len(scene.split("test")) == len(imported.split("test"))
            assert len(scene.touches) == 20 and scene.meta.capture_plan["simulated_touches"]["mesh"] == "gt/points.ply"
            marker = json.loads((out / "scenes" / obj / f"{setting}-s0-paper-touches.json").read_text())
            assert marker["train_views"] == [f.file_path for f in (views or imported.split("train"))]

    report = (out / "report.md").read_text()
    assert "# Tactile-informed 3DGS on" in report
    assert "## Against the paper: glossy-synthetic, minimal" in report
    assert "| paper (paper) | 0.0082 | 0.0026 |" in report  # Table 2's bell, and its average
    assert "## Against the paper: shiny-blender, full-views" in report
    assert "| 3dgs+t (paper) | 0.0029 | 0.0022 |" in report  # Table 3's toaster
    assert "## Against the paper: shiny-blender, minimal" not in report  # the paper has no such table

    # resumable: a second invocation finds everything done
    assert main([*command, "--methods", "paper", "--settings", "minimal"]) == 0
    assert "2 of 2 runs already finished" in capsys.readouterr().err


def test_bench_paper_dataset_errors_name_the_option(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert main(["bench", "paper", "--dataset", str(tmp_path / "empty"), "--out", str(tmp_path / "r")]) != 0
    err = capsys.readouterr().err
    assert "dataset" in err and "no scene directories" in err and "Traceback" not in err
