"""tacsplat rig check on the mock rig: a ready rig passes; a missing sensor, a missing servo, a stale or missing
calibration and an unseen board are each named in the table and in the one error line (exit 1)."""

import json
import os
from datetime import datetime

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
