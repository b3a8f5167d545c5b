"""An ending signal that lands while a command that opens the hand imports a native module (MuJoCo's pybind11
modules, trimesh's parts) before the hand connects: it ends the command as the same signal does anywhere else, with
no traceback, and the hand is never connected. Raised inside such an import, its exception came out as
``ImportError: initialization failed`` (a traceback, exit 1), or was dropped (MuJoCo imports its renderer under
``except ImportError``, trimesh its parts under ``except BaseException``) and the capture connected the hand, torque
on, after the operator asked it to stop."""

import signal
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import write_mock_rig  # noqa: E402

pytestmark = pytest.mark.timeout(300)

# `tacsplat ARGS` in a process that raises SIGNUM on itself as MODULE is first imported; WRAP: that import then fails
# as a pybind11 module's init does when a signal's handler raised inside it (ImportError, the handler's as cause)
TACSPLAT_SIGNALLED_IN_IMPORT = """
import signal, sys

MODULE, SIGNUM, WRAP = sys.argv.pop(1), int(sys.argv.pop(1)), sys.argv.pop(1) == "wrap"


class SignalInImport:
    def find_spec(self, name, path=None, target=None):
        if name != MODULE:
            return None
        sys.meta_path.remove(self)
        try:
            signal.raise_signal(SIGNUM)  # (its handler runs before this returns)
        except BaseException as exc:
            if WRAP:
                raise ImportError("initialization failed") from exc
            raise
        return None  # (held: the import goes on)


sys.meta_path.insert(0, SignalInImport())
from tacsplat.cli import run

run()
"""

IN_IMPORTS = {  # what MuJoCo's and trimesh's imports did with a signal's exception raised inside them
    "mujoco-core-traceback": ("mujoco._structs", "wrap"),
    "mujoco-renderer-dropped": ("mujoco._render", "wrap"),
    "trimesh-part-dropped": ("trimesh.path", "raise"),
}


def _tacsplat_signalled_in_import(args: list[str], module: str, how: str, signum: int) -> subprocess.CompletedProcess:
    command = [sys.executable, "-c", TACSPLAT_SIGNALLED_IN_IMPORT, module, str(int(signum)), how, *args]
    return subprocess.run(command, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=240)


@pytest.mark.parametrize("module, how", IN_IMPORTS.values(), ids=IN_IMPORTS.keys())
def test_sigterm_inside_a_native_import_ends_the_capture_before_the_hand_connects(tmp_path, module, how):
    out = tmp_path / "scene"
    args = ["capture", "--rig", write_mock_rig(tmp_path), "--out", str(out), "--mock"]
    done = _tacsplat_signalled_in_import(args, module, how, signal.SIGTERM)
    text = done.stdout + done.stderr
    assert done.returncode == 143, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    assert "interrupted (SIGTERM)." in done.stdout
    assert "The capture did not start (no scene was written)" in done.stdout
    assert done.stdout.rstrip().splitlines()[-1] == "Hand: not connected; nothing was sent to its servos."


@pytest.mark.parametrize(
    "command",
    [["rig", "check"], ["calibrate", "hand", "--out", "hand.json"], ["calibrate", "hand-eye", "--out", "he.json"]],
)
def test_ctrl_c_inside_mujocos_import_ends_a_command_before_the_hand_connects(tmp_path, command):
    rig = write_mock_rig(tmp_path)
    args = [*(a if not a.endswith(".json") else str(tmp_path / a) for a in command), "--rig", rig, "--mock"]
    done = _tacsplat_signalled_in_import(args, "mujoco._render", "wrap", signal.SIGINT)
    assert done.returncode == 130, (done.stdout + done.stderr)[-3000:]
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    assert "interrupted" in done.stderr
    assert "servo" not in done.stdout  # no table of rig check, no torque-off line of a calibration: never connected
    assert not list(tmp_path.glob("*.json"))
