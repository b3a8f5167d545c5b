"""Device faults mid-capture (a servo stops answering; the camera stops giving frames; the bus dies): a clear
message naming the device and the exact resume command, torque off on the emulated servos that answer, a last line
that says only what was confirmed, and a scene that resumes."""

import errno
import io
import os
import sys
import threading
from pathlib import Path

import pytest

from tacsplat.acquisition.config import load_rig
from tacsplat.acquisition.operator_session import EXIT_FAULT, run_capture
from tacsplat.datasets import Scene, check_scene
from tacsplat.errors import CameraError, InvalidInputError

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import ScriptedKeys, write_mock_rig  # noqa: E402

pytestmark = pytest.mark.timeout(120)


def _capture_with_fault(tmp_path, keys: str, fault_before_key: int, inject):
    rig = write_mock_rig(tmp_path)
    out = tmp_path / "scene"
    opened = {}
    output = io.StringIO()
    code = run_capture(
        load_rig(rig, mock=True),
        out,
        keys=ScriptedKeys(keys, {fault_before_key: lambda: inject(opened)}),
        output=output,
        on_open=lambda rig, logger: opened.update(rig=rig),
    )
    return code, output.getvalue(), opened["rig"].mock, rig, out


def last_line(text: str) -> str:
    return text.rstrip("\n").rsplit("\n", 1)[-1]


def _resume_to_the_end(rig, out, keys):
    output = io.StringIO()
    code = run_capture(load_rig(rig, mock=True), out, resume=True, keys=ScriptedKeys(keys), output=output)
    assert code == 0, output.getvalue()
    return Scene.load(out)


def test_servo_that_stops_answering_mid_grasp(tmp_path):
    # one view, one grasp, then servo 6 (middle_2) is cut off just before the second grasp
    code, text, mock, rig, out = _capture_with_fault(
        tmp_path, "\ngg\n", 2, lambda opened: opened["rig"].mock.emulator.disconnect(6)
    )
    assert code == EXIT_FAULT, text
    assert "DEVICE FAULT" in text and "Dynamixel hand" in text and "servo 6" in text and "middle_2" in text, text
    assert "torque is off" not in text  # servo 6 never confirmed it: only what was confirmed is said
    assert (
        last_line(text) == "Hand: torque off NOT confirmed on servo 6 (middle_2): cut the servo power (confirmed "
        "on the other 15)."
    ), text
    assert f"tacsplat capture --rig {rig} --out {out} --resume --mock" in text
    torque = mock.emulator.torque_enabled()
    assert not any(on for sid, on in torque.items() if sid != 6), torque  # every servo that answers is off
    scene, problems = check_scene(out)
    assert problems == [] and len(scene.frames) == 1 and [t.grasp for t in scene.touches] == [0] * 4

    scene = _resume_to_the_end(rig, out, "\n\ngg\n")
    assert [t.grasp for t in scene.touches] == [0] * 4 + [1] * 4 + [2] * 4
    assert [f.split for f in scene.frames] == ["train"] * 3 + ["test"]


def _stall_camera(opened) -> None:
    """The camera hangs; a frame it delivered just before is still there to read (as from a real one): taken
    here, so that the grasp's read is the one that times out, whatever the timing."""
    opened["rig"].mock.stall_camera()
    try:
        opened["rig"].camera.read()
    except CameraError:
        pass


def test_camera_that_stops_giving_frames(tmp_path):
    code, text, mock, rig, out = _capture_with_fault(tmp_path, "\n\ng\n", 2, _stall_camera)
    assert code == EXIT_FAULT, text
    assert "DEVICE FAULT: wrist camera: no new frame within 1 s" in text, text
    assert last_line(text) == "Hand: torque off confirmed on all 16 servos.", text
    assert f"--out {out} --resume --mock" in text
    assert not any(mock.emulator.torque_enabled().values())
    scene = Scene.load(out)
    assert len(scene.frames) == 2 and scene.touches == []

    scene = _resume_to_the_end(rig, out, "\nggg\n")
    assert [f.split for f in scene.frames] == ["train"] * 3 + ["test"] and len(scene.touches) == 12


def test_ctrl_c_leaves_the_hand_safe_and_says_how_to_resume(tmp_path):
    def interrupt(opened):
        raise KeyboardInterrupt

    code, text, mock, rig, out = _capture_with_fault(tmp_path, "\ng\n", 2, interrupt)
    assert code == 130, text
    assert "interrupted (SIGINT)" in text and f"--out {out} --resume --mock" in text
    assert last_line(text) == "Hand: torque off confirmed on all 16 servos.", text
    assert not any(mock.emulator.torque_enabled().values())
    assert len(Scene.load(out).frames) == 1


