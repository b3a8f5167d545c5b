"""Emulated devices for ``tacsplat capture --mock``: a real rig's code path with no hardware attached.

* the hand: the real :class:`~tacsplat.drivers.DynamixelHand` and ``dynamixel_sdk``
  talking to :class:`~tacsplat.drivers.dxl_emulator.DxlEmulator` on a pseudo-terminal, its servos stopped at the
  joint limits and off by the rig file's ``sim.true_errors`` (read with ``hand.calibration`` when the rig names
  one, else sign 1 and offset 0), moved by :class:`EmulatorPerson` for ``calibrate hand``; the presses of
  ``calibrate hand-eye`` and ``mounts`` are :class:`~tacsplat.acquisition.mock_presser.EmulatorPresser`'s;
* the wrist camera: the real :class:`~tacsplat.drivers.WristCamera` reading a
  looping video of a ChArUco board rendered with ``cv2.aruco`` and warped by
  known camera poses (``camera_poses`` holds them, OpenCV board frame);
* the tactile sensors: the real :class:`~tacsplat.drivers.OpticalTactileSensor`
  reading looping videos of synthetic tactile images (untouched gel, then ball
  presses and a frame with no contact), with a calibration fitted on rendered
  ball presses. Each grasp reads one frame per sensor, so the touches are
  not geometrically consistent with the hand: the mock proves the code path,
  not the tactile geometry (the twin does that).

The generated files (videos, calibrations) are cached in a folder keyed by the
settings, so a resumed or repeated mock capture reuses them. ``mock_devices.unplugged`` and
``board_in_view: false`` leave devices out and the board out of view (what ``rig check`` must name). Faults for
tests:
:meth:`MockDevices.stall_camera` (the camera stops delivering frames) and
``mock.emulator.disconnect(servo_id)`` (a servo stops answering). With
``mock_devices.servo_port`` the servos are an emulator in a process of its own
(``python -m tacsplat.drivers.dxl_emulator``), which outlives a capture that is
killed or signalled.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import tempfile
import threading
import time
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from tacsplat.acquisition.config import RigConfig
from tacsplat.drivers.calibration import RAD_PER_TICK
from tacsplat.drivers.dynamixel_table import CENTRE_TICK
from tacsplat.errors import ConfigError
from tacsplat.geometry import invert_pose, look_at, tactile_pixel_grid
from tacsplat.sim.hand import JOINT_LIMITS, nominal_T_hand_cam
from tacsplat.sim.tactile import render_tactile_rgb

log = logging.getLogger(__name__)

REFERENCE_FRAMES = 5  # untouched frames at the start of each tactile video (the sensor's reference)
ASSET_VERSION = 4  # bump when the generated files change
LIVE_CAMERA_FPS = 30.0
BALL_RADIUS_M = 4e-3
SUPERSAMPLE = 2
MOCK_T_HAND_CAM = nominal_T_hand_cam()  # the mock camera calibration's hand-eye: the hand model's designed pose


class LoopingCapture:
    """A ``cv2.VideoCapture`` of a file that starts again at its end (a device that never runs out), paced at
    ``fps`` like a live camera when given; :meth:`stall` makes ``read`` block as a hung USB camera does."""

    def __init__(self, path: str, fps: float | None = None):
        self._cap = cv2.VideoCapture(path)
        self._period = 1.0 / fps if fps else 0.0
        self._next = time.monotonic()
        self._stalled = threading.Event()
        self._released = threading.Event()
        self._shown: np.ndarray | None = None

    def __getattr__(self, name: str):  # the rest of cv2.VideoCapture: isOpened, get, set
        return getattr(self._cap, name)

    def read(self):
        if self._period:
            self._next += self._period
            self._released.wait(max(0.0, self._next - time.monotonic()))
        if self._stalled.is_set():
            self._released.wait()
            return False, None
        if (shown := self._shown) is not None:
            return True, shown.copy()
        ok, image = self._cap.read()
        if not ok:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, image = self._cap.read()
        return ok, image

    def show(self, image_rgb: np.ndarray | None) -> None:
        """Deliver this image [H, W, 3] RGB from now on instead of the file's frames (None: the file again)."""
        self._shown = None if image_rgb is None else np.ascontiguousarray(image_rgb[:, :, ::-1])

    def stall(self) -> None:
        self._stalled.set()

    def release(self) -> None:
        self._released.set()
        self._cap.release()


