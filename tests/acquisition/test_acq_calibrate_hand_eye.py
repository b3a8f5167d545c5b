"""tacsplat calibrate hand-eye: on twins hiding random hand-eye errors (up to 5 mm and 3 degrees) it finds T_hand_cam
within 1 mm and 0.5 degree from fingertip presses on a sphere resting on the board, runs with standard input
closed (on the twin and through the real drivers on --mock), and refuses presses that leave an axis undetermined,
naming it."""

import os
import re
import sys

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from tacsplat.acquisition.calibrate import calibrate_hand_eye
from tacsplat.acquisition.config import example_rig, load_rig
from tacsplat.acquisition.presses import SPHERE_RADIUS_M, hand_eye_plan
from tacsplat.cli import main
from tacsplat.drivers.press_calibration import fit_presses, load_hand_eye
from tacsplat.errors import InvalidInputError
from tacsplat.sim.hand import nominal_T_hand_cam

pytestmark = pytest.mark.timeout(300)

FINE_BOARD = {"squares_x": 14, "squares_y": 10, "square_length_m": 0.015, "marker_length_m": 0.011}


def _draw(seed: int) -> dict:
    """A hand-eye error up to 5 mm and 3 degrees."""
    rng = np.random.default_rng(seed)
    t, r = rng.normal(size=3), rng.normal(size=3)
    t *= 0.005 * rng.uniform(0.3, 1.0) / np.linalg.norm(t)
    r *= 3.0 * rng.uniform(0.3, 1.0) / np.linalg.norm(r)
    return {"hand_eye": {"translation_m": t.tolist(), "rotation_deg": r.tolist()}}


def _rig(tmp_path, errors: dict, **more) -> str:
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"rig": "sim", "board": FINE_BOARD, "sim": {"true_errors": errors}, **more}))
    return str(path)


