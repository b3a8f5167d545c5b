"""A rig: sim file sets only what the twin reads: a key of the real rig's devices that no twin run reads (a hand
port, a camera source, a tactile timeout, mock_devices, a sensor's source or calibration, a sensor entry without its
mounting) is one error naming the file and every such key, in every command that takes the file; the keys the twin
reads (the calibration files, the inline poses, the board, the plan, sim) still load and are used."""

import dataclasses
import typing
from pathlib import Path

import numpy as np
import pytest
import yaml

from tacsplat.acquisition import config as rig_config
from tacsplat.acquisition.capture_scene import capture_settings
from tacsplat.acquisition.config import (
    TWIN_READS,
    TWIN_SENSOR,
    TWIN_SENSOR_READS,
    RigConfig,
    TactileSensorConfig,
    load_rig,
)
from tacsplat.acquisition.devices import twin_config
from tacsplat.cli import main
from tacsplat.errors import ConfigError

# a value other than the default for each key of the real rig's sections that the twin never reads
UNREAD = {
    "hand.port": "/dev/nothing",
    "hand.baudrate": 9600,
    "hand.ids": list(range(1, 17)),
    "camera.source": 3,
    "camera.fps": 30.0,
    "camera.timeout_s": 1.0,
    "tactile.sensor_name": "gelsight",
    "tactile.gel_thickness_m": 0.01,
    "tactile.timeout_s": 1.0,
    "grasp.poll_s": 0.01,
    "grasp.open_s": 1.0,
    "mock_devices.camera_width": 16,
    "mock_devices.tactile_pixel_size_m": 1e-4,
    "mock_devices.servo_timeout_s": 0.2,
    "mock_devices.unplugged": ["camera"],
    "mock_devices.board_in_view": False,
}
T_MOUNT = [[1.0, 0.0, 0.0, 0.002], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
T_HAND_CAM = [[1.0, 0.0, 0.0, 0.01], [0.0, 1.0, 0.0, -0.05], [0.0, 0.0, 1.0, 0.03], [0.0, 0.0, 0.0, 1.0]]


def _write(tmp_path, data: dict):
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"rig": "sim", **data}))
    return path


def _section(dotted: str, value) -> dict:
    section, key = dotted.split(".")
    return {section: {key: value}}


def test_every_key_of_the_real_rigs_sections_is_either_read_by_the_twin_or_refused():
    """The keys refused are exactly those the twin does not read: each of the hand's, camera's and tactile section's
    that UNREAD names, and every key of grasp and mock_devices (which UNREAD samples)."""
    hints = typing.get_type_hints(RigConfig)
    unread = {
        f"{section}.{f.name}"
        for section, (read, _) in TWIN_READS.items()
        for f in dataclasses.fields(hints[section])
        if f.name not in read
    }
    assert unread == {key for key in UNREAD if not key.startswith(("grasp.", "mock_devices."))} | {
        f"{section}.{f.name}" for section in ("grasp", "mock_devices") for f in dataclasses.fields(hints[section])
    }
    assert {f.name for f in dataclasses.fields(TactileSensorConfig)} - set(TWIN_SENSOR_READS[0]) == {
        "source",
        "calibration",
    }


@pytest.mark.parametrize("dotted", list(UNREAD))
def test_a_key_refused_on_a_twin_changes_nothing_a_twin_run_reads(dotted):
    """Set in code (where the file's rule does not apply), each refused key leaves the twin and the scene's settings
    as they were: a file that set it would have been ignored."""
    base = RigConfig(rig="sim")
    section, key = dotted.split(".")
    value = UNREAD[dotted]
    changed = dataclasses.replace(
        base,
        **{
            section: dataclasses.replace(
                getattr(base, section), **{key: tuple(value) if isinstance(value, list) else value}
            )
        },
    )
    assert twin_config(changed) == twin_config(base)
    assert capture_settings(changed) == capture_settings(base)


@pytest.mark.parametrize("dotted", list(UNREAD))
def test_a_sim_rig_that_sets_a_key_the_twin_never_reads_is_one_error_naming_file_and_key(tmp_path, dotted):
    rig = _write(tmp_path, _section(dotted, UNREAD[dotted]))
    with pytest.raises(ConfigError) as err:
        load_rig(rig)
    assert str(err.value) == f"{rig}: {dotted}: {TWIN_READS[dotted.split('.')[0]][1]}"


@pytest.mark.parametrize(
    "command",
    [
        ["rig", "check"],
        ["sim-capture", "--out", "{out}"],
        ["capture", "--out", "{out}"],
        ["calibrate", "hand", "--out", "{out}"],
        ["calibrate", "hand-eye", "--out", "{out}"],
        ["calibrate", "mounts", "--out", "{out}", "--hand-eye", "{he}"],
    ],
)
def test_each_command_refuses_it_before_it_starts(tmp_path, capsys, command):
    rig = _write(tmp_path, {"plan": {"views": {"train": 2}}, "hand": {"calibration": "hand.json", "port": "/dev/x"}})
    out, he = tmp_path / "out", tmp_path / "he.json"
    args = [a.format(out=out, he=he) for a in command] + ["--rig", str(rig)]
    assert main(args) == 1
    stdout, err = capsys.readouterr()
    assert err.strip() == f"error: {rig}: hand.port: {TWIN_READS['hand'][1]}", err
    assert stdout == "" and not out.exists() and not he.exists()