def test_a_fault_before_the_scene_exists_says_to_start_again_not_to_resume(tmp_path, monkeypatch):
    from tacsplat.acquisition.mock import MockDevices

    rig = write_mock_rig(tmp_path)
    out = tmp_path / "scene"
    opened = MockDevices.__enter__

    def servo_6_dead_from_the_start(self):  # the hand's first ping finds no servo 6
        opened(self)
        self.emulator.disconnect(6)
        return self

    with monkeypatch.context() as patch:
        patch.setattr(MockDevices, "__enter__", servo_6_dead_from_the_start)
        output = io.StringIO()
        code = run_capture(load_rig(rig, mock=True), out, keys=ScriptedKeys("\n"), output=output)
    text = output.getvalue()
    assert code == EXIT_FAULT, text
    assert "DEVICE FAULT" in text and "servo 6" in text, text
    assert "--resume" not in text, text
    assert "The capture did not start" in text and f"tacsplat capture --rig {rig} --out {out} --mock\n" in text, text
    assert not out.exists() or not any(out.iterdir())  # nothing half-made that the advised command would trip on

    output = io.StringIO()  # the advised command works once the servo answers
    assert run_capture(load_rig(rig, mock=True), out, keys=ScriptedKeys("\nq"), output=output) == 1, output.getvalue()
    assert len(Scene.load(out).frames) == 1


def _mid_grasp(fault, opened: dict, after_commands: int = 5):
    """An ``on_open`` that runs ``fault(mock)`` once the hand has taken ``after_commands`` goals (the fingers move);
    ``opened["mock"]`` is the rig's MockDevices."""

    def on_open(rig, logger):
        opened["mock"], command, count = rig.mock, rig.hand.command_joint_positions, []

        def counting(q):
            count.append(1)
            if len(count) == after_commands:
                fault(rig.mock)
            command(q)

        rig.hand.command_joint_positions = counting

    return on_open


def _unplug(mock) -> None:
    mock.emulator.stop()  # the U2D2 disappears: the pty's other end is gone


# A dead bus costs the mock two torque-offs (the fault's, the close's) of 16 servos x 2 tries x its status timeout
# (0.5 s, sized for a loaded host); 0.2 s here, still 4x the real hand's, cuts that by more than half.
DEAD_BUS_RIG = {"mock_devices": {"servo_timeout_s": 0.2}}


def _every_servo_silent(mock) -> None:
    for sid in mock.emulator.servos:
        mock.emulator.disconnect(sid)


@pytest.mark.parametrize("fault", [_unplug, _every_servo_silent], ids=["adapter unplugged", "every servo silent"])
def test_a_dead_bus_mid_grasp_says_that_no_servo_confirmed_torque_off(tmp_path, fault):
    rig = write_mock_rig(tmp_path, **DEAD_BUS_RIG)
    out = tmp_path / "scene"
    output = io.StringIO()
    opened = {}
    code = run_capture(
        load_rig(rig, mock=True), out, keys=ScriptedKeys("\ng\n"), output=output, on_open=_mid_grasp(fault, opened)
    )
    text = output.getvalue()
    assert code == EXIT_FAULT, text
    assert "DEVICE FAULT: Dynamixel hand" in text and "torque is off" not in text, text
    assert last_line(text) == "Hand: torque off NOT confirmed on any of the 16 servos: cut the servo power.", text
    assert all(opened["mock"].emulator.torque_enabled().values())  # what was said is true: nothing reached them
    assert len(Scene.load(out).frames) == 1 and Scene.load(out).touches == []

    scene = _resume_to_the_end(rig, out, "\n\nggg\n")
    assert [t.grasp for t in scene.touches] == [0] * 4 + [1] * 4 + [2] * 4


