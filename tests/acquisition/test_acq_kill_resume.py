"""Crash safety of a capture: SIGKILL in the middle of a grasp, then --resume finishes the plan; a grasp whose
touches were cut short is redone whole."""

import io
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tacsplat.acquisition.config import load_rig
from tacsplat.acquisition.session import run_capture
from tacsplat.datasets import Scene, SceneWriter

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import ScriptedKeys, write_mock_rig  # noqa: E402

pytestmark = pytest.mark.timeout(120)


def _snapshot(scene_dir: Path) -> dict:
    """Every record of a scene with its file's bytes and pose."""
    scene = Scene.load(scene_dir)
    frames = {("frame", f.id): ((scene_dir / f.file_path).read_bytes(), f.split, f.T_world_cam.tobytes())
              for f in scene.frames}
    touches = {("touch", t.id): ((scene_dir / t.depth_file).read_bytes(), t.grasp, t.finger, t.T_world_sensor.tobytes())
               for t in scene.touches}
    return {**frames, **touches}


class _Lines:
    """Collects a process's output lines in a thread; ``wait_for`` blocks until a line contains a text."""

    def __init__(self, stream):
        self.lines: list[str] = []
        self._cond = threading.Condition()
        threading.Thread(target=self._run, args=(stream,), daemon=True).start()

    def _run(self, stream):
        for line in stream:
            with self._cond:
                self.lines.append(line)
                self._cond.notify_all()

    def wait_for(self, text: str, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not any(text in line for line in self.lines):
                remaining = deadline - time.monotonic()
                assert remaining > 0, f"no {text!r} in the output:\n{''.join(self.lines)}"
                self._cond.wait(remaining)


def test_sigkill_in_the_middle_of_a_grasp_then_resume_finishes_the_plan(tmp_path):
    # a slow close (2 s from open to closed) so that the kill lands while the fingers are moving
    rig = write_mock_rig(tmp_path, grasp={"close_speed_rad_s": 0.6})
    (tmp_path / "fast").mkdir()
    out = tmp_path / "scene"
    proc = subprocess.Popen([sys.executable, "-m", "tacsplat.cli", "capture", "--rig", rig, "--out", str(out), "--mock"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = _Lines(proc.stdout)
        proc.stdin.write("\n\n\ng")
        proc.stdin.flush()
        lines.wait_for("grasp 0 recorded")
        proc.stdin.write("g")
        proc.stdin.flush()
        lines.wait_for("grasp 1: closing")
        time.sleep(0.4)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    before = _snapshot(out)  # the index is consistent after the kill
    assert sorted(k for k in before if k[0] == "frame") == [("frame", i) for i in range(3)]
    assert sorted(k for k in before if k[0] == "touch") == [("touch", i) for i in range(4)]  # grasp 0 only

    output = io.StringIO()
    fast = write_mock_rig(tmp_path / "fast")  # same plan, the example's quick close
    code = run_capture(load_rig(fast, mock=True), out, resume=True, keys=ScriptedKeys("gg\n"), output=output)
    assert code == 0, output.getvalue()
    after = _snapshot(out)
    for key, record in before.items():  # every completed record is still there, unchanged
        assert after[key] == record, key
    scene = Scene.load(out)
    assert [f.split for f in scene.frames] == ["train"] * 3 + ["test"]
    assert [t.id for t in scene.touches] == list(range(12))  # each record exactly once, no gaps
    assert [t.grasp for t in scene.touches] == [0] * 4 + [1] * 4 + [2] * 4


def test_a_grasp_cut_short_while_writing_its_touches_is_redone_whole(tmp_path):
    rig = write_mock_rig(tmp_path)
    out = tmp_path / "scene"
    config = load_rig(rig, mock=True)
    assert run_capture(config, out, keys=ScriptedKeys("\ngg"), output=io.StringIO()) == 1
    # what a kill between the 2nd and 3rd touch of grasp 1 leaves: drop its last two touches
    with SceneWriter.resume(out) as writer:
        writer.remove_last()
        writer.remove_last()
    partial = _snapshot(out)
    assert sum(1 for k in partial if k[0] == "touch") == 6

    output = io.StringIO()
    code = run_capture(config, out, resume=True, keys=ScriptedKeys("\n\ng\ng\n"), output=output)
    text = output.getvalue()
    assert code == 0, text
    assert "removed 2 touches of a grasp cut short" in text
    scene = Scene.load(out)
    assert [t.grasp for t in scene.touches] == [0] * 4 + [1] * 4 + [2] * 4
    assert [t.finger for t in scene.touches[4:8]] == ["index", "middle", "ring", "thumb"]
    after = _snapshot(out)
    for i in range(4):  # grasp 0 untouched
        assert after[("touch", i)] == partial[("touch", i)]
    assert all(np.isfinite(t.T_world_sensor).all() for t in scene.touches)