def _write_video(path: Path, frames_rgb: list[np.ndarray]) -> None:
    h, w = frames_rgb[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (w, h))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write an FFV1 video to {path}")
    for frame in frames_rgb:
        writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    writer.release()


def render_board(spec, K: np.ndarray, width: int, height: int, T_cam_board: np.ndarray) -> np.ndarray:
    """An RGB image [H, W, 3] uint8 of the ChArUco board seen by a pinhole camera (``K`` tacsplat convention,
    pixel centres at +0.5) at ``T_cam_board`` (OpenCV board frame), by a supersampled homography warp."""
    px = 60  # board image pixels per square
    board_img = spec.board().generateImage((spec.squares_x * px, spec.squares_y * px), marginSize=0)
    m_per_px = spec.square_length_m / px
    K_hi = np.diag([SUPERSAMPLE, SUPERSAMPLE, 1.0]) @ K
    H = K_hi @ np.column_stack([T_cam_board[:3, 0], T_cam_board[:3, 1], T_cam_board[:3, 3]])
    H = H @ np.diag([m_per_px, m_per_px, 1.0])
    shift = lambda d: np.array([[1.0, 0, d], [0, 1.0, d], [0, 0, 1.0]])  # noqa: E731
    H_cv = shift(-0.5) @ H @ shift(0.5)  # warpPerspective puts pixel centres at integers
    big = cv2.warpPerspective(
        board_img, H_cv, (width * SUPERSAMPLE, height * SUPERSAMPLE), flags=cv2.INTER_LINEAR, borderValue=150
    )
    gray = cv2.resize(big, (width, height), interpolation=cv2.INTER_AREA)
    return np.repeat(gray[:, :, None], 3, axis=2)


def camera_poses(spec, count: int) -> list[np.ndarray]:
    """``T_cam_board`` of the mock camera's video: looking at the board centre from 0.3-0.4 m, around it."""
    centre = np.array([spec.squares_x * spec.square_length_m / 2, spec.squares_y * spec.square_length_m / 2, 0.0])
    rng = np.random.default_rng(7)
    eyes = [
        centre + np.array([0.08 * np.cos(a), 0.06 * np.sin(a), -rng.uniform(0.3, 0.4)])
        for a in (2 * np.pi * k / max(count, 1) for k in range(count))
    ]
    return [invert_pose(look_at(eye, centre, up=(0.0, -1.0, 0.0))) for eye in eyes]


def servo_ticks(config: RigConfig, q_true: np.ndarray) -> np.ndarray:
    """[16] where the emulated servos stand (ticks, unrounded) at true joint angles ``q_true``: the nominal hand's
    ticks off by ``sim.true_errors``'s servo signs and offsets."""
    e = config.sim.true_errors
    theta = np.asarray(e.servo_signs()) * np.asarray(q_true, dtype=np.float64) + np.asarray(e.servo_offsets())
    return theta / RAD_PER_TICK + CENTRE_TICK


def servo_angles(config: RigConfig, ticks: np.ndarray) -> np.ndarray:
    """[16] the true joint angles of emulated servos standing at ``ticks``: the inverse of :func:`servo_ticks`."""
    e = config.sim.true_errors
    theta = (np.asarray(ticks, dtype=np.float64) - CENTRE_TICK) * RAD_PER_TICK
    return (theta - np.asarray(e.servo_offsets())) / np.asarray(e.servo_signs())


def own_emulator(config: RigConfig, what: str, to: str) -> None:
    """A ConfigError when ``mock_devices.servo_port`` puts the servo emulator in a process of its own, where no one
    does ``what`` (for ``to`` with --mock): checked before any device opens."""
    if config.mock_devices.servo_port:
        raise ConfigError(
            "mock_devices.servo_port",
            f"the servo emulator runs in another process, where no one {what}: leave servo_port out to {to} "
            "with --mock",
            config.source,
        )


