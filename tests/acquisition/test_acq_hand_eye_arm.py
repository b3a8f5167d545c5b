"""tacsplat calibrate hand-eye --arm-poses: from arm stations whose board images are rendered through a known,
distorted camera at a known T_hand_cam, it finds T_hand_cam within 1 mm and 0.5 degree; each bad input is one error
naming the file, the field and the station, and a hand turned about one axis only is refused."""

import json
import re

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from tacsplat.acquisition.config import BoardConfig
from tacsplat.acquisition.mock import render_board
from tacsplat.cli import main
from tacsplat.drivers.press_calibration import load_hand_eye, save_hand_eye
from tacsplat.drivers.wrist_camera import CameraCalibration
from tacsplat.geometry import invert_pose, look_at, make_pose

pytestmark = pytest.mark.timeout(60)

W, H = 640, 480
K = np.array([[600.0, 0.0, 322.0], [0.0, 600.0, 241.0], [0.0, 0.0, 1.0]])  # tacsplat convention (+0.5)
K_OPENCV = K - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
DIST = np.array([-0.12, 0.03, 0.0, 0.0, 0.0])  # a mild barrel lens: the images must be undistorted
BOARD = BoardConfig()  # the rig's board: 7 x 5 squares of 30 mm
T_HAND_CAM = make_pose(Rotation.from_rotvec([0.05, -0.1, 0.2]).as_matrix(), [0.012, -0.058, 0.031])
T_BASE_BOARD = make_pose(np.diag([1.0, -1.0, -1.0]), [0.5, -0.1, 0.0])  # OpenCV board frame, face up in the base
CENTRE = (T_BASE_BOARD @ [3.5 * BOARD.square_length_m, 2.5 * BOARD.square_length_m, 0.0, 1.0])[:3]


def _raw_image(T_base_cam: np.ndarray) -> np.ndarray:
    """The camera's raw (distorted) BGR image of the board from ``T_base_cam``."""
    ideal = render_board(BOARD.spec(), K, W, H, invert_pose(T_base_cam) @ T_BASE_BOARD)
    maps = cv2.initInverseRectificationMap(K_OPENCV, DIST, None, K_OPENCV, (W, H), cv2.CV_32FC1)
    return cv2.remap(ideal, maps[0], maps[1], cv2.INTER_LINEAR, borderValue=150)


