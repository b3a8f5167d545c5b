"""Optical tactile sensor: calibrate on ball presses rendered by the twin, read a press back from a video file."""

import json
import re
import threading
import time

import cv2
import numpy as np
import pytest

from tacsplat.cli import main as tacsplat_main
from tacsplat.drivers import TactileSensor
from tacsplat.drivers.optical_tactile import (
    SHALLOW_DEPTH_M,
    OpticalTactileSensor,
    TactileCalibration,
    calibrate_tactile,
    depth_warning,
    fit_sphere,
    poisson_integrate,
)
from tacsplat.errors import CameraError, InvalidInputError, TactileError
from tacsplat.geometry import make_pose, tactile_pixel_grid
from tacsplat.sim.tactile import render_tactile_rgb

pytestmark = pytest.mark.timeout(120)

H, W = 240, 320
PIXEL_M = 8e-5  # 0.08 mm per pixel (DIGIT-like)
BALL_M = 4e-3


def ball_press(cx, cy, indentation_m, ball_m=BALL_M):
    """True indentation [H, W] of a ball of radius ``ball_m`` pressed ``indentation_m`` deep at pixel (cx, cy)."""
    ys, xs = np.indices((H, W)) + 0.5
    rho2 = ((xs - cx) ** 2 + (ys - cy) ** 2) * PIXEL_M**2
    depth = np.sqrt(np.maximum(ball_m**2 - rho2, 0.0)) - (ball_m - indentation_m)
    return np.maximum(depth, 0.0).astype(np.float32)


def tactile_image(depth, rng):
    """The twin's synthetic tactile image plus camera noise (sigma 1 grey level)."""
    image = render_tactile_rgb(depth, PIXEL_M).astype(np.float64) + rng.normal(0.0, 1.0, (H, W, 3))
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


CALIBRATION_PRESSES = [
    (100, 80, 6e-4),
    (220, 160, 8e-4),
    (160, 120, 1e-3),
    (90, 170, 5e-4),
    (230, 70, 9e-4),
    (160, 60, 7e-4),
]


