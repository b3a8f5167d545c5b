"""Hand and camera calibration files: every value is checked where it enters, one ConfigError names file and field."""

import json
import math

import numpy as np
import pytest

from tacsplat.drivers.calibration import HandCalibration
from tacsplat.drivers.wrist_camera import CameraCalibration, CharucoBoardSpec
from tacsplat.errors import ConfigError, InvalidInputError
from tacsplat.geometry import make_pose

JOINTS = [f"{finger}_{k}" for finger in ("index", "middle", "ring", "thumb") for k in range(4)]


def raises_config_error(path, field):
    """The one error: a ConfigError naming this file and this field."""
    return pytest.raises(ConfigError, match=rf"^{path}: {field}: ")


# -- hand.json -----------------------------------------------------------------
def hand_json(**index_0) -> dict:
    joints = {name: {"sign": 1, "offset_rad": 0.0} for name in JOINTS}
    joints["index_0"] = {"sign": 1, "offset_rad": 0.0} | index_0
    return {"format": "tacsplat-hand-calibration", "version": 1, "joints": joints}


def test_good_hand_calibration_round_trips(tmp_path):
    cal = HandCalibration(tuple(JOINTS), np.where(np.arange(16) % 2, 1.0, -1.0), np.linspace(-math.pi, math.pi, 16))
    cal.save(tmp_path / "hand.json")
    loaded = HandCalibration.load(tmp_path / "hand.json", JOINTS)
    np.testing.assert_array_equal(loaded.signs, cal.signs)
    np.testing.assert_array_equal(loaded.offsets_rad, cal.offsets_rad)


@pytest.mark.parametrize(
    "field, value",
    [
        ("offset_rad", 45.0),  # the reported calibration: 45 rad moved the servo seven turns
        ("offset_rad", 1e9),  # wrapped through int32
        ("offset_rad", -3.2),
        ("offset_rad", "0.1"),
        ("offset_rad", True),
        ("offset_rad", None),
        ("offset_rad", [0.1]),
        ("sign", True),
        ("sign", 0),
        ("sign", 2),
        ("sign", -0.5),
        ("sign", "1"),
        ("sign", None),
    ],
)
def test_bad_hand_calibration_value_names_file_and_field(tmp_path, field, value):
    path = tmp_path / "hand.json"
    path.write_text(json.dumps(hand_json(**{field: value})))
    with raises_config_error(path, rf"joints\.index_0\.{field}"):
        HandCalibration.load(path, JOINTS)


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e400"])
def test_non_finite_offset_is_refused(tmp_path, literal):
    path = tmp_path / "hand.json"
    path.write_text(json.dumps(hand_json()).replace('"offset_rad": 0.0', f'"offset_rad": {literal}', 1))
    with raises_config_error(path, r"joints\.index_0\.offset_rad"):
        HandCalibration.load(path, JOINTS)


def test_duplicated_joint_is_refused(tmp_path):
    path = tmp_path / "hand.json"
    text = json.dumps(hand_json())
    # a second index_0 entry: plain json.loads would keep the last one silently
    path.write_text(text.replace('"joints": {', '"joints": {"index_0": {"sign": -1, "offset_rad": 0.3}, ', 1))
    with raises_config_error(path, r"joints\.index_0") as exc:
        HandCalibration.load(path, JOINTS)
    assert "twice" in str(exc.value)


def test_unknown_and_missing_joints_are_refused(tmp_path):
    path = tmp_path / "hand.json"
    data = hand_json()
    data["joints"]["pinky_0"] = {"sign": 1, "offset_rad": 0.0}
    path.write_text(json.dumps(data))
    with raises_config_error(path, r"joints\.pinky_0"):
        HandCalibration.load(path, JOINTS)
    del data["joints"]["pinky_0"], data["joints"]["thumb_3"]
    path.write_text(json.dumps(data))
    with raises_config_error(path, r"joints\.thumb_3"):
        HandCalibration.load(path, JOINTS)


@pytest.mark.parametrize("version", [True, 2, "1", None])
def test_hand_calibration_version_must_be_1(tmp_path, version):
    path = tmp_path / "hand.json"
    path.write_text(json.dumps(hand_json() | {"version": version}))
    with raises_config_error(path, "version"):
        HandCalibration.load(path, JOINTS)


@pytest.mark.parametrize(
    "signs, offsets, what",
    [
        (np.ones(16), np.full(16, 4.0), "offset"),
        (np.ones(16), np.full(16, np.nan), "offset"),
        (np.zeros(16), np.zeros(16), "sign"),
        (np.ones(15), np.zeros(16), "16"),
    ],
)
def test_hand_calibration_built_in_code_is_checked_too(signs, offsets, what):
    with pytest.raises(InvalidInputError, match=what):
        HandCalibration(tuple(JOINTS), signs, offsets)


# -- camera.json -----------------------------------------------------------------
K_GOOD = np.array([[600.0, 0.0, 321.5], [0.0, 605.0, 237.5], [0.0, 0.0, 1.0]])
T_GOOD = make_pose(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [0.01, 0.02, 0.06])


