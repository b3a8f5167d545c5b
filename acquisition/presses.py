"""The presses of ``tacsplat calibrate hand-eye`` and ``calibrate mounts``: the plan (which fingertip, bent how,
pressed where), and its execution, each press recorded the same way: the joints as read, the contact points from the
depth map, and the wrist camera's pose by PnP on the ChArUco board it sees.

* on a twin, :class:`TwinPressSession`: :class:`~tacsplat.sim.person.TwinPresser` places the hand, the board is
  rendered at the camera's true pose (:func:`~tacsplat.acquisition.mock.render_board`);
* on a real rig or ``--mock``, :class:`RigPressSession`: the hand holds each press's joints and a person
  (:class:`TerminalPresser`; on ``--mock``, :class:`~tacsplat.acquisition.mock_presser.EmulatorPresser`) makes the press,
  read through the rig's drivers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from tacsplat.acquisition.config import BoardConfig
from tacsplat.acquisition.logger import BoardPoseSource, CaptureRejected
from tacsplat.drivers.press_calibration import MIN_CONTACT_POINTS, Press
from tacsplat.errors import CameraError, ConfigError, HandError, TactileError
from tacsplat.geometry import invert_pose, make_pose, tactile_depth_to_points
from tacsplat.sim.hand import FINGER_NAMES

INDENTATION_M = 0.0006  # how far a press sinks the gel
CONTACT_DEPTH_M = 1e-5  # a pixel indented this much is in contact
CAMERA_PX = (640, 480)  # the twin's wrist camera as the calibration sees the board
SPHERE_RADIUS_M = 0.0125  # a 25 mm ball bearing
YAWS_DEG = (0.0, 90.0, 180.0, 270.0)  # the hand turned about the pad's normal until the camera sees the board


@dataclass(frozen=True)
class PressSpec:
    """One press to make: ``finger`` with the joints at ``q`` [16], on the sphere at ``placement``, with the pad's
    ``spot`` (x, y in the sensor frame, metres) on it."""

    finger: str
    q: tuple
    surface: str = "sphere"
    spot: tuple = (0.0, 0.0)
    placement: int = 0

    def where(self) -> str:
        return "the board" if self.surface == "board" else f"the sphere (placement {self.placement + 1})"

    def describe(self) -> str:
        return f"{self.finger} on {self.where()}"


def _pose_q(finger: str, abduction: float, flexion: tuple, others: tuple = (0.0, 0.0, 0.0)) -> tuple:
    """Joints [16]: ``finger`` at ``abduction`` and ``flexion``, the other fingers at ``others`` (flexions)."""
    q = np.tile([0.0, *others], len(FINGER_NAMES))  # each finger: abduction 0, then its flexions
    k = FINGER_NAMES.index(finger)
    q[4 * k : 4 * k + 4] = [abduction, *flexion]
    return tuple(q.tolist())


FLEXIONS = ((0.5, 0.4, 0.3), (0.9, 0.6, 0.4))
ABDUCTIONS = (-0.3, 0.3)
CURLED = (1.2, 1.2, 1.0)  # the fingers not pressing, out of the way
SPOTS_M = ((0.008, 0.0), (-0.008, 0.0), (0.0, 0.006), (0.0, -0.006), (0.006, 0.005), (-0.006, -0.005))  # on the pad
STAND_HEIGHT_M = 0.06  # the sphere's centre over the board on its stand for calibrate mounts (measured)
SPHERE_PLACEMENTS = (
    (0.025, -0.025, SPHERE_RADIUS_M),  # resting near a corner of the board (hand-eye; unknown to the solver)
    (0.105, -0.075, STAND_HEIGHT_M),  # on a stand over the board's centre (mounts; its height known, its place not)
)


def hand_eye_plan(fingers=FINGER_NAMES) -> list[PressSpec]:
    """Every fingertip on the sphere, a little and more bent, spread either way: the hand around the sphere in
    many poses."""
    return [PressSpec(f, _pose_q(f, a, flex), "sphere") for f in fingers for flex in FLEXIONS for a in ABDUCTIONS]


def mounts_plan(fingers=FINGER_NAMES) -> list[PressSpec]:
    """Every fingertip on the sphere on its stand with six places of its pad (its two ends, two sides, two corners),
    each at two bends and two spreads, the other fingers curled out of the way: the patches' lever arm fixes each
    sensor's rotations, the fingertip's poses separate its offset from the sphere's place."""
    return [
        PressSpec(f, _pose_q(f, a, flex, CURLED), "sphere", spot, placement=1)
        for f in fingers
        for spot in SPOTS_M
        for flex in FLEXIONS
        for a in ABDUCTIONS
    ]


