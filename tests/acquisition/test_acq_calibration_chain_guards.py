"""Guards of the calibration chain, on twins and --mock: calibrate hand-eye finds a wrist camera turned about its
optical axis (not a local minimum) and refuses presses its noise cannot explain; --arm-poses refuses inverted or
swapped poses; calibrate mounts refuses a sensor without presses, keeps a sensor mounted far off (and says so) and
writes the rig's hand-eye file with the mounts; a rig file's own T_hand_cam or T_fingertip_sensor that overrides a
calibration file is warned of and failed by rig check, as is a twin that hides errors no file calibrates. A failed
calibration writes nothing and keeps the earlier files."""

import dataclasses
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from tacsplat.acquisition.calibrate import calibrate_mounts
from tacsplat.acquisition.config import RigConfig, checked, example_rig, load_rig
from tacsplat.cli import main
from tacsplat.drivers.press_calibration import MountsFit, load_hand_eye, load_mounts, save_hand_eye, save_mounts
from tacsplat.geometry import invert_pose, make_pose
from tacsplat.sim.hand import FINGER_NAMES, nominal_T_hand_cam

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from test_acq_hand_eye_arm import _run as _arm_run  # noqa: E402
from test_acq_hand_eye_arm import _stations, folder  # noqa: E402, F401  (folder: the arm stations' fixture)

pytestmark = pytest.mark.timeout(300)

FINE_BOARD = {"squares_x": 14, "squares_y": 10, "square_length_m": 0.015, "marker_length_m": 0.011}


def _rig(where: Path, errors: dict, **more) -> str:
    where.mkdir(parents=True, exist_ok=True)
    path = where / "rig.yaml"
    path.write_text(yaml.safe_dump({"rig": "sim", "board": FINE_BOARD, "sim": {"true_errors": errors}, **more}))
    return str(path)


def _matrix(e: dict) -> np.ndarray:
    rotation = Rotation.from_rotvec(e.get("rotation_deg", [0, 0, 0]), degrees=True).as_matrix()
    return make_pose(rotation, e.get("translation_m", [0, 0, 0]))


