"""Every way a capture can be asked to end, on `tacsplat capture --mock` in a subprocess whose servos are an
emulator in a process of its own (it outlives the capture): SIGINT, SIGTERM, SIGHUP and SIGQUIT mid-grasp leave
every servo with torque off, the last line says so, the exit code is 128 + signum, and the scene resumes; SIGKILL
mid-grasp runs no code of the capture, and its guard process turns the torque off. A closed terminal window (its
terminal hangs up, with or without SIGHUP) ends it as SIGHUP does."""

import fcntl
import io
import os
import signal
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

from tacsplat.acquisition.config import load_rig
from tacsplat.acquisition.operator_session import run_capture
from tacsplat.datasets import Scene
from tacsplat.drivers.dxl_emulator import EmulatorProcess

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import ScriptedKeys, Terminal, capture_on_a_terminal, write_mock_rig  # noqa: E402

pytestmark = pytest.mark.timeout(300)


def _capture_killed_mid_grasp(
    tmp_path, emu: EmulatorProcess, signum: int, again_after_s: float | None = None
) -> tuple[subprocess.Popen, Terminal, Path]:
    """One view, then a slow grasp (2 s from open to closed) that ``signum`` interrupts while the fingers close
    (sent a second time ``again_after_s`` later, if given)."""
    rig = write_mock_rig(tmp_path, grasp={"close_speed_rad_s": 0.6}, mock_devices={"servo_port": emu.path})
    out = tmp_path / "scene"
    proc, term = capture_on_a_terminal(rig, out)
    try:
        term.wait_for("board: seen")
        term.type("\rg")
        term.wait_for("grasp 0: closing")
        assert all(emu.torque_enabled().values())
        time.sleep(0.4)
        os.kill(proc.pid, signum)
        if again_after_s is not None:
            time.sleep(again_after_s)
            os.kill(proc.pid, signum)
        proc.wait(60)
        term.wait_closed()  # the capture, and its guard, are gone: all the output is in
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        term.close()
    assert "grasp 0 recorded" not in term.text, f"the signal came after the grasp:\n{term.text[-2000:]}"
    return proc, term, out


def _resume_to_the_end(tmp_path, out: Path) -> Scene:
    (tmp_path / "resume").mkdir()
    output = io.StringIO()
    rig = write_mock_rig(tmp_path / "resume")  # the same plan; the example's quick close, servos in this process
    code = run_capture(load_rig(rig, mock=True), out, resume=True, keys=ScriptedKeys("\r\r\rggg"), output=output)
    assert code == 0, output.getvalue()
    return Scene.load(out)


@pytest.mark.parametrize(
    "signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT], ids=lambda s: signal.Signals(s).name
)
def test_an_ending_signal_mid_grasp_leaves_every_servo_off_and_says_so(tmp_path, signum):
    with EmulatorProcess() as emu:
        proc, term, out = _capture_killed_mid_grasp(tmp_path, emu, signum)
        torque = emu.torque_enabled()
    assert not any(torque.values()), torque
    assert proc.returncode == 128 + signum, term.text[-2000:]
    assert f"interrupted ({signal.Signals(signum).name})" in term.text, term.text[-2000:]
    assert f"--out {out} --resume --mock" in term.text
    assert term.last_line() == "Hand: torque off confirmed on all 16 servos.", term.text[-2000:]
    assert "Traceback" not in term.text and "hand guard" not in term.text  # closed: the guard said nothing
    if signum in (signal.SIGHUP, signal.SIGQUIT):
        return  # they end the capture as SIGTERM does (one SignalInterrupt): its resume stands for theirs
    scene = _resume_to_the_end(tmp_path, out)
    assert [f.split for f in scene.frames] == ["train"] * 3 + ["test"]
    assert [t.grasp for t in scene.touches] == [0] * 4 + [1] * 4 + [2] * 4


