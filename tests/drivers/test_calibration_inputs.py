"""`calibrate tactile`, `tactile depth` and `calibrate camera` on real data given wrong: sizes that disagree with the
labels or give a depth no press has, images that are not the sensor's colour images, options out of range, too few
or repeated photos, a poor fit. Each is one clear message naming its cause."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacsplat.cli import main
from tacsplat.drivers.cli import CalibrateTactile, _check_label_sizes
from tacsplat.drivers.optical_tactile import TactileCalibration, image_problem

pytestmark = pytest.mark.timeout(120)

TESTS = Path(__file__).resolve().parents[1] / "data"
PRESSES = TESTS / "gelsight_taxim_ballpress"  # a reference, six of the real presses and their labels
PHOTOS = sorted((TESTS / "chessboard_opencv_left").glob("left*.jpg"))
SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "gelsight_taxim_ballpress"
SIZES = ["--ball-radius-mm", "2", "--pixel-size-mm", "0.1245"]  # the data set's (labels.json)
CHESSBOARD = ["--board", "chessboard", "--inner-corners", "9x6", "--square-mm", "25"]


def tactile(folder, out, *extra) -> int:
    return main(["calibrate", "tactile", str(folder), "--out", str(out), *extra])


def camera(out, *photos, extra=CHESSBOARD) -> int:
    return main(["calibrate", "camera", *map(str, photos), "--out", str(out), *extra])


def one_error(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "error:" in line]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def copy_presses(tmp_path, change=None) -> Path:
    """The real presses and reference in a folder of their own, each image passed through ``change(name, bgr)``."""
    folder = tmp_path / "presses"
    folder.mkdir()
    for path in PRESSES.glob("*.png"):
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        cv2.imwrite(str(folder / path.name), image if change is None else change(path.name, image))
    return folder


def grey(image):
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


# --- sizes ---------------------------------------------------------------------------------------------------------


def test_options_that_disagree_with_the_labels_sizes_are_a_usage_error(tmp_path, capsys):
    """The reviewer's case: a 4 mm ball at 0.08 mm per pixel, with labels of a 2 mm ball at 0.1245 mm."""
    out = tmp_path / "t.npz"
    labels = PRESSES / "labels.json"
    assert tactile(PRESSES, out, "--ball-radius-mm", "4", "--pixel-size-mm", "0.08", "--labels", str(labels)) == 2
    err = one_error(capsys)
    for word in ("--pixel-size-mm 0.08 mm", "pixel_size_mm 0.1245 mm", "--ball-radius-mm 4 mm", "ball_radius_mm 2 mm"):
        assert word in err, err
    assert str(labels) in err
    assert not list(tmp_path.iterdir())  # refused before any work


def test_label_sizes_within_rounding_of_the_options_pass():
    def check(pixel_mm, ball_mm):
        args = CalibrateTactile(PRESSES, Path("t.npz"), ball_mm, pixel_mm, labels=PRESSES / "labels.json")
        _check_label_sizes(args, {"pixel_size_mm": 0.1245, "ball_radius_mm": 2.0})

    check(0.125, 2.01)  # rounded: within 1 %
    with pytest.raises(Exception, match="--ball-radius-mm 2.05 mm"):
        check(0.1245, 2.05)


@pytest.mark.skipif(not SHARED.is_dir(), reason="the shared real data set is not here")
def test_a_wrong_scale_that_the_radius_check_cannot_see_is_refused_by_its_depth(tmp_path, capsys):
    """4 mm at 0.08 mm per pixel for Taxim's 2 mm ball at 0.1245 mm: the held-out spheres fit the wrong ball (the
    labels and the fit share the scale) but the presses come out 0.16 mm deep; they were pressed about 1 mm."""
    out = tmp_path / "t.npz"
    assert tactile(SHARED, out, "--ball-radius-mm", "4", "--pixel-size-mm", "0.08") == 1
    err = one_error(capsys)
    assert "peak indentation is 0.1" in err and "--pixel-size-mm" in err and "--ball-radius-mm" in err, err
    assert not out.exists() and (tmp_path / "t.rejected.png").exists()


@pytest.mark.parametrize("peak_mm, refused, warned", [(0.16, True, False), (0.245, False, True), (0.4, False, False)])
def test_the_depth_band_refuses_a_wrong_scale_and_warns_of_shallow_presses(peak_mm, refused, warned):
    """A press 0.5 mm deep of a 1 mm ball on a coarse image reads 0.245 mm (the peak under-reads): written, with a
    warning; a 6x wrong scale (0.16 mm) is refused."""
    from types import SimpleNamespace

    from tacsplat.drivers.optical_tactile import check_problem, depth_warning

    summary = {"median_fitted_radius_m": 1e-3, "median_peak_indentation_m": peak_mm * 1e-3}
    calib = SimpleNamespace(check_summary=summary, ball_radius_m=1e-3, presses=[])
    assert (check_problem(calib) is not None) == refused
    assert (depth_warning(calib) is not None) == warned