@pytest.fixture(scope="module")
def calibration_folder(tmp_path_factory):
    rng = np.random.default_rng(0)
    folder = tmp_path_factory.mktemp("ball_presses")
    rgb = tactile_image(np.zeros((H, W), np.float32), rng)
    cv2.imwrite(str(folder / "reference.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    for k, (cx, cy, d) in enumerate(CALIBRATION_PRESSES):
        rgb = tactile_image(ball_press(cx, cy, d), rng)
        cv2.imwrite(str(folder / f"press_{k:02d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return folder


@pytest.fixture(scope="module")
def calibration_file(calibration_folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("cal") / "index_tactile.npz"
    code = tacsplat_main(
        [
            "calibrate",
            "tactile",
            str(calibration_folder),
            "--out",
            str(out),
            "--ball-radius-mm",
            str(BALL_M * 1e3),
            "--pixel-size-mm",
            str(PIXEL_M * 1e3),
        ]
    )
    assert code == 0
    return out


def test_poisson_integration_recovers_a_surface_from_its_gradients():
    ys, xs = np.indices((120, 160)) * PIXEL_M
    depth = 3e-4 * np.exp(-((xs - 0.0064) ** 2 + (ys - 0.0048) ** 2) / (2 * 0.0012**2))
    gy, gx = np.gradient(depth, PIXEL_M)
    recovered = poisson_integrate(gx, gy, PIXEL_M)
    assert np.sqrt(np.mean((recovered - depth) ** 2)) < 0.01 * depth.max()
    with pytest.raises(InvalidInputError, match="NaN"):
        poisson_integrate(np.full((5, 5), np.nan), np.zeros((5, 5)), PIXEL_M)


def test_calibration_command_finds_every_contact_circle(calibration_file):
    calib = TactileCalibration.load(calibration_file)
    assert len(calib.presses) == len(CALIBRATION_PRESSES)
    for press, (cx, cy, d) in zip(calib.presses, CALIBRATION_PRESSES):
        true_radius = np.sqrt(2 * BALL_M * d - d**2) / PIXEL_M
        # find_contact_circle uses array-index pixel centres: the true centre (cx, cy) is at (cx - 0.5, cy - 0.5)
        np.testing.assert_allclose(press["centre_px"], [cx - 0.5, cy - 0.5], atol=0.5)
        # the circle is the steepest colour change; the renderer's central differences put it 1-2 px inside the edge
        assert -3.0 < press["contact_radius_px"] - true_radius < 0.5
    assert calibration_file.with_suffix(".png").exists()
    # presses 0.5-1 mm deep, as documented: no shallow warning (its median read is checked, not only the band's ends)
    assert calib.check_summary["median_peak_indentation_m"] > SHALLOW_DEPTH_M and depth_warning(calib) is None


def test_sensor_reads_ball_press_depth_from_a_video_file(calibration_file, tmp_path):
    rng = np.random.default_rng(1)
    truth = ball_press(150, 130, 7.5e-4)  # a press the calibration never saw
    path = tmp_path / "digit.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (W, H))
    assert writer.isOpened()
    frames = [np.zeros((H, W), np.float32)] * 5 + [truth]  # untouched gel first: the reference
    for depth in frames:
        writer.write(cv2.cvtColor(tactile_image(depth, rng), cv2.COLOR_RGB2BGR))
    writer.release()
    T_hand_sensor = make_pose(np.eye(3), [0.01, 0.02, 0.1])
    with OpticalTactileSensor("index", str(path), calibration_file, T_hand_sensor, reference_frames=5) as sensor:
        assert isinstance(sensor, TactileSensor)
        reading = sensor.read()
    assert reading.frame == "hand" and reading.meta["frame_index"] == 5
    np.testing.assert_array_equal(reading.T_ref_sensor, T_hand_sensor)
    assert reading.pixel_size_m == pytest.approx(PIXEL_M)
    depth = reading.depth
    contact = depth > 0
    assert not contact[truth == 0].any()  # no phantom contact away from the ball
    assert contact.sum() > 0.6 * (truth > 0).sum()
    # depth is the ball's print relative to the contact's rim (zero height outside the contact): its shape is the
    # ball's, and it is at most the indentation (the rim, 1-2 px inside the rendered edge, is at zero)
    assert 0.6 * truth.max() < depth.max() <= 1.05 * truth.max()
    offset = truth[contact] - depth[contact]
    assert np.std(offset) < 0.05 * truth.max(), "the print is the ball's cap shifted by the rim's depth"
    x, y = tactile_pixel_grid(H, W, PIXEL_M)
    _, radius = fit_sphere(np.column_stack([x[contact], y[contact], -depth[contact]]))
    assert abs(radius - BALL_M) < 0.1 * BALL_M
    r, c = np.unravel_index(np.argmax(depth), depth.shape)
    assert abs(r - 129.5) <= 3 and abs(c - 149.5) <= 3


def _weights(dtype=np.float32):
    """The MLP's weights (5 inputs, 8 hidden, 2 outputs), all zero."""
    return [np.zeros(shape, dtype) for shape in ((5, 8), (8,), (8, 2), (2,))]


def _meta(**changes) -> str:
    meta = {"format": "tacsplat-tactile-calibration", "version": 2, "layers": 2, "pixel_size_m": PIXEL_M}
    meta |= {"image_size": [H, W], "ball_radius_m": BALL_M, "change_threshold": 6.0, "noise_floor_m": 2e-5}
    return json.dumps(meta | changes)


@pytest.mark.parametrize(
    "contents, words",
    [
        ({"something": np.zeros(3)}, "not a tactile calibration file"),
        ({"meta": json.dumps([1, 2])}, "[format]"),  # JSON, but no object
        ({"meta": json.dumps(None)}, "[format]"),
        ({"meta": _meta(), **{f"w{i}": w.astype(str) for i, w in enumerate(_weights())}}, "[w0..]"),
        ({"meta": _meta(), **{f"w{i}": w for i, w in enumerate(_weights(np.complex128))}}, "[w0..]"),
        ({"meta": _meta(), **{f"w{i}": w for i, w in enumerate(_weights(np.int8))}}, "[w0..]"),
    ],
    ids=["no meta", "meta a list", "meta null", "string weights", "complex weights", "int8 weights"],
)
def test_bad_calibration_file_is_a_clear_error(tmp_path, contents, words):
    bad = tmp_path / "bad.npz"
    np.savez(bad, **contents)
    with pytest.raises(TactileError, match=re.escape(f"{bad}") + ".*" + re.escape(words)):
        TactileCalibration.load(bad)
    good = tmp_path / "good.npz"
    np.savez(good, meta=_meta(), **{f"w{i}": w for i, w in enumerate(_weights())})
    assert TactileCalibration.load(good).weights[0].dtype == np.float32


def _damaged(data: bytes, how: str) -> bytes:
    """A tactile calibration file's bytes emptied, cut in half, its deflated data broken, or its compression method
    one zipfile does not know."""
    if how == "empty":
        return b""
    if how == "truncated":
        return data[: len(data) // 2]
    out = bytearray(data)
    if how == "bad deflate data":  # each member's first byte of data: a final block of the reserved type 3
        start = 0
        while (start := data.find(b"PK\x03\x04", start)) >= 0:
            name, extra = (int.from_bytes(data[start + k : start + k + 2], "little") for k in (26, 28))
            out[start + 30 + name + extra] = 0xFF
            start += 4
    else:  # an unknown compression method in the central directory
        start = 0
        while (start := data.find(b"PK\x01\x02", start)) >= 0:
            out[start + 10 : start + 12] = (99).to_bytes(2, "little")
            start += 4
    return bytes(out)


@pytest.mark.parametrize("how", ["empty", "truncated", "bad deflate data", "unknown compression"])
def test_an_empty_truncated_or_damaged_calibration_file_is_the_same_clear_error(tmp_path, how):
    weights = [
        np.zeros((5, 8), np.float32),
        np.zeros(8, np.float32),
        np.zeros((8, 2), np.float32),
        np.zeros(2, np.float32),
    ]
    good = tmp_path / "good.npz"
    TactileCalibration(weights, PIXEL_M, (H, W)).save(good)
    bad = tmp_path / "index.npz"
    bad.write_bytes(_damaged(good.read_bytes(), how))
    with pytest.raises(TactileError, match=re.escape(f"{bad}: not a tactile calibration file")):
        TactileCalibration.load(bad)


def test_calibration_without_any_contact_fails_clearly():
    rng = np.random.default_rng(2)
    flat = tactile_image(np.zeros((H, W), np.float32), rng)
    with pytest.raises(TactileError, match="no ball press"):
        TactileCalibration.fit(flat, [tactile_image(np.zeros((H, W), np.float32), rng)], BALL_M, PIXEL_M)


def test_check_every_that_holds_out_no_press_says_so():
    rng = np.random.default_rng(3)
    flat = tactile_image(np.zeros((H, W), np.float32), rng)
    names = [f"press_{k}.png" for k in range(6)]
    with pytest.raises(TactileError, match=r"--check-every 10 holds out no press of the 6 given") as error:
        calibrate_tactile(flat, [flat] * 6, names, BALL_M, PIXEL_M, check_every=10)
    assert "at least 3" not in str(error.value)  # 6 presses are enough; the check is what is missing


def _read_depth(calibration_file, truth, seed):
    """Depth read from a rendering of ``truth`` against a rendered untouched gel, and the sphere fitted to it."""
    rng = np.random.default_rng(seed)
    reference = tactile_image(np.zeros((H, W), np.float32), rng)
    calib = TactileCalibration.load(calibration_file)
    depth = calib.depth(tactile_image(truth, rng), reference).astype(np.float64)
    contact = depth > 0
    x, y = tactile_pixel_grid(H, W, PIXEL_M)
    radius = fit_sphere(np.column_stack([x[contact], y[contact], -depth[contact]]))[1] if contact.sum() > 10 else 0.0
    return depth, radius, calib.depth(tactile_image(np.zeros((H, W), np.float32), rng), reference)


def test_a_press_covering_much_of_the_gel_keeps_its_depth(calibration_file):
    """A ball of radius 40 mm pressed 0.8 mm deep: its print covers 40 % of the image (and would vanish if the
    threshold were taken from the statistics of the whole image, the print included)."""
    truth = ball_press(160, 120, 8e-4, ball_m=0.04)
    depth, _, untouched = _read_depth(calibration_file, truth, seed=5)
    assert (depth > 0).sum() > 0.6 * (truth > 0).sum()
    assert depth.max() > 0.6 * truth.max()
    assert not (depth > 0)[truth == 0].any()
    assert not untouched.any()  # an untouched gel still reads no contact


def test_a_press_cut_by_the_image_border_keeps_its_shape(calibration_file):
    """The ball's centre 5 px inside the right border: the depth is not pinned to zero at the border."""
    truth = ball_press(315, 120, 8e-4)
    depth, radius, _ = _read_depth(calibration_file, truth, seed=3)
    assert depth.max() > 0.6 * truth.max()
    assert abs(radius - BALL_M) < 0.1 * BALL_M, radius


def test_a_frame_half_unlit_reads_no_phantom_contact_and_its_lit_half_still_reads_a_press(calibration_file):
    """Half the frame black (an LED or the cable failing): the dark pixels say nothing of the gel, so they are
    neither a contact nor a background that would bend the rest; a press in the lit half reads as it would."""
    rng = np.random.default_rng(4)
    reference = tactile_image(np.zeros((H, W), np.float32), rng)
    calib = TactileCalibration.load(calibration_file)
    dark = np.arange(W)[None, :] < W // 2  # [1, W]
    untouched = tactile_image(np.zeros((H, W), np.float32), rng)
    assert not (calib.depth(np.where(dark[..., None], 0, untouched).astype(np.uint8), reference) > 0).any()
    truth = ball_press(240, 120, 8e-4)
    pressed = tactile_image(truth, rng)
    whole = calib.depth(pressed, reference)
    half = calib.depth(np.where(dark[..., None], 0, pressed).astype(np.uint8), reference)
    assert not (half > 0)[:, : W // 2].any()
    assert abs(float(half.max()) - float(whole.max())) < 0.05 * float(whole.max())


class ModeCamera:
    """A UVC-like camera: 640x480 by default, switched to any size by CAP_PROP_FRAME_WIDTH/HEIGHT; it stops
    delivering after ``frames`` frames (never if None)."""

    def __init__(self, source, frames=None):
        self.width, self.height, self.frames, self.released = 640, 480, frames, threading.Event()

    def isOpened(self):
        return True

    def set(self, prop, value):
        if prop in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT):
            setattr(self, "width" if prop == cv2.CAP_PROP_FRAME_WIDTH else "height", int(value))
            return True
        return False

    def get(self, prop):
        sizes = {cv2.CAP_PROP_FRAME_WIDTH: self.width, cv2.CAP_PROP_FRAME_HEIGHT: self.height}
        return sizes.get(prop, 30.0 if prop == cv2.CAP_PROP_FPS else 0.0)

    def read(self):
        time.sleep(0.01)
        if self.frames is not None:
            if self.frames <= 0:
                return False, None  # unplugged
            self.frames -= 1
        return True, np.full((self.height, self.width, 3), 128, np.uint8)

    def release(self):
        self.released.set()


def test_sensor_asks_the_camera_for_the_calibrations_image_size():
    """Opened with no width/height (as the rig opens it), the sensor asks for the calibration's size."""
    calib = TactileCalibration(_weights(), PIXEL_M, (H, W))
    with OpticalTactileSensor("index", 0, calib, timeout_s=1.0, capture_factory=ModeCamera) as sensor:
        assert sensor.read().depth.shape == (H, W)


def test_a_sensor_that_fails_while_taking_its_reference_releases_the_camera():
    cameras = []

    def dies_after_two_frames(source):
        cameras.append(ModeCamera(source, frames=2))
        return cameras[-1]

    calib = TactileCalibration(_weights(), PIXEL_M, (H, W))
    sensor = OpticalTactileSensor(
        "index", 0, calib, width=W, height=H, timeout_s=0.5, capture_factory=dies_after_two_frames
    )
    with pytest.raises(CameraError, match="no frame after 2 frames"):
        sensor.open()
    assert cameras[0].released.wait(3.0), "the camera was never released"
