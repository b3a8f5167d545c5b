"""A full or read-only disk under a SceneWriter and `inspect --plot`: one StorageError naming the file, no
temporary file left, nothing recorded lost, and the scene goes on once there is space."""

from __future__ import annotations

import errno
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from tacsplat.datasets import Scene, SceneMeta, SceneWriter, check_scene
from tacsplat.errors import StorageError
from tacsplat.files import storage_error

PAGE = 4096  # tmpfs counts space in pages: a file grows into its last page's slack without new space


DISK_FULL = storage_error(OSError(errno.ENOSPC, "No space left on device"), ".").reason


def _fill(mount) -> None:
    """Take every free page of the mount (a filler file that grows until the disk is full)."""
    with open(mount.path / "filler", "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * PAGE)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC


def _temporary_files(mount) -> list:
    return [p for p in mount.path.rglob("*") if p.name.endswith(".tmp")]


def _refused(call, path) -> StorageError:
    with pytest.raises(StorageError) as info:
        call()
    assert info.value.path == path and "disk is full" in str(info.value), str(info.value)
    return info.value


def test_each_write_of_a_record_on_a_full_disk_is_one_storage_error_and_the_scene_goes_on(tmpfs, h):
    mount = tmpfs("256k")
    path = h.build_scene(mount.path / "scene")
    writer = SceneWriter.resume(path)
    journal = path / "journal.jsonl"
    _fill(mount)

    _refused(lambda: writer.add_frame(h.frame_image(4), h.ring_pose(4)), path / "images/000004.png")
    _refused(
        lambda: writer.add_touch(h.touch_depth(4), h.touch_pose(4), grasp=2, finger="index"),
        path / "touches/000004.npz",
    )
    _refused(lambda: writer.set_gt_mesh(trimesh.creation.icosphere(radius=0.05)), path / "gt/mesh.ply")
    # A journal line longer than the slack of the journal's last page: written in part, then the disk is full.
    journaled = journal.read_bytes()
    slack = -len(journaled) % PAGE
    _refused(lambda: writer.annotate("long", "x" * (slack + 100)), journal)
    assert journal.read_bytes() == journaled  # the part written is cut again: no torn line for records to follow
    # A short one fits in the slack: journaled, then scene.json (a new file beside the old) finds no space.
    _refused(lambda: writer.annotate("short", 1), path / "scene.json")
    assert _temporary_files(mount) == []
    _, problems = check_scene(path)  # the index is behind the journal, as after a crash, and says so
    assert [p.field for p in problems] == ["annotations"] and "resum" in str(problems[0])

    mount.resize("2m")  # space freed: the same writer goes on, ids unchanged
    assert writer.add_frame(h.frame_image(4), h.ring_pose(4)).id == 4
    writer.close()
    with SceneWriter.resume(path) as again:
        assert again.annotations == {"short": 1}
        assert (again.num_frames, again.num_touches) == (5, 4)
    scene = Scene.load(path)
    assert scene.load_image(scene.frames[4])[0, 0, 0] == np.float32(4 / 255)


def test_a_scene_cannot_start_on_a_full_disk_and_leaves_a_folder_a_rerun_takes(tmpfs, h):
    mount = tmpfs("64k")
    _fill(mount)
    path = mount.path / "scene"
    with pytest.raises(StorageError) as info:
        SceneWriter.create(path, h.intrinsics(), SceneMeta("sim", "x"), h.SENSOR)
    assert info.value.path.parent == path and "disk is full" in str(info.value)
    assert _temporary_files(mount) == [] and not (path / "journal.jsonl").exists()
    (mount.path / "filler").unlink()
    with SceneWriter.create(path, h.intrinsics(), SceneMeta("sim", "x"), h.SENSOR) as writer:
        writer.add_frame(h.frame_image(0), h.ring_pose(0))
    assert len(Scene.load(path).frames) == 1


def test_resume_on_a_read_only_scene_names_the_journal(tmpfs, h):
    mount = tmpfs("256k")
    path = h.build_scene(mount.path / "scene")
    mount.read_only()
    with pytest.raises(StorageError, match="read-only") as info:
        SceneWriter.resume(path)
    assert info.value.path == path / "journal.jsonl"


def _inspect(*args):
    return subprocess.run(
        [sys.executable, "-m", "tacsplat", "inspect", *map(str, args)], capture_output=True, text=True
    )


def test_inspect_plot_on_a_read_only_mount_is_one_error_before_the_summary(tmpfs, scene_dir):
    mount = tmpfs("256k")
    mount.read_only()
    done = _inspect(scene_dir, "--plot", mount.path / "ro" / "p.png")
    assert done.returncode == 1 and done.stdout == ""  # refused before the summary is printed
    assert done.stderr.splitlines() == [  # (the nearest folder that exists: the plot's own is made only to write)
        f"error: {mount.path}: the file system is read-only: write to another folder"
    ], done.stderr
    assert not (mount.path / "ro").exists()


def test_inspect_plot_on_a_full_disk_leaves_no_partial_picture(tmpfs, scene_dir):
    mount = tmpfs("64k")
    (mount.path / "pictures").mkdir()
    _fill(mount)
    (mount.path / "filler").write_bytes(b"\0" * (60 * 1024))  # room for the writability probe, not the picture
    done = _inspect(scene_dir, "--plot", mount.path / "pictures" / "p.png")
    assert done.returncode == 1
    assert done.stderr.splitlines() == [f"error: {mount.path / 'pictures' / 'p.png'}: {DISK_FULL}"], done.stderr
    assert list((mount.path / "pictures").iterdir()) == []