@pytest.mark.parametrize("signum, gap_s", [(signal.SIGINT, 0.05), (signal.SIGTERM, 0.05)], ids=["sigint", "sigterm"])
def test_a_second_signal_while_the_capture_ends_does_not_cut_its_last_words(tmp_path, signum, gap_s):
    """Ctrl-C twice: the first ends the capture, the second comes while it closes the hand, writes its last words
    or exits. The same exit and last lines as one signal; once a traceback, or a death by the signal itself."""
    with EmulatorProcess() as emu:
        proc, term, out = _capture_killed_mid_grasp(tmp_path, emu, signum, again_after_s=gap_s)
        torque = emu.torque_enabled()
    assert not any(torque.values()), torque
    assert proc.returncode == 128 + signum, term.text[-2000:]
    assert "Traceback" not in term.text, term.text[-2000:]
    assert f"--out {out} --resume --mock" in term.text
    assert term.last_line() == "Hand: torque off confirmed on all 16 servos.", term.text[-2000:]


def test_sigkill_mid_grasp_the_guard_turns_the_torque_off(tmp_path):
    with EmulatorProcess() as emu:
        proc, term, out = _capture_killed_mid_grasp(tmp_path, emu, signal.SIGKILL)
        torque = emu.torque_enabled()  # the terminal closed: the guard has done its work and gone
    assert proc.returncode == -signal.SIGKILL
    assert not any(torque.values()), torque
    assert term.last_line().startswith(
        f"hand guard of {emu.path}: the process {proc.pid} ended without closing the "
        "hand; torque off confirmed on all 16 servos"
    ), term.text[-2000:]
    scene = _resume_to_the_end(tmp_path, out)
    assert [t.grasp for t in scene.touches] == [0] * 4 + [1] * 4 + [2] * 4


@pytest.mark.parametrize(
    "controlling, stderr_on",
    [(True, "file"), (True, "terminal"), (False, "file")],
    ids=["sighup-stderr-to-a-file", "sighup-stderr-on-the-terminal", "no-sighup-eof-and-eio-only"],
)
def test_a_closed_terminal_ends_the_capture_as_sighup_does(tmp_path, controlling, stderr_on):
    """The operator closes the terminal window: the capture's terminal hangs up (reads give nothing, restoring it and
    writing to it fail with EIO) and, when it is the controlling terminal, SIGHUP comes. Either way: torque off,
    exit 129 (not 1 with a traceback, nor 120 for output that could not be flushed), and the resume command and the
    torque-off line on standard error when that is a log file."""

    def take_the_terminal():  # the pty becomes the capture's controlling terminal, as a terminal window's shell is
        fcntl.ioctl(0, termios.TIOCSCTTY, 0)

    with EmulatorProcess() as emu:
        rig = write_mock_rig(tmp_path, mock_devices={"servo_port": emu.path})
        out, log = tmp_path / "scene", tmp_path / "stderr.txt"
        with open(log, "w") as err:
            proc, term = capture_on_a_terminal(
                rig,
                out,
                stderr=err if stderr_on == "file" else None,
                start_new_session=True,
                preexec_fn=take_the_terminal if controlling else None,
            )
        try:
            term.wait_for("board: seen")
            term.type("\r")
            term.wait_for("recorded")
            assert all(emu.torque_enabled().values())
        finally:
            term.close()  # the window is closed
            try:
                proc.wait(60)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
        time.sleep(0.3)  # (the guard, had it been needed, is quick)
        torque = emu.torque_enabled()
    told = log.read_text()
    assert not any(torque.values()), torque
    assert proc.returncode == 128 + signal.SIGHUP, told
    assert "Traceback" not in told and "Exception ignored" not in told, told
    if stderr_on == "file":
        assert "interrupted (SIGHUP)" in told and f"--out {out} --resume --mock" in told, told
        assert told.rstrip("\n").rsplit("\n", 1)[-1] == "Hand: torque off confirmed on all 16 servos.", told
    assert len(Scene.load(out).frames) == 1  # the view taken is kept
