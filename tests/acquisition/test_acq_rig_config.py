"""Rig YAML: the shipped examples load; each invalid value is one ConfigError naming the key and the file."""

import pytest
import yaml

from tacsplat.acquisition.config import example_rig, load_rig
from tacsplat.errors import ConfigError


@pytest.mark.parametrize("name", ["real", "mock", "sim"])
def test_shipped_rig_files_load(name):
    config = load_rig(example_rig(name), mock=name != "sim")
    assert config.rig in ("real", "sim")
    assert config.source == str(example_rig(name))


def test_real_rig_without_mock_needs_its_calibration_files():
    with pytest.raises(ConfigError) as err:
        load_rig(example_rig("real"))
    assert err.value.key == "camera.calibration" and "file not found" in str(err.value)
    assert "real.yaml" in str(err.value)


def _real(**changes):
    data = yaml.safe_load(example_rig("real").read_text())
    for dotted, value in changes.items():
        node = data
        *parents, last = dotted.split("/")
        for p in parents:
            node = node[int(p)] if isinstance(node, list) else node.setdefault(p, {})
        node[last] = value
    return data


@pytest.mark.parametrize(
    "changes, key, words",
    [
        ({"rig": "robot"}, "rig", "must be 'real' or 'sim'"),
        ({"hand/prot": "/dev/ttyUSB1"}, "hand.prot", "unknown key"),
        ({"hand/baudrate": "fast"}, "hand.baudrate", "expected an integer"),
        ({"hand/ids": [0, 1, 2]}, "hand.ids", "16 distinct"),
        ({"board/max_reprojection_px": 0}, "board.max_reprojection_px", "must be positive"),
        ({"board/dictionary": "DICT_9X9_1"}, "board.dictionary", "unknown ArUco dictionary"),
        ({"board/marker_length_m": 0.05}, "board.marker_length_m", "smaller than"),
        ({"camera/T_hand_cam": [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "camera.T_hand_cam",
         "not a rigid transform"),
        ({"camera/T_hand_cam": [[1, 0], [0, 1]]}, "camera.T_hand_cam", "4x4"),
        ({"tactile/sensors/1/finger": "pinky"}, "tactile.sensors[1].finger", "must be one of"),
        ({"tactile/sensors/1/finger": "index"}, "tactile.sensors[1].finger", "two sensors"),
        ({"tactile/sensors/0/T_fingertip_sensor": "identity"}, "tactile.sensors[0].T_fingertip_sensor", "4x4"),
        ({"grasp/close_pose": [0.1] * 15}, "grasp.close_pose", "16 joint positions"),
        ({"grasp/stall_error_rad": -1}, "grasp.stall_error_rad", "must be positive"),
        ({"plan/views/train": -2}, "plan.views.train", "non-negative"),
        ({"plan/views/mode": "hemisphere"}, "plan.views.mode", "positioned by the operator"),
        ({"plan/grasps/mode": "auto"}, "plan.grasps.mode", "'operator' or 'random'"),
        ({"plan/grasps/count": 2.5}, "plan.grasps.count", "expected an integer"),
    ],
)
def test_invalid_rig_is_one_error_naming_key_and_file(tmp_path, changes, key, words):
    path = tmp_path / "bad_rig.yaml"
    path.write_text(yaml.safe_dump(_real(**changes)))
    with pytest.raises(ConfigError) as err:
        load_rig(path, mock=True)
    assert err.value.key == key, str(err.value)
    assert words in str(err.value)
    assert str(path) in str(err.value)


def test_unreadable_or_empty_rig_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_rig(tmp_path / "missing.yaml")
    (tmp_path / "broken.yaml").write_text("rig: [real\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_rig(tmp_path / "broken.yaml")
    (tmp_path / "empty.yaml").write_text("")
    with pytest.raises(ConfigError) as err:
        load_rig(tmp_path / "empty.yaml")
    assert err.value.key == "rig"


def test_sim_rig_checks_its_object(tmp_path):
    path = tmp_path / "sim.yaml"
    path.write_text(yaml.safe_dump({"rig": "sim", "sim": {"object": "spaceship"}}))
    with pytest.raises(ConfigError) as err:
        load_rig(path)
    assert err.value.key == "sim.object" and "teapot" in str(err.value)


def test_capture_command_checks_the_output_folder_before_opening_devices(tmp_path, capsys):
    from tacsplat.cli import main

    rig = str(example_rig("mock"))
    assert main(["capture", "--rig", rig, "--out", str(tmp_path / "none"), "--resume", "--mock"]) == 1
    assert "--resume: " in capsys.readouterr().err
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "journal.jsonl").write_text("{}\n")
    assert main(["capture", "--rig", rig, "--out", str(tmp_path / "old"), "--mock"]) == 1
    assert "already holds a scene: add --resume" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("rig: real\nhand: {port: 3}\n")
    assert main(["capture", "--rig", str(bad), "--out", str(tmp_path / "new"), "--mock"]) == 1
    assert f"{bad}: hand.port: expected a non-empty string" in capsys.readouterr().err


@pytest.mark.parametrize("args, option", [(["--views", "-1"], "--views"), (["--grasps", "-3"], "--grasps"),
                                          (["--object", "spaceship"], "--object"),
                                          (["--mesh", "/no/such/mesh.ply"], "--mesh"),
                                          (["--resolution", "4"], "--resolution")])
def test_sim_capture_options_are_checked_before_the_twin_starts(tmp_path, capsys, args, option):
    from tacsplat.cli import main

    assert main(["sim-capture", *args, "--out", str(tmp_path / "scene")]) == 1
    assert f"error: {option}: " in capsys.readouterr().err
    assert not (tmp_path / "scene").exists()
