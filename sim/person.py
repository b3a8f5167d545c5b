"""The person's part of the calibration commands, played by the twin: the command runs to its end without keys.

A :class:`~tacsplat.drivers.joint_calibration.Person` for ``tacsplat calibrate hand`` on a ``rig: sim`` file:
with the hand's torque off, it pushes a joint towards a stop with a torque (the twin's physics moves the
finger), then eases off to a light press that holds it against the stop while the servos are read, as a person's
finger does.
"""

from __future__ import annotations

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
