"""The presses of ``tacsplat calibrate hand-eye`` and ``calibrate mounts`` on a twin: the plan (which fingertip,
bent how, pressed where) and its execution by :class:`~tacsplat.sim.person.TwinPresser`, each press recorded as a
real rig records it: the joints as read, the contact points from the depth map, and the wrist camera's pose by
PnP on the ChArUco board it sees (rendered at the camera's true pose, :func:`~tacsplat.acquisition.mock.render_board`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from tacsplat.acquisition.config import BoardConfig
from tacsplat.drivers.press_calibration import MIN_CONTACT_POINTS, Press
from tacsplat.errors import CameraError
from tacsplat.geometry import invert_pose, make_pose, tactile_depth_to_points
from tacsplat.sim.hand import FINGER_NAMES

INDENTATION_M = 0.0006  # how far a press sinks the gel
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

    def describe(self) -> str:
        where = "the board" if self.surface == "board" else f"the sphere (placement {self.placement + 1})"
        return f"{self.finger} on {where}"


def _pose_q(finger: str, abduction: float, flexion: tuple, others: tuple = (0.0, 0.0, 0.0)) -> tuple:
    """Joints [16]: ``finger`` at ``abduction`` and ``flexion``, the other fingers at ``others`` (flexions)."""
    q = np.zeros(16)
    for j in range(len(FINGER_NAMES)):
        q[4 * j + 1 : 4 * j + 4] = others
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
    out = []
    for elevation in np.radians([0.0, 30.0, 60.0, 80.0]):
        for azimuth in np.radians(np.arange(0.0, 360.0, 45.0)):
            out.append(
                np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
            )
    return out


class TwinPressSession:
    """Makes a plan's presses on a twin and records each as a :class:`Press`."""

    def __init__(self, twin, board: BoardConfig, say: Callable[[str], None] = print):
        from tacsplat.sim.camera import intrinsics_from_fovy
        from tacsplat.sim.person import TwinPresser

        self.board = board
        self.spec = board.spec()
        self.size = (self.spec.squares_x * self.spec.square_length_m, self.spec.squares_y * self.spec.square_length_m)
        self.presser = TwinPresser(twin, self.size, SPHERE_RADIUS_M, SPHERE_PLACEMENTS)
        self.K = intrinsics_from_fovy(twin.config.wrist_fovy_deg, *CAMERA_PX).K
        self.K_opencv = self.K.copy()
        self.K_opencv[:2, 2] -= 0.5
        self.say = say
        self.twin = twin

    def _board_seen(self, T_board_cam: np.ndarray):
        """The board's PnP pose of the camera at ``T_board_cam`` (its image rendered there), or None."""
        from tacsplat.acquisition.mock import render_board
        from tacsplat.drivers.wrist_camera import T_WORLD_BOARD, board_pose

        if T_board_cam[2, 3] <= 0.02:  # the camera under, or on, the board
            return None
        image = render_board(self.spec, self.K, *CAMERA_PX, invert_pose(T_board_cam) @ T_WORLD_BOARD)
        try:
            pose = board_pose(image, self.spec, self.K_opencv, None, self.board.min_corners)
        except CameraError:
            return None
        return pose if pose.rms_px <= self.board.max_reprojection_px else None

    def _candidates(self, spec: PressSpec) -> list[np.ndarray]:
        """Pad poses for ``spec`` that keep the hand and the whole pad above the board with the camera looking down
        at it, best first (the board's centre nearest the image's)."""
        q = np.array(spec.q)
        T_hand_pad = self.presser.T_hand_pad(spec.finger, q)
        T_hand_cam = self._true_T_hand_cam()
        hand_points = np.array([T[:3, 3] for T in self.presser.T_hand_pads(q).values()] + [[0.0, 0.0, 0.0]])
        t = self.twin.config.tactile
        half = np.array([t.width_px, t.height_px]) * t.pixel_size_m / 2
        pad_corners = np.array([[sx * half[0], sy * half[1], 0.0] for sx in (-1, 1) for sy in (-1, 1)])
        sq = self.spec.square_length_m
        gx, gy = np.meshgrid(np.arange(1, self.spec.squares_x) * sq, -np.arange(1, self.spec.squares_y) * sq)
        corners = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size), np.ones(gx.size)])  # [4, N] board frame
        scored = []
        for direction in _directions():
            for yaw in YAWS_DEG:
                T_board_pad = _pad_target(spec, direction, yaw)
                T_board_hand = T_board_pad @ invert_pose(T_hand_pad)
                T_board_cam = T_board_hand @ T_hand_cam
                above = (T_board_hand[:3, :3] @ hand_points.T + T_board_hand[:3, 3:4])[2]
                gel = (T_board_pad[:3, :3] @ pad_corners.T + T_board_pad[:3, 3:4])[
                    2
                ]  # an off-centre press: the pad clear of the board (not yet checked for hand-eye's centred presses)
                if T_board_cam[2, 3] < 0.04 or above.min() < 0.003 or (any(spec.spot) and gel.min() < 0.002):
                    continue
                c = invert_pose(T_board_cam) @ corners
                u = (self.K[:2, :2] @ (c[:2] / np.maximum(c[2], 1e-9)) + self.K[:2, 2:3]).T
                seen = int(np.sum((c[2] > 0.02) & np.all((u > 10) & (u < np.array(CAMERA_PX) - 10), axis=1)))
                if seen >= self.board.min_corners:
                    scored.append((-seen, T_board_pad))
        return [T for _, T in sorted(scored, key=lambda s: s[0])]

    def _true_T_hand_cam(self) -> np.ndarray:
        return invert_pose(self.twin.T_world_hand()) @ self.twin.wrist_camera.pose()  # the person sees the view

    def run(self, plan: list[PressSpec]) -> list[Press]:
        """The presses, a status line each; a press whose camera cannot see the board at any yaw is skipped."""
        presses = []
        for i, spec in enumerate(plan):
            best = None
            for T_board_pad in self._candidates(spec)[:3]:
                depth, T_board_cam = self.presser.press(spec.finger, np.array(spec.q), T_board_pad)
                pose = self._board_seen(T_board_cam)
                if pose is not None:
                    best = (depth, pose, self.twin.hand.fingertip_poses()[spec.finger])
                    break
            head = f"press {i + 1}/{len(plan)}: {spec.describe()}"
            if best is None:
                self.say(f"{head}: the wrist camera does not see the board; skipped")
                continue
            depth, pose, T_hand_fingertip = best
            points = tactile_depth_to_points(depth, self.twin.config.tactile.pixel_size_m, np.eye(4))
            presses.append(Press(spec.finger, T_hand_fingertip, points, pose.T_world_cam, spec.surface, spec.placement))
            ok = "ok" if len(points) >= MIN_CONTACT_POINTS else "too little contact"
            self.say(f"{head}: {len(points)} contact pixels, board {pose.corners} corners {pose.rms_px:.2f} px; {ok}")
        return presses
