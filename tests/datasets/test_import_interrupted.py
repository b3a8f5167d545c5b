"""An import or a copy stopped part-way: SIGTERM and SIGHUP remove its folder; after SIGKILL every reader refuses
what is left, saying to import again; a rerun says to remove the folder, never to --resume (imports have none).
An import writes its index files once, when it finishes."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import cv2
import numpy as np
import pytest

import tacsplat.datasets.writer as writer_module
from tacsplat.cli import main
from tacsplat.datasets import Scene, SceneMeta, SceneWriter, check_scene
from tacsplat.datasets.blender import import_blender
from tacsplat.errors import SceneFormatError
from tacsplat.geometry import look_at, opencv_to_opengl

pytestmark = pytest.mark.timeout(300)

# A process running `tacsplat import blender SRC --out OUT` (or, with "copy" first, copy_scene(SRC, OUT)) that
# pauses after its second frame until its stdin ends: the test signals it there, mid-import, with no race.
CHILD = r"""
import signal, sys
from tacsplat.cli import main
from tacsplat.datasets import SceneWriter, copy_scene

if sys.argv[1] == "nohup":
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
add_frame = SceneWriter.add_frame

def paused(self, *args, **kwargs):
    frame = add_frame(self, *args, **kwargs)
    if frame.id == 1:
        print("paused", flush=True)
        sys.stdin.read()
    return frame

SceneWriter.add_frame = paused
if sys.argv[2] == "copy":
    copy_scene(sys.argv[3], sys.argv[4])
    sys.exit(0)
sys.exit(main(["import", "blender", sys.argv[3], "--out", sys.argv[4]]))
"""


def _blender_src(root, views: int = 3):
    """A NeRF-synthetic-like dataset of ``views`` train and ``views`` test views, 8x6 RGBA."""
    for split in ("train", "test"):
        (root / split).mkdir(parents=True)
        frames = []
        for i in range(views):
            image = np.full((6, 8, 4), [30 * i, 90, 200, 255], np.uint8)
            cv2.imwrite(str(root / split / f"r_{i}.png"), image)
            pose = opencv_to_opengl(look_at([4.0 * np.cos(i), 4.0 * np.sin(i), 1.0], [0.0, 0.0, 0.0]))
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": pose.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.69, "frames": frames}))
    return root


def _paused(src, out, kind: str = "import", nohup: bool = False) -> subprocess.Popen:
    """The child, once it has written two frames and waits."""
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, "nohup" if nohup else "-", kind, str(src), str(out)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = proc.stdout.readline()  # (blocks until the child pauses, or ends: then the assertion shows why)
    assert line == "paused\n", line + proc.communicate(timeout=120)[1]
    assert (out / "journal.jsonl").is_file()
    return proc


def _end(proc: subprocess.Popen, signum: int) -> tuple[int, str]:
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP], ids=lambda s: signal.Signals(s).name)
def test_sigterm_or_sighup_mid_import_removes_its_folder(tmp_path, signum):
    src, out = _blender_src(tmp_path / "src"), tmp_path / "out"
    code, err = _end(_paused(src, out), signum)
    assert code == 128 + signum and err.strip().endswith("interrupted") and "Traceback" not in err, err
    assert not out.exists()
    import_blender(src, out)  # the rerun takes the folder
    assert len(Scene.load(out).frames) == 6


def test_sigterm_mid_copy_removes_its_folder(tmp_path):
    src = import_blender(_blender_src(tmp_path / "src"), tmp_path / "scene")
    out = tmp_path / "copy"
    code, err = _end(_paused(src, out, "copy"), signal.SIGTERM)
    assert code != 0 and "SignalInterrupt: SIGTERM" in err, err
    assert not out.exists()


def test_an_ignored_sighup_stays_ignored(tmp_path):
    """``nohup tacsplat import ...``: the import goes on when the terminal closes."""
    src, out = _blender_src(tmp_path / "src"), tmp_path / "out"
    proc = _paused(src, out, nohup=True)
    proc.send_signal(signal.SIGHUP)
    _, err = proc.communicate("", timeout=120)  # (stdin closed: it goes on)
    assert proc.returncode == 0, err
    assert len(Scene.load(out).frames) == 6


def test_the_signal_handlers_come_back_after_an_import(tmp_path):
    def mine(signum, frame):
        pass

    previous = signal.signal(signal.SIGTERM, mine)
    try:
        import_blender(_blender_src(tmp_path / "src"), tmp_path / "out")
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_a_killed_import_is_refused_by_every_reader(tmp_path, capsys):
    src, out = _blender_src(tmp_path / "src"), tmp_path / "out"
    code, _ = _end(_paused(src, out), signal.SIGKILL)
    assert code == -signal.SIGKILL and out.is_dir()
    _, problems = check_scene(out)
    assert f"never finished (2 frames and 0 touches written): remove {out} and import again" in str(problems[0])
    with pytest.raises(SceneFormatError, match="never finished"):
        Scene.load(out)
    assert main(["inspect", str(out)]) == 1
    assert "never finished" in capsys.readouterr().out


def test_a_rerun_into_an_imported_scene_says_to_remove_it(tmp_path, capsys):
    """Not to continue it with --resume, which no import has."""
    src, out = _blender_src(tmp_path / "src"), tmp_path / "out"
    import_blender(src, out)
    assert main(["import", "blender", str(src), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"{out} already holds a scene: remove it to import again, or choose another --out" in err
    assert "--resume" not in err


def test_a_killed_copy_is_refused(tmp_path):
    src = import_blender(_blender_src(tmp_path / "src"), tmp_path / "scene")
    out = tmp_path / "copy"
    _end(_paused(src, out, "copy"), signal.SIGKILL)
    with pytest.raises(SceneFormatError, match=f"copy writing this scene never finished .*remove {out} and copy"):
        Scene.load(out)


def test_a_finished_import_and_an_import_from_before_the_mark_load(tmp_path, h):
    out = import_blender(_blender_src(tmp_path / "src"), tmp_path / "out")
    assert check_scene(out)[1] == []
    with SceneWriter.create(tmp_path / "old", h.intrinsics(), SceneMeta("import", "old")) as writer:  # (no job)
        writer.add_frame(h.frame_image(0), h.ring_pose(0))
    assert len(Scene.load(tmp_path / "old").frames) == 1
    with SceneWriter.resume(out) as writer:  # a finished import goes on as any scene (simulate-touches)
        writer.add_frame(h.frame_image(0, 8, 6), h.ring_pose(0), intrinsics=writer.frames[0].intrinsics)
        assert len(Scene.load(out).frames) == 7  # written at once again


def test_an_import_writes_its_index_once_and_a_capture_after_every_record(tmp_path, h, monkeypatch):
    """Rewriting the whole index after each record made an import of N frames take N^2 time."""
    written = []
    write = writer_module.atomic_write_json
    monkeypatch.setattr(
        writer_module, "atomic_write_json", lambda path, obj: (written.append(path.name), write(path, obj))
    )
    out = import_blender(_blender_src(tmp_path / "src", views=5), tmp_path / "out")
    assert written.count("transforms.json") == 2  # the creation's (empty), the finished import's
    assert len(Scene.load(out).frames) == 10
    written.clear()
    with SceneWriter.create(tmp_path / "capture", h.intrinsics(), SceneMeta("real", "cup")) as writer:
        for i in range(3):
            writer.add_frame(h.frame_image(i), h.ring_pose(i))
            assert len(json.loads((tmp_path / "capture" / "transforms.json").read_text())["frames"]) == i + 1
    assert written.count("transforms.json") == 4