class EmulatorPerson:
    """The person of ``tacsplat calibrate hand --mock``: moves each emulated servo by hand (torque off) against the
    stop a joint limit puts it at, and holds it there."""

    def __init__(self, mock: "MockDevices", settle_s: float = 0.1):
        mock.own_emulator("moves its joints by hand", "calibrate the hand")
        self.mock, self.settle_s = mock, settle_s
        self.ids = list(mock.config.hand.ids)

    def hold_at_stop(self, joint: int, upper: bool, instruction: str) -> None:
        sid = self.ids[joint]
        target = (self.mock.upper_stop_ticks if upper else self.mock.lower_stop_ticks)[sid]
        lo, hi = self.mock.servo_stops[sid]
        self.mock.emulator.move_by_hand(sid, target + (hi - lo) * (1 if target == hi else -1))  # pushed past it
        # like a person: push until the joint is at its stop, or has not moved for settle_s
        last, still_since = self.mock.emulator.position(sid), time.monotonic()
        while time.monotonic() - still_since < self.settle_s:
            time.sleep(0.005)
            now = self.mock.emulator.position(sid)
            if now == target:
                return
            if now != last:
                last, still_since = now, time.monotonic()

    def let_go(self, joint: int) -> None:
        self.mock.emulator.move_by_hand(self.ids[joint], None)


def sphere_press(shape: tuple[int, int], pixel_m: float, spot: tuple, radius_m: float, indentation_m: float):
    """The indentation [h, w] float32 of a sphere of ``radius_m`` pressed ``indentation_m`` into the gel with its
    lowest point over the gel's ``spot`` (x, y metres in the sensor frame)."""
    x, y = tactile_pixel_grid(*shape, pixel_m)
    rho2 = (x - spot[0]) ** 2 + (y - spot[1]) ** 2
    return np.maximum(np.sqrt(np.maximum(radius_m**2 - rho2, 0.0)) - (radius_m - indentation_m), 0.0).astype(np.float32)


