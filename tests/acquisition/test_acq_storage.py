"""A full or read-only disk under `sim-capture` and `simulate-touches`: one `error:` line that says so and names
the file, no temporary file, nothing recorded lost, and a resumed capture completes everything, the ground-truth
mesh included."""

import errno
import subprocess
import sys

import numpy as np
import pytest

from tacsplat.datasets import Scene, SceneMeta, SceneWriter, SensorModel, check_scene
from tacsplat.files import storage_error
from tacsplat.geometry import look_at
from tacsplat.types import CameraIntrinsics

pytestmark = pytest.mark.timeout(180)

# The library teapot's ground-truth mesh (about 180 kB) does not fit on a 150 kB disk.
CAPTURE = [
    "sim-capture",
    "--object",
    "teapot",
    "--views",
    "1",
    "--test-views",
    "1",
    "--grasps",
    "1",
    "--resolution",
    "16",
    "--seed",
    "2",
]


DISK_FULL = storage_error(OSError(errno.ENOSPC, "No space left on device"), ".").reason


def _tacsplat(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "tacsplat", "-q", *map(str, args)],
        capture_output=True,
        text=True,
        stdin=subprocess.DEVNULL,
    )


def test_sim_capture_on_a_full_disk_stops_cleanly_and_resumes_with_the_ground_truth_mesh(tmpfs):
    mount = tmpfs("150k")
    out = mount.path / "scene"
    done = _tacsplat(*CAPTURE, "--out", out)
    assert done.returncode == 1
    assert done.stderr.splitlines() == [f"error: {out / 'gt' / 'mesh.ply'}: {DISK_FULL}"], done.stderr
    assert [p for p in mount.path.rglob("*") if p.name.endswith(".tmp")] == []
    assert (out / "journal.jsonl").is_file()  # the scene exists: --resume continues it

    inspected = _tacsplat("inspect", out)
    assert (
        inspected.returncode == 1
        and "[gt.mesh]: a capture on the twin without its ground-truth mesh" in inspected.stdout
    ), inspected.stdout

    mount.resize("8m")  # space freed
    done = _tacsplat(*CAPTURE, "--out", out, "--resume")
    assert done.returncode == 0, done.stderr
    scene, problems = check_scene(out)
    assert problems == []
    assert scene.gt_mesh_path.is_file() and scene.gt_mesh_path == out / "gt" / "mesh.ply"
    assert len(scene.frames) == 2 and scene.gt_depth(scene.split("test")[0]) is not None
    assert len(scene.touches) == 4


def test_simulate_touches_on_a_read_only_scene_is_refused_before_the_twin_starts(tmpfs, tmp_path):
    mount = tmpfs("1m")
    path = mount.path / "scene"
    with SceneWriter.create(
        path,
        CameraIntrinsics(np.array([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]), 16, 16),
        SceneMeta("sim", "sheet"),
        SensorModel("gel", 8, 8, 1e-4, 2e-3),
    ) as writer:
        writer.add_frame(np.zeros((16, 16, 3), np.uint8), look_at([0, 0.3, 0.3], [0, 0, 0]))
    mount.read_only()
    # The mesh is flat (refused when it is read): the read-only scene is refused before the mesh is even read.
    sheet = tmp_path / "sheet.obj"
    sheet.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    done = _tacsplat("simulate-touches", "--mesh", sheet, path, "--grasps", "1")
    assert done.returncode == 1
    assert done.stderr.splitlines() == [f"error: {path}: the file system is read-only: write to another folder"], (
        done.stderr
    )
    assert len(Scene.load(path).frames) == 1


def test_sim_capture_resume_on_a_read_only_disk_says_so(tmpfs):
    mount = tmpfs("1m")
    out = mount.path / "scene"
    out.mkdir()
    (out / "journal.jsonl").write_text("{}\n")
    mount.read_only()
    done = _tacsplat(*CAPTURE, "--out", out, "--resume")
    assert done.returncode == 1
    assert done.stderr.splitlines() == [
        f"error: --out: {out}: the file system is read-only: write to another folder"
    ], done.stderr