def test_presses_all_wider_than_the_ball_blame_the_sizes(tmp_path, capsys):
    assert tactile(PRESSES, tmp_path / "t.npz", "--ball-radius-mm", "0.5", "--pixel-size-mm", "0.1245") == 1
    err = one_error(capsys)
    assert "not smaller than the ball's 4.0 px" in err and "check --ball-radius-mm and --pixel-size-mm" in err, err
    assert "press the ball" not in err


def test_labels_of_no_press_are_warned_about_by_name(tmp_path, capsys):
    data = json.loads((PRESSES / "labels.json").read_text())
    data["presses"][0]["file"] = "press_99.png"
    data["presses"][1]["file"] = "nothing.png"
    # no sizes in the file, so that a ball too small for the presses ends the run right after the labels are matched
    del data["pixel_size_mm"], data["ball_radius_mm"]
    labels = tmp_path / "labels.json"
    labels.write_text(json.dumps(data))
    extra = ["--labels", str(labels), "--ball-radius-mm", "0.5", "--pixel-size-mm", "0.1245"]
    assert tactile(PRESSES, tmp_path / "t.npz", *extra) == 1
    out = capsys.readouterr().out
    warnings = [line for line in out.splitlines() if line.startswith("warning:")]
    assert len(warnings) == 1 and "press_99.png, nothing.png" in warnings[0] and "match no press" in warnings[0], out


# --- images that are not the sensor's colour images ----------------------------------------------------------------


def test_real_and_rendered_gel_images_pass_the_image_check():
    from tacsplat.sim.tactile import render_tactile_rgb

    folders = [PRESSES] + ([SHARED] if SHARED.is_dir() else [])
    for path in (p for folder in folders for p in folder.glob("*.png")):
        rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
        assert image_problem(rgb) is None, path
    assert image_problem(render_tactile_rgb(np.zeros((120, 160), np.float32), 1.6e-4)) is None


def test_greyscale_presses_are_refused_naming_a_file(tmp_path, capsys):
    folder = copy_presses(tmp_path, lambda name, image: image if name == "reference.png" else grey(image))
    assert tactile(folder, tmp_path / "t.npz", *SIZES) == 1
    err = one_error(capsys)
    assert "press_00.png: greyscale" in err and "must be the sensor's colour images" in err, err
    assert not (tmp_path / "t.npz").exists()


REFERENCES = {
    "black": lambda image: np.zeros_like(image),
    "flat": lambda image: np.full_like(image, (140, 130, 150)),  # one colour, no gel
    "greyscale": grey,
}


@pytest.mark.parametrize("kind", REFERENCES)
def test_a_reference_that_is_no_image_of_the_lit_gel_is_refused(kind, tmp_path, capsys):
    folder = copy_presses(tmp_path, lambda name, image: REFERENCES[kind](image) if name == "reference.png" else image)
    assert tactile(folder, tmp_path / "t.npz", *SIZES) == 1
    err = one_error(capsys)
    assert f"reference.png: the reference image of the untouched gel is {kind}" in err, err
    assert not (tmp_path / "t.npz").exists()


@pytest.mark.parametrize("kind", REFERENCES)
def test_tactile_depth_refuses_such_a_reference(kind, tmp_path, capsys):
    calibration = tmp_path / "t.npz"
    weights = [np.zeros((5, 8), np.float32), np.zeros(8, np.float32), np.zeros((8, 2), np.float32)]
    TactileCalibration([*weights, np.zeros(2, np.float32)], 1.245e-4, (120, 160)).save(calibration)
    reference = tmp_path / "reference.png"
    cv2.imwrite(str(reference), REFERENCES[kind](cv2.imread(str(PRESSES / "reference.png"))))
    args = ["tactile", "depth", "--calibration", str(calibration), "--reference", str(reference)]
    assert main([*args, "--out", str(tmp_path / "depth"), str(PRESSES / "press_09.png")]) == 1
    err = one_error(capsys)
    assert f"--reference {reference}: the image of the untouched gel is {kind}" in err, err
    assert not (tmp_path / "depth").exists()


# --- options out of range: usage errors (exit 2) -------------------------------------------------------------------