class MockDevices:
    """Files and emulators behind a mocked real rig; a context manager (starts and stops the servo emulator)."""

    def __init__(self, config: RigConfig, cache_dir: str | Path | None = None):
        from tacsplat.drivers.dxl_emulator import DxlEmulator

        self.config = config
        m = config.mock_devices
        files = {k: v for k, v in asdict(m).items() if not k.startswith("servo_") and k != "unplugged"}  # of the files
        fingers = [s.finger for s in config.tactile.sensors]
        settings = json.dumps([ASSET_VERSION, files, asdict(config.board), fingers], sort_keys=True)
        key = hashlib.sha1(settings.encode()).hexdigest()[:12]
        root = Path(cache_dir) if cache_dir else Path(tempfile.gettempdir()) / f"tacsplat-mock-rig-{os.getuid()}"
        self.folder = root / key
        self.camera_video = self.folder / "wrist_camera.avi"
        self.camera_calibration = self.folder / "wrist_camera.json"
        self.tactile_calibration = self.folder / "tactile_calibration.npz"
        self.K = np.array(
            [[m.camera_focal_px, 0, m.camera_width / 2], [0, m.camera_focal_px, m.camera_height / 2], [0, 0, 1.0]]
        )
        self.camera_poses = camera_poses(config.board.spec(), m.camera_frames)
        if not (self.folder / "done").is_file():
            self._generate()
        lower, upper = servo_ticks(config, JOINT_LIMITS[:, 0]), servo_ticks(config, JOINT_LIMITS[:, 1])
        self.servo_stops = {sid: (min(a, b), max(a, b)) for sid, a, b in zip(config.hand.ids, lower, upper)}
        self.upper_stop_ticks = dict(zip(config.hand.ids, upper))  # where each joint's upper limit puts its servo
        self.lower_stop_ticks = dict(zip(config.hand.ids, lower))
        initial = dict(zip(config.hand.ids, servo_ticks(config, np.zeros(len(JOINT_LIMITS)))))  # the open hand
        self.emulator = (
            None if m.servo_port else DxlEmulator(ids=config.hand.ids, initial_ticks=initial, stops=self.servo_stops)
        )  # None: an emulator process's
        self.captures: dict[str, LoopingCapture] = {}

    # --- files ------------------------------------------------------------------------------------
    def tactile_video(self, finger: str) -> Path:
        return self.folder / f"tactile_{finger}.avi"

    def own_emulator(self, what: str, to: str) -> None:
        """A ConfigError when the servo emulator runs in a process of its own (:func:`own_emulator`)."""
        own_emulator(self.config, what, to)

    def _generate(self) -> None:
        from tacsplat.drivers.optical_tactile import TactileCalibration
        from tacsplat.drivers.wrist_camera import CameraCalibration, opencv_K_from_tacsplat

        m, spec = self.config.mock_devices, self.config.board.spec()
        self.folder.parent.mkdir(parents=True, exist_ok=True)
        frames = [
            render_board(spec, self.K, m.camera_width, m.camera_height, T)
            if m.board_in_view
            else np.full((m.camera_height, m.camera_width, 3), 150, np.uint8)
            for T in self.camera_poses
        ]
        # written into a folder of its own, renamed to the cache's when complete (a cleanup removes it otherwise)
        with tempfile.TemporaryDirectory(prefix=".mock-", dir=self.folder.parent, ignore_cleanup_errors=True) as tmp:
            work = Path(tmp)
            _write_video(work / self.camera_video.name, frames)
            K_opencv = opencv_K_from_tacsplat(self.K)
            calibration = CameraCalibration(
                K_opencv, np.zeros(5), m.camera_width, m.camera_height, 0.0, spec, T_hand_cam=MOCK_T_HAND_CAM
            )
            calibration.save(work / self.camera_calibration.name)
            h, w, pix = m.tactile_height, m.tactile_width, m.tactile_pixel_size_m
            reference = render_tactile_rgb(np.zeros((h, w), np.float32), pix)
            presses = [(0.3, 0.35, 6e-4), (0.7, 0.6, 8e-4), (0.5, 0.5, 1e-3), (0.3, 0.7, 5e-4), (0.7, 0.3, 9e-4)]
            press_images = [
                render_tactile_rgb(
                    sphere_press((h, w), pix, ((x - 0.5) * w * pix, (y - 0.5) * h * pix), BALL_RADIUS_M, d), pix
                )
                for x, y, d in presses
            ]
            TactileCalibration.fit(reference, press_images, BALL_RADIUS_M, pix).save(
                work / self.tactile_calibration.name
            )
            for i, s in enumerate(self.config.tactile.sensors):
                # untouched gel (the reference), then one frame per grasp: three presses and, at a place that
                # differs per finger, no contact (sensor 0: the 2nd grasp, 1: the 3rd, 2: the 4th, 3: the 1st)
                readings = [press_images[(i + k) % len(press_images)] for k in range(3)]
                readings.insert((i + 1) % 4, reference)
                _write_video(work / self.tactile_video(s.finger).name, [reference] * REFERENCE_FRAMES + readings)
            (work / "done").write_text("ok\n")
            with contextlib.suppress(OSError):  # another process generated the same folder meanwhile
                os.replace(work, self.folder)

    # --- devices ----------------------------------------------------------------------------------
    @property
    def servo_port(self) -> str:
        """The servos' port: the emulator in this process, or ``mock_devices.servo_port`` (one in its own)."""
        return self.emulator.path if self.emulator is not None else self.config.mock_devices.servo_port

    @property
    def camera_source(self) -> str:
        """The wrist camera's source name: not a file path, so the driver reads it as a live device (the newest
        frame, paced at 30 fps) rather than a file (every frame in order)."""
        return f"mock-camera:{self.camera_video}"

    def capture_factory(self, name: str):
        """A ``capture_factory`` for the drivers' video readers that loops the file and remembers the capture."""

        def factory(source):
            if name in self.config.mock_devices.unplugged:
                return cv2.VideoCapture()  # never opened, as a device that is not there
            if name == "camera":
                cap = LoopingCapture(str(self.camera_video), fps=LIVE_CAMERA_FPS)
            else:
                cap = LoopingCapture(str(source))
            self.captures[name] = cap
            return cap

        return factory

    def stall_camera(self) -> None:
        """Fault: the wrist camera stops delivering frames (as when it is unplugged or its driver hangs)."""
        self.captures["camera"].stall()

    def __enter__(self) -> "MockDevices":
        if self.emulator is not None:
            self.emulator.start()
            for name in self.config.mock_devices.unplugged:
                if name.startswith("servo "):
                    self.emulator.disconnect(int(name.split()[1]))
        return self

    def __exit__(self, *exc) -> None:
        for cap in self.captures.values():
            cap._released.set()
        if self.emulator is not None:
            self.emulator.stop()
