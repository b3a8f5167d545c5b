"""Calibration commands that run on a rig file: ``tacsplat calibrate hand`` (the hand's joint signs, zeros and
ranges, :mod:`tacsplat.drivers.joint_calibration`), ``calibrate hand-eye`` (the wrist camera's pose on the hand
from fingertip presses, :mod:`tacsplat.drivers.press_calibration`; on the twin so far).

The same command runs on the real rig (a person at the terminal moves the joints), on ``--mock`` (the servo
emulator, whose hand moves them) and on a ``rig: sim`` file (the twin pushes them); in the last two the hardware
hides the rig file's ``sim.true_errors``, which the calibration must find.
"""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Callable, Iterator, TextIO

import numpy as np

from tacsplat.acquisition.config import RigConfig
from tacsplat.drivers.calibration import HandCalibration
from tacsplat.drivers.joint_calibration import JointResult, calibrate_joints
from tacsplat.errors import ConfigError, InvalidInputError


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


def _twin_presses(
    config: RigConfig,
    plan: list,
    say: Callable[[str], None],
    what: str = "calibrate hand-eye",
    where: str = "resting on the board",
):
    """``(presses, the rig's T_hand_cam, the rig's mounts)`` of a plan's presses on the twin of a ``rig: sim``
    config (the twin plays the person: it presses the fingertips on a sphere resting on the board)."""
    if config.rig != "sim":
        raise ConfigError(
            "rig",
            f"{what} runs on a rig: sim twin only so far (the real rig's and --mock's "
            "guided presses are not written yet)",
            config.source,
        )
    from tacsplat.acquisition.devices import twin_config
    from tacsplat.acquisition.presses import SPHERE_RADIUS_M, TwinPressSession
    from tacsplat.sim.twin import SimTwin

    say(f"the twin presses its fingertips on a {2000 * SPHERE_RADIUS_M:.0f} mm sphere {where}")
    with SimTwin(twin_config(config)) as twin:
        presses = TwinPressSession(twin, config.board, say).run(plan)
        mounts = {pad.name: pad.T_fingertip_sensor for pad in twin.tactile_sensors}
        return presses, twin.T_hand_cam, mounts


def _change(T_from: np.ndarray, T_to: np.ndarray) -> str:
    from scipy.spatial.transform import Rotation

    D = np.linalg.inv(T_from) @ T_to
    return (
        f"{1000 * np.linalg.norm(D[:3, 3]):.2f} mm, {np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()):.2f} deg"
    )


def calibrate_hand_eye(config: RigConfig, out: Path, say: Callable[[str], None] = print):
    """``T_hand_cam`` from fingertip presses on a sphere resting on the board (the sensors at the rig's mounts),
    written to ``out``; the press set is refused when it leaves an axis undetermined."""
    from tacsplat.acquisition.presses import SPHERE_RADIUS_M, hand_eye_plan
    from tacsplat.drivers.press_calibration import fit_presses, save_hand_eye

    presses, T_hand_cam, mounts = _twin_presses(config, hand_eye_plan(), say)
    fit = fit_presses(presses, SPHERE_RADIUS_M, T_hand_cam, mounts, what="hand-eye")
    save_hand_eye(fit, out)
    say(
        f"T_hand_cam: {len(presses)} presses, rms {fit.rms_mm:.3f} mm; {_change(T_hand_cam, fit.T_hand_cam)} from the "
        "rig's previous value"
    )
    say(f"wrote {out} (name it as camera.hand_eye in the rig file)")
    return fit


def calibrate_mounts(config: RigConfig, out: Path, say: Callable[[str], None] = print):
    """Each sensor's ``T_fingertip_sensor`` from presses of four places of its pad on a sphere on a stand of known
    height over the board (two bends, two spreads each), solved per sensor with the sphere's place, ``T_hand_cam`` the rig's (run calibrate hand-eye
    first); a residual line per sensor; written to ``out``. A sensor whose presses leave an axis undetermined is
    refused, naming the presses to add."""
    from tacsplat.acquisition.presses import SPHERE_RADIUS_M, STAND_HEIGHT_M, mounts_plan
    from tacsplat.drivers.press_calibration import fit_mount, save_mounts

    presses, T_hand_cam, mounts = _twin_presses(
        config,
        mounts_plan(),
        say,
        "calibrate mounts",
        f"on a stand, its centre {1000 * STAND_HEIGHT_M:.0f} mm over the board",
    )
    fits = {}
    for finger in dict.fromkeys(p.finger for p in presses):
        start = mounts.get(finger, np.eye(4))
        mine = [p for p in presses if p.finger == finger]
        fit = fit_mount(mine, SPHERE_RADIUS_M, T_hand_cam, start, STAND_HEIGHT_M, f"calibrate mounts: {finger}")
        fits[finger] = fit
        say(
            f"{finger}: {fit.presses} presses ({fit.dropped} dropped), rms {fit.rms_mm:.3f} mm; {_change(start, fit.T_fingertip_sensor)} from "
            "the rig's previous mounting"
        )
    if not fits:
        raise InvalidInputError("calibrate mounts: no presses recorded (the wrist camera never saw the board)")
    save_mounts(fits, out)
    say(f"wrote {out} ({len(fits)} sensors; name it as tactile.mounts in the rig file)")
    return fits
