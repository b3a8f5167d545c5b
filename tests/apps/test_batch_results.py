"""What a batch writes: results.csv with every scalar metric of every run of the batch file (those an earlier
invocation finished included), and worker processes that log at the batch process's levels (a library's INFO that
the CLI hides stays hidden)."""

from __future__ import annotations

import csv
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from tacsplat.apps.batch import RESULT_COLUMNS
from tacsplat.apps.executors import run_jobs
from tacsplat.cli import main

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders; spawned
# workers get this process's sys.path

from batch_test_jobs import FileJob  # noqa: E402

BATCH = """\
jobs:
  - {kind: capture, out: scenes/t, object: teapot, views: 2, test_views: 1, grasps: 0, resolution: 32}
  - {kind: reconstruct, out: runs/meshed, scene: scenes/t, iterations: 5, export_mesh: true}
  - {kind: reconstruct, out: runs/new, scene: scenes/t, iterations: 5}
"""

# runs/meshed as an earlier invocation left it: trained, its meshes exported (their metrics in metrics.json)
MESHED = {
    "cd": 0.25,
    "psnr": 12.5,
    "cd_seen": 0.2,
    "mesh_cd": 0.125,
    "mesh_watertight": True,
    "mesh_untouched_cd": None,
    "gt_source": "scene gt/",
    "method": "paper",
    "mechanisms": {"touch": True},
    "settings": {"seed": 4},
}


def read_csv(path: Path) -> tuple[list[str], list[dict]]:
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        return list(reader.fieldnames), list(reader)


def test_results_hold_every_scalar_metric_of_every_run_also_one_finished_before(tmp_path):
    """Before: the twelve fixed columns alone (no cd_seen, no mesh_* of an export_mesh run)."""
    path, out = tmp_path / "b.yaml", tmp_path / "out"
    path.write_text(BATCH)
    meshed = out / "runs/meshed"
    meshed.mkdir(parents=True)
    (meshed / "metrics.json").write_text(json.dumps(MESHED | {"scene": str(out / "scenes/t")}))
    for name in ("mesh.ply", "mesh-untouched.ply"):
        (meshed / name).write_text("ply")  # (complete: skipped)

    assert main(["batch", str(path), "--out", str(out), "--executor", "local"]) == 0
    header, rows = read_csv(out / "results.csv")
    assert [r["job"] for r in rows] == ["reconstruct runs/meshed", "reconstruct runs/new"]
    new = json.loads((out / "runs/new/metrics.json").read_text())
    scalars = {k for m in (MESHED, new) for k, v in m.items() if not isinstance(v, (dict, list))}
    assert header == [*RESULT_COLUMNS, *sorted(scalars - set(RESULT_COLUMNS))]
    assert {"cd_seen", "depth_bias", "psnr_splat", "mesh_cd", "mesh_watertight"} <= set(header)
    assert "settings" not in header and "mechanisms" not in header
    assert {k: rows[0][k] for k in ("scene", "seed", "cd_seen", "mesh_cd", "mesh_watertight", "mesh_untouched_cd")} == {
        "scene": "scenes/t",
        "seed": "4",
        "cd_seen": "0.2",
        "mesh_cd": "0.125",
        "mesh_watertight": "True",
        "mesh_untouched_cd": "",
    }
    assert rows[1]["mesh_cd"] == "" and rows[1]["scene"] == "scenes/t"
    assert all(rows[1][k] == str(v) for k, v in new.items() if k in header and k != "scene")

    written = (out / "results.csv").read_text()
    assert main(["batch", str(path), "--out", str(out), "--executor", "local"]) == 0  # every job skipped
    assert (out / "results.csv").read_text() == written


@dataclass(frozen=True)
class LibraryLoggingJob(FileJob):
    """Logs as PyOpenGL does when MuJoCo's renderer imports it, and as tacsplat does."""

    def __call__(self) -> dict:
        logging.getLogger("OpenGL.acceleratesupport").info("No OpenGL_accelerate module loaded")
        logging.getLogger("tacsplat.test_worker").info("ours")
        return super().__call__()


@pytest.fixture
def opengl_at_warning():
    """OpenGL's logger at WARNING, as the CLI sets it (its INFO is noise)."""
    logger = logging.getLogger("OpenGL")
    level = logger.level
    logger.setLevel(logging.WARNING)
    yield
    logger.setLevel(level)


def test_a_worker_logs_at_the_levels_of_the_batch_process(tmp_path, caplog, opengl_at_warning):
    """Before: a worker set the root's level alone, so PyOpenGL's INFO line led every batch's log."""
    with caplog.at_level(logging.INFO):
        run_jobs([LibraryLoggingJob("talks", tmp_path / "talks")], tmp_path, executor="processes", progress=False)
    assert [(r.name, r.getMessage()) for r in caplog.records if r.name != "tacsplat.apps.executors"] == [
        ("tacsplat.test_worker", "ours")
    ]
