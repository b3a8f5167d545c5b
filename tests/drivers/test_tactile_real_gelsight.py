"""Tactile depth on a real GelSight: Taxim's ball presses (tests/data, MIT), not images this project rendered.

The real gel has illumination drift, a shadow beside each press and a soft rim,
so a fixed grey-level threshold finds "contacts" covering the whole image. The
calibration command fits on two thirds of the presses and checks the rest.
"""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tacsplat.cli import main as tacsplat_main
from tacsplat.drivers.optical_tactile import TactileCalibration, color_change, depth_warning, find_contact_circle

pytestmark = pytest.mark.timeout(300)

DATA = Path(__file__).resolve().parents[1] / "data" / "gelsight_taxim_ballpress"
SHARED = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "gelsight_taxim_ballpress"
PIXEL_MM, BALL_MM = 0.1245, 2.0
BALL_PX = BALL_MM / PIXEL_MM


def read_rgb(path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def write_rgb(path, rgb) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(np.clip(np.rint(rgb), 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR))


def labels(folder=DATA) -> dict:
    return {p["file"]: p for p in json.loads((folder / "labels.json").read_text())["presses"]}


def calibrate(folder, out, *extra) -> int:
    return tacsplat_main(
        [
            "calibrate",
            "tactile",
            str(folder),
            "--out",
            str(out),
            "--ball-radius-mm",
            str(BALL_MM),
            "--pixel-size-mm",
            str(PIXEL_MM),
            *extra,
        ]
    )


@pytest.fixture(scope="module")
def calibration_run(tmp_path_factory):
    """``calibrate tactile`` on the six real presses (four fitted, two held out) with the hand labels."""
    out = tmp_path_factory.mktemp("gelsight") / "gelsight.npz"
    folder = tmp_path_factory.mktemp("presses")
    for path in DATA.glob("*.png"):
        shutil.copy(path, folder)
    return calibrate(folder, out, "--labels", str(DATA / "labels.json")), out


def test_contact_circles_of_real_presses_agree_with_the_hand_labels():
    reference = read_rgb(DATA / "reference.png")
    for name, label in labels().items():
        circle = find_contact_circle(color_change(read_rgb(DATA / name), reference))
        assert circle is not None, name
        centre_error = np.hypot(circle.cx - label["center_xy_px"][0], circle.cy - label["center_xy_px"][1])
        assert centre_error < 5.0, f"{name}: centre {circle.cx:.1f}, {circle.cy:.1f} vs label {label['center_xy_px']}"
        # the labels (15-17 px) include the soft rim: some exceed the ball's own radius (16.06 px), which no contact can
        assert 0.7 * label["contact_radius_px"] < circle.radius < BALL_PX, f"{name}: radius {circle.radius:.1f} px"


def test_calibrate_tactile_fits_two_thirds_and_checks_the_held_out_presses(calibration_run, capsys):
    code, out = calibration_run
    assert code == 0
    calib = TactileCalibration.load(out)
    checked = [p for p in calib.presses if p["role"] == "check"]
    fitted = [p for p in calib.presses if p["role"] == "fit"]
    assert len(checked) == 2 and len(fitted) == 4  # every third press is held out
    for press in checked:
        assert press["detected"], press["file"]
        assert abs(press["fitted_radius_m"] * 1e3 - BALL_MM) < 0.2 * BALL_MM, press
        assert 0.2e-3 < press["peak_indentation_m"] < 2.5e-3, press
        assert press["label_radius_px"] == labels()[press["file"]]["contact_radius_px"]
    assert calib.check_summary["detected"] == 2 and calib.check_summary["presses"] == 2
    assert abs(calib.check_summary["median_fitted_radius_m"] * 1e3 - BALL_MM) < 0.15 * BALL_MM
    assert cv2.imread(str(out.with_suffix(".png"))) is not None  # the contact circles over each press
    assert depth_warning(calib) is None  # real presses pressed as documented read deeper than the shallow warning


def test_tactile_depth_command_on_held_out_presses(calibration_run, tmp_path):
    _, cal = calibration_run
    out = tmp_path / "depth"
    held_out = [DATA / "press_09.png", DATA / "press_26.png"]
    assert (
        tacsplat_main(
            [
                "tactile",
                "depth",
                "--calibration",
                str(cal),
                "--reference",
                str(DATA / "reference.png"),
                "--out",
                str(out),
                *map(str, held_out),
                str(DATA / "reference.png"),
            ]
        )
        == 0
    )
    for path in held_out:
        with np.load(out / f"{path.stem}.npz") as data:
            depth = data["depth"]
        assert depth.dtype == np.float32 and depth.shape == (120, 160)
        assert (depth >= 0).all() and 0.2e-3 < depth.max() < 2.5e-3
        label = labels()[path.name]
        rows, cols = np.nonzero(depth)
        assert np.hypot(cols.mean() - label["center_xy_px"][0], rows.mean() - label["center_xy_px"][1]) < 4.0
        radius_px = np.sqrt(len(rows) / np.pi)  # 0 outside the contact: the contact is about the ball's cap
        assert 0.6 * label["contact_radius_px"] < radius_px < 1.05 * BALL_PX
        assert cv2.imread(str(out / f"{path.stem}.png")) is not None
    with np.load(out / "reference.npz") as data:
        assert not data["depth"].any()  # the untouched gel is no contact


def test_tactile_depth_refuses_bad_images_and_keeps_what_is_written(calibration_run, tmp_path, capsys):
    _, cal = calibration_run
    out = tmp_path / "depth"
    args = [
        "tactile",
        "depth",
        "--calibration",
        str(cal),
        "--reference",
        str(DATA / "reference.png"),
        "--out",
        str(out),
    ]
    assert tacsplat_main(args + [str(DATA / "press_09.png")]) == 0
    written = (out / "press_09.npz").read_bytes()
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((60, 80, 3), np.uint8))
    assert tacsplat_main(args + [str(DATA / "press_26.png"), str(small)]) == 1
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "small.png" in err and "80x60" in err and "160x120" in err
    assert not (out / "press_26.npz").exists()  # checked before anything is written
    assert tacsplat_main(args + [str(tmp_path / "missing.png")]) == 1
    assert "missing.png" in capsys.readouterr().err
    assert tacsplat_main(args + [str(DATA / "press_09.png")]) == 1  # would replace an earlier result
    err = capsys.readouterr().err
    assert "press_09.npz" in err and "--overwrite" in err
    assert (out / "press_09.npz").read_bytes() == written