@pytest.mark.parametrize(
    "option, extra",
    [
        ("--square-mm", ["--square-mm", "-15"]),
        ("--square-mm", ["--square-mm", "nan"]),
        ("--marker-mm", ["--square-mm", "15", "--marker-mm", "16"]),
        ("--dictionary", ["--dictionary", "DICT_FOO"]),
        (
            "--dictionary",
            [
                "--squares-x",
                "14",
                "--squares-y",
                "10",
                "--square-mm",
                "15",
                "--marker-mm",
                "11",
                "--dictionary",
                "DICT_4X4_50",
            ],
        ),  # 70 markers needed, 50 in the dictionary
        ("--inner-corners", ["--board", "chessboard", "--square-mm", "25"]),
    ],
)
def test_camera_options_out_of_range_are_usage_errors(option, extra, tmp_path, capsys):
    assert camera(tmp_path / "c.json", PHOTOS[0], extra=extra) == 2
    assert option in one_error(capsys)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    "option, value",
    [
        ("--ball-radius-mm", "-2"),
        ("--ball-radius-mm", "nan"),
        ("--pixel-size-mm", "0"),
        ("--pixel-size-mm", "inf"),
        ("--check-every", "0"),
        ("--check-every", "1"),
        ("--max-radius-error", "-1"),
        ("--max-radius-error", "nan"),
    ],
)
def test_tactile_options_out_of_range_are_usage_errors(option, value, tmp_path, capsys):
    sizes = dict(zip(SIZES[::2], SIZES[1::2])) | {option: value}
    assert tactile(PRESSES, tmp_path / "t.npz", *[x for pair in sizes.items() for x in pair]) == 2
    assert option in one_error(capsys)
    assert not list(tmp_path.iterdir())


# --- camera: too few photos, a poor fit, copies --------------------------------------------------------------------


def test_a_board_found_in_every_one_of_too_few_photos_asks_for_more_photos(tmp_path, capsys):
    assert camera(tmp_path / "c.json", *PHOTOS[:2]) == 1
    err = one_error(capsys)
    assert "found in 2 of 2 images" in err and "take more photos" in err and "--inner-corners" not in err, err


def test_an_rms_error_over_a_pixel_is_a_warning(tmp_path, capsys):
    """Every other photo stretched 8 % along x, as another camera's pixels would be: the photos disagree."""
    folder = tmp_path / "photos"
    folder.mkdir()
    for k, path in enumerate(PHOTOS):
        image = cv2.imread(str(path))
        if k % 2:
            image = cv2.resize(image, None, fx=1.08, fy=1.0, interpolation=cv2.INTER_LINEAR)[:, :640]
        cv2.imwrite(str(folder / f"{path.stem}.png"), image)
    out = tmp_path / "c.json"
    assert camera(out, folder) == 0
    data = json.loads(out.read_text())
    assert data["rms_px"] > 1.0
    assert any("RMS reprojection error is" in w and "over 1 px" in w for w in data["warnings"]), data["warnings"]
    assert f"warning: the RMS reprojection error is {data['rms_px']:.2f} px" in capsys.readouterr().out


def test_copies_of_a_photo_are_left_out_of_the_solve(tmp_path, capsys):
    """Four copies of left03.jpg beside left01, left02, left03: K_std_px is the three photos' own."""
    alone = tmp_path / "alone.json"
    assert camera(alone, *PHOTOS[:3]) == 0
    folder = tmp_path / "photos"
    folder.mkdir()
    for path in PHOTOS[:3]:
        shutil.copy(path, folder)
    for k in range(4):
        shutil.copy(PHOTOS[2], folder / f"left03_copy{k}.jpg")
    capsys.readouterr()
    out = tmp_path / "c.json"
    assert camera(out, folder) == 0
    printed = capsys.readouterr().out
    data, own = json.loads(out.read_text()), json.loads(alone.read_text())
    # (to 1e-4: two OpenCV solves of the same photos differed in the 6th digit in the full suite under load; with the
    # copies in the solve K_std_px was half the three photos')
    assert data["K_std_px"] == pytest.approx(own["K_std_px"], rel=1e-4)
    assert np.allclose(data["K_opencv"], own["K_opencv"])
    assert set(data["per_image_rms_px"]) == {p.name for p in PHOTOS[:3]}
    copies = ", ".join(f"left03_copy{k}.jpg" for k in range(4))
    assert f"warning: {copies} show the board where left03.jpg does (the same photo" in printed, printed
    assert "left out of the calibration, left03.jpg kept" in printed and "3 of 7 images used" in printed