def _error(T: np.ndarray, errors: dict) -> tuple[float, float]:
    """(mm, degrees) between ``T`` and the twin's true T_hand_cam."""
    e = errors["hand_eye"]
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(e["rotation_deg"], degrees=True).as_matrix()
    E[:3, 3] = e["translation_m"]
    D = np.linalg.inv(nominal_T_hand_cam() @ E) @ T
    return 1000 * float(np.linalg.norm(D[:3, 3])), float(np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_it_recovers_a_hidden_hand_eye_error_within_1_mm_and_half_a_degree(tmp_path, seed):
    errors = _draw(seed)
    fit = calibrate_hand_eye(load_rig(_rig(tmp_path, errors)), tmp_path / "he.json", lambda s: 0)
    mm, deg = _error(load_hand_eye(tmp_path / "he.json"), errors)
    print(f"seed {seed}: {mm:.3f} mm, {deg:.3f} deg, rms {fit.rms_mm:.3f} mm")
    assert mm < 1.0 and deg < 0.5


def test_the_command_runs_with_stdin_closed_and_the_capture_then_uses_the_file(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    errors = _draw(7)
    rig, out = _rig(tmp_path, errors), tmp_path / "calibration" / "hand_eye.json"
    assert main(["calibrate", "hand-eye", "--rig", rig, "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(line.startswith("press 1/16: index on the sphere") for line in lines)
    assert lines[-2].startswith("T_hand_cam: ") and lines[-1].startswith(f"wrote {out}")
    from tacsplat.acquisition.devices import twin_config
    from tacsplat.sim.twin import SimTwin

    rig = _rig(tmp_path, errors, camera={"hand_eye": "calibration/hand_eye.json"})
    with SimTwin(twin_config(load_rig(rig))) as twin:  # the rig's hand pose from the camera is now the truth
        D = np.linalg.inv(twin.T_world_hand()) @ twin.hand_pose_from_wrist_camera()
        assert 1000 * np.linalg.norm(D[:3, 3]) < 1.0


def test_presses_that_leave_an_axis_undetermined_are_refused_naming_it(tmp_path):
    from tacsplat.acquisition.devices import twin_config
    from tacsplat.acquisition.presses import TwinPressSession
    from tacsplat.sim.twin import SimTwin

    config = load_rig(_rig(tmp_path, _draw(3)))
    with SimTwin(twin_config(config)) as twin:
        presses = TwinPressSession(twin, config.board, lambda s: 0).run(hand_eye_plan(["thumb"])[:1])
    with pytest.raises(
        InvalidInputError, match=r"hand-eye: the presses leave undetermined: hand-eye .*press the sphere"
    ):
        fit_presses(presses, SPHERE_RADIUS_M, nominal_T_hand_cam())
    with pytest.raises(InvalidInputError, match="no presses recorded"):
        fit_presses([], SPHERE_RADIUS_M, nominal_T_hand_cam())


def _sensors() -> list:
    """The mock rig's index and thumb sensors (fewer presses)."""
    sensors = yaml.safe_load(example_rig("mock").read_text())["tactile"]["sensors"]
    return [s for s in sensors if s["finger"] in ("index", "thumb")]


def _mock_rig(tmp_path, errors, camera=None, tactile=None) -> str:
    """A --mock rig file (mock.yaml's board and emulated devices) with the twin's true ``errors`` and two sensors
    (``camera``, ``tactile``: more keys of those sections)."""
    from tests.acquisition.acq_helpers import write_mock_rig

    extra = {} if camera is None else {"camera": camera}
    return write_mock_rig(
        tmp_path,
        sim={"true_errors": errors},
        tactile={"sensors": _sensors(), **(tactile or {})},
        **extra,
    )


def test_mock_presses_are_guided_through_the_real_drivers_and_find_the_hidden_error(tmp_path, capsys, monkeypatch):
    """--mock runs the real rig's code path with standard input closed: the real hand, camera and tactile drivers read the emulated person's presses (the servo emulator
    holding each press's joints, the sphere in the gel's image, the board at the camera's true pose)."""
    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    errors = _draw(4)
    rig = _mock_rig(tmp_path, errors)
    out = tmp_path / "hand_eye.json"
    assert main(["calibrate", "hand-eye", "--rig", rig, "--out", str(out), "--mock"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].startswith("press 1/8: index on the sphere (placement 1): ") and lines[1].endswith("; ok")
    assert re.search(
        r"the wrist camera finds at most \d of the board's corners, fewer than 6 \(board.min_corners\)", lines[3]
    )
    assert lines[-1].startswith(f"wrote {out}")
    mm, deg = _error(load_hand_eye(out), errors)
    assert mm < 0.5 and deg < 0.5, (mm, deg)


def test_sigterm_mid_presses_exits_with_torque_off_confirmed_and_nothing_written(tmp_path):
    import signal

    from tests.acquisition.acq_helpers import sigterm_when, write_mock_rig

    rig = write_mock_rig(tmp_path, tactile={"sensors": _sensors()})
    out, he = tmp_path / "mounts.json", tmp_path / "hand_eye.json"
    args = ["calibrate", "mounts", "--rig", rig, "--out", str(out), "--hand-eye", str(he), "--mock"]
    code, stdout, stderr = sigterm_when(args, "press 2/")
    assert code == 128 + signal.SIGTERM, stderr
    assert "torque off confirmed on all 16 servos" in stdout
    assert f"interrupted (SIGTERM): {out} not written" in stderr
    assert not out.exists() and not he.exists()


def test_on_mock_a_press_skipped_for_the_board_says_how_many_corners_the_camera_finds(tmp_path):
    """The line of a press --mock's person skipped said only "fewer than 6 of the board's corners", where a real rig's
    gives the corners its camera found ("board not found: N corners of the ..."); the index fingertip's third press
    has no pose of the hand that shows the camera 6 of them."""
    from tacsplat.acquisition.mock import MockDevices
    from tacsplat.acquisition.mock_presser import EmulatorPresser

    config = load_rig(_mock_rig(tmp_path, {}), mock=True)
    with MockDevices(config) as mock:
        why = EmulatorPresser(mock).press(hand_eye_plan(["index"])[2])
    found = re.fullmatch(
        r"at every pose of the hand near the sphere the wrist camera finds at most (\d+) of the board's corners, "
        r"fewer than 6 \(board.min_corners\)",
        why or "",
    )
    assert found and int(found[1]) < 6, why


def test_a_person_at_a_real_rig_is_told_each_press_in_one_line():
    from tacsplat.acquisition.presses import TerminalPresser, mounts_plan

    lines = []
    person = TerminalPresser(lines.append)
    assert person.press(hand_eye_plan()[0]) is None and person.press(mounts_plan()[0]) is None
    person.release(mounts_plan()[0])
    assert lines == [
        "  press the index fingertip with its pad's centre on the sphere (placement 1), the wrist camera seeing the "
        "board; hold it still",
        "  press the index fingertip with its pad at x +8 mm, y +0 mm of the gel's centre on the sphere (placement 2), "
        "the wrist camera seeing the board; hold it still",
        "  lift the index fingertip off",
    ]


NAMED = {"camera": {"hand_eye": "calibration/hand_eye.json"}, "tactile": {"mounts": "calibration/mounts.json"}}


@pytest.mark.parametrize("command", ["hand", "hand-eye", "mounts"])
def test_a_rig_file_naming_the_files_not_written_yet_calibrates_on_the_twin(tmp_path, capsys, command):
    """docs/real-rig.md's rig file names camera.hand_eye and tactile.mounts from the start: each calibration command
    runs on it before they are written (a named file not there yet counts as none), and writes its file."""
    out = (
        tmp_path / "calibration" / {"hand": "hand.json", "hand-eye": "hand_eye.json", "mounts": "mounts.json"}[command]
    )
    code = main(["calibrate", command, "--rig", _rig(tmp_path, _draw(5), **NAMED), "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    assert out.is_file()


def test_on_mock_a_rig_naming_the_files_not_written_yet_opens_and_calibrates(tmp_path, capsys, monkeypatch):
    """The real rig's code path (open_rig) with camera.hand_eye and tactile.mounts named, neither written yet: the
    hand-eye starts from the camera calibration's T_hand_cam and nominal mounts, and writes the file it names."""
    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    errors = _draw(4)
    rig = _mock_rig(tmp_path, errors, camera=NAMED["camera"], tactile=NAMED["tactile"])
    out = tmp_path / "calibration" / "hand_eye.json"
    assert main(["calibrate", "hand-eye", "--rig", rig, "--out", str(out), "--mock"]) == 0, capsys.readouterr().err
    mm, deg = _error(load_hand_eye(out), errors)
    assert mm < 0.5 and deg < 0.5, (mm, deg)


@pytest.mark.parametrize("key, file", [("camera.hand_eye", "hand_eye.json"), ("tactile.mounts", "mounts.json")])
def test_a_named_file_that_is_there_but_unreadable_is_one_error_naming_it_and_its_key(tmp_path, capsys, key, file):
    path = tmp_path / "calibration" / file
    path.parent.mkdir()
    path.write_text('{"format": ')  # a truncated file
    out = tmp_path / "calibration" / "new_hand_eye.json"
    code = main(["calibrate", "hand-eye", "--rig", _rig(tmp_path, _draw(5), **NAMED), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and not out.exists()
    assert err.splitlines()[-1].startswith(f"error: {path}: {key}: not valid JSON"), err


def test_a_wall_clock_step_does_not_make_the_presses_fresh_frames_look_stale(monkeypatch):
    """The drivers stamp frames with time.monotonic(); NTP steps the wall clock back 5 s mid-calibration. The
    presses still take the frames read after the person was told: the press is recorded, not skipped."""
    import time
    from types import SimpleNamespace

    from tacsplat.acquisition.config import BoardConfig
    from tacsplat.acquisition.presses import RigPressSession
    from tacsplat.types import TactileReading

    wall = time.time
    monkeypatch.setattr(time, "time", lambda: wall() - 5.0)
    pressed = [False]

    class Hand:
        joint_names, joint_limits = [f"j{k}" for k in range(16)], np.tile([-1.0, 1.0], (16, 1))
        q = np.zeros(16)

        def command_joint_positions(self, q):
            self.q = np.asarray(q, float)

        def read_joint_positions(self):
            return self.q

        def fingertip_poses(self):
            return {"index": np.eye(4)}

    class Sensor:
        name = "index"

        def read(self):
            depth = np.full((8, 8), 1e-3 if pressed[0] else 0.0, np.float32)
            return TactileReading(depth, 1e-4, np.eye(4), timestamp=time.monotonic())

    class Person:
        timeout_s = 2.0

        def press(self, spec):
            pressed[0] = True

        def release(self, spec):
            pressed[0] = False

    image = np.zeros((4, 4, 3), np.uint8)
    camera = SimpleNamespace(read=lambda: (image, time.monotonic()), K=np.diag([100.0, 100.0, 1.0]))
    said = []
    session = RigPressSession(Hand(), camera, [Sensor()], BoardConfig(), Person(), said.append)
    pose = SimpleNamespace(T=np.eye(4), corners=20, reprojection_px=0.3)
    session.poses = SimpleNamespace(camera_pose=lambda image: pose)
    presses = session.run(hand_eye_plan(["index"])[:1])
    assert len(presses) == 1 and said[-1].endswith("; ok"), said


@pytest.mark.parametrize("command", ["hand-eye", "mounts"])
def test_on_mock_a_servo_emulator_in_another_process_is_refused_before_any_device_opens(tmp_path, capsys, command):
    """The emulated person must read where the servos stand: with ``mock_devices.servo_port`` they are in another
    process, which ``calibrate hand`` refuses before connecting; so do hand-eye and mounts (no torque on first)."""
    from tests.acquisition.acq_helpers import write_mock_rig

    rig = write_mock_rig(tmp_path, mock_devices={"servo_port": str(tmp_path / "no-such-port")})
    args = ["calibrate", command, "--rig", rig, "--out", str(tmp_path / "out.json"), "--mock"]
    args += ["--hand-eye", str(tmp_path / "hand_eye.json")] if command == "mounts" else []
    assert main(args) == 1  # (the rig file's mistake)
    captured = capsys.readouterr()
    assert "mock_devices.servo_port: the servo emulator runs in another process" in captured.err, captured.err
    assert "torque on" not in captured.out + captured.err
