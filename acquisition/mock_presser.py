"""The person of ``tacsplat calibrate hand-eye --mock`` and ``calibrate mounts --mock``: :class:`EmulatorPresser`
makes each press of :class:`~tacsplat.acquisition.presses.RigPressSession` on the emulated devices of
:class:`~tacsplat.acquisition.mock.MockDevices`."""

from __future__ import annotations

import numpy as np

from tacsplat.acquisition.mock import MockDevices, render_board, servo_angles, sphere_press
from tacsplat.acquisition.presses import INDENTATION_M, SPHERE_RADIUS_M, board_seen, pad_poses
from tacsplat.drivers.wrist_camera import T_WORLD_BOARD
from tacsplat.geometry import invert_pose
from tacsplat.sim.hand import HandKinematics, nominal_T_hand_cam
from tacsplat.sim.tactile import render_tactile_rgb


class EmulatorPresser:
    """The person of ``tacsplat calibrate hand-eye --mock`` and ``calibrate mounts --mock``: puts each press's pad on
    the sphere as planned, at its true pose (the hand's joints where the emulated servos stand, through the rig
    file's ``sim.true_errors``: the servos', the wrist camera's and each mount's), and shows the press to the
    emulated devices: the sphere in the gel to the finger's tactile sensor, the board at the camera's true pose to
    the wrist camera. Lifting shows the untouched gel."""

    # the emulated press is shown at once, so this bounds only a stuck pipeline: on a loaded host the sensor's
    # frames (video decode, optical model, integration) can lag by seconds, and 2 s failed there
    timeout_s = 30.0
    # what the emulator must be in this process for: calibrate's _presses refuses a servo_port with it before any
    # device opens, so the MockDevices this class is given always holds its emulator
    needs = "reads where its servos stand"

    def __init__(self, mock: MockDevices):
        self.mock, self.config = mock, mock.config
        self.kinematics = HandKinematics()
        e = self.config.sim.true_errors
        self.T_hand_cam = nominal_T_hand_cam() @ e.hand_eye.matrix()
        self.mount_errors = {finger: error.matrix() for finger, error in e.mounts.items()}
        m = self.config.mock_devices
        self.tactile_shape = (m.tactile_height, m.tactile_width)
        self.reference = render_tactile_rgb(np.zeros(self.tactile_shape, np.float32), m.tactile_pixel_size_m)

    def _true_joints(self) -> np.ndarray:
        """[16] the true joint angles where the emulated servos stand."""
        return servo_angles(self.config, [self.mock.emulator.position(sid) for sid in self.config.hand.ids])

    def press(self, spec) -> str | None:
        """Make the press (None), or say why not: no pose of the hand lets the camera see the board well enough (the
        number of corners it finds, as a real rig's skip line gives it)."""
        m, pix = self.config.mock_devices, self.config.mock_devices.tactile_pixel_size_m
        pads = {
            finger: T @ self.mount_errors.get(finger, np.eye(4))
            for finger, T in self.kinematics.fingertip_poses(self._true_joints()).items()
        }
        half = np.array([m.tactile_width, m.tactile_height]) * pix / 2
        size = (m.camera_width, m.camera_height)
        board = self.config.board
        poses, most = pad_poses(spec, pads, self.T_hand_cam, half, board, self.mock.K, size)
        found = []  # the corners the camera finds at each pose tried
        for T_board_pad in poses[:3]:  # as a person does: the hand turned until the camera sees the board
            T_board_cam = T_board_pad @ invert_pose(pads[spec.finger]) @ self.T_hand_cam
            pose, corners = board_seen(board, self.mock.K, size, T_board_cam)
            if pose is not None:
                break
            found.append(corners)
        else:
            corners = max(found, default=most)  # no pose tried: the most any pose shows
            near = "at every pose of the hand near the sphere the wrist camera"
            if corners < board.min_corners:
                return (
                    f"{near} finds at most {corners} of the board's corners, fewer than {board.min_corners} "
                    "(board.min_corners)"
                )
            return (
                f"{near} finds the board's corners, with a reprojection error over {board.max_reprojection_px:g} px "
                "(board.max_reprojection_px)"
            )
        image = render_board(board.spec(), self.mock.K, *size, invert_pose(T_board_cam) @ T_WORLD_BOARD)
        self.mock.captures["camera"].show(image)
        depth = sphere_press(self.tactile_shape, pix, spec.spot, SPHERE_RADIUS_M, INDENTATION_M)
        self.mock.captures[spec.finger].show(render_tactile_rgb(depth, pix))
        return None

    def release(self, spec) -> None:
        self.mock.captures[spec.finger].show(self.reference)
