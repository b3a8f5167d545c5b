"""A servo latches a hardware error while keys wait to be read (a fast typist, piped input): the heartbeat finds it
and turns torque off, and the session ends on it as a device fault before a waiting key records anything."""

import io
import os
import sys
import time
from pathlib import Path

import pytest

from tacsplat.acquisition.config import load_rig
from tacsplat.acquisition.operator_session import EXIT_FAULT, run_capture

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import ScriptedKeys, write_mock_rig  # noqa: E402

pytestmark = pytest.mark.timeout(120)

OVERHEATING = 0x04  # Hardware Error Status bit (one of the firmware's shutdown bits)


def _overheat_and_wait_for_the_heartbeat(rig, logger) -> None:
    """Servo 5 overheats; returns once the heartbeat has found it and turned every servo's torque off."""
    emulator = rig.mock.emulator
    emulator.set_hardware_error(5, OVERHEATING)
    while any(emulator.torque_enabled().values()):  # (bounded by the test's timeout)
        time.sleep(0.05)


@pytest.mark.parametrize("keys_from", ["pipe", "stream"])
def test_a_fault_found_while_keys_wait_ends_the_session_before_they_act(tmp_path, keys_from):
    out = tmp_path / "scene"
    output = io.StringIO()
    config = load_rig(write_mock_rig(tmp_path), mock=True)
    if keys_from == "stream":
        code = run_capture(
            config, out, keys=ScriptedKeys("\nq"), output=output, on_open=_overheat_and_wait_for_the_heartbeat
        )
    else:  # queued before the session reads any: select never waits, so never times out
        read_fd, write_fd = os.pipe()
        os.write(write_fd, b"\nq")
        os.close(write_fd)
        with os.fdopen(read_fd) as keys:
            code = run_capture(config, out, keys=keys, output=output, on_open=_overheat_and_wait_for_the_heartbeat)
    text = output.getvalue()
    assert code == EXIT_FAULT, text
    assert "DEVICE FAULT: Dynamixel hand" in text and "overheating" in text, text
    assert "recorded" not in text, text
    assert text.rstrip("\n").rsplit("\n", 1)[-1] == "Hand: torque off confirmed on all 16 servos.", text
