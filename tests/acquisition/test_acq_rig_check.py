"""tacsplat rig check on the mock rig: a ready rig passes; a missing sensor, a missing servo, a stale or missing
calibration and an unseen board are each named in the table and in the one error line (exit 1)."""

import dataclasses
import json
import os
import time
from datetime import datetime

import cv2
import numpy as np
import pytest
import yaml

from tacsplat.cli import main
from tacsplat.drivers.calibration import HandCalibration
from tacsplat.sim.hand import JOINT_NAMES


def _mock_rig(tmp_path, **changes) -> str:
    from tests.acquisition.acq_helpers import write_mock_rig

    HandCalibration.identity(JOINT_NAMES).save(tmp_path / "hand.json")
    return write_mock_rig(tmp_path, hand={"calibration": "hand.json"}, **changes)


def _check(rig, capsys) -> tuple[int, dict[str, tuple[str, str]], str]:
    code = main(["rig", "check", "--rig", rig, "--mock"])
    out, err = capsys.readouterr()
    rows = {}
    for line in out.splitlines()[1:]:
        parts = line.split("  ")
        cells = [p.strip() for p in parts if p.strip()]
        if len(cells) >= 3:
            rows[cells[0]] = (cells[1], "  ".join(cells[2:]))
    return code, rows, err


def test_a_ready_mock_rig_passes_every_check(tmp_path, capsys):
    code, rows, err = _check(_mock_rig(tmp_path, hardware_changed="2024-01-01"), capsys)
    assert code == 0, err
    assert all(status == "ok" for status, _ in rows.values()), rows
    names = set(rows)
    assert {"hand.calibration", "camera.T_hand_cam", "board", "tactile ring (source 6)"} <= names
    assert any(name.startswith("servos (16 on ") for name in names)
    assert rows["board"][1].startswith("seen: ")


def test_a_missing_sensor_a_missing_servo_a_stale_calibration_and_an_unseen_board_are_each_named(tmp_path, capsys):
    rig = _mock_rig(
        tmp_path,
        hardware_changed="2025-03-14 15:30",
        mock_devices={"unplugged": ["ring", "servo 3"], "board_in_view": False},
    )
    old = datetime(2025, 3, 1).timestamp()
    os.utime(tmp_path / "hand.json", (old, old))  # calibrated before the hardware changed
    code, rows, err = _check(rig, capsys)
    assert code == 1
    failed = {name for name, (status, _) in rows.items() if status == "FAIL"}
    servos = next(name for name in rows if name.startswith("servos"))
    assert failed == {"hand.calibration", "tactile ring (source 6)", servos, "board"}
    assert "stale: written 2025-03-01 00:00, before hardware_changed 2025-03-14 15:30" in rows["hand.calibration"][1]
    assert "servos 3 (index_3) did not answer" in rows[servos][1]
    assert "cannot open" in rows["tactile ring (source 6)"][1] or "ring" in rows["tactile ring (source 6)"][1]
    assert rows["board"][1].startswith("not seen")
    last = err.splitlines()[-1]  # (above it, the driver's log: servo 3 could not confirm torque off)
    assert last.startswith("error: rig check: 4 of 14 checks failed: ") and "tactile ring (source 6)" in last


@pytest.mark.parametrize(
    "content, words",
    [(None, "missing"), ('{"format": "tacsplat-hand-calibration", "version": 1, "joints": {}}', "joints.index_0")],
)
def test_a_missing_or_implausible_hand_calibration_is_named(tmp_path, capsys, content, words):
    rig = _mock_rig(tmp_path)
    (tmp_path / "hand.json").unlink()
    if content:
        (tmp_path / "hand.json").write_text(content)
    code, rows, err = _check(rig, capsys)
    assert code == 1 and rows["hand.calibration"][0] == "FAIL" and words in rows["hand.calibration"][1]
    assert "hand.calibration" in err.splitlines()[-1]


def test_a_hand_calibration_far_from_the_truth_reads_joints_outside_their_limits(tmp_path, capsys):
    rig = _mock_rig(tmp_path)
    offsets = np.zeros(16)
    offsets[JOINT_NAMES.index("ring_0")] = 1.0  # a whole radian off: the open hand reads -57 degrees
    HandCalibration(tuple(JOINT_NAMES), np.ones(16), offsets).save(tmp_path / "hand.json")
    code, rows, err = _check(rig, capsys)
    servos = next(name for name in rows if name.startswith("servos"))
    assert code == 1 and rows[servos][0] == "FAIL" and "ring_0 reads -57.3 deg" in rows[servos][1]
    assert yaml.safe_load(open(rig))["hand"]["calibration"] == "hand.json"


