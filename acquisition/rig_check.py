"""``tacsplat rig check``: is the rig ready to capture? Every device answers, every calibration file the rig names
is there, plausible (it parses, its values are in range), younger than the rig file's ``hardware_changed`` and not
overridden by another value in the rig file itself, and the wrist camera sees the board; one table, one row per
check. A twin whose ``sim.true_errors`` hide errors that no calibration file corrects fails as a real rig without
that file does.

On ``--mock`` the devices are emulated (``mock_devices.unplugged`` and ``board_in_view`` stage faults) and the camera
and tactile calibrations are the mock's own, as a mock capture uses them; the hand calibration is the rig's.
"""

from __future__ import annotations

import time
from contextlib import nullcontext
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Callable

import numpy as np

from tacsplat.acquisition.config import RigConfig
from tacsplat.acquisition.devices import import_device_modules, uncalibrated_hand
from tacsplat.errors import TacsplatError
from tacsplat.sim.hand import FINGER_NAMES, JOINT_LIMITS, JOINT_NAMES

FPS_WINDOW_S = 0.5  # how long each camera's frame rate is measured
READ_TOLERANCE_RAD = np.radians(5.0)  # a joint read this far outside its limits with hand.json: a wrong calibration


@dataclass(frozen=True)
class Row:
    """One check: what (a device, or the rig file's key of a calibration file), ``ok``, and what was found."""

    item: str
    ok: bool
    detail: str


def _calibration_file(rows: list[Row], config: RigConfig, key: str, name: str | None, load: Callable[[Path], object]):
    """Append a calibration file's row (there, parses, younger than hardware_changed) if the rig names one (``name``);
    returns what it loaded (None if not)."""
    if not name:
        return None
    path = config.path(name)
    if not path.is_file():
        rows.append(Row(key, False, f"{path}: missing"))
        return None
    try:
        loaded = load(path)
    except TacsplatError as exc:
        rows.append(Row(key, False, f"unusable: {exc}"))
        return None
    written = datetime.fromtimestamp(path.stat().st_mtime)
    changed = config.hardware_changed
    if changed is not None and written < changed:
        stale = f"stale: written {written:%Y-%m-%d %H:%M}, before hardware_changed {changed:%Y-%m-%d %H:%M}"
        rows.append(Row(key, False, f"{path}: {stale}; calibrate again"))
    else:
        rows.append(Row(key, True, f"{path}: written {written:%Y-%m-%d %H:%M}"))
    return loaded


def _hand_file(rows: list[Row], config: RigConfig):
    """Append the hand calibration's row if the rig names one; returns it loaded (None if not)."""
    from tacsplat.drivers.calibration import HandCalibration

    return _calibration_file(
        rows, config, "hand.calibration", config.hand.calibration, lambda p: HandCalibration.load(p, JOINT_NAMES)
    )


def _servos(config: RigConfig, mock, hand_calibration) -> Row:
    """Every servo answers (torque off throughout); with a hand calibration, every joint reads inside its limits."""
    from tacsplat.acquisition.devices import dynamixel_hand

    hand = dynamixel_hand(config, mock)
    item = f"servos ({len(config.hand.ids)} on {hand.port_name})"
    try:
        hand.connect(torque=False)
        theta = hand.read_motor_angles()
    except TacsplatError as exc:
        return Row(item, False, str(exc))
    finally:
        hand.close()
    detail = f"all answer; {hand.torque_off_report}"
    if hand_calibration is not None:
        q = hand_calibration.joint_angles(theta)
        out = np.flatnonzero(
            (q < JOINT_LIMITS[:, 0] - READ_TOLERANCE_RAD) | (q > JOINT_LIMITS[:, 1] + READ_TOLERANCE_RAD)
        )
        if out.size:
            joints = ", ".join(f"{JOINT_NAMES[i]} reads {np.degrees(q[i]):+.1f} deg" for i in out)
            return Row(item, False, f"outside the joint limits with the hand calibration: {joints} (calibrate hand)")
        detail += "; every joint reads inside its limits"
    return Row(item, True, detail)


def _frames(reader_read, seconds: float) -> tuple[np.ndarray, float]:
    """The last image read and the frame rate over ``seconds``."""
    start, count, image = time.monotonic(), 0, None
    while count < 2 or time.monotonic() - start < seconds:
        image = reader_read()
        count += 1
    return image, (count - 1) / (time.monotonic() - start)