def _pad_target(spec: PressSpec, direction: np.ndarray, yaw_deg: float) -> np.ndarray:
    """``T_board_pad``: the pad's ``spot`` pressed on the sphere's point in ``direction`` (unit, from its centre),
    the gel facing it and turned by ``yaw_deg`` about its normal."""
    z = -direction
    x = np.cross([0.0, 0.0, 1.0], z) if abs(z[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z]) @ Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    centre = np.array(SPHERE_PLACEMENTS[spec.placement])
    origin = centre + (SPHERE_RADIUS_M - INDENTATION_M) * direction - R @ np.array([*spec.spot, 0.0])
    return make_pose(R, origin)


def _directions() -> list[np.ndarray]:
    """Where on the sphere a pad may press: around it, from the side to 80 degrees up."""
    return [
        np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        for elevation in np.radians([0.0, 30.0, 60.0, 80.0])
        for azimuth in np.radians(np.arange(0.0, 360.0, 45.0))
    ]


def board_seen(board: BoardConfig, K: np.ndarray, image_size: tuple[int, int], T_board_cam: np.ndarray):
    """``(pose, corners)``: the board's PnP pose from its image rendered for a camera (intrinsics ``K`` of
    ``image_size``) at ``T_board_cam``, None when the board is not seen well enough to capture (a person would move
    the hand), and how many of its corners the camera finds."""
    from tacsplat.acquisition.mock import render_board
    from tacsplat.drivers.wrist_camera import T_WORLD_BOARD, board_pose, opencv_K_from_tacsplat

    if T_board_cam[2, 3] <= 0.02:  # the camera under, or on, the board
        return None, 0
    spec = board.spec()
    image = render_board(spec, K, *image_size, invert_pose(T_board_cam) @ T_WORLD_BOARD)
    try:
        pose = board_pose(image, spec, opencv_K_from_tacsplat(K), None, board.min_corners)
    except CameraError:  # too few corners (or no PnP): counted for the press's line
        return None, len(spec.detect(image)[0])
    return (pose if pose.rms_px <= board.max_reprojection_px else None), pose.corners


def pad_poses(
    spec: PressSpec,
    T_hand_pads: dict[str, np.ndarray],
    T_hand_cam: np.ndarray,
    pad_half_m: np.ndarray,
    board: BoardConfig,
    K: np.ndarray,
    image_size: tuple[int, int],
) -> tuple[list[np.ndarray], int]:
    """Where a person puts the pad for ``spec``: poses ``T_board_pad`` that keep the hand (its pads ``T_hand_pads``
    at the press's joints, its base) and the whole pad above the board with the wrist camera (at ``T_hand_cam``,
    intrinsics ``K`` of ``image_size``) looking down at it, best first (most board corners in view); and the most
    board corners in view at any pose that keeps the hand and pad above the board (under ``board.min_corners``
    when there are no poses)."""
    T_hand_pad = T_hand_pads[spec.finger]
    hand_points = np.array([T[:3, 3] for T in T_hand_pads.values()] + [[0.0, 0.0, 0.0]])
    pad_corners = np.array([[sx * pad_half_m[0], sy * pad_half_m[1], 0.0] for sx in (-1, 1) for sy in (-1, 1)])
    grid = board.spec()
    sq = grid.square_length_m
    gx, gy = np.meshgrid(np.arange(1, grid.squares_x) * sq, -np.arange(1, grid.squares_y) * sq)
    corners = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size), np.ones(gx.size)])  # [4, N] board frame
    scored, most = [], 0
    for direction in _directions():
        for yaw in YAWS_DEG:
            T_board_pad = _pad_target(spec, direction, yaw)
            T_board_hand = T_board_pad @ invert_pose(T_hand_pad)
            T_board_cam = T_board_hand @ T_hand_cam
            above = (T_board_hand[:3, :3] @ hand_points.T + T_board_hand[:3, 3:4])[2]
            gel = (T_board_pad[:3, :3] @ pad_corners.T + T_board_pad[:3, 3:4])[2]  # an off-centre press: the pad
            # clear of the board (not checked for hand-eye's centred presses)
            if T_board_cam[2, 3] < 0.04 or above.min() < 0.003 or (any(spec.spot) and gel.min() < 0.002):
                continue
            c = invert_pose(T_board_cam) @ corners
            u = (K[:2, :2] @ (c[:2] / np.maximum(c[2], 1e-9)) + K[:2, 2:3]).T
            seen = int(np.sum((c[2] > 0.02) & np.all((u > 10) & (u < np.array(image_size) - 10), axis=1)))
            most = max(most, seen)
            if seen >= board.min_corners:
                scored.append((-seen, T_board_pad))
    return [T for _, T in sorted(scored, key=lambda s: s[0])], most


