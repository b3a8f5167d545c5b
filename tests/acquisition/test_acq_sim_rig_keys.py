"""A rig: sim file sets only what the twin reads: a key of the real rig's devices that no twin run reads (a hand
port, a camera source, a tactile timeout, mock_devices, a sensor entry without its mounting) is one error naming the
file and the key, in every command that takes the file; the keys the twin reads (the calibration files, the inline
poses, the board, the plan, sim) still load and are used."""

import dataclasses
import typing

import numpy as np
import pytest
import yaml

from tacsplat.acquisition.capture_scene import capture_settings
from tacsplat.acquisition.config import TWIN_READS, TWIN_SENSOR, RigConfig, load_rig
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
    """A sensor entry copied from a real rig gives a source and a calibration, which the twin does not read."""
    sensors = [
        {"finger": "index", "source": 0, "calibration": "index.npz", "T_fingertip_sensor": T_MOUNT},
        {"finger": "thumb", "source": 1, "calibration": "thumb.npz"},
    ]
    rig = _write(tmp_path, {"tactile": {"sensors": sensors}})
    with pytest.raises(ConfigError) as err:
        load_rig(rig)
    assert str(err.value) == f"{rig}: tactile.sensors[1].T_fingertip_sensor: {TWIN_SENSOR}"


def test_the_keys_a_twin_reads_load_and_are_used(tmp_path, capsys):
    """Every key TWIN_READS allows, with the sections the twin reads whole, loads; the twin takes the hand
    calibration, the inline T_hand_cam and the sensor's mounting, and calibrate hand-eye --arm-poses the camera
    calibration."""
    sensor = {"finger": "middle", "source": 0, "calibration": "unused.npz", "T_fingertip_sensor": T_MOUNT}
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