def _pose_files(rows: list[Row], config: RigConfig) -> None:
    """Append the rows of the hand-eye and mounts files the rig names (calibrate hand-eye, calibrate mounts). A
    file's row fails where the rig file's own value overrides a different one of the file's (a capture would not
    use what was calibrated), and a mounts file's where it has no entry for a sensor of the rig (a capture would
    take that sensor as mounted at the identity)."""
    from tacsplat.drivers.press_calibration import MAX_STD, MOUNT_MAX_STD, load_hand_eye, load_mounts

    T_hand_cam = _calibration_file(
        rows, config, "camera.hand_eye", config.camera.hand_eye, lambda p: load_hand_eye(p, key="camera.hand_eye")
    )
    if T_hand_cam is not None and config.camera.T_hand_cam is not None:
        if differs := _differs(
            np.asarray(config.camera.T_hand_cam), T_hand_cam, 1000 * MAX_STD[1], np.degrees(MAX_STD[0])
        ):
            _fail(rows, f"the rig file's camera.T_hand_cam, {differs} from it, overrides it: remove camera.T_hand_cam")
    mounts = _calibration_file(
        rows, config, "tactile.mounts", config.tactile.mounts, lambda p: load_mounts(p, FINGER_NAMES, "tactile.mounts")
    )
    if mounts is None:
        return
    inline = {
        s.finger: (i, np.asarray(s.T_fingertip_sensor))
        for i, s in enumerate(config.tactile.sensors)
        if s.T_fingertip_sensor is not None
    }
    problems = []
    if missing := [f for f in _rig_fingers(config) if f not in mounts and f not in inline]:
        problems.append(f"no entry for the {', '.join(missing)} sensor (calibrate mounts again, every sensor pressed)")
    for finger, (i, T) in inline.items():
        if finger in mounts and (differs := _differs(T, mounts[finger], MOUNT_MAX_STD[1], MOUNT_MAX_STD[0])):
            problems.append(
                f"the rig file's tactile.sensors[{i}].T_fingertip_sensor, {differs} from its entry, overrides it: remove it"
            )
    if problems:
        _fail(rows, "; ".join(problems))


def _differs(T_a: np.ndarray, T_b: np.ndarray, same_mm: float, same_deg: float) -> str:
    """``"1.23 mm, 0.45 deg"`` from ``T_a`` to ``T_b`` when further than ``same_mm`` or ``same_deg``; ``""`` if not.
    Two values closer than what their calibration determines are one (copied by hand to fewer digits, say)."""
    from tacsplat.acquisition.arm_hand_eye import pose_change, pose_gap

    mm, deg = pose_gap(T_a, T_b)
    return pose_change(T_a, T_b) if mm > same_mm or deg > same_deg else ""


def _fail(rows: list[Row], problem: str) -> None:
    """Fail the last row (a calibration file's), adding ``problem`` to what it says."""
    rows[-1] = Row(rows[-1].item, False, f"{rows[-1].detail}; {problem}")


def _rig_fingers(config: RigConfig) -> list[str]:
    """The fingers with a tactile sensor: a twin's every finger, a real rig's ``tactile.sensors``."""
    return list(FINGER_NAMES) if config.rig == "sim" else [s.finger for s in config.tactile.sensors]


def _uncalibrated_twin(rows: list[Row], config: RigConfig) -> None:
    """Append a failing row for each calibration a twin hides errors of (``sim.true_errors``) but the rig neither
    names a file for nor gives itself: a capture would take that part as nominal, as a real rig's would."""
    e = config.sim.true_errors
    if why := uncalibrated_hand(config):
        rows.append(Row("hand.calibration", False, why))
    known = config.camera.hand_eye or config.camera.T_hand_cam is not None
    if not known and _is_error(e.hand_eye):
        why = "none named, and the twin hides a hand-eye error (sim.true_errors): tacsplat calibrate hand-eye writes it"
        rows.append(Row("camera.hand_eye", False, why))
    inline = {s.finger for s in config.tactile.sensors if s.T_fingertip_sensor is not None}
    hidden = [f for f, error in e.mounts.items() if _is_error(error) and f not in inline]
    if not config.tactile.mounts and hidden:
        why = f"none named, and the twin hides mounting errors of the {', '.join(hidden)} sensors (sim.true_errors)"
        rows.append(Row("tactile.mounts", False, f"{why}: tacsplat calibrate mounts writes it"))


def _is_error(error) -> bool:
    """A pose error (``sim.true_errors``) that is not the identity."""
    return any(error.translation_m) or any(error.rotation_deg)


def _T_hand_cam_row(config: RigConfig, cam_cal) -> Row:
    """``T_hand_cam`` is known, found as a capture finds it (:func:`~tacsplat.acquisition.devices.rig_T_hand_cam`:
    the rig file's, its ``camera.hand_eye`` file's, the camera calibration's), and where it came from."""
    from tacsplat.acquisition.devices import rig_T_hand_cam_origin

    try:
        T_hand_cam, origin = rig_T_hand_cam_origin(config, cam_cal)
    except TacsplatError as exc:
        return Row("camera.T_hand_cam", False, f"not known: {exc}")
    return Row("camera.T_hand_cam", T_hand_cam is not None, origin)