@pytest.fixture
def camera_file(tmp_path):
    """A valid camera calibration file, and a function that rewrites one of its fields."""
    path = tmp_path / "camera.json"
    CameraCalibration(
        K_GOOD,
        np.array([-0.28, 0.09, 0.0005, -0.0003, 0.0]),
        640,
        480,
        0.31,
        CharucoBoardSpec(),
        {"img0.png": 0.3},
        T_hand_cam=T_GOOD,
    ).save(path)

    def rewrite(update):
        data = json.loads(path.read_text())
        update(data)
        path.write_text(json.dumps(data))
        return path

    return path, rewrite


def test_good_camera_calibration_loads(camera_file):
    path, _ = camera_file
    cal = CameraCalibration.load(path)
    np.testing.assert_array_equal(cal.K_opencv, K_GOOD)
    np.testing.assert_array_equal(cal.T_hand_cam, T_GOOD)
    assert (cal.width, cal.height, cal.rms_px, cal.per_image_rms_px) == (640, 480, 0.31, {"img0.png": 0.3})
    assert cal.board == CharucoBoardSpec()


def _set(key, value):
    def update(data):
        target = data
        *parents, last = key.split(".")
        for p in parents:
            target = target[p]
        target[last] = value

    return update


def _K(**entries):
    K = K_GOOD.tolist()
    for name, value in entries.items():
        K[int(name[1])][int(name[2])] = value
    return K


BAD_CAMERA_FIELDS = [
    ("K_opencv", _K(k00=-600.0)),  # negative focal length
    ("K_opencv", _K(k11=0.0)),
    ("K_opencv", _K(k02=700.0)),  # principal point right of the image
    ("K_opencv", _K(k12=-3.0)),  # above it
    ("K_opencv", _K(k20=1.0)),  # not a pinhole matrix
    ("K_opencv", _K(k01="0")),
    ("K_opencv", _K(k01=True)),
    ("K_opencv", [[600.0, 0.0, 321.5], [0.0, 605.0, 237.5]]),
    ("K_opencv", [[600.0, 0.0], [0.0, 605.0, 237.5], [0.0, 0.0, 1.0]]),
    ("K_opencv", None),
    ("width", 0),
    ("width", -640),
    ("width", 640.5),
    ("width", "640"),
    ("width", True),
    ("height", None),
    ("dist", [0.1, "0.2", 0.0, 0.0, 0.0]),
    ("dist", [0.1, 0.2, 0.0]),
    ("dist", [[0.1, 0.2], [0.0, 0.0, 0.0]]),
    ("dist", None),
    ("T_hand_cam", (2.0 * T_GOOD).tolist()),  # scaled: not a rigid transform
    ("T_hand_cam", (T_GOOD @ np.diag([1.0, 1.0, -1.0, 1.0])).tolist()),  # a reflection
    ("T_hand_cam", T_GOOD[:3].tolist()),
    ("T_hand_cam", "identity"),
    ("rms_px", "0.3"),
    ("rms_px", -1.0),
    ("board.square_length_m", -0.03),
    ("board.squares_x", 7.5),
    ("board.marker_length_m", 0.05),  # larger than the square
    ("board.dictionary", "DICT_NOPE"),
    ("board.legacy_pattern", "no"),
    ("board.colour", "red"),
    ("board.type", ["chessboard"]),  # a list where a name belongs (unhashable)
    ("per_image_rms_px.img0.png", "0.3"),
    ("version", 2),
    ("pixel_centres", "tacsplat (+0.5)"),
    ("T_hand_camera", np.eye(4).tolist()),  # a misspelt field is not silently ignored
]


@pytest.mark.parametrize("field, value", BAD_CAMERA_FIELDS)
def test_bad_camera_calibration_value_names_file_and_field(camera_file, field, value):
    path, rewrite = camera_file
    if field.startswith("per_image_rms_px."):
        rewrite(lambda d: d["per_image_rms_px"].update({"img0.png": value}))
    else:
        rewrite(_set(field, value))
    with raises_config_error(path, field.replace(".", r"\.")):
        CameraCalibration.load(path)


@pytest.mark.parametrize(
    "field, value",
    [
        ("K_opencv", _K(k01=math.nan)),
        ("dist", [math.inf, 0.0, 0.0, 0.0, 0.0]),
        ("T_hand_cam", np.where(np.eye(4) == 1, T_GOOD, math.nan).tolist()),
    ],
)
def test_non_finite_camera_values_are_refused(camera_file, field, value):
    path, rewrite = camera_file
    rewrite(_set(field, value))
    assert "NaN" in path.read_text() or "Infinity" in path.read_text()
    with raises_config_error(path, field):
        CameraCalibration.load(path)


@pytest.mark.parametrize("field", ["width", "height", "K_opencv", "dist"])
def test_missing_camera_field_is_refused(camera_file, field):
    path, rewrite = camera_file
    rewrite(lambda d: d.pop(field))
    with raises_config_error(path, field):
        CameraCalibration.load(path)


def test_duplicated_camera_key_is_refused(camera_file):
    path, _ = camera_file
    path.write_text(path.read_text().replace('"width": 640', '"width": 640, "width": 1280', 1))
    with raises_config_error(path, "width"):
        CameraCalibration.load(path)