def _varied_cameras() -> list[np.ndarray]:
    """Six camera poses 0.33-0.42 m from the board's centre, tilted up to 30 degrees towards every side and
    rolled: the hand turns about many axes."""
    rng = np.random.default_rng(3)
    poses = []
    for k in range(6):
        azimuth, tilt = 2 * np.pi * k / 6, np.radians(rng.uniform(10, 30))
        direction = [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
        roll = np.radians(rng.uniform(-40, 40))
        eye = CENTRE + rng.uniform(0.33, 0.42) * np.array(direction)
        poses.append(look_at(eye, CENTRE + rng.normal(0, 0.01, 3), up=(np.cos(roll), np.sin(roll), 0.0)))
    return poses


def _one_axis_cameras() -> list[np.ndarray]:
    """Five camera poses turned about the vertical through the board's centre only."""
    first = look_at(CENTRE + [0.05, 0.0, 0.36], CENTRE, up=(1.0, 0.0, 0.0))
    turn = lambda deg: make_pose(Rotation.from_euler("z", deg, degrees=True).as_matrix(), [0, 0, 0])  # noqa: E731
    about_centre = lambda deg: make_pose(np.eye(3), CENTRE) @ turn(deg) @ make_pose(np.eye(3), -CENTRE)  # noqa: E731
    return [about_centre(deg) @ first for deg in (-40, -20, 0, 20, 40)]


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """A rig (a real rig's file, its camera calibration, a previous T_hand_cam) and the stations' images."""
    folder = tmp_path_factory.mktemp("arm")
    CameraCalibration(K_OPENCV, DIST, W, H, board=BOARD.spec()).save(folder / "camera.json")
    rig = {
        "rig": "real",
        "camera": {"calibration": "camera.json", "T_hand_cam": np.eye(4).tolist()},
        "tactile": {"sensors": [{"finger": "index", "source": 2, "calibration": "index.npz"}]},
        "board": {"squares_x": BOARD.squares_x, "squares_y": BOARD.squares_y},
    }
    (folder / "rig.yaml").write_text(yaml.safe_dump(rig))
    for prefix, cameras in (("station", _varied_cameras()), ("turn", _one_axis_cameras())):
        for k, T_base_cam in enumerate(cameras):
            cv2.imwrite(str(folder / f"{prefix}_{k}.png"), _raw_image(T_base_cam))
            np.save(folder / f"{prefix}_{k}.npy", T_base_cam @ invert_pose(T_HAND_CAM))  # T_base_hand
    cv2.imwrite(str(folder / "blank.png"), np.full((H, W, 3), 150, np.uint8))
    (folder / "broken.png").write_bytes(b"not a png")
    return folder


def _stations(folder, prefix: str = "station") -> list[dict]:
    return [
        {"T_base_hand": np.load(path).tolist(), "image": path.with_suffix(".png").name}
        for path in sorted(folder.glob(f"{prefix}_*.npy"))
    ]


def _run(folder, stations, name: str, rig: str = "rig.yaml", suffix: str = ".yaml") -> tuple[int, str, str]:
    """``calibrate hand-eye --arm-poses`` on ``stations`` written to ``name``: (exit code, the file written)."""
    poses = folder / f"{name}{suffix}"
    text = json.dumps({"stations": stations}) if suffix == ".json" else yaml.safe_dump({"stations": stations})
    poses.write_text(text)
    out = folder / f"{name}_hand_eye.json"
    args = ["calibrate", "hand-eye", "--rig", str(folder / rig), "--out", str(out), "--arm-poses", str(poses)]
    return main(args), poses, out


def _error(T: np.ndarray) -> tuple[float, float]:
    """(mm, degrees) between ``T`` and the true T_hand_cam."""
    D = invert_pose(T_HAND_CAM) @ T
    return 1000 * float(np.linalg.norm(D[:3, 3])), float(np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()))


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_arm_stations_give_T_hand_cam_within_1_mm_and_half_a_degree(folder, capsys, suffix):
    code, _, out = _run(folder, _stations(folder), "good", suffix=suffix)
    lines = capsys.readouterr().out.splitlines()
    assert code == 0
    mm, deg = _error(load_hand_eye(out))
    print(f"T_hand_cam {mm:.3f} mm, {deg:.3f} deg off the truth")
    assert mm < 1.0 and deg < 0.5
    assert [line.split(":")[0] for line in lines[:6]] == [f"stations[{k}] station_{k}.png" for k in range(6)]
    assert all("corners" in line and " px" in line for line in lines[:6])
    assert lines[6].startswith("T_hand_cam from 6 arm stations: translation [")
    assert lines[7].startswith("consistency: the board's pose in the arm's base is ")
    assert lines[8].endswith("deg from the rig's previous value") and lines[9].startswith(f"wrote {out}")
    saved = json.loads(out.read_text())
    assert saved["stations"] == 6 and "presses" not in saved and saved["rms_mm"] < 1.0


def test_the_change_is_from_the_rigs_hand_eye_file_even_when_it_is_the_one_written(folder, capsys):
    save_hand_eye(folder / "previous.json", np.eye(4), 10, 0.3)
    rig = yaml.safe_load((folder / "rig.yaml").read_text())
    rig["camera"] = {"calibration": "camera.json", "hand_eye": "previous.json"}
    (folder / "rig_with_hand_eye.yaml").write_text(yaml.safe_dump(rig))
    poses = folder / "again.yaml"
    poses.write_text(yaml.safe_dump({"stations": _stations(folder)}))
    out = folder / "previous.json"
    args = ["calibrate", "hand-eye", "--rig", str(folder / "rig_with_hand_eye.yaml"), "--out", str(out)]
    assert main(args + ["--arm-poses", str(poses)]) == 0
    change = re.search(r"T_hand_cam: ([\d.]+) mm, ([\d.]+) deg from the rig's previous value", capsys.readouterr().out)
    mm, deg = _error(np.eye(4))  # the previous file's identity, not the new value
    assert abs(float(change[1]) - mm) < 1.0 and abs(float(change[2]) - deg) < 0.5
    assert json.loads(out.read_text())["stations"] == 6


