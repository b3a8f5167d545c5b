"""A rig file's sim.true_errors: parsed and checked (one error naming the file and field), and the twin's servos
hide the joint errors the way a miscalibrated real hand does."""

import numpy as np
import pytest
import yaml

from tacsplat.acquisition.config import load_rig, parse_rig
from tacsplat.acquisition.devices import twin_config
from tacsplat.drivers.calibration import HandCalibration
from tacsplat.errors import ConfigError
from tacsplat.sim.hand import JOINT_LIMITS, JOINT_NAMES, HandKinematics
from tacsplat.sim.twin import SimTwin


def _sim_rig(tmp_path, true_errors, **more):
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"rig": "sim", "sim": {"object": "torus", "true_errors": true_errors}, **more}))
    return path


def test_every_kind_of_true_error_is_read_in_the_twins_joint_order(tmp_path):
    errors = {
        "joint_offsets_rad": {"index_0": 0.05, "thumb_3": -0.1},
        "joint_signs": {"middle_1": -1},
        "hand_eye": {"translation_m": [0.004, 0, -0.002], "rotation_deg": [0, 2.5, 0]},
        "mounts": {"ring": {"translation_m": [0.001, 0.002, 0], "rotation_deg": [3, 0, 0]}},
    }
    e = load_rig(_sim_rig(tmp_path, errors)).sim.true_errors
    assert e.servo_offsets() == (0.05,) + (0.0,) * 14 + (-0.1,)
    assert e.servo_signs()[JOINT_NAMES.index("middle_1")] == -1 and sum(e.servo_signs()) == 14
    E = e.hand_eye.matrix()
    assert np.allclose(E[:3, 3], [0.004, 0, -0.002])
    assert np.isclose(np.degrees(np.arccos((np.trace(E[:3, :3]) - 1) / 2)), 2.5)
    assert np.allclose(e.mounts["ring"].matrix()[:3, 3], [0.001, 0.002, 0])


@pytest.mark.parametrize(
    "errors, key, words",
    [
        ({"joint_offsets_rad": {"index_7": 0.1}}, "sim.true_errors.joint_offsets_rad.index_7", "unknown joint"),
        (
            {"joint_offsets_rad": {"index_0": 3.5}},
            "sim.true_errors.joint_offsets_rad.index_0",
            "[-3.14159, 3.14159] rad",
        ),
        ({"joint_offsets_rad": {"index_0": "a lot"}}, "sim.true_errors.joint_offsets_rad.index_0", "finite number"),
        ({"joint_signs": {"ring_2": 0}}, "sim.true_errors.joint_signs.ring_2", "1 or -1"),
        ({"hand_eye": {"translation_m": [0, 0, 0.2]}}, "sim.true_errors.hand_eye.translation_m[2]", "[-0.05, 0.05]"),
        ({"hand_eye": {"rotation_deg": [1, 2]}}, "sim.true_errors.hand_eye.rotation_deg", "list of more than 2"),
        ({"hand_eye": {"rotation": [1, 2, 3]}}, "sim.true_errors.hand_eye.rotation", "unknown key"),
        ({"mounts": {"pinky": {}}}, "sim.true_errors.mounts.pinky", "unknown finger"),
        ({"mounts": {"index": {"rotation_deg": [0, 45, 0]}}}, "sim.true_errors.mounts.index.rotation_deg[1]", "30"),
        ({"mounts": {"index": {"shift": [0, 0, 0]}}}, "sim.true_errors.mounts.index.shift", "unknown key"),
        ({"joints": {}}, "sim.true_errors.joints", "unknown key"),
    ],
)
def test_each_invalid_true_error_is_one_error_naming_the_file_and_field(errors, key, words):
    with pytest.raises(ConfigError) as err:
        parse_rig({"rig": "sim", "sim": {"true_errors": errors}}, "my-rig.yaml")
    assert err.value.key == key and words in str(err.value)
    assert str(err.value).startswith("my-rig.yaml: ")


def test_hardware_changed_is_a_date_or_a_date_and_time(tmp_path):
    assert parse_rig(yaml.safe_load("rig: sim\nhardware_changed: 2025-03-14 15:30\n")).hardware_changed.hour == 15
    with pytest.raises(ConfigError, match="hardware_changed: expected a date"):
        parse_rig({"rig": "sim", "hardware_changed": "last week"}, "rig.yaml")


@pytest.fixture(scope="module")
def offsets():
    return np.random.default_rng(5).uniform(-0.1, 0.1, 16)


def _settle(twin, seconds=1.5):
    twin.sleep(seconds)
    return twin.data.qpos[[twin.model.joint(n).qposadr[0] for n in JOINT_NAMES]].copy()


def test_the_twins_servos_read_and_move_off_the_truth_by_the_hidden_offsets(tmp_path, offsets):
    signs = np.ones(16)
    signs[5] = -1
    errors = {
        "joint_offsets_rad": dict(zip(JOINT_NAMES, offsets.tolist())),
        "joint_signs": {JOINT_NAMES[5]: -1},
    }
    with SimTwin(twin_config(load_rig(_sim_rig(tmp_path, errors)))) as twin:
        hand = twin.hand
        q_true = np.clip(np.full(16, 0.3), JOINT_LIMITS[:, 0] + 0.15, JOINT_LIMITS[:, 1] - 0.15)
        q_true[5] = -0.05  # the reversed servo: its command -q + offset stays inside the limits the hand clamps to
        hand.command_joint_positions(signs * q_true + offsets)  # what the uncalibrated hand must be told
        true = _settle(twin)
        assert np.abs(true - q_true).max() < 0.01  # position servos under gravity compensation
        read = hand.read_joint_positions()
        assert np.allclose(read, signs * true + offsets)  # a servo reads sign * q + offset
        assert np.allclose(hand.read_motor_angles(), read)  # no calibration: joint = motor angle
        # the rig computes poses from what it reads, not from the hidden truth
        kin = HandKinematics()
        assert np.allclose(hand.fingertip_poses()["index"], kin.fingertip_poses(read)["index"])
        assert not np.allclose(hand.fingertip_poses()["index"], kin.fingertip_poses(true)["index"], atol=1e-3)
        reading = twin.tactile_sensors[0].read()
        assert np.allclose(reading.T_ref_sensor, hand.fingertip_poses()["index"])


def test_with_the_true_calibration_the_twin_reads_and_moves_to_the_truth(tmp_path, offsets):
    errors = {"joint_offsets_rad": dict(zip(JOINT_NAMES, offsets.tolist()))}
    HandCalibration(tuple(JOINT_NAMES), np.ones(16), offsets).save(tmp_path / "hand.json")
    rig = _sim_rig(tmp_path, errors, hand={"calibration": "hand.json"})
    with SimTwin(twin_config(load_rig(rig))) as twin:
        q = np.clip(np.full(16, 0.4), JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1])
        twin.hand.command_joint_positions(q)
        true = _settle(twin)
        assert np.abs(true - q).max() < 0.01
        assert np.allclose(twin.hand.read_joint_positions(), true)
        assert np.allclose(twin.hand.read_joint_targets(), q)


def test_a_sim_rigs_missing_hand_calibration_is_one_error_naming_the_file(tmp_path):
    rig = load_rig(_sim_rig(tmp_path, {}, hand={"calibration": "nowhere/hand.json"}))
    with pytest.raises(ConfigError) as err:
        SimTwin(twin_config(rig))
    assert "nowhere/hand.json" in str(err.value) and "file not found" in str(err.value)
