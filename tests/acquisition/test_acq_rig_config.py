"""Rig YAML: the shipped examples load; each invalid value is one ConfigError naming the key and the file."""

import pytest
import yaml

from tacsplat.acquisition.config import CapturePlan, HandConfig, example_rig, load_rig
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
        ({"board/max_reprojection_px": 0}, "board.max_reprojection_px", "must be in (0, 50] px, got 0"),
        ({"board/dictionary": "DICT_9X9_1"}, "board.dictionary", "unknown ArUco dictionary"),
        ({"board/marker_length_m": 0.05}, "board.marker_length_m", "smaller than"),
        (
            {"camera/T_hand_cam": [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
            "camera.T_hand_cam",
            "not a rigid transform",
        ),
        ({"camera/T_hand_cam": [[1, 0], [0, 1]]}, "camera.T_hand_cam", "4x4"),
        ({"tactile/sensors/1/finger": "pinky"}, "tactile.sensors[1].finger", "must be one of"),
        ({"tactile/sensors/1/finger": "index"}, "tactile.sensors[1].finger", "two sensors"),
        ({"tactile/sensors/0/T_fingertip_sensor": "identity"}, "tactile.sensors[0].T_fingertip_sensor", "4x4"),
        ({"grasp/close_pose": [0.1] * 15}, "grasp.close_pose", "16 joint positions"),
        ({"grasp/stall_error_rad": -1}, "grasp.stall_error_rad", "must be in (0, 3.14159] rad, got -1"),
        ({"plan/views/train": -2}, "plan.views.train", "must be >= 1, got -2"),
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


REFLECTION = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]]
PROJECTIVE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1]]


@pytest.mark.parametrize(
    "changes, key, words",
    [
        ({"object": ""}, "object", "expected a non-empty string"),
        ({"hand/port": "  "}, "hand.port", "expected a non-empty string"),
        ({"hand/baudrate": 12345}, "hand.baudrate", "one of the Dynamixel rates (9600, 57600, 115200, 1000000"),
        ({"hand/ids": list(range(15)) + [300]}, "hand.ids[15]", "must be in [0, 252], got 300"),
        ({"camera/source": -1}, "camera.source", "a device index (>= 0) or a path"),
        ({"camera/fps": 0}, "camera.fps", "must be in (0, 1000] Hz, got 0"),
        ({"camera/timeout_s": 1e6}, "camera.timeout_s", "must be in (0, 60] s"),
        ({"board/square_length_m": 3}, "board.square_length_m", "must be in (0, 1] m, got 3"),
        ({"board/squares_x": 50}, "board.dictionary", "DICT_5X5_100 has 100 markers; a 50 x 10 board needs 250"),
        ({"board/min_corners": 2}, "board.min_corners", "must be in [4, 10000], got 2"),
        ({"board/min_corners": 200}, "board.min_corners", "a 14 x 10 board has 117 inner corners"),
        ({"board/legacy_pattern": "yes"}, "board.legacy_pattern", "expected true or false"),
        ({"tactile/gel_thickness_m": 0.5}, "tactile.gel_thickness_m", "must be in (0, 0.02] m, got 0.5"),
        (
            {"tactile/sensors/2/T_fingertip_sensor": REFLECTION},
            "tactile.sensors[2].T_fingertip_sensor",
            "rotation determinant is -1, expected 1",
        ),
        (
            {"tactile/sensors/2/T_fingertip_sensor": PROJECTIVE},
            "tactile.sensors[2].T_fingertip_sensor",
            "last row is [0.0, 0.0, 0.5, 1.0], expected [0, 0, 0, 1]",
        ),
        (
            {"tactile/sensors/2/T_fingertip_sensor": [[float("nan")] * 4] * 4},
            "tactile.sensors[2].T_fingertip_sensor",
            "contains NaN",
        ),
        ({"tactile/sensors/0/source": -3}, "tactile.sensors[0].source", "a device index (>= 0) or a path"),
        ({"tactile/timeout_s": 0}, "tactile.timeout_s", "must be in (0, 60] s"),
        (
            {"grasp/close_pose": [0.0] * 3 + [7.0] + [0.0] * 12},
            "grasp.close_pose[3]",
            "must be in [-3.14159, 3.14159] rad",
        ),
        ({"grasp/settle_tol_rad": 0.2}, "grasp.settle_tol_rad", "smaller than grasp.stall_error_rad (0.15)"),
        ({"grasp/max_close_s": 0.01}, "grasp.max_close_s", "longer than grasp.poll_s (0.02)"),
        ({"grasp/open_s": -1}, "grasp.open_s", "must be in [0, 60] s, got -1"),
        ({"plan/views/train": 0}, "plan.views.train", "must be >= 1, got 0"),
        ({"plan/views/test": -1}, "plan.views.test", "must be >= 0, got -1"),
        ({"plan/grasps/seed": -1}, "plan.grasps.seed", "must be >= 0, got -1"),
        ({"mock_devices/camera_width": 0}, "mock_devices.camera_width", "must be in [16, 4096] px, got 0"),
    ],
)
def test_physically_impossible_values_are_one_error_naming_the_field_and_the_range(tmp_path, changes, key, words):
    path = tmp_path / "bad_rig.yaml"
    path.write_text(yaml.safe_dump(_real(**changes)))
    with pytest.raises(ConfigError) as err:
        load_rig(path, mock=True)
    assert err.value.key == key, str(err.value)
    assert words in str(err.value) and str(path) in str(err.value), str(err.value)


