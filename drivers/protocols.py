"""The device interface (DESIGN.md): real drivers and the MuJoCo twin both implement these.

``tacsplat.acquisition`` only ever sees these Protocols.
"""

from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable

import numpy as np

from tacsplat.types import TactileReading


class _HandModel(Protocol):
    """What a hand and its model share: the joints, their limits and the hand's solid shape."""

    @property
    def joint_names(self) -> Sequence[str]: ...

    @property
    def joint_limits(self) -> np.ndarray:
        """[n_joints, 2] lower and upper limits in radians."""

    @property
    def link_names(self) -> Sequence[str]:
        """The boxes of :meth:`link_boxes`."""

    def link_boxes(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The hand's solid shape at joint positions ``q`` [n_joints]: ``(T_hand_box [L, 4, 4], half_extents
        [L, 3])``."""


@runtime_checkable
class Hand(_HandModel, Protocol):
    """A multi-finger hand; a context manager that always leaves the hardware safe (torque off)."""

    def read_joint_positions(self) -> np.ndarray:
        """[n_joints] radians."""

    @property
    def effort_unit(self) -> str:
        """The unit of :meth:`read_joint_state`'s efforts: ``"A"`` (servo current), ``"N m"`` (joint torque)."""

    def read_joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        """``(positions [n_joints] radians, efforts [n_joints] in effort_unit)`` from one read."""

    def command_joint_positions(self, q: np.ndarray) -> None:
        """Command [n_joints] radians (clamped to the joint limits, clamping logged)."""

    def fingertip_poses(self) -> dict[str, np.ndarray]:
        """Tactile sensor frames in the hand frame, ``{finger: T_hand_sensor}``, from forward kinematics."""

    def close(self) -> None: ...

    def __enter__(self) -> "Hand": ...

    def __exit__(self, *exc) -> None: ...


@runtime_checkable
class HandKinematics(_HandModel, Protocol):
    """Forward kinematics of a hand model (the twin's MJCF, :class:`tacsplat.sim.hand.HandKinematics`),
    given to the real hand driver when the rig is assembled: drivers never import the simulator."""

    def fingertip_poses(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """``{finger: T_hand_sensor [4, 4]}`` at joint positions ``q`` [n_joints]."""


@runtime_checkable
class TactileSensor(Protocol):
    @property
    def name(self) -> str: ...

    def read(self) -> TactileReading:
        """A reading whose pose is in the hand frame (``frame == "hand"``)."""


@runtime_checkable
class Camera(Protocol):
    @property
    def K(self) -> np.ndarray:
        """[3, 3] OpenCV intrinsics of the undistorted images."""

    @property
    def width(self) -> int: ...

    @property
    def height(self) -> int: ...

    def read(self) -> tuple[np.ndarray, float]:
        """``(image [H, W, 3] uint8 RGB undistorted, timestamp seconds)``."""
