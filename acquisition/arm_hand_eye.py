"""``tacsplat calibrate hand-eye --arm-poses FILE``: the wrist camera's pose on the hand (``T_hand_cam``) from a hand
on an arm, by :func:`~tacsplat.drivers.wrist_camera.hand_eye_calibration` (Park & Martin, ``A X = X B``).

The poses file (YAML, or JSON when its name ends in ``.json``) lists stations: the hand's pose in the arm's base as
the arm's controller reports it (``T_base_hand``, 4x4, metres) and the wrist camera's raw image taken there
(``image``, a path relative to the file)::

    stations:
      - T_base_hand: [[1, 0, 0, 0.45], [0, 1, 0, 0.02], [0, 0, 1, 0.38], [0, 0, 0, 1]]
        image: station_01.png
      - ...

Each image is undistorted as the camera driver undistorts its frames and the rig's board found in it by PnP, as a
capture does (a station whose board is not seen, or is seen worse than ``board.max_reprojection_px``, is skipped).
The board lies still in the arm's base, so every station implies the same board pose there,
``T_base_hand @ T_hand_cam @ T_cam_board``: their spread is the result's consistency.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from typing import Annotated, Callable

import cv2
import numpy as np
import yaml
from pydantic import AfterValidator, Field, ValidationError
from scipy.spatial.transform import Rotation

from tacsplat.acquisition.config import RigConfig
from tacsplat.drivers.calibration import field_error
from tacsplat.drivers.calibration_files import CalibrationFile, Rigid
from tacsplat.errors import CameraError, ConfigError
from tacsplat.geometry import invert_pose, make_pose

MIN_STATIONS = 3  # where the board is seen: two motions between them
MAX_REACH_M = 5.0  # a hand further from the arm's base was given in millimetres
# The hand must turn about two axes: turned about one only, T_hand_cam's rotation about that axis and its offset
# along it are undetermined. Motions of at least MIN_TURN_DEG count, and two of their axes must lie this far apart.
MIN_TURN_DEG = 5.0
MIN_AXIS_ANGLE_DEG = 15.0
# A sound station set puts the board within this of the stations' mean at its farthest station (mm, degrees): an
# arm's controller reports the hand's pose to about a millimetre and 0.1 degree, PnP gives a board's at 0.3-0.5 m to
# about a millimetre and 0.2 degree, and the farthest of up to 15 stations lies about twice that out. Further off,
# a pose or an image is wrong.
MAX_SPREAD = (5.0, 2.0)
# The wrist camera sits on the hand or on the arm's last link: within a hand's length (the hand model's is about
# 0.2 m) of the hand's frame, with room for a bracket. Further, T_hand_cam was solved from wrong poses.
MAX_HAND_CAM_M = 0.3


def _in_reach(T_base_hand: np.ndarray) -> np.ndarray:
    reach = float(np.linalg.norm(T_base_hand[:3, 3]))
    if reach > MAX_REACH_M:
        raise ValueError(f"puts the hand {reach:g} m from the arm's base: give the translation in metres")
    return T_base_hand


class _Station(CalibrationFile, extra="ignore"):
    T_base_hand: Annotated[Rigid, AfterValidator(_in_reach)]
    image: Annotated[str, Field(min_length=1)]


class _ArmPoses(CalibrationFile, extra="ignore"):
    stations: list[_Station]


def read_arm_poses(path: Path) -> list[_Station]:
    """The stations of a poses file; one ConfigError names the file and the field (``stations[2].T_base_hand``)."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) else "not a text file"
        raise ConfigError("--arm-poses", f"cannot read {path}: {reason}") from None
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (json.JSONDecodeError, yaml.YAMLError) as exc:
        kind = "JSON" if path.suffix.lower() == ".json" else "YAML"
        raise ConfigError("--arm-poses", f"{path} is not valid {kind}: {exc}") from None
    try:
        return _ArmPoses.model_validate(data).stations
    except ValidationError as exc:
        raise ConfigError(*field_error(exc, _ArmPoses), source=path) from None


