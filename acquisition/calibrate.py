"""Calibration commands that run on a rig file: ``tacsplat calibrate hand`` (the hand's joint signs, zeros and
ranges, :mod:`tacsplat.drivers.joint_calibration`).

The same command runs on the real rig (a person at the terminal moves the joints), on ``--mock`` (the servo
emulator, whose hand moves them) and on a ``rig: sim`` file (the twin pushes them); in the last two the hardware
hides the rig file's ``sim.true_errors``, which the calibration must find.
"""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Callable, Iterator, TextIO

from tacsplat.acquisition.config import RigConfig
from tacsplat.drivers.calibration import HandCalibration
from tacsplat.drivers.joint_calibration import JointResult, calibrate_joints


@contextmanager
def limp_hand(
    config: RigConfig, stdin: TextIO | None = None, say: Callable[[str], None] = print
) -> Iterator[tuple[object, object, list[str], str]]:
    """``(hand, person, servo names, device)`` of the rig with the hand's torque off; leaving it closes the hand,
    confirming torque off servo by servo (said through ``say``), however the block ends (an ending signal
    included)."""
    if config.rig == "sim":
        from tacsplat.acquisition.devices import twin_config
        from tacsplat.sim.person import TwinPerson
        from tacsplat.sim.twin import SimTwin

        settings = dataclasses.replace(twin_config(config), hand_calibration=None)  # raw servos: no calibration yet
        with SimTwin(settings) as twin:
            twin.hand.set_torque(False)
            yield twin.hand, TwinPerson(twin), [f"joint {k}" for k in range(16)], "the twin's hand"
        return
    from tacsplat.drivers.dynamixel_hand import MAX_BUS_WATCHDOG_S, DynamixelHand, DynamixelHandConfig
    from tacsplat.drivers.joint_calibration import TerminalPerson
    from tacsplat.sim.hand import HandKinematics

    mock = None
    if config.mock:
        from tacsplat.acquisition.mock import EmulatorPerson, MockDevices

        mock = MockDevices(config)
        port = mock.servo_port
        settings = DynamixelHandConfig(
            min_packet_timeout_s=config.mock_devices.servo_timeout_s, bus_watchdog_s=MAX_BUS_WATCHDOG_S
        )
    else:
        port, settings = config.hand.port, None
    hand = DynamixelHand(
        port, config.hand.baudrate, config.hand.ids, None, config=settings, kinematics=HandKinematics()
    )
    servos = [f"servo {sid}" for sid in config.hand.ids]
    with mock if mock is not None else nullcontext():
        person = EmulatorPerson(mock) if mock is not None else TerminalPerson(stdin)
        try:
            hand.connect(torque=False)
            yield hand, person, servos, hand.device
        finally:
            hand.close()
            if hand.torque_off_report is not None:
                say(f"{hand.device}: {hand.torque_off_report}")


def calibrate_hand(
    config: RigConfig, out: Path, say: Callable[[str], None] = print, stdin: TextIO | None = None
) -> tuple[HandCalibration, list[JointResult]]:
    """Calibrate the rig's hand (torque off, each joint against both stops) and write ``out``; the hand is left with
    torque off."""
    with limp_hand(config, stdin, say) as (hand, person, servos, device):
        say(f"{device}: torque off; each joint in turn goes against its upper, then its lower stop")
        calibration, results = calibrate_joints(hand, person, servos, say, device)
    calibration.save(out)
    say(f"wrote {out} ({len(results)} joints)")
    return calibration, results
