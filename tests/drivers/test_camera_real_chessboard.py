"""Camera calibration on real photos: OpenCV's own chessboard samples (tests/data, Apache-2.0) and its result."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacsplat.cli import main as tacsplat_main
from tacsplat.drivers.wrist_camera import CameraCalibration, ChessboardSpec

pytestmark = pytest.mark.timeout(120)

DATA = Path(__file__).resolve().parents[1] / "data" / "chessboard_opencv_left"
PHOTOS = sorted(DATA.glob("left*.jpg"))
# OpenCV's modules/python/test/test_calibration.py on the same 13 photos (flags 0: k3 free); K with pixel
# centres at integers (OpenCV's convention, the one camera.json stores)
OPENCV = {"rms": 0.1963, "fx": 532.810, "fy": 532.933, "cx": 342.495, "cy": 233.888}


def calibrate(out, *photos, extra=()):
    return tacsplat_main(
        [
            "calibrate",
            "camera",
            *map(str, photos),
            "--board",
            "chessboard",
            "--inner-corners",
            "9x6",
            "--square-mm",
            "25",
            "--out",
            str(out),
            *extra,
        ]
    )


def test_chessboard_calibration_matches_opencvs_own_result(tmp_path, capsys):
    out = tmp_path / "camera.json"
    assert calibrate(out, DATA) == 0
    printed = capsys.readouterr().out
    data = json.loads(out.read_text())
    K = np.array(data["K_opencv"])
    for key, value in zip(("fx", "fy", "cx", "cy"), (K[0, 0], K[1, 1], K[0, 2], K[1, 2])):
        assert abs(value - OPENCV[key]) < 2.0, (key, value)
    assert abs(data["rms_px"] - OPENCV["rms"]) < 0.01
    assert data["pixel_centres"] == "opencv (integer)" and data["distortion_model"] == "opencv5"
    assert len(data["dist"]) == 5 and abs(data["dist"][4]) > 0.05  # k3 is free by default
    std = data["K_std_px"]
    assert set(std) == {"fx", "fy", "cx", "cy"} and all(0 < std[k] < 2.0 for k in std)
    assert data["warnings"] == []  # 13 varied views, corners in every part of the image
    calib = CameraCalibration.load(out)
    assert calib.board == ChessboardSpec(9, 6, 0.025) and calib.K_std_px == pytest.approx(std)
    assert f"fx {K[0, 0]:.2f}" in printed and f"cx {K[0, 2] + 0.5:.2f}" in printed  # printed at tacsplat's +0.5
    assert cv2.imread(str(tmp_path / "camera_coverage.png")) is not None


def test_three_photos_warn_that_the_calibration_is_poorly_constrained(tmp_path, capsys):
    out = tmp_path / "camera.json"
    assert calibrate(out, *PHOTOS[:3]) == 0
    captured = capsys.readouterr()
    data = json.loads(out.read_text())
    assert data["warnings"], "three photos leave whole parts of the image without corners"
    text = " ".join(data["warnings"])
    assert "poorly constrained" in text and "border" in text and "left" in text
    assert "warning" in (captured.out + captured.err).lower() and "poorly constrained" in captured.out + captured.err
    picture = cv2.imread(str(tmp_path / "camera_coverage.png"))
    assert picture is not None and picture.shape[:2] == (480, 640)


def test_distortion_model_is_chosen_by_a_flag(tmp_path):
    for model, count in (("opencv4", 5), ("rational8", 8)):
        out = tmp_path / f"{model}.json"
        assert calibrate(out, DATA, extra=("--distortion", model)) == 0
        calib = CameraCalibration.load(out)
        assert calib.distortion_model == model and calib.dist.size == count
        if model == "opencv4":
            assert calib.dist[4] == 0.0  # k3 held at zero


def test_board_and_photo_problems_are_one_clear_error(tmp_path, capsys):
    out = tmp_path / "camera.json"
    out.write_text("an earlier calibration")
    assert (
        tacsplat_main(
            [
                "calibrate",
                "camera",
                str(DATA),
                "--board",
                "chessboard",
                "--inner-corners",
                "10x7",
                "--square-mm",
                "25",
                "--out",
                str(out),
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "--inner-corners" in err and "0 of 13" in err
    assert (
        tacsplat_main(
            ["calibrate", "camera", str(DATA), "--board", "chessboard", "--square-mm", "25", "--out", str(out)]
        )
        == 2  # a usage error
    )
    assert "--inner-corners" in capsys.readouterr().err
    assert (
        tacsplat_main(
            [
                "calibrate",
                "camera",
                str(DATA),
                "--board",
                "chessboard",
                "--inner-corners",
                "9x6",
                "--square-mm",
                "25",
                "--marker-mm",
                "20",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "--marker-mm" in capsys.readouterr().err
    photos = tmp_path / "photos"
    photos.mkdir()
    for path in PHOTOS[:4]:
        shutil.copy(path, photos)
    (photos / "left99.jpg").write_bytes(b"not a jpeg")
    assert calibrate(out, photos) == 1
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "left99.jpg" in err
    assert out.read_text() == "an earlier calibration"  # nothing already written is lost


def test_photos_named_alike_in_two_folders_are_told_apart(tmp_path, capsys):
    """Two sessions' folders, each with its img01.jpg ...: each photo is named by its path from their common folder,
    in the report and the file, not mixed up by its bare name."""
    for session, photos in (("s1", PHOTOS[:6]), ("s2", PHOTOS[6:12])):
        (tmp_path / session).mkdir()
        for k, path in enumerate(photos):
            shutil.copy(path, tmp_path / session / f"img{k + 1:02d}.jpg")
    out = tmp_path / "camera.json"
    assert calibrate(out, tmp_path / "s1", tmp_path / "s2") == 0
    names = {f"{session}/img{k:02d}.jpg" for session in ("s1", "s2") for k in range(1, 7)}
    assert set(json.loads(out.read_text())["per_image_rms_px"]) == names
    printed = capsys.readouterr().out
    assert all(f"  {name}: " in printed for name in names)
    assert calibrate(out, tmp_path / "s1", tmp_path / "s1" / "img01.jpg") == 1
    assert "img01.jpg: given twice" in capsys.readouterr().err


def test_out_named_like_its_picture_is_refused_before_any_work(tmp_path, capsys):
    """The corner picture goes to --out with .png: an --out of X.png would be the calibration, then the picture."""
    assert calibrate(tmp_path / "camera.png", DATA) == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "--out" in err and "overwritten by the picture" in err
    assert not list(tmp_path.iterdir())  # nothing written


def test_a_photo_too_small_to_hold_the_board_is_skipped_not_a_crash(tmp_path, capsys):
    """OpenCV's adaptive threshold asserts on an image under 15 px a side: such a photo shows no board."""
    import cv2
    import numpy as np

    from tacsplat.cli import main

    for n in (1, 2):  # (the photos of one calibration share a size)
        cv2.imwrite(str(tmp_path / f"tiny{n}.png"), np.zeros((14, 14, 3), np.uint8))
    argv = ["calibrate", "camera", str(tmp_path), "--board", "chessboard", "--inner-corners", "9x6"]
    assert main([*argv, "--square-mm", "25", "--out", str(tmp_path / "c.json")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: ") and "found in 0 of 2 images" in err[-1], err