def pose_gap(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(millimetres, degrees) from pose ``T_a`` to pose ``T_b``."""
    D = invert_pose(T_a) @ T_b
    return 1000 * float(np.linalg.norm(D[:3, 3])), float(np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()))


def pose_change(T_from: np.ndarray, T_to: np.ndarray) -> str:
    """``"1.23 mm, 0.45 deg"`` from pose ``T_from`` to pose ``T_to``."""
    return "{:.2f} mm, {:.2f} deg".format(*pose_gap(T_from, T_to))


def _axis_spread_deg(T_base_hand: list[np.ndarray]) -> float:
    """The widest angle (degrees, 0-90) between the rotation axes of two of the hand's motions between stations
    that turn it at least :data:`MIN_TURN_DEG` (0 when fewer than two do)."""
    turns = [
        Rotation.from_matrix((invert_pose(T_j) @ T_i)[:3, :3]).as_rotvec()
        for T_i, T_j in itertools.combinations(T_base_hand, 2)
    ]
    axes = [turn / np.linalg.norm(turn) for turn in turns if np.degrees(np.linalg.norm(turn)) >= MIN_TURN_DEG]
    if len(axes) < 2:
        return 0.0
    cosines = np.abs(np.array(axes) @ np.array(axes).T)  # an axis and its opposite are one axis
    return float(np.degrees(np.arccos(min(1.0, cosines.min()))))


def calibrate_hand_eye_from_arm(config: RigConfig, poses_file: Path, out: Path, say: Callable[[str], None] = print):
    """``T_hand_cam`` from the arm stations of ``poses_file`` (the board found in each image with the rig's camera
    calibration and board), written to ``out`` with the number of stations used; a line per station, then the
    result, its consistency and its change from the rig's previous ``T_hand_cam``. Returns ``T_hand_cam``."""
    from tacsplat.acquisition.devices import inline_T_hand_cam, rig_T_hand_cam
    from tacsplat.drivers.press_calibration import save_hand_eye
    from tacsplat.drivers.wrist_camera import CameraCalibration, board_pose, hand_eye_calibration, undistort

    calibration_file = config.path(config.camera.calibration)
    if not calibration_file.is_file():
        raise ConfigError(
            "camera.calibration",
            f"file not found: {calibration_file} (the board is found in the images with the camera's intrinsics: "
            "run tacsplat calibrate camera first)",
            config.source,
        )
    calibration = CameraCalibration.load(calibration_file)
    # the rig's T_hand_cam as a capture reads it, or None (a hand-eye file not written yet counts as none), read
    # before ``out`` is written: it may be the rig's file
    previous = rig_T_hand_cam(config, calibration, calibrating=True)
    stations = read_arm_poses(poses_file)
    spec = config.board.spec()
    if calibration.board != spec:
        say(f"note: {calibration_file.name} was calibrated on another board than the rig's; the rig's board is used")
    maps = calibration.undistort_maps()
    K_opencv = calibration.undistorted_K_opencv()  # the undistorted images' intrinsics
    hands, cams, seen = [], [], []
    for i, station in enumerate(stations):
        name = f"stations[{i}]"
        path = poses_file.parent / Path(station.image).expanduser()
        if not path.is_file():
            raise ConfigError(f"{name}.image", f"image not found: {path}", poses_file)
        raw = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if raw is None:
            raise ConfigError(f"{name}.image", f"cannot read the image {path}", poses_file)
        h, w = raw.shape[:2]
        if (w, h) != (calibration.width, calibration.height):
            raise ConfigError(
                f"{name}.image",
                f"{path.name} is {w}x{h}, but the camera calibration {calibration_file.name} is "
                f"{calibration.width}x{calibration.height} (give the camera's raw images)",
                poses_file,
            )
        image = undistort(cv2.cvtColor(raw, cv2.COLOR_BGR2RGB), maps)  # as the camera driver does
        try:
            pose = board_pose(image, spec, K_opencv, None, config.board.min_corners)
        except CameraError as exc:
            say(f"{name} {station.image}: skipped: {str(exc).removeprefix('wrist camera: ')}")
            continue
        if pose.rms_px > config.board.max_reprojection_px:
            say(
                f"{name} {station.image}: skipped: board reprojection error {pose.rms_px:.2f} px, over "
                f"board.max_reprojection_px ({config.board.max_reprojection_px:g} px)"
            )
            continue
        say(f"{name} {station.image}: board {pose.corners} corners, {pose.rms_px:.2f} px")
        hands.append(station.T_base_hand)
        cams.append(pose.T_world_cam)
        seen.append(name)
    if len(seen) < MIN_STATIONS:
        raise ConfigError(
            "stations",
            f"the board was seen at {len(seen)} of {len(stations)} stations; at least {MIN_STATIONS} are needed: "
            "add stations where the wrist camera sees the whole board",
            poses_file,
        )
    spread = _axis_spread_deg(hands)
    if spread < MIN_AXIS_ANGLE_DEG:
        raise ConfigError(
            "stations",
            f"the hand turns about one axis only between the {len(seen)} stations where the board is seen (the axes "
            f"of its turns of {MIN_TURN_DEG:g} deg or more are at most {spread:.1f} deg apart; at least "
            f"{MIN_AXIS_ANGLE_DEG:g} deg are needed), which leaves T_hand_cam undetermined: add stations with the "
            "hand rotated about another axis",
            poses_file,
        )
    T_hand_cam = hand_eye_calibration(hands, cams)
    # the board's pose in the arm's base, as each station implies it, against their mean
    boards = [T_hand @ T_hand_cam @ invert_pose(T_cam) for T_hand, T_cam in zip(hands, cams)]
    mean = make_pose(
        Rotation.from_matrix([T[:3, :3] for T in boards]).mean().as_matrix(), np.mean(boards, axis=0)[:3, 3]
    )
    gaps = np.array([pose_gap(mean, T) for T in boards])  # [n, 2] mm, deg
    farthest = int(np.argmax(gaps[:, 0]))
    rms_mm = float(np.sqrt(np.mean(gaps[:, 0] ** 2)))
    t_mm = ", ".join(f"{1000 * x:.2f}" for x in T_hand_cam[:3, 3])
    r_deg = ", ".join(f"{x:.3f}" for x in Rotation.from_matrix(T_hand_cam[:3, :3]).as_rotvec(degrees=True))
    say(f"T_hand_cam from {len(seen)} arm stations: translation [{t_mm}] mm, rotation vector [{r_deg}] deg")
    say(
        f"consistency: the board's pose in the arm's base is {np.median(gaps[:, 0]):.2f} mm, "
        f"{np.median(gaps[:, 1]):.3f} deg from the stations' mean (median; the farthest, {seen[farthest]}, "
        f"{gaps[farthest, 0]:.2f} mm, {gaps[farthest, 1]:.3f} deg)"
    )
    _refuse_inconsistent(T_hand_cam, gaps, seen, poses_file)
    save_hand_eye(out, T_hand_cam, None, rms_mm, stations=len(seen))
    if previous is not None:
        say(f"T_hand_cam: {pose_change(previous, T_hand_cam)} from the rig's previous value")
    say(f"wrote {out} ({inline_T_hand_cam(config) or 'name it as camera.hand_eye in the rig file'})")
    return T_hand_cam


def _refuse_inconsistent(T_hand_cam: np.ndarray, gaps: np.ndarray, seen: list[str], poses_file: Path) -> None:
    """Refuse a ``T_hand_cam`` whose stations disagree on the board's pose (``gaps``: mm, degrees from their mean)
    by more than :data:`MAX_SPREAD`, or that puts the camera further than :data:`MAX_HAND_CAM_M` from the hand."""
    worst, at = gaps.max(axis=0), [seen[int(k)] for k in gaps.argmax(axis=0)]
    reach = float(np.linalg.norm(T_hand_cam[:3, 3]))
    found = []
    if worst[0] > MAX_SPREAD[0] or worst[1] > MAX_SPREAD[1]:
        found.append(
            f"the stations put the board in the arm's base up to {worst[0]:.2f} mm ({at[0]}) and {worst[1]:.2f} deg "
            f"({at[1]}) from their mean (a sound set: within {MAX_SPREAD[0]:g} mm, {MAX_SPREAD[1]:g} deg)"
        )
    if reach > MAX_HAND_CAM_M:
        found.append(
            f"T_hand_cam puts the camera {reach:.2f} m from the hand (a wrist camera: within {MAX_HAND_CAM_M:g} m)"
        )
    if found:
        raise ConfigError(
            "stations",
            f"{'; '.join(found)}; nothing written: are the poses T_base_hand (the hand in the arm's base, not "
            "T_hand_base), in metres, each with its own station's image?",
            poses_file,
        )
