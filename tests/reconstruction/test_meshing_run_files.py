"""`export mesh --out` never replaces what the run or its scene owns, and a run retrained (`reconstruct --overwrite`
or `--resume`) drops the meshes of its old Gaussians."""

from __future__ import annotations

import json
import logging
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tacsplat.cli import main
from tacsplat.datasets import Scene, SceneWriter
from tacsplat.reconstruction.metrics import ground_truth_surface

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import build_sphere_scene, one_error_line, pause_training  # noqa: E402

FAST = ["--sh-degree", "0", "--lambda-s", "0", "--backend", "cpu", "--init.no-use-sfm", "--quiet"]
EXPORT = ["--voxel", "0.08", "--views", "12", "--cone-deg", "60"]
USAGE = "tacsplat export mesh: error: "


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A 3-step run of the sphere (with a ground-truth mesh) and its scene, in one folder; tests copy it."""
    root = tmp_path_factory.mktemp("trained")
    scene = build_sphere_scene(root / "scene", size=24, train_views=3, test_views=1)
    with SceneWriter.resume(scene) as writer:
        writer.set_gt_mesh(trimesh.creation.icosphere(subdivisions=2, radius=0.05))
    assert main(["reconstruct", str(scene), "--out", str(root / "run"), "--iterations", "3", *FAST]) == 0
    return root


@pytest.fixture
def copy(trained, tmp_path) -> tuple[Path, Path]:
    """(scene, run) copies of :func:`trained`'s, the run's config pointing at the copied scene."""
    scene = Path(shutil.copytree(trained / "scene", tmp_path / "scene"))
    run = Path(shutil.copytree(trained / "run", tmp_path / "run"))
    config = json.loads((run / "config.json").read_text())
    config["scene"]["path"] = str(scene.resolve())
    (run / "config.json").write_text(json.dumps(config))
    return scene, run


def _export(run: Path, *extra: str) -> int:
    return main(["export", "mesh", str(run), *EXPORT, *extra])


def test_export_refuses_the_runs_splat_and_the_scenes_ground_truth_even_with_overwrite(copy, capsys):
    scene, run = copy
    for out in (run / "splat.ply", scene / "gt" / "mesh.ply", scene / "new.ply"):
        before = out.read_bytes() if out.exists() else None
        for extra in ((), ("--overwrite",)):
            assert _export(run, "--out", str(out), *extra) == 2
            one_error_line(capsys, "--out", str(out), prefix=USAGE)
            assert (out.read_bytes() if out.exists() else None) == before


def test_export_refuses_a_file_it_did_not_write_unless_overwrite_and_replaces_its_own(copy, tmp_path, capsys):
    _, run = copy
    other = tmp_path / "other.ply"
    trimesh.creation.box().export(other)  # a PLY, without the export's `observed`
    before = other.read_bytes()
    assert _export(run, "--out", str(other)) == 2
    one_error_line(capsys, "--out", "--overwrite", prefix=USAGE)
    assert other.read_bytes() == before
    assert _export(run, "--out", str(other), "--overwrite") == 0
    assert b"property uchar observed" in other.read_bytes()[:1000]
    assert _export(run, "--out", str(other)) == 0  # a previous export is replaced
    assert _export(run) == 0 and _export(run) == 0  # RUN/mesh.ply too


def _exported(run: Path) -> None:
    assert _export(run) == 0
    assert (run / "mesh.ply").is_file() and "mesh_fscore_5" in json.loads((run / "metrics.json").read_text())


def test_reconstruct_overwrite_drops_the_old_mesh_and_its_metrics(copy):
    scene, run = copy
    _exported(run)
    assert main(["reconstruct", str(scene), "--out", str(run), "--iterations", "2", *FAST, "--overwrite"]) == 0
    assert not (run / "mesh.ply").exists()
    assert not any(k.startswith("mesh_") for k in json.loads((run / "metrics.json").read_text()))


def test_a_resume_that_trains_on_drops_the_old_mesh_and_its_metrics(copy):
    scene, run = copy
    _exported(run)
    assert main(["reconstruct", str(scene), "--out", str(run), *FAST, "--resume", "--iterations", "4"]) == 0
    assert not (run / "mesh.ply").exists()
    assert not any(k.startswith("mesh_") for k in json.loads((run / "metrics.json").read_text()))


def test_an_export_into_a_run_being_trained_is_refused_and_one_elsewhere_is_not(copy, tmp_path, capsys, monkeypatch):
    """`export mesh` writes RUN/mesh.ply and RUN/metrics.json: while `reconstruct --resume` trains the run (its lock
    held), that export is refused as `evaluate` is, and the finished run reports no stale mesh; an export to a file
    outside the run writes nothing of the run's and goes ahead."""
    import threading

    scene, run = copy
    in_training, finish = pause_training(monkeypatch)
    resume = ["reconstruct", str(scene), "--out", str(run), *FAST, "--resume", "--iterations", "5"]
    first = {}
    job = threading.Thread(target=lambda: first.update(code=main(resume)))
    job.start()
    try:
        assert in_training.wait(120)
        before = (run / "metrics.json").read_bytes()
        capsys.readouterr()
        assert _export(run) == 1
        one_error_line(capsys, "RUN", str(run), "another tacsplat process", prefix="error: ")
        assert not (run / "mesh.ply").exists() and (run / "metrics.json").read_bytes() == before
        elsewhere = tmp_path / "elsewhere" / "mesh.ply"
        assert _export(run, "--out", str(elsewhere)) == 0 and elsewhere.is_file()
        assert (run / "metrics.json").read_bytes() == before
    finally:
        finish.set()
        job.join(120)
    assert first["code"] == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["iterations"] == 5 and not any(k.startswith("mesh_") for k in metrics)
    assert not (run / "mesh.ply").exists()
    _exported(run)  # the run released: the export goes ahead