def test_a_sim_rigs_sensor_without_its_mounting_is_refused(tmp_path):
    """A sensor entry gives its finger's mounting, and only that."""
    sensors = [{"finger": "index", "T_fingertip_sensor": T_MOUNT}, {"finger": "thumb"}]
    rig = _write(tmp_path, {"tactile": {"sensors": sensors}})
    with pytest.raises(ConfigError) as err:
        load_rig(rig)
    assert str(err.value) == f"{rig}: tactile.sensors[1].T_fingertip_sensor: {TWIN_SENSOR}"


def test_the_keys_a_twin_reads_load_and_are_used(tmp_path, capsys):
    """Every key TWIN_READS allows, with the sections the twin reads whole, loads; the twin takes the hand
    calibration, the inline T_hand_cam and the sensor's mounting, and calibrate hand-eye --arm-poses the camera
    calibration."""
    sensor = {"finger": "middle", "T_fingertip_sensor": T_MOUNT}
    rig = _write(
        tmp_path,
        {
            "object": "cup",
            "hardware_changed": "2025-03-14",
            "hand": {"calibration": "hand.json"},
            "camera": {"hand_eye": "he.json", "T_hand_cam": T_HAND_CAM, "calibration": "camera.json"},
            "tactile": {"mounts": "mounts.json", "sensors": [sensor]},
            "board": {"squares_x": 14, "squares_y": 10, "square_length_m": 0.015, "marker_length_m": 0.011},
            "plan": {"views": {"train": 2, "test": 1, "mode": "hemisphere"}, "grasps": {"count": 1, "mode": "random"}},
            "sim": {"object": "torus", "resolution": 16},
            "grasp": {},
            "mock_devices": None,
        },
    )
    config = load_rig(rig)
    twin = twin_config(config, calibrating=True)
    assert twin.hand_calibration == str(tmp_path / "hand.json")
    np.testing.assert_array_equal(twin.T_hand_cam, T_HAND_CAM)
    np.testing.assert_array_equal(twin.mounts["middle"], T_MOUNT)
    assert config.scene_object == "cup"
    poses = tmp_path / "stations.yaml"
    poses.write_text("stations: []\n")
    out = tmp_path / "hand_eye.json"
    assert main(["calibrate", "hand-eye", "--rig", str(rig), "--out", str(out), "--arm-poses", str(poses)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {rig}: camera.calibration: file not found: {tmp_path / 'camera.json'} "), err


@pytest.mark.parametrize("key", ["source", "calibration"])
def test_a_sim_rigs_sensor_giving_a_source_or_calibration_is_refused_naming_it(tmp_path, key):
    """The twin opens no device and reads no tactile calibration: a sensor entry copied from a real rig says so."""
    value = {"source": 2, "calibration": "index.npz"}[key]
    rig = _write(tmp_path, {"tactile": {"sensors": [{"finger": "index", key: value, "T_fingertip_sensor": T_MOUNT}]}})
    with pytest.raises(ConfigError) as err:
        load_rig(rig)
    assert str(err.value) == f"{rig}: tactile.sensors[0].{key}: {TWIN_SENSOR_READS[1]}"


@pytest.mark.parametrize("key", ["source", "calibration"])
def test_a_real_rigs_sensor_needs_its_source_and_calibration(tmp_path, key):
    sensor = {"finger": "index", "source": 2, "calibration": "index.npz"}
    del sensor[key]
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump({"rig": "real", "tactile": {"sensors": [{"finger": "thumb", **sensor}, sensor]}}))
    with pytest.raises(ConfigError) as err:
        load_rig(rig, check_files=False)
    assert str(err.value) == f"{rig}: tactile.sensors[0].{key}: missing (a required key)"


def test_a_real_rig_file_made_sim_is_one_error_naming_every_key_the_twin_never_reads(tmp_path):
    """The real rig's example file with rig: sim: one run names them all (the first as the error's key; a section the
    twin reads none of, as the section), not one run per key."""
    text = (Path(rig_config.__file__).parent / "rigs" / "real.yaml").read_text()
    assert "\nrig: real\n" in text
    rig = tmp_path / "rig.yaml"
    rig.write_text(text.replace("\nrig: real\n", "\nrig: sim\n"))
    with pytest.raises(ConfigError) as err:
        load_rig(rig)
    unread = ["hand.port", "hand.baudrate", "hand.ids", "camera.source", "camera.timeout_s"]
    unread += ["tactile.sensor_name", "tactile.gel_thickness_m", "grasp (the whole section)"]
    unread += [f"tactile.sensors[{i}].{key}" for i in range(4) for key in ("source", "calibration")]
    assert err.value.key == "hand.port"
    assert str(err.value) == (
        f"{rig}: hand.port: {TWIN_READS['hand'][1]}; the twin reads none of these: {', '.join(unread)} "
        "(remove them all)"
    )


def test_a_sim_rig_with_several_unread_keys_names_each(tmp_path):
    """Keys of several sections and a sensor's, in the order of TWIN_READS, then the sensors'."""
    sensors = [{"finger": "index", "T_fingertip_sensor": T_MOUNT}, {"finger": "ring", "source": 3}]
    data = {
        "mock_devices": {"camera_width": 16, "unplugged": ["camera"]},
        "tactile": {"timeout_s": 1.0, "sensors": sensors},
        "camera": {"fps": 30.0},
    }
    rig = _write(tmp_path, data)
    with pytest.raises(ConfigError) as err:
        load_rig(rig)
    assert str(err.value) == (
        f"{rig}: camera.fps: {TWIN_READS['camera'][1]}; the twin reads none of these: camera.fps, tactile.timeout_s, "
        "mock_devices (the whole section), tactile.sensors[1].source (remove them all)"
    )