def check_rig(config: RigConfig) -> list[Row]:
    """Every check of a ``rig: real`` config (emulated devices with ``config.mock``)."""
    import_device_modules(config)
    from tacsplat.drivers.optical_tactile import TactileCalibration
    from tacsplat.drivers.wrist_camera import CameraCalibration

    if config.mock:
        from tacsplat.acquisition.mock import MockDevices

    rows: list[Row] = []
    hand_cal = _hand_file(rows, config)
    if why := uncalibrated_hand(config):
        rows.append(Row("hand.calibration", False, why))
    sensors = config.tactile.sensors
    with MockDevices(config) if config.mock else nullcontext() as mock:
        if mock is not None:
            cam_cal = CameraCalibration.load(mock.camera_calibration)
            rows.append(Row("camera.calibration", True, f"generated by --mock ({mock.camera_calibration})"))
            tactile = {s.finger: TactileCalibration.load(mock.tactile_calibration) for s in sensors}
            rows += [Row(f"tactile.sensors[{i}].calibration", True, "generated by --mock") for i in range(len(sensors))]
        else:
            cam_cal = _calibration_file(
                rows, config, "camera.calibration", config.camera.calibration, CameraCalibration.load
            )
            tactile = {
                s.finger: _calibration_file(
                    rows, config, f"tactile.sensors[{i}].calibration", s.calibration, TactileCalibration.load
                )
                for i, s in enumerate(sensors)
            }
        _pose_files(rows, config)
        rows.append(_T_hand_cam_row(config, cam_cal))
        # the devices
        rows.append(_servos(config, mock, hand_cal))
        rows += _camera_rows(config, mock, cam_cal)
        for s in sensors:
            rows.append(_tactile_row(config, mock, s, tactile.get(s.finger)))
    return rows


def _tactile_row(config: RigConfig, mock, sensor, calibration) -> Row:
    """The tactile sensor answers (its rate) at its ``calibration``'s image size, asked of it as a capture asks
    (any size when its calibration is unusable)."""
    from tacsplat.acquisition.devices import device_source
    from tacsplat.drivers.video import VideoReader

    source, reader = device_source(mock, sensor.finger, sensor.source)
    if calibration is not None:
        reader["height"], reader["width"] = (int(n) for n in calibration.image_size)
    item = f"tactile {sensor.finger} (source {sensor.source})"
    try:
        with VideoReader(source, timeout_s=config.tactile.timeout_s, name=f"tactile {sensor.finger}", **reader) as r:
            image, fps = _frames(lambda: r.read().image, FPS_WINDOW_S)
    except TacsplatError as exc:
        return Row(item, False, str(exc))
    h, w = image.shape[:2]
    return Row(item, True, f"{w}x{h} at {fps:.0f} fps")


def _camera_rows(config: RigConfig, mock, cam_cal) -> list[Row]:
    """The wrist camera answers (its rate), and sees the board well enough to capture."""
    from tacsplat.acquisition.devices import device_source
    from tacsplat.acquisition.logger import BoardPoseSource
    from tacsplat.drivers.wrist_camera import WristCamera

    item = f"wrist camera (source {config.camera.source})"
    if cam_cal is None:
        return [Row(item, False, "not opened: its calibration is unusable"), Row("board", False, "not looked for")]
    source, reader = device_source(mock, "camera", config.camera.source)
    try:
        with WristCamera(source, cam_cal, fps=config.camera.fps, timeout_s=config.camera.timeout_s, **reader) as cam:
            image, fps = _frames(lambda: cam.read()[0], FPS_WINDOW_S)
            poses = BoardPoseSource(cam, config.board, np.eye(4))
            rows = [Row(item, True, f"{cam.width}x{cam.height} at {fps:.0f} fps")]
            try:
                est = poses.measure(image)
            except TacsplatError as exc:
                return rows + [Row("board", False, f"not seen: {exc}; put the board in the wrist camera's view")]
    except TacsplatError as exc:
        return [Row(item, False, str(exc)), Row("board", False, "not looked for")]
    limit = config.board.max_reprojection_px
    seen = f"seen: {est.corners} corners, reprojection {est.reprojection_px:.2f} px"
    if est.reprojection_px > limit:
        return rows + [Row("board", False, f"{seen}, over board.max_reprojection_px {limit:g}")]
    return rows + [Row("board", True, seen)]


def check_twin(config: RigConfig) -> list[Row]:
    """A ``rig: sim`` config: its calibration files (those named, and those its hidden errors need) and the twin's
    devices."""
    from tacsplat.acquisition.devices import twin_config
    from tacsplat.sim.twin import SimTwin

    rows: list[Row] = []
    _hand_file(rows, config)
    _pose_files(rows, config)
    _uncalibrated_twin(rows, config)
    if not all(row.ok for row in rows):
        return rows
    with SimTwin(twin_config(config)) as twin:
        q = twin.hand.read_joint_positions()
        rows.append(Row("twin hand", True, f"{len(q)} joints answer"))
        for sensor in twin.tactile_sensors:
            h, w = sensor.read().depth.shape
            rows.append(Row(f"twin tactile {sensor.name}", True, f"{w}x{h} depth maps"))
    rows.append(Row("board", True, "none: the twin's world frame is MuJoCo's"))
    return rows


def table(rows: list[Row]) -> str:
    """The rows as a plain-text table."""
    width = max(len(r.item) for r in rows)
    lines = [f"{'check':<{width}}  status  detail"]
    lines += [f"{r.item:<{width}}  {'ok' if r.ok else 'FAIL':<6}  {r.detail}" for r in rows]
    return "\n".join(lines)