class TwinPressSession:
    """Makes a plan's presses on a twin and records each as a :class:`Press`."""

    def __init__(self, twin, board: BoardConfig, say: Callable[[str], None] = print):
        from tacsplat.sim.camera import intrinsics_from_fovy
        from tacsplat.sim.person import TwinPresser

        self.board, self.say, self.twin = board, say, twin
        spec = board.spec()
        size = (spec.squares_x * spec.square_length_m, spec.squares_y * spec.square_length_m)
        self.presser = TwinPresser(twin, size, SPHERE_RADIUS_M, SPHERE_PLACEMENTS)
        self.K = intrinsics_from_fovy(twin.config.wrist_fovy_deg, *CAMERA_PX).K

    def _candidates(self, spec: PressSpec) -> list[np.ndarray]:
        pads = self.presser.T_hand_pads(np.array(spec.q))
        T_hand_cam = invert_pose(self.twin.T_world_hand()) @ self.twin.wrist_camera.pose()  # the person sees it
        half = np.array(self.twin.config.tactile.pad_size_m) / 2
        return pad_poses(spec, pads, T_hand_cam, half, self.board, self.K, CAMERA_PX)[0]

    def run(self, plan: list[PressSpec]) -> list[Press]:
        """The presses, a status line each; a press whose camera cannot see the board at any yaw is skipped."""
        presses = []
        for i, spec in enumerate(plan):
            head = f"press {i + 1}/{len(plan)}: {spec.describe()}"
            for T_board_pad in self._candidates(spec)[:3]:
                depth, T_board_cam = self.presser.press(spec.finger, np.array(spec.q), T_board_pad)
                pose = board_seen(self.board, self.K, CAMERA_PX, T_board_cam)[0]
                if pose is not None:
                    break
            else:
                self.say(f"{head}: the wrist camera does not see the board; skipped")
                continue
            T_hand_fingertip = self.twin.hand.fingertip_poses()[spec.finger]
            points = tactile_depth_to_points(depth, self.twin.config.tactile.pixel_size_m, np.eye(4))
            presses.append(Press(spec.finger, T_hand_fingertip, points, pose.T_world_cam, spec.surface, spec.placement))
            ok = "ok" if len(points) >= MIN_CONTACT_POINTS else "too little contact"
            self.say(f"{head}: {len(points)} contact pixels, board {pose.corners} corners {pose.rms_px:.2f} px; {ok}")
        return presses


CONTACT_READINGS = 3  # consecutive readings in contact (or out of it) that make a press (or a lift)
HOLD_TOLERANCE_RAD = 0.02  # the joints are at a press's pose when every one is this close to it ...
STILL_RAD = 1e-3  # ... and moves less than this between readings, for CONTACT_READINGS readings
HOLD_TIMEOUT_S = 5.0


def describe_spot(spec: PressSpec) -> str:
    """The place of the pad a press uses, as a person reads it."""
    if not any(spec.spot):
        return "its pad's centre"
    x, y = (1000 * v for v in spec.spot)
    return f"its pad at x {x:+.0f} mm, y {y:+.0f} mm of the gel's centre"


class TerminalPresser:
    """The person at a real rig's terminal: told each press, makes it; the press is taken when the pad's contact is
    steady, so no key is needed."""

    timeout_s = 120.0  # to make a press, then to lift it off

    def __init__(self, say: Callable[[str], None] = print):
        self.say = say

    def press(self, spec: PressSpec) -> None:
        """Tell the press (the person will try it)."""
        self.say(
            f"  press the {spec.finger} fingertip with {describe_spot(spec)} on {spec.where()}, "
            "the wrist camera seeing the board; hold it still"
        )

    def release(self, spec: PressSpec) -> None:
        self.say(f"  lift the {spec.finger} fingertip off")