def test_a_bus_death_while_the_operator_waits_ends_the_session_at_once(tmp_path):
    """No key touches the hand: its heartbeat finds the dead bus, turns torque off, and the session says so."""
    rig = write_mock_rig(tmp_path, **DEAD_BUS_RIG)
    out = tmp_path / "scene"
    read_fd, write_fd = os.pipe()  # keys the session waits for, as from a terminal
    os.write(write_fd, b"\n")
    output = io.StringIO()

    bound = threading.Timer(30.0, os.write, (write_fd, b"q"))  # a bound: q stops the session
    try:
        with os.fdopen(read_fd) as keys:
            code = run_capture(
                load_rig(rig, mock=True),
                out,
                keys=keys,
                output=output,
                on_open=lambda rig_, logger: (bound.start(), _every_servo_silent(rig_.mock)),
            )
    finally:
        bound.cancel()
        os.close(write_fd)
    text = output.getvalue()
    assert code == EXIT_FAULT, text
    assert "DEVICE FAULT: Dynamixel hand" in text and "heartbeat" in text, text
    assert last_line(text) == "Hand: torque off NOT confirmed on any of the 16 servos: cut the servo power.", text


def test_an_encoder_glitch_mid_grasp_is_a_fault_not_a_recorded_grasp(tmp_path):
    rig = write_mock_rig(tmp_path)
    out = tmp_path / "scene"
    output = io.StringIO()
    glitch = _mid_grasp(lambda mock: mock.emulator.inject_position_offset(5, 1500), {})  # middle_1 reads 2.3 rad high
    code = run_capture(load_rig(rig, mock=True), out, keys=ScriptedKeys("\ng\n"), output=output, on_open=glitch)
    text = output.getvalue()
    assert code == EXIT_FAULT, text
    assert "DEVICE FAULT: Dynamixel hand" in text and "servo 5 (middle_1)" in text and "outside its limits" in text
    assert last_line(text) == "Hand: torque off confirmed on all 16 servos.", text
    assert len(Scene.load(out).frames) == 1 and Scene.load(out).touches == []  # no grasp at a wrong pose


def _full_disk(path):
    from tacsplat.files import storage_error

    return storage_error(OSError(errno.ENOSPC, "No space left on device"), path)


@pytest.mark.parametrize(
    "fault, told",
    [
        (_full_disk, "STORAGE FAULT: {path}: the disk is full"),
        (lambda path: InvalidInputError(f"depth: {path} holds NaN"), "FAULT: depth: {path} holds NaN"),
    ],
    ids=["disk full", "another error"],
)
def test_a_full_disk_or_another_error_mid_grasp_ends_as_a_device_fault_does(tmp_path, fault, told):
    """Not a device's fault, but the hand was holding: the rig closes, the resume command and, last, what the hand
    confirmed are printed, and the exit code is the fault's; the records before it are kept and resume."""
    rig = write_mock_rig(tmp_path)
    out = tmp_path / "scene"
    path = out / "touches" / "000001.npz"
    opened = {}

    def on_open(rig_, logger):
        opened["mock"], add_touch = rig_.mock, logger.writer.add_touch

        def second_fails(*args, **kwargs):  # the grasp's second touch is not written
            if len(logger.writer.touches) == 1:
                raise fault(path)
            return add_touch(*args, **kwargs)

        logger.writer.add_touch = second_fails

    output = io.StringIO()
    code = run_capture(load_rig(rig, mock=True), out, keys=ScriptedKeys("\ng\n"), output=output, on_open=on_open)
    text = output.getvalue()
    assert code == EXIT_FAULT, text
    assert told.format(path=path) in text, text
    assert f"tacsplat capture --rig {rig} --out {out} --resume --mock\n" in text, text
    assert last_line(text) == "Hand: torque off confirmed on all 16 servos.", text
    assert not any(opened["mock"].emulator.torque_enabled().values())
    scene = Scene.load(out)
    assert len(scene.frames) == 1 and [t.grasp for t in scene.touches] == [0]  # the cut grasp: redone on resume

    scene = _resume_to_the_end(rig, out, "\n\nggg\n")
    assert [t.grasp for t in scene.touches] == [0] * 4 + [1] * 4 + [2] * 4


def test_an_unexpected_error_mid_session_still_ends_with_the_hands_line(tmp_path):
    def bug():
        raise FileNotFoundError("grasps/000000.npz")  # (not a TacsplatError: a bug's traceback follows)

    output = io.StringIO()
    rig = write_mock_rig(tmp_path)
    opened = {}
    with pytest.raises(FileNotFoundError):
        run_capture(
            load_rig(rig, mock=True),
            tmp_path / "scene",
            keys=ScriptedKeys("\ng\n", {2: bug}),
            output=output,
            on_open=lambda rig_, logger: opened.update(rig=rig_),
        )
    assert last_line(output.getvalue()) == "Hand: torque off confirmed on all 16 servos.", output.getvalue()
    assert not any(opened["rig"].mock.emulator.torque_enabled().values())