def test_a_twin_rig_checks_each_calibration_file_it_names(tmp_path, capsys):
    """rig: sim: the hand, hand-eye and mounts files are checked as a real rig's; a stale hand-eye file and a mounts
    file with an unknown finger are named, and the twin is not started for a rig that fails them."""
    from tacsplat.drivers.press_calibration import save_hand_eye

    HandCalibration.identity(JOINT_NAMES).save(tmp_path / "hand.json")
    save_hand_eye(tmp_path / "hand_eye.json", np.eye(4), presses=16, rms_mm=0.01)
    old = datetime(2025, 3, 1).timestamp()
    os.utime(tmp_path / "hand_eye.json", (old, old))
    mounts = {
        "format": "tacsplat-mounts",
        "version": 1,
        "sensors": {"pinky": {"T_fingertip_sensor": np.eye(4).tolist()}},
    }
    (tmp_path / "mounts.json").write_text(json.dumps(mounts))
    rig = tmp_path / "rig.yaml"
    rig.write_text(
        yaml.safe_dump(
            {
                "rig": "sim",
                "hardware_changed": "2025-03-14",
                "hand": {"calibration": "hand.json"},
                "camera": {"hand_eye": "hand_eye.json"},
                "tactile": {"mounts": "mounts.json"},
                "sim": {"resolution": 16},
            }
        )
    )
    code = main(["rig", "check", "--rig", str(rig)])
    out, err = capsys.readouterr()
    rows = {line.split()[0]: line.split(None, 2)[1:] for line in out.splitlines()[1:]}
    assert code == 1
    assert rows["hand.calibration"][0] == "ok"
    assert rows["camera.hand_eye"][0] == "FAIL" and "stale" in rows["camera.hand_eye"][1]
    assert rows["tactile.mounts"][0] == "FAIL" and "sensors.pinky" in rows["tactile.mounts"][1]
    assert "twin hand" not in rows
    assert err.splitlines()[-1] == "error: rig check: 2 of 3 checks failed: camera.hand_eye; tactile.mounts"


def _real_rig(tmp_path, T_hand_cam_in_camera_file: bool, hand_eye: str | None) -> str:
    """A real rig (nothing plugged in: its device rows fail) as docs/real-rig.md writes it: camera.json from
    calibrate camera (with or without a T_hand_cam), and a hand-eye file named as camera.hand_eye."""
    from tacsplat.drivers.wrist_camera import CameraCalibration

    K = np.array([[600.0, 0, 319.5], [0, 600, 239.5], [0, 0, 1]])
    T = np.eye(4) if T_hand_cam_in_camera_file else None
    CameraCalibration(K, np.zeros(5), 640, 480, T_hand_cam=T).save(tmp_path / "camera.json")
    camera = {"source": str(tmp_path / "no_camera"), "calibration": "camera.json", "timeout_s": 0.2}
    if hand_eye:
        camera["hand_eye"] = hand_eye
    sensor = {"finger": "index", "source": str(tmp_path / "no_gel"), "calibration": "index.npz"}
    rig = {
        "rig": "real",
        "hand": {"port": str(tmp_path / "no_tty")},
        "camera": camera,
        "tactile": {"sensors": [sensor]},
    }
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    return str(tmp_path / "rig.yaml")


def _rows(capsys) -> dict[str, tuple[str, str]]:
    out = capsys.readouterr().out
    return {
        line[: out.index("status")].strip(): line[out.index("status") :].split(None, 1) for line in out.splitlines()[1:]
    }


def test_a_real_rig_knows_T_hand_cam_from_its_hand_eye_file_as_a_capture_does(tmp_path, capsys):
    """camera.json from calibrate camera has no T_hand_cam; the hand-eye file the rig names gives it (the row says
    so); a hand-eye file named but not there fails the row, though the camera file has one (a capture would
    refuse that rig)."""
    from tacsplat.drivers.press_calibration import save_hand_eye

    save_hand_eye(tmp_path / "hand_eye.json", np.eye(4), presses=16, rms_mm=0.1)
    assert main(["rig", "check", "--rig", _real_rig(tmp_path, False, "hand_eye.json")]) == 1  # nothing plugged in
    rows = _rows(capsys)
    assert rows["camera.T_hand_cam"] == ["ok", f"from camera.hand_eye ({tmp_path / 'hand_eye.json'})"]

    assert main(["rig", "check", "--rig", _real_rig(tmp_path, True, "missing.json")]) == 1
    rows = _rows(capsys)
    assert rows["camera.hand_eye"][0] == "FAIL"
    status, detail = rows["camera.T_hand_cam"]
    assert status == "FAIL" and f"{tmp_path / 'missing.json'}: camera.hand_eye: file not found" in detail

    assert main(["rig", "check", "--rig", _real_rig(tmp_path, True, None)]) == 1
    assert _rows(capsys)["camera.T_hand_cam"] == ["ok", "from the camera calibration"]