def test_an_empty_section_keeps_its_defaults(tmp_path):
    path = tmp_path / "sim.yaml"
    path.write_text("rig: sim\nhand:\n  # port: /dev/ttyUSB1\nplan:\n")
    config = load_rig(path)
    assert config.hand == HandConfig() and config.plan == CapturePlan()


def test_zero_test_views_and_zero_grasps_are_a_valid_plan(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(_real(**{"plan/views/test": 0, "plan/grasps/count": 0})))
    plan = load_rig(path, mock=True).plan
    assert (plan.views.train, plan.views.test, plan.grasps.count) == (20, 0, 0)


@pytest.mark.parametrize(
    "sim, key, words",
    [
        ({"resolution": 10000}, "sim.resolution", "must be in [8, 4096] px, got 10000"),
        ({"object_radius": 2.0}, "sim.object_radius", "must be in [0.025, 0.3] m, got 2"),
        ({"object_radius": float("inf")}, "sim.object_radius", "expected a finite number"),
        ({"seed": -1}, "sim.seed", "must be >= 0, got -1"),
        ({"texture": "plaid"}, "sim.texture", "must be one of 'none', 'checker', got 'plaid'"),
        ({"object_radius": 0.08, "view_radius_m": 0.05}, "plan.views.radius_m", "larger than sim.object_radius (0.08)"),
    ],
)
def test_sim_rig_values_are_checked(tmp_path, sim, key, words):
    view_radius = sim.pop("view_radius_m", None)
    path = tmp_path / "sim.yaml"
    path.write_text(
        yaml.safe_dump({"rig": "sim", "sim": sim, "plan": {"views": {"mode": "hemisphere", "radius_m": view_radius}}})
    )
    with pytest.raises(ConfigError) as err:
        load_rig(path)
    assert err.value.key == key and words in str(err.value) and str(path) in str(err.value), str(err.value)


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


@pytest.mark.parametrize(
    "args, option, words",
    [
        (["--views", "-1"], "--views", "must be >= 1, got -1"),
        (["--views", "0"], "--views", "must be >= 1, got 0"),
        (["--test-views", "-1"], "--test-views", "must be >= 0, got -1"),
        (["--grasps", "-3"], "--grasps", "must be >= 0, got -3"),
        (["--object", "spaceship"], "--object", "unknown library object"),
        (["--mesh", "/no/such/mesh.ply"], "--mesh", "file not found"),
        (["--resolution", "4"], "--resolution", "must be in [8, 4096] px, got 4"),
        (["--resolution", "0"], "--resolution", "must be in [8, 4096] px, got 0"),
        (["--resolution", "100000"], "--resolution", "must be in [8, 4096] px, got 100000"),
        (["--object-radius", "0"], "--object-radius", "must be in [0.025, 0.3] m"),
        (["--object-radius", "-0.1"], "--object-radius", "must be in [0.025, 0.3] m"),
        (["--object-radius", "5"], "--object-radius", "must be in [0.025, 0.3] m"),
        (["--object-radius", "nan"], "--object-radius", "must be in [0.025, 0.3] m"),
        (["--seed", "-1"], "--seed", "must be >= 0, got -1"),
    ],
)
def test_sim_capture_options_are_checked_before_the_twin_starts(tmp_path, capsys, args, option, words):
    from tacsplat.cli import main

    # a value out of its range is a usage error (2); a file that is not there is a runtime error (1)
    assert main(["sim-capture", *args, "--out", str(tmp_path / "scene")]) == (1 if option == "--mesh" else 2)
    err = capsys.readouterr().err
    assert f"error: {option}: {words}" in err, err
    assert not (tmp_path / "scene").exists()
