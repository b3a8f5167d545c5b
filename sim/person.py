"""The person's part of the calibration commands, played by the twin: the command runs to its end without keys.

:class:`TwinPresser` presses fingertips on the calibration board or a sphere for ``tacsplat calibrate hand-eye``
and ``calibrate mounts``.

A :class:`~tacsplat.drivers.joint_calibration.Person` for ``tacsplat calibrate hand`` on a ``rig: sim`` file:
with the hand's torque off, it pushes a joint towards a stop with a torque (the twin's physics moves the
finger), then eases off to a light press that holds it against the stop while the servos are read, as a person's
finger does.
"""

from __future__ import annotations

import numpy as np

from tacsplat.geometry import invert_pose
from tacsplat.sim.twin import SimTwin

PUSH_NM = 0.1  # moves a free finger joint at about 2 rad/s against the joint damping
HOLD_NM = 0.01  # presses it against the stop: the stop gives about 0.2 mrad, the same at both ends
PUSH_S = 1.0  # long enough to cross the widest joint range (1.9 rad)
HOLD_S = 0.3


class TwinPerson:
    """Moves the twin's joints by hand (its torque must be off: :meth:`~tacsplat.sim.twin.SimHand.set_torque`)."""

    def __init__(self, twin: SimTwin):
        self.twin = twin

    def _push(self, joint: int, torque_nm: float) -> None:
        self.twin.data.qfrc_applied[self.twin.hand.dof_of(joint)] = torque_nm

    def hold_at_stop(self, joint: int, upper: bool, instruction: str) -> None:
        direction = 1.0 if upper else -1.0
        self._push(joint, direction * PUSH_NM)
        self.twin.sleep(PUSH_S)
        self._push(joint, direction * HOLD_NM)
        self.twin.sleep(HOLD_S)

    def let_go(self, joint: int) -> None:
        self._push(joint, 0.0)


BOARD_THICKNESS_M = 0.01
BOARD_IN_TWIN = np.array([[1.0, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, -0.5], [0, 0, 0, 1]])  # well clear of the object


class TwinPresser:
    """Presses the twin's fingertips on a calibration board lying face up (its printed face the plane ``z = 0`` of
    the board's frame, the world of a real rig), or on a sphere resting on it, as a person holding the hand does:
    the joints are set (torque on, the hand holds them) and the hand is placed so that the pad, at its true pose
    (the hidden mounting error included), sinks ``indentation_m`` into the surface. Depth is rendered against the
    board and sphere only; the board lies at :data:`BOARD_IN_TWIN`, far from the object."""

    def __init__(self, twin: SimTwin, board_size_m: tuple[float, float], sphere_radius_m: float, sphere_centres: tuple):
        import trimesh

        from tacsplat.sim.tactile import TactileDepthRenderer

        self.twin = twin
        w, h = board_size_m
        board = trimesh.creation.box((w, h, BOARD_THICKNESS_M))
        board.apply_translation((w / 2, -h / 2, -BOARD_THICKNESS_M / 2))  # the printed face at z = 0
        balls = [
            trimesh.creation.icosphere(subdivisions=5, radius=sphere_radius_m).apply_translation(c)
            for c in sphere_centres
        ]
        self.surfaces = trimesh.util.concatenate([board, *balls])
        self.renderer = TactileDepthRenderer(self.surfaces, twin.config.tactile)
        self.pads = {pad.name: pad for pad in twin.tactile_sensors}

    def T_hand_pads(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """Every pad's true pose [4, 4] on the hand with the joints set to ``q`` (as the rig commands them)."""
        self.twin.hand.set_joint_positions(q)
        T_hand_world = invert_pose(self.twin.T_world_hand())
        return {name: T_hand_world @ pad.T_world_sensor() for name, pad in self.pads.items()}

    def press(self, finger: str, q: np.ndarray, T_board_pad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Press: the pad at ``T_board_pad`` [4, 4] (board frame), joints at ``q``; returns ``(depth [h, w],
        T_board_cam)``: the pad's indentation map and the wrist camera's true pose on the board."""
        T_hand_pad = self.T_hand_pads(q)[finger]
        self.twin.set_hand_base_pose(BOARD_IN_TWIN @ T_board_pad @ invert_pose(T_hand_pad))
        T_board = invert_pose(BOARD_IN_TWIN)
        depth = self.renderer.render(T_board @ self.pads[finger].T_world_sensor())
        return depth, T_board @ self.twin.wrist_camera.pose()