def test_an_export_value_out_of_range_is_a_usage_error_naming_its_option(copy, tmp_path, capsys):
    """Exit 2 and one usage line naming the option, for a value out of range whatever tells it: MeshConfig's checks,
    or (--cone-deg 0.001) the run's cameras, none of --views lying that near a training camera's (it was exit 1)."""
    _, run = copy
    out = tmp_path / "new" / "m.ply"
    for option, value in (("--cone-deg", "0.001"), ("--cone-deg", "nan"), ("--voxel", "0.001"), ("--views", "5"),
                          ("--seal", "2")):  # fmt: skip
        assert _export(run, "--out", str(out), option, value) == 2
        one_error_line(capsys, f"{option}: ", prefix=USAGE)
    assert not out.parent.exists()


def test_a_mesh_exported_by_hand_as_the_runs_untouched_mesh_has_its_metrics_recorded(copy, tmp_path):
    """docs/meshes.md's `export mesh RUN --no-touches --out RUN/mesh-untouched.ply` records mesh_untouched_*, as a
    batch's export does (a mesh file in the run has its metrics); one elsewhere records nothing."""
    _, run = copy
    assert _export(run, "--no-touches", "--out", str(tmp_path / "elsewhere.ply")) == 0
    assert not any(k.startswith("mesh_") for k in json.loads((run / "metrics.json").read_text()))
    assert _export(run, "--no-touches", "--out", str(run / "mesh-untouched.ply")) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert "mesh_untouched_fscore_5" in metrics and not any(k.startswith("mesh_fscore") for k in metrics)


def test_a_scene_ground_truth_of_zero_extent_is_not_measured_against(copy, capsys, caplog):
    """A scene's gt/mesh.ply whose vertices all lie at one point has a radius of 0 to measure distances in (export
    mesh's metrics never ended, in a k-d tree of one repeated point): one warning naming it, and the mesh is
    exported without metrics."""
    scene, run = copy
    with SceneWriter.resume(scene) as writer:
        writer.set_gt_mesh(trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False))
    warning = f"{scene / 'gt' / 'mesh.ply'}: no extent (all its vertices at one point): not used as the ground truth"
    with caplog.at_level(logging.WARNING, logger="tacsplat.reconstruction.metrics"):
        assert ground_truth_surface(Scene.load(scene)) is None
    assert [r.getMessage() for r in caplog.records if r.name == "tacsplat.reconstruction.metrics"] == [warning]
    capsys.readouterr()
    assert _export(run) == 0
    out, err = capsys.readouterr()
    assert err.splitlines() == [f"WARNING tacsplat.reconstruction.metrics: {warning}"], err
    summary = json.loads(out)
    assert (run / "mesh.ply").is_file() and not [k for k in summary if k.startswith("mesh_fscore")], summary