def with_markers_and_drift(rgb, shift_px, gain):
    """The image with a grid of dark marker dots (displaced by ``shift_px``) under a smooth illumination ``gain``."""
    h, w = rgb.shape[:2]
    out = rgb.astype(np.float64) * gain[..., None]
    for y in np.arange(6, h, 12):
        for x in np.arange(6, w, 12):
            cv2.circle(out, (int(round(x + shift_px[0])), int(round(y + shift_px[1]))), 2, (35, 35, 45), -1)
    return np.clip(out, 0, 255)


def test_marker_dots_and_illumination_drift_do_not_make_contacts(calibration_run):
    reference = read_rgb(DATA / "reference.png")
    press = read_rgb(DATA / "press_13.png")
    h, w = reference.shape[:2]
    ys, xs = np.indices((h, w))
    drift = 1.0 + 0.12 * (xs / w - 0.5) - 0.08 * (ys / h - 0.5)  # the lights dimmed on one side since the reference
    plain = find_contact_circle(color_change(press, reference))
    marked_ref = with_markers_and_drift(reference, (0, 0), np.ones((h, w)))
    marked = find_contact_circle(color_change(with_markers_and_drift(press, (0.6, -0.4), drift), marked_ref))
    assert marked is not None
    assert np.hypot(marked.cx - plain.cx, marked.cy - plain.cy) < 1.5 and abs(marked.radius - plain.radius) < 1.5
    untouched = with_markers_and_drift(reference, (0.4, 0.3), drift)
    assert find_contact_circle(color_change(untouched, marked_ref)) is None
    calib = TactileCalibration.load(calibration_run[1])
    assert not calib.depth(untouched, marked_ref).any()
    assert calib.depth(with_markers_and_drift(press, (0.6, -0.4), drift), marked_ref).max() > 0.2e-3


def test_calibration_refuses_presses_that_disagree_with_the_ball(tmp_path, capsys):
    """Held-out presses of a larger ball (the real presses magnified 1.6x about their contact) are refused."""
    folder = tmp_path / "presses"
    folder.mkdir()
    shutil.copy(DATA / "reference.png", folder)
    names = sorted(labels())
    for k, name in enumerate(names):
        rgb = read_rgb(DATA / name)
        if k % 3 == 2:  # the held-out ones
            cx, cy = labels()[name]["center_xy_px"]
            zoom = cv2.getRotationMatrix2D((cx, cy), 0.0, 1.6)
            rgb = cv2.warpAffine(
                rgb, zoom, (rgb.shape[1], rgb.shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
            )
        write_rgb(folder / name, rgb)
    out = tmp_path / "gelsight.npz"
    out.write_bytes(b"an earlier calibration")
    assert calibrate(folder, out) == 1
    err = capsys.readouterr().err
    assert err.count("error:") == 1
    assert "press_09.png" in err and "press_26.png" in err and "capture" in err
    assert out.read_bytes() == b"an earlier calibration"  # nothing already written is lost


@pytest.mark.slow
@pytest.mark.skipif(not SHARED.is_dir(), reason="the shared real data set is not here")
def test_all_thirty_shared_presses(tmp_path, capsys):
    """The measurement of the closing note: 20 presses fitted, 10 held out."""
    out = tmp_path / "gelsight.npz"
    assert calibrate(SHARED, out, "--labels", str(SHARED / "labels.json")) == 0
    summary = TactileCalibration.load(out).check_summary
    print(capsys.readouterr().out)
    assert summary["presses"] == 10 and summary["detected"] == 10
    assert abs(summary["median_fitted_radius_m"] * 1e3 - BALL_MM) < 0.15 * BALL_MM


def test_out_named_like_its_picture_is_refused_before_any_work(tmp_path, capsys):
    """The press picture goes to --out with .png: an --out of X.png would be the picture, then the calibration."""
    assert calibrate(DATA, tmp_path / "gelsight.png") == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "--out" in err and "overwritten by the picture" in err and ".npz" in err
    assert not list(tmp_path.iterdir())  # nothing written