class RigPressSession:
    """Makes a plan's presses on a rig's devices (a real rig, or ``--mock``'s) with a person's help, recording each
    as :class:`TwinPressSession` does: the hand holds the press's joints (torque on), the person presses the pad as
    told (``person.press``), and once the pad's contact is steady the joints as read, the contact points from the
    depth map and the wrist camera's pose by PnP on the board (a frame taken after the contact became steady) make
    the press; then the person lifts the pad off."""

    def __init__(self, hand, camera, sensors: list, board: BoardConfig, person, say: Callable[[str], None] = print):
        self.hand, self.camera = hand, camera
        self.sensors = {s.name: s for s in sensors}
        self.poses = BoardPoseSource(camera, board, np.eye(4))
        self.person, self.say = person, say

    def _hold(self, q: np.ndarray) -> None:
        """Command the joints to ``q`` (within their limits) and wait until they are there and still, so that the
        press is made and read at one pose (HandError naming the joints if not)."""
        q = np.clip(q, self.hand.joint_limits[:, 0], self.hand.joint_limits[:, 1])
        self.hand.command_joint_positions(q)
        deadline, still, last = time.monotonic() + HOLD_TIMEOUT_S, 0, None
        while True:
            now = self.hand.read_joint_positions()
            off = np.abs(now - q)
            moved = np.inf if last is None else np.abs(now - last).max()
            still = still + 1 if np.all(off <= HOLD_TOLERANCE_RAD) and moved <= STILL_RAD else 0
            if still >= CONTACT_READINGS:
                return
            if time.monotonic() > deadline:
                names = [self.hand.joint_names[k] for k in np.flatnonzero(off > HOLD_TOLERANCE_RAD)] or ["all"]
                raise HandError(
                    getattr(self.hand, "device", "hand"),
                    f"joints {', '.join(names)} did not come to rest at a press's pose within {HOLD_TIMEOUT_S:g} s "
                    f"(off by up to {np.degrees(off.max()):.1f} deg): is the hand blocked?",
                )
            last = now
            time.sleep(0.01)

    def _contact(self, finger: str, touching: bool, after: float):
        """The reading once ``finger``'s pad has been in contact (``touching``) or out of it for
        :data:`CONTACT_READINGS` readings in a row of frames taken after ``after`` (``time.monotonic()`` seconds,
        the drivers' frame timestamps, which a wall-clock step does not move: not a frame from before the person was
        told); None after the person's ``timeout_s``."""
        deadline, run = time.monotonic() + self.person.timeout_s, 0
        while time.monotonic() < deadline:
            reading = self.sensors[finger].read()
            if reading.timestamp < after:
                continue
            contact = int(np.count_nonzero(reading.depth > CONTACT_DEPTH_M)) >= MIN_CONTACT_POINTS
            run = run + 1 if contact == touching else 0
            if run >= CONTACT_READINGS:
                return reading
        return None

    def _board(self, after: float):
        """The board's pose in a wrist camera frame taken at or after ``after`` (``time.monotonic()`` seconds), or the
        reason it is not seen."""
        deadline = time.monotonic() + self.person.timeout_s
        while True:
            image, stamp = self.camera.read()
            if stamp < after and time.monotonic() < deadline:
                continue
            try:
                return self.poses.camera_pose(image)
            except CaptureRejected as exc:
                return str(exc)

    def run(self, plan: list[PressSpec]) -> list[Press]:
        """The presses, a status line each; a press without contact, or whose camera does not see the board, is
        skipped."""
        if missing := sorted({spec.finger for spec in plan} - set(self.sensors)):
            raise ConfigError("tactile.sensors", f"the presses need a sensor on {', '.join(missing)}")
        presses = []
        for i, spec in enumerate(plan):
            head = f"press {i + 1}/{len(plan)}: {spec.describe()}"
            self._hold(np.array(spec.q))
            told = time.monotonic()
            if why := self.person.press(spec):  # --mock's person found no pose of the hand where the camera sees it
                self.say(f"{head}: {why}; skipped")
                continue
            reading = self._contact(spec.finger, True, told)
            pose = None if reading is None else self._board(reading.timestamp)
            T_hand_fingertip = self.hand.fingertip_poses()[spec.finger]
            told = time.monotonic()
            self.person.release(spec)
            if self._contact(spec.finger, False, told) is None:
                raise TactileError(spec.finger, f"still in contact {self.person.timeout_s:g} s after the press")
            if reading is None:
                self.say(f"{head}: no contact within {self.person.timeout_s:g} s; skipped")
                continue
            if isinstance(pose, str):
                self.say(f"{head}: {pose}; skipped")
                continue
            points = tactile_depth_to_points(reading.depth, reading.pixel_size_m, np.eye(4), CONTACT_DEPTH_M)
            presses.append(Press(spec.finger, T_hand_fingertip, points, pose.T, spec.surface, spec.placement))
            self.say(
                f"{head}: {len(points)} contact pixels, board {pose.corners} corners {pose.reprojection_px:.2f} px; ok"
            )
        return presses