@pytest.mark.parametrize("minutes", [-1, 1])
def test_a_hardware_changed_time_with_a_utc_offset_is_compared_as_that_instant(tmp_path, capsys, minutes):
    """hardware_changed: 2025-03-14T15:30:00Z (a YAML timestamp with an offset): a file written a minute before that
    instant is stale, one a minute after is not, whatever this machine's time zone."""
    from datetime import timezone

    changed = datetime(2025, 3, 14, 15, 30, tzinfo=timezone.utc)
    rig = _mock_rig(tmp_path, hardware_changed=changed)
    assert "hardware_changed: 2025-03-14 15:30:00+00:00" in open(rig).read()  # a timestamp, not a string
    written = changed.timestamp() + 60 * minutes
    os.utime(tmp_path / "hand.json", (written, written))
    code, rows, err = _check(rig, capsys)
    status, detail = rows["hand.calibration"]
    assert (status == "FAIL" and "stale" in detail) if minutes < 0 else status == "ok", (detail, err)
    assert code == (1 if minutes < 0 else 0), err


class _ModeCamera:
    """A UVC-like tactile camera: 640x480 unless asked for another size, which it delivers if ``switches``."""

    switches = True

    def __init__(self, source):
        self.w, self.h = 640, 480

    def isOpened(self):
        return True

    def set(self, prop, value):
        if self.switches and prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            setattr(self, "w" if prop == cv2.CAP_PROP_FRAME_WIDTH else "h", int(value))
            return True
        return False

    def get(self, prop):
        settings = {cv2.CAP_PROP_FRAME_WIDTH: self.w, cv2.CAP_PROP_FRAME_HEIGHT: self.h, cv2.CAP_PROP_FPS: 30.0}
        return settings.get(prop, 0)

    def read(self):
        time.sleep(0.01)
        return True, np.full((self.h, self.w, 3), 128, np.uint8)

    def release(self):
        pass


@pytest.mark.parametrize("switches", [True, False])
def test_tactile_sensors_are_asked_for_their_calibrations_size(tmp_path, capsys, monkeypatch, switches):
    """A tactile camera whose default mode is not its calibration's (160x120 on --mock) passes when it can switch
    to that size, as a capture opens it; one that cannot fails its row, saying so."""
    from tacsplat.acquisition.mock import MockDevices

    factory = MockDevices.capture_factory
    monkeypatch.setattr(_ModeCamera, "switches", switches)
    monkeypatch.setattr(
        MockDevices, "capture_factory", lambda self, name: factory(self, name) if name == "camera" else _ModeCamera
    )
    code, rows, err = _check(_mock_rig(tmp_path), capsys)
    row = rows["tactile index (source 2)"]
    if switches:
        assert code == 0 and row[0] == "ok" and row[1].startswith("160x120 at "), rows
    else:
        assert code == 1 and row[0] == "FAIL" and "asked for 160x120, the device delivers 640x480" in row[1], rows


def test_the_shipped_mock_rig_passes_rig_check_as_its_header_says(tmp_path, capsys, monkeypatch):
    """mock.yaml names no calibration file ("none are needed with --mock"): its emulated servos hide no joint
    errors, so a missing hand calibration is not a failure there, as on a twin hiding none."""
    from tacsplat.acquisition.config import example_rig

    (tmp_path / "rig.yaml").write_text(example_rig("mock").read_text())
    monkeypatch.chdir(tmp_path)
    code, rows, err = _check("rig.yaml", capsys)
    assert code == 0, err
    assert "hand.calibration" not in rows


def test_a_hand_calibration_is_needed_where_the_joints_read_off_their_truth():
    """:func:`uncalibrated_hand`: a real rig's hand always (its servos' offsets are unknown), an emulated or twin
    hand when ``sim.true_errors`` hides joint errors; never once one is named."""
    from tacsplat.acquisition.config import example_rig, load_rig
    from tacsplat.acquisition.devices import uncalibrated_hand

    real = load_rig(example_rig("real"), check_files=False)
    assert "raw angles" in uncalibrated_hand(
        dataclasses.replace(real, hand=dataclasses.replace(real.hand, calibration=None))
    )
    mock = load_rig(example_rig("mock"), mock=True)
    assert uncalibrated_hand(mock) is None
    offsets = dataclasses.replace(mock.sim.true_errors, joint_offsets_rad={"ring_0": 0.05})
    hidden = dataclasses.replace(mock, sim=dataclasses.replace(mock.sim, true_errors=offsets))
    assert "hides joint errors" in uncalibrated_hand(hidden)
    named = dataclasses.replace(hidden, hand=dataclasses.replace(hidden.hand, calibration="hand.json"))
    assert uncalibrated_hand(named) is None
