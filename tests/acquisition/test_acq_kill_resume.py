"""Crash safety of a capture: SIGKILL in the middle of a grasp, then --resume finishes the plan; a grasp whose
touches were cut short is redone whole."""

import io
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tacsplat.acquisition.config import load_rig
from tacsplat.acquisition.operator_session import run_capture
from tacsplat.datasets import Scene, SceneWriter

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import ScriptedKeys, capture_on_a_terminal, write_mock_rig  # noqa: E402

pytestmark = pytest.mark.timeout(120)


def _snapshot(scene_dir: Path) -> dict:
    """Every record of a scene with its file's bytes and pose."""
    scene = Scene.load(scene_dir)
    frames = {
        ("frame", f.id): ((scene_dir / f.file_path).read_bytes(), f.split, f.T_world_cam.tobytes())
        for f in scene.frames
    }
    touches = {
        ("touch", t.id): ((scene_dir / t.depth_file).read_bytes(), t.grasp, t.finger, t.T_world_sensor.tobytes())
        for t in scene.touches
    }
    return {**frames, **touches}


@pytest.mark.timeout(300)
def test_sigkill_in_the_middle_of_a_grasp_then_resume_finishes_the_plan(tmp_path):
    # a slow close (2 s from open to closed) so that the kill lands while the fingers are moving
    rig = write_mock_rig(tmp_path, grasp={"close_speed_rad_s": 0.6})
    (tmp_path / "fast").mkdir()
    out = tmp_path / "scene"
    proc, term = capture_on_a_terminal(rig, out)  # in a terminal: single keys (cbreak), a live status line
    try:
        term.wait_for("board: seen")
        term.type("\r\r\rg")
        term.wait_for("grasp 0 recorded")
        term.type("g")
        term.wait_for("grasp 1: closing")
        time.sleep(0.4)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
        term.close()
    assert proc.returncode == -signal.SIGKILL
    assert "\r\x1b[Kboard: seen" in term.text  # the live status line, redrawn in place
    before = _snapshot(out)  # the index is consistent after the kill
    assert sorted(k for k in before if k[0] == "frame") == [("frame", i) for i in range(3)]
    touches = sorted(k for k in before if k[0] == "touch")
    assert touches == [("touch", i) for i in range(4)], f"killed outside grasp 1's closing:\n{term.text[-2000:]}"

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


def test_a_capture_opens_a_hand_left_closed_before_the_tactile_references(tmp_path, monkeypatch):
    """A capture cut short leaves the fingers where they stood (its guard turns the torque off, the servos stay): the
    next capture opens the hand before each sensor averages its untouched-gel reference, or a gel still pressed on
    the object would bias every reading after it."""
    from tacsplat.acquisition.devices import open_rig
    from tacsplat.drivers.dxl_emulator import EmulatorProcess
    from tacsplat.drivers.optical_tactile import OpticalTactileSensor

    def ticks(emu) -> np.ndarray:
        return np.array([s["present_position"] for _, s in sorted(emu.status().items())])

    with EmulatorProcess() as emu:
        config = load_rig(write_mock_rig(tmp_path, mock_devices={"servo_port": emu.path}), mock=True)
        with open_rig(config) as rig:
            opened = ticks(emu)
            rig.hand.command_joint_positions(config.grasp.close_pose)
            deadline = time.monotonic() + 10
            while np.abs(ticks(emu) - opened).max() < 300 and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.5)  # (the servos reach the close pose)
        closed = ticks(emu)
        assert np.abs(closed - opened).max() > 300  # the fingers stay closed, torque off
        at_reference = []
        take = OpticalTactileSensor.capture_reference
        monkeypatch.setattr(
            OpticalTactileSensor, "capture_reference", lambda self: (at_reference.append(ticks(emu)), take(self))
        )
        with open_rig(config) as rig:
            pass
    assert len(at_reference) == len(config.tactile.sensors)
    for seen in at_reference:
        assert np.abs(seen - opened).max() <= 40, (seen - opened, closed - opened)  # ~3.5 degrees: open
