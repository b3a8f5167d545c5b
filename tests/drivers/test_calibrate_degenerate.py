"""`tacsplat calibrate camera` refuses photo sets that cannot determine the intrinsics (repeated photos, a board
facing the camera, boards parallel to each other) and results that are no camera; ChArUco photos rendered here
through a known pinhole camera."""

import json

import cv2
import numpy as np
import pytest

from tacsplat.cli import main
from tacsplat.drivers.wrist_camera import CameraCalibration, CharucoBoardSpec, detect_board_views

pytestmark = pytest.mark.timeout(120)

W, H = 640, 480
K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
SPEC = CharucoBoardSpec()  # 7 x 5 squares of 30 mm
BOARD = SPEC.board().generateImage((700, 500), marginSize=0)  # 100 px per square: 0.3 mm per board pixel


def photo(tilt_deg: float = 0.0, axis=(1.0, 0.0, 0.0), shift=(0.0, 0.0), distance: float = 0.45) -> np.ndarray:
    """The board, its centre at ``shift`` (m) off the optical axis at ``distance``, tilted about ``axis``."""
    R = cv2.Rodrigues(np.radians(tilt_deg) * np.asarray(axis) / np.linalg.norm(axis))[0]
    t = np.array([shift[0], shift[1], distance]) - R @ np.array([0.105, 0.075, 0.0])
    homography = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ np.diag([0.0003, 0.0003, 1.0])
    return cv2.warpPerspective(BOARD, homography, (W, H), flags=cv2.INTER_LINEAR, borderValue=160)


GOOD = [
    photo(25, (1, 0, 0)),
    photo(25, (-1, 0, 0), (0.03, 0)),
    photo(25, (0, 1, 0), (0, 0.03)),
    photo(25, (0, -1, 0), (-0.03, 0)),
    photo(30, (1, 1, 0), (0.04, 0.04)),
    photo(30, (1, -1, 0), (-0.04, 0.03)),
    photo(0, shift=(0.05, -0.05), distance=0.5),
    photo(20, (-1, 1, 0), (-0.05, -0.04)),
]


def _calibrate(tmp_path, images, *extra):
    folder = tmp_path / "photos"
    folder.mkdir(exist_ok=True)
    for i, image in enumerate(images):
        cv2.imwrite(str(folder / f"view_{i}.png"), image)
    return main(["calibrate", "camera", str(folder), "--out", str(tmp_path / "camera.json"), *extra])


def _one_error(capsys) -> str:
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and captured.err.startswith("error: calibration: "), captured.err
    assert "Traceback" not in captured.err and "fx" not in captured.out  # nothing calibrated is printed as a result
    return captured.err


def test_three_copies_of_one_photo_are_refused_naming_them(tmp_path, capsys):
    """The issue's case: fx = 93,421,543 px "+- 0.00", k1 = -967953, exit 0, no warning."""
    (tmp_path / "camera.json").write_text("an earlier calibration")
    assert _calibrate(tmp_path, [photo()] * 3) == 1
    err = _one_error(capsys)
    assert "1 distinct pose" in err and "view_0.png, view_1.png, view_2.png" in err and "tilted" in err
    assert (tmp_path / "camera.json").read_text() == "an earlier calibration"  # nothing written over it
    assert not (tmp_path / "camera.png").exists()


def test_a_board_that_always_faces_the_camera_is_refused(tmp_path, capsys):
    """Distinct poses (moved, nearer, farther) but one orientation: the focal length is unobservable."""
    photos = [
        photo(shift=s, distance=d)
        for s, d in (((0, 0), 0.45), ((0.05, 0.03), 0.4), ((-0.05, -0.04), 0.5), ((0.04, -0.05), 0.55))
    ]
    assert _calibrate(tmp_path, photos) == 1
    err = _one_error(capsys)
    assert "1 orientation(s)" in err and "view_1.png 0," in err and "focal length unobservable" in err
    assert not (tmp_path / "camera.json").exists()


def test_boards_parallel_to_each_other_are_refused(tmp_path, capsys):
    photos = [photo(25, (1, 0, 0), shift=s) for s in ((0, 0), (0.05, 0.03), (-0.05, -0.04), (0.04, -0.05))]
    assert _calibrate(tmp_path, photos) == 1
    err = _one_error(capsys)
    assert "1 orientation(s)" in err and "view_1.png 2" in err  # tilted about 25 degrees, all the same way


def test_a_varied_set_calibrates_and_a_repeated_photo_is_a_warning(tmp_path, capsys):
    assert _calibrate(tmp_path, GOOD + [GOOD[2]]) == 0
    out = capsys.readouterr().out
    calib = CameraCalibration.load(tmp_path / "camera.json")
    assert abs(calib.K_opencv[0, 0] - 600) < 6 and abs(calib.K_opencv[1, 1] - 600) < 6
    assert "warning: view_8.png shows the board where view_2.png does" in out
    assert any("view_8.png" in w for w in json.loads((tmp_path / "camera.json").read_text())["warnings"])


@pytest.mark.parametrize(
    "K_opencv, dist, std, words",
    [
        (
            [[93421543.0, 0, 320], [0, 93421543.0, 240], [0, 0, 1]],
            [-967953.0, 0, 0, 0, 0],
            0.004,
            "field of view of 0.000393 degrees",
        ),  # the result
        ([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]], [0.0] * 5, 0.0, "standard deviation of fx, fy, cx, cy is zero"),
        ([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]], [-30.0, 0, 0, 0, 0], 0.5, "folds the image back"),
        ([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]], [400.0, 0, 0, 0, 0], 0.5, "beyond 1/2 to 2"),
        ([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]], [np.nan, 0, 0, 0, 0], 0.5, "not finite"),
    ],
)
def test_a_result_that_is_no_camera_is_named(K_opencv, dist, std, words):
    from tacsplat.drivers.wrist_camera import calibration_problem

    views, _ = detect_board_views([GOOD[0]], SPEC, ["view_0.png"])
    calib = CameraCalibration(
        np.array(K_opencv), np.array(dist), W, H, K_std_px=dict.fromkeys(("fx", "fy", "cx", "cy"), std)
    )
    problem = calibration_problem(calib, views)
    assert problem is not None and words in problem, problem
    good = CameraCalibration(
        K.copy(),
        np.array([-0.28, 0.09, 0.0005, -0.0003, 0.0]),
        W,
        H,
        K_std_px=dict.fromkeys(("fx", "fy", "cx", "cy"), 0.5),
    )
    assert calibration_problem(good, views) is None  # a wide-angle webcam's lens