def _off(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(mm, degrees) from ``truth`` to ``T``."""
    D = invert_pose(truth) @ T
    return 1000 * float(np.linalg.norm(D[:3, 3])), float(np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()))


def _rows(out: str) -> dict[str, tuple[str, str]]:
    """rig check's table: item: (status, detail)."""
    start = out.index("status")
    return {line[:start].strip(): tuple(line[start:].split(None, 1)) for line in out.splitlines()[1:]}


# --- calibrate hand-eye --------------------------------------------------------------------------------------


@pytest.mark.parametrize("yaw", [10, -25])
def test_a_camera_turned_about_its_optical_axis_is_found_not_a_local_minimum(tmp_path, capsys, yaw):
    """From the nominal start alone the solve stopped 11 mm and 1.3 degrees off (rms 0.78 mm) for a 10-degree turn."""
    errors = {"hand_eye": {"rotation_deg": [0, 0, yaw], "translation_m": [0.003, -0.002, 0.004]}}
    out = tmp_path / "hand_eye.json"
    assert main(["calibrate", "hand-eye", "--rig", _rig(tmp_path, errors), "--out", str(out)]) == 0
    mm, deg = _off(load_hand_eye(out), nominal_T_hand_cam() @ _matrix(errors["hand_eye"]))
    assert mm < 1.0 and deg < 0.5, (mm, deg, capsys.readouterr().out.splitlines()[-2])


def test_on_the_shipped_mock_rig_a_camera_turned_about_its_optical_axis_is_found(tmp_path, capsys, monkeypatch):
    """The same through the real drivers (--mock), standard input closed, on mock.yaml's own board and camera as
    real-rig.md's chain on --mock uses them (its 7x5 board of 30 mm squares skipped every press)."""
    import os

    from tests.acquisition.acq_helpers import write_mock_rig

    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    errors = {"hand_eye": {"rotation_deg": [0, 0, 10]}}
    rig = write_mock_rig(tmp_path, sim={"true_errors": errors})
    out = tmp_path / "hand_eye.json"
    assert main(["calibrate", "hand-eye", "--rig", rig, "--out", str(out), "--mock"]) == 0, capsys.readouterr().err
    mm, deg = _off(load_hand_eye(out), nominal_T_hand_cam() @ _matrix(errors["hand_eye"]))
    assert mm < 1.0 and deg < 0.5, (mm, deg)


def test_on_mock_a_board_of_large_squares_skips_each_press_saying_why(tmp_path, capsys, monkeypatch):
    """From 4-10 cm a camera of 320x240 pixels, f 280 px (mock's old default) shows too few of a 7x5 board's 30 mm
    squares: each press line said "does not see the board" and the error told a person to press the fingertips,
    where --mock's emulated person presses them."""
    import os

    from tests.acquisition.acq_helpers import write_mock_rig

    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    coarse = {"squares_x": 7, "squares_y": 5, "square_length_m": 0.03, "marker_length_m": 0.022}
    out = tmp_path / "hand_eye.json"
    camera = {"camera_width": 320, "camera_height": 240, "camera_focal_px": 280.0}
    rig = write_mock_rig(tmp_path, board=coarse, mock_devices=camera)
    assert main(["calibrate", "hand-eye", "--rig", rig, "--out", str(out), "--mock"]) == 1
    stdout, err = capsys.readouterr()
    lines = [line for line in stdout.splitlines() if line.startswith("press ") and "/16: " in line]
    assert len(lines) == 16 and not out.exists()
    for line in lines:
        assert re.search(
            r": at every pose of the hand near the sphere the wrist camera finds at most [0-5] of the board's corners, "
            r"fewer than 6 \(board.min_corners\); skipped$",
            line,
        ), line
    assert err.splitlines()[-1] == (
        "error: hand-eye: no presses recorded: every press was skipped (its line above says why)"
    )


def _doc(name: str) -> str:
    return (Path(__file__).parents[2] / "docs" / name).read_text()


def test_real_rig_md_the_shipped_rigs_and_the_camera_steps_name_one_board():
    """real-rig.md said to print a 14x10 board of 15 mm squares while its camera step's command (without board
    options: a 7x5 board of 30 mm squares), hardware.md and real.yaml named the 7x5 one."""
    (line,) = {line for line in _doc("real-rig.md").splitlines() if line.startswith("board: {squares_x")}  # one
    board = yaml.safe_load(line)["board"]
    assert board == FINE_BOARD
    for name in ("real", "mock"):
        shipped = yaml.safe_load(example_rig(name).read_text())["board"]
        assert {key: shipped.get(key) for key in board} == board, name
    options = (
        f"--squares-x {board['squares_x']} --squares-y {board['squares_y']} "
        f"--square-mm {1000 * board['square_length_m']:g} --marker-mm {1000 * board['marker_length_m']:g}"
    )
    (step2,) = [line for line in _doc("real-rig.md").splitlines() if line.startswith("| 2 |")]
    assert f"`tacsplat calibrate camera photos/ {options} --out " in step2, step2
    hardware = " ".join(_doc("hardware.md").split())
    assert f"`tacsplat calibrate camera photos/ {options} --out camera.json`" in hardware


def test_real_rig_md_s_twin_example_hides_an_error_of_each_calibrated_part():
    """real-rig.md pointed to sim.yaml for sim.true_errors, which has no example of them."""
    text = _doc("real-rig.md")
    block = re.search(r"```yaml\n(rig: sim\n.*?)```", text, re.S).group(1)
    config = checked(RigConfig, yaml.safe_load(block))
    errors = config.sim.true_errors
    assert errors.joint_offsets_rad and errors.joint_signs and errors.mounts
    assert np.abs(errors.hand_eye.matrix() - np.eye(4)).max() > 0
    assert config.hand.calibration and config.camera.hand_eye and config.tactile.mounts  # what steps 1, 3, 4 write


def _calibrated_mounts(path: Path) -> None:
    """A mounts file of every sensor at the identity (the twin's true mounts when it hides no mounting error)."""
    fingers = list(FINGER_NAMES)
    identity = {f: np.eye(4) for f in fingers}
    save_mounts(MountsFit(np.eye(4), identity, {}, dict.fromkeys(fingers, 0.01), dict.fromkeys(fingers, 12), {}), path)


def test_presses_whose_rms_the_noise_cannot_explain_are_refused_and_the_old_file_kept(tmp_path, capsys, monkeypatch):
    """With the mounts calibrated, presses of a ball that moved 5 mm between presses fit no T_hand_cam within what
    the gel's noise and the mounts' precision explain: refused, naming what to check; the earlier file is kept."""
    from tacsplat.acquisition import presses

    run = presses.TwinPressSession.run

    def ball_moved(self, plan):  # every other press: the ball 5 mm further along x
        moved = make_pose(np.eye(3), [0.005, 0.0, 0.0])
        out = run(self, plan)
        return [dataclasses.replace(p, T_world_cam=moved @ p.T_world_cam) if i % 2 else p for i, p in enumerate(out)]

    monkeypatch.setattr(presses.TwinPressSession, "run", ball_moved)
    _calibrated_mounts(tmp_path / "mounts.json")
    out = tmp_path / "hand_eye.json"
    out.write_text("old hand-eye\n")
    rig = _rig(tmp_path, {"hand_eye": {"rotation_deg": [0, 0, 10]}}, tactile={"mounts": "mounts.json"})
    assert main(["calibrate", "hand-eye", "--rig", rig, "--out", str(out)]) == 1
    err = capsys.readouterr().err.splitlines()[-1]
    assert "mm (rms) off the sphere, more than the gel's noise and the calibrated mounts explain" in err, err
    assert "did not move between presses" in err
    assert out.read_text() == "old hand-eye\n"


def test_an_inline_T_hand_cam_that_shadows_the_hand_eye_file_is_warned_of_and_failed_by_rig_check(tmp_path, capsys):
    errors = {"hand_eye": {"translation_m": [0.003, -0.002, 0.004], "rotation_deg": [1, -2, 2]}}
    camera = {"hand_eye": "hand_eye.json", "T_hand_cam": nominal_T_hand_cam().tolist()}
    rig = _rig(tmp_path, errors, camera=camera)
    out = tmp_path / "hand_eye.json"
    assert main(["calibrate", "hand-eye", "--rig", rig, "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    warning = f"{rig} gives camera.T_hand_cam, which a capture uses instead of a hand-eye file: remove it"
    assert lines[0] == f"warning: {warning}"  # before the presses: there is time to stop
    assert lines[-1] == f"wrote {out} ({warning})"
    assert main(["rig", "check", "--rig", rig]) == 1
    status, detail = _rows(capsys.readouterr().out)["camera.hand_eye"]
    assert status == "FAIL" and "the rig file's camera.T_hand_cam, " in detail and "overrides it" in detail
    camera["T_hand_cam"] = load_hand_eye(out).tolist()  # the same value in the rig file: nothing overridden
    rig = _rig(tmp_path, errors, camera=camera)
    assert main(["rig", "check", "--rig", rig]) == 0, capsys.readouterr().out


# --- calibrate hand-eye --arm-poses --------------------------------------------------------------------------


def _inverted(stations):
    return [{**s, "T_base_hand": invert_pose(np.array(s["T_base_hand"])).tolist()} for s in stations]


def _swapped(stations):
    out = [dict(s) for s in stations]
    out[1]["T_base_hand"], out[4]["T_base_hand"] = stations[4]["T_base_hand"], stations[1]["T_base_hand"]
    return out


@pytest.mark.parametrize("change", [_inverted, _swapped])
def test_arm_poses_given_inverted_or_swapped_are_refused_and_the_old_file_kept(folder, capsys, change):  # noqa: F811
    name = change.__name__.strip("_")
    old = folder / f"{name}_hand_eye.json"
    save_hand_eye(old, np.eye(4), None, 0.1, stations=6)
    before = old.read_bytes()
    code, poses, out = _arm_run(folder, change(_stations(folder)), name)
    assert code == 1 and out == old and out.read_bytes() == before
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.startswith(f"error: {poses}: stations: the stations put the board in the arm's base up to "), err
    assert "are the poses T_base_hand (the hand in the arm's base, not T_hand_base)" in err


# --- calibrate mounts ----------------------------------------------------------------------------------------

MOUNT_ERRORS = {
    "hand_eye": {"translation_m": [0.004, 0.003, -0.004], "rotation_deg": [2, 2, -2]},
    "mounts": {"thumb": {"rotation_deg": [0, 0, 25]}, "middle": {"translation_m": [0.002, 0.0, 0.0]}},
}


def test_mounts_without_hand_eye_write_the_rigs_hand_eye_file_keep_a_far_mount_and_warn_of_an_inline_one(
    tmp_path, capsys
):
    """One run of calibrate mounts without --hand-eye on a twin whose rig names its hand-eye file (the nominal
    T_hand_cam; the truth 4 mm and 3 degrees off it), a thumb sensor mounted 25 degrees turned, and the middle
    sensor's mount given in the rig file itself (the identity; the truth 2 mm off it)."""
    save_hand_eye(tmp_path / "hand_eye.json", nominal_T_hand_cam(), 16, 0.3)
    middle = {"finger": "middle", "T_fingertip_sensor": np.eye(4).tolist()}
    tactile = {"mounts": "mounts.json", "sensors": [middle]}
    rig = _rig(tmp_path, MOUNT_ERRORS, camera={"hand_eye": "hand_eye.json"}, tactile=tactile)
    lines = []
    calibrate_mounts(load_rig(rig), tmp_path / "mounts.json", None, lines.append)

    # the rig's hand-eye file is written with the mounts, said before any press: left out of step with the old one,
    # a capture's touches were 2.9 mm off the mesh (0.03 mm with both)
    he = tmp_path / "hand_eye.json"
    assert f"T_hand_cam is solved with the mounts: {he} (the rig's camera.hand_eye) will be written with them" in lines
    assert lines[-2] == f"wrote {he} (the rig's camera.hand_eye)"
    mm, deg = _off(load_hand_eye(he), nominal_T_hand_cam() @ _matrix(MOUNT_ERRORS["hand_eye"]))
    assert mm < 1.0 and deg < 0.5, (mm, deg)
    assert json.loads(he.read_text())["presses"] > 16  # the mounts' presses, not the old file's

    # the thumb mounted 25 degrees turned is found and kept (it was refused as "too far from its start"), and said
    mm, deg = _off(
        load_mounts(tmp_path / "mounts.json", FINGER_NAMES)["thumb"], _matrix(MOUNT_ERRORS["mounts"]["thumb"])
    )
    assert mm < 0.5 and deg < 1.0, (mm, deg)
    (thumb,) = [line for line in lines if line.startswith("thumb: ")]
    assert re.search(r"; 0\.\d\d mm, 2[45]\.\d\d deg from the rig's previous mounting \(a large change, ", thumb), thumb

    # the middle sensor's own T_fingertip_sensor shadows the mounts file: warned of before the presses and after, and
    # rig check fails the file
    warning = f"{rig} gives tactile.sensors[0].T_fingertip_sensor, which a capture uses instead of the mounts file"
    assert f"warning: {warning}: remove it" in lines[:3]
    assert lines[-1] == f"wrote {tmp_path / 'mounts.json'} (4 sensors; {warning}: remove it)"
    assert main(["rig", "check", "--rig", rig]) == 1
    status, detail = _rows(capsys.readouterr().out)["tactile.mounts"]
    assert status == "FAIL" and "the rig file's tactile.sensors[0].T_fingertip_sensor, 2.0" in detail, detail


def test_without_hand_eye_a_rig_naming_no_hand_eye_file_is_refused_before_any_press(tmp_path, capsys):
    out = tmp_path / "mounts.json"
    assert main(["calibrate", "mounts", "--rig", _rig(tmp_path, MOUNT_ERRORS), "--out", str(out)]) == 2  # usage
    stdout, err = capsys.readouterr()
    assert "press" not in stdout and not out.exists()
    line = "tacsplat calibrate mounts: error: --hand-eye: calibrate mounts solves T_hand_cam with the mounts"
    assert len(err.splitlines()) == 1 and err.startswith(line), err


def _mounts_refused(tmp_path, capsys) -> str:
    """``calibrate mounts`` (the ring's mount 2 degrees off) over earlier files: refused, both kept; its error line."""
    out, he = tmp_path / "mounts.json", tmp_path / "hand_eye.json"
    out.write_text("old mounts\n")
    he.write_text("old hand-eye\n")
    errors = {"hand_eye": MOUNT_ERRORS["hand_eye"], "mounts": {"ring": {"rotation_deg": [2, -2, 0]}}}
    assert main(["calibrate", "mounts", "--rig", _rig(tmp_path, errors), "--out", str(out), "--hand-eye", str(he)]) == 1
    assert out.read_text() == "old mounts\n" and he.read_text() == "old hand-eye\n"
    return capsys.readouterr().err.splitlines()[-1]


def test_a_sensor_without_a_usable_press_is_refused_and_the_old_files_kept(tmp_path, capsys, monkeypatch):
    """Every ring press skipped (its camera view never showed the board, say): the mounts file was written without
    the ring, which a capture then took as mounted at the identity."""
    from tacsplat.acquisition import presses

    run = presses.TwinPressSession.run
    monkeypatch.setattr(
        presses.TwinPressSession, "run", lambda self, plan: [p for p in run(self, plan) if p.finger != "ring"]
    )
    err = _mounts_refused(tmp_path, capsys)
    assert err.startswith("error: calibrate mounts: no usable press of the ring sensor (each was skipped"), err


# --- rig check ------------------------------------------------------------------------------------------------


def test_rig_check_fails_a_mounts_file_without_a_sensor_of_the_rig(tmp_path, capsys):
    fingers = [f for f in FINGER_NAMES if f != "ring"]
    identity = {f: np.eye(4) for f in fingers}
    fit = MountsFit(np.eye(4), identity, {}, dict.fromkeys(fingers, 0.01), dict.fromkeys(fingers, 12), {})
    save_mounts(fit, tmp_path / "mounts.json")
    assert main(["rig", "check", "--rig", _rig(tmp_path, {}, tactile={"mounts": "mounts.json"})]) == 1
    status, detail = _rows(capsys.readouterr().out)["tactile.mounts"]
    assert status == "FAIL" and detail.endswith(
        "no entry for the ring sensor (calibrate mounts again, every sensor pressed)"
    )


def test_rig_check_fails_a_twin_hiding_errors_that_no_calibration_file_corrects(tmp_path, capsys):
    """As a real rig's check fails a missing hand calibration: the twin's capture would take each part as nominal."""
    errors = {"joint_offsets_rad": {"index_1": 0.05}, **MOUNT_ERRORS}
    assert main(["rig", "check", "--rig", _rig(tmp_path, errors)]) == 1
    out, err = capsys.readouterr()
    rows = _rows(out)
    assert {item for item, (status, _) in rows.items() if status == "FAIL"} == {
        "hand.calibration",
        "camera.hand_eye",
        "tactile.mounts",
    }
    assert rows["hand.calibration"][1].endswith(
        "twin hides joint errors (sim.true_errors): tacsplat calibrate hand writes it"
    )
    assert "mounting errors of the middle, thumb sensors" in rows["tactile.mounts"][1]
    assert (
        err.splitlines()[-1]
        == "error: rig check: 3 of 3 checks failed: hand.calibration; camera.hand_eye; tactile.mounts"
    )
    assert main(["rig", "check", "--rig", str(example_rig("sim"))]) == 0  # a twin that hides nothing needs no file


def test_mounts_whose_presses_the_noise_cannot_explain_are_refused_and_the_old_files_kept(
    tmp_path, capsys, monkeypatch
):
    """The sphere moved 10 mm on its stand between presses: no mounts fit the presses within the gel's noise and a
    calibrated mount's precision. Judged by that rms, no longer by the distance from the start."""
    from tacsplat.acquisition import presses

    run = presses.TwinPressSession.run

    def stand_moved(self, plan):  # every other press on the stand: the sphere 10 mm further along x
        moved = make_pose(np.eye(3), [0.010, 0.0, 0.0])
        out = run(self, plan)
        return [
            dataclasses.replace(p, T_world_cam=moved @ p.T_world_cam) if p.placement == 1 and i % 2 else p
            for i, p in enumerate(out)
        ]

    monkeypatch.setattr(presses.TwinPressSession, "run", stand_moved)
    err = _mounts_refused(tmp_path, capsys)
    assert "at the best solution found the contact points lie off the sphere by (rms) the " in err, err
    assert "more than the gel's noise and a calibrated mount explain (0.58 mm)" in err