def test_a_hand_turned_about_one_axis_is_refused(folder, capsys):
    code, poses, out = _run(folder, _stations(folder, "turn"), "one_axis")
    err = capsys.readouterr().err
    assert code == 1 and not out.exists()
    assert f"{poses}: stations: the hand turns about one axis only" in err
    assert "add stations with the hand rotated about another axis" in err


def _mirrored(T):
    return (np.diag([1.0, 1.0, -1.0, 1.0]) @ np.array(T)).tolist()


def _with(index: int, **changes):
    """The stations with station ``index`` changed (a value of None drops the field)."""

    def change(stations):
        stations[index] = {k: v for k, v in {**stations[index], **changes}.items() if v is not None}
        return stations

    return change


def _millimetres(stations):
    stations[3]["T_base_hand"] = (np.array(stations[3]["T_base_hand"]) * [1, 1, 1, 1000]).tolist()
    stations[3]["T_base_hand"][3][3] = 1.0
    return stations


REFUSALS = {  # case: (change to the stations, what the error says)
    "no T_base_hand": (_with(1, T_base_hand=None), "stations[1].T_base_hand: missing"),
    "no image": (_with(2, image=None), "stations[2].image: missing"),
    "mirrored": (lambda s: _with(0, T_base_hand=_mirrored(s[0]["T_base_hand"]))(s), "stations[0].T_base_hand: not a"),
    "3x4": (lambda s: _with(4, T_base_hand=s[4]["T_base_hand"][:3])(s), "stations[4].T_base_hand: must be a 4x4"),
    "last row": (
        lambda s: _with(5, T_base_hand=s[5]["T_base_hand"][:3] + [[0, 0, 1, 1]])(s),
        "stations[5].T_base_hand: not a rigid transform: last row",
    ),
    "not finite": (
        lambda s: _with(2, T_base_hand=[[float("nan")] + s[2]["T_base_hand"][0][1:]] + s[2]["T_base_hand"][1:])(s),
        "stations[2].T_base_hand: contains NaN",
    ),
    "millimetres": (_millimetres, "stations[3].T_base_hand: puts the hand"),
    "image missing": (_with(1, image="nowhere.png"), "stations[1].image: image not found"),
    "image unreadable": (_with(3, image="broken.png"), "stations[3].image: cannot read the image"),
    "board seen at 2 stations": (
        lambda s: [_with(k, image="blank.png")(s) for k in (0, 2, 3, 5)][-1],
        "stations: the board was seen at 2 of 6 stations; at least 3 are needed",
    ),
}


@pytest.mark.parametrize("case", REFUSALS)
def test_each_bad_station_is_one_error_naming_the_file_and_field(folder, capsys, case):
    change, message = REFUSALS[case]
    code, poses, out = _run(folder, change(_stations(folder)), case.replace(" ", "_"))
    captured = capsys.readouterr()
    assert code == 1 and not out.exists()
    assert captured.err.count("\n") == 1 and "Traceback" not in captured.err
    assert f"error: {poses}: {message}" in captured.err
    if case == "board seen at 2 stations":
        assert "stations[0] blank.png: skipped: board not found" in captured.out


def test_a_missing_poses_file_or_camera_calibration_is_one_error_naming_it(folder, capsys):
    out = folder / "never.json"
    missing = folder / "missing.yaml"
    args = ["calibrate", "hand-eye", "--rig", str(folder / "rig.yaml"), "--out", str(out), "--arm-poses", str(missing)]
    assert main(args) == 1
    assert f"error: --arm-poses: cannot read {missing}: No such file or directory" in capsys.readouterr().err
    rig = yaml.safe_load((folder / "rig.yaml").read_text())
    rig["camera"]["calibration"] = "no_camera.json"
    (folder / "rig_without_camera.yaml").write_text(yaml.safe_dump(rig))
    code, _, out = _run(folder, _stations(folder), "no_camera", rig="rig_without_camera.yaml")
    err = capsys.readouterr().err
    assert code == 1 and not out.exists()
    assert f"rig_without_camera.yaml: camera.calibration: file not found: {folder / 'no_camera.json'}" in err
