"""Calibration commands that run on a rig file: ``tacsplat calibrate hand`` (the hand's joint signs, zeros and
ranges, :mod:`tacsplat.drivers.joint_calibration`), ``calibrate hand-eye`` and ``calibrate mounts`` (the wrist
camera's pose on the hand and each sensor's on its fingertip from fingertip presses on a sphere,
:mod:`tacsplat.drivers.press_calibration`).

The same command runs on the real rig (a person at the terminal moves the joints or makes the presses), on
``--mock`` (the emulated devices' person does) and on a ``rig: sim`` file (the twin does); in the last two the
hardware hides the rig file's ``sim.true_errors``, which the calibration must find.
"""

from __future__ import annotations

import dataclasses
import os
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Callable, Iterator, TextIO

import numpy as np

from tacsplat.acquisition.arm_hand_eye import pose_change, pose_gap
from tacsplat.acquisition.config import RigConfig
from tacsplat.acquisition.devices import import_device_modules, inline_mounts, inline_T_hand_cam
from tacsplat.drivers.calibration import HandCalibration
from tacsplat.drivers.joint_calibration import JointResult, calibrate_joints


@contextmanager
def limp_hand(
    config: RigConfig, stdin: TextIO | None = None, say: Callable[[str], None] = print
) -> Iterator[tuple[object, object, list[str], str]]:
    """``(hand, person, servo names, device)`` of the rig with the hand's torque off; leaving it closes the hand,
    confirming torque off servo by servo (said through ``say``), however the block ends (an ending signal
    included)."""
    import_device_modules(config)
    if config.rig == "sim":
        from tacsplat.acquisition.devices import twin_config
        from tacsplat.sim.person import TwinPerson
        from tacsplat.sim.twin import SimTwin

        # raw servos: no calibration yet; the rig's hand-eye and mounts files may not be written yet either
        settings = dataclasses.replace(twin_config(config, calibrating=True), hand_calibration=None)
        with SimTwin(settings) as twin:
            twin.hand.set_torque(False)
            yield twin.hand, TwinPerson(twin), [f"joint {k}" for k in range(16)], "the twin's hand"
        return
    from tacsplat.acquisition.devices import dynamixel_hand
    from tacsplat.drivers.joint_calibration import TerminalPerson

    mock = None
    if config.mock:
        from tacsplat.acquisition.mock import EmulatorPerson, MockDevices

        mock = MockDevices(config)
    hand = dynamixel_hand(config, mock)
    servos = [f"servo {sid}" for sid in config.hand.ids]
    with mock if mock is not None else nullcontext():
        person = EmulatorPerson(mock) if mock is not None else TerminalPerson(stdin)
        try:
            hand.connect(torque=False)
            yield hand, person, servos, hand.device
        finally:
            hand.close()
            _torque_off(hand, say)


def calibrate_hand(
    config: RigConfig, out: Path, say: Callable[[str], None] = print, stdin: TextIO | None = None
) -> tuple[HandCalibration, list[JointResult]]:
    """Calibrate the rig's hand (torque off, each joint against both stops) and write ``out``; the hand is left with
    torque off."""
    with limp_hand(config, stdin, say) as (hand, person, servos, device):
        say(f"{device}: torque off; each joint in turn goes against its upper, then its lower stop")
        calibration, results = calibrate_joints(hand, person, servos, say, device)
    calibration.save(out)
    say(f"wrote {out} ({len(results)} joints; {_naming(config, out, config.hand.calibration, 'hand.calibration')})")
    return calibration, results


def _presses(
    config: RigConfig, plan: Callable[..., list], say: Callable[[str], None], where: str = "resting on the board"
):
    """``(presses, the rig's T_hand_cam, the rig's mounts)`` of the presses of ``plan(fingers)`` for the rig's
    sensors: on a ``rig: sim`` twin the twin presses its fingertips on a sphere ``where``; on a real rig a person
    does, guided line by line (on ``--mock``, :class:`~tacsplat.acquisition.mock_presser.EmulatorPresser`). A
    hand-eye or mounts file the rig names that is not written yet counts as none (the command may be writing it)."""
    import_device_modules(config)
    from tacsplat.acquisition.presses import SPHERE_RADIUS_M

    if config.rig == "sim":
        from tacsplat.acquisition.devices import twin_config
        from tacsplat.acquisition.presses import TwinPressSession
        from tacsplat.sim.twin import SimTwin

        say(f"the twin presses its fingertips on a {2000 * SPHERE_RADIUS_M:.0f} mm sphere {where}")
        with SimTwin(twin_config(config, calibrating=True)) as twin:  # the files it writes may not be there yet
            presses = TwinPressSession(twin, config.board, say).run(plan())
            mounts = {pad.name: pad.T_fingertip_sensor for pad in twin.tactile_sensors}
            return presses, twin.T_hand_cam, mounts
    from tacsplat.acquisition.devices import open_rig, rig_mounts
    from tacsplat.acquisition.presses import RigPressSession, TerminalPresser

    if config.mock:  # refused before the hand's torque comes on
        from tacsplat.acquisition.mock import own_emulator
        from tacsplat.acquisition.mock_presser import EmulatorPresser

        own_emulator(config, EmulatorPresser.needs, "press")
    fingers = [s.finger for s in config.tactile.sensors]
    say(
        f"press each fingertip on a {2000 * SPHERE_RADIUS_M:.0f} mm sphere {where} as told; a press is taken when "
        "its contact is steady"
    )
    hands = []
    try:
        with open_rig(config, on_hand=hands.append, hand_eye_required=False, calibrating=True) as rig:
            person = EmulatorPresser(rig.mock) if rig.mock is not None else TerminalPresser(say)
            presses = RigPressSession(rig.hand, rig.camera, rig.sensors, config.board, person, say).run(plan(fingers))
            T_hand_cam = np.array(rig.extra["T_hand_cam"])
    finally:  # however it ended, what closing the hand confirmed
        for hand in hands:
            _torque_off(hand, say)
    mounts = rig_mounts(config, calibrating=True)
    return presses, T_hand_cam, {finger: mounts.get(finger, np.eye(4)) for finger in fingers}


def _torque_off(hand, say: Callable[[str], None]) -> None:
    """Say what closing ``hand`` confirmed (torque off, servo by servo), if it was connected."""
    if hand.torque_off_report is not None:
        say(f"{hand.device}: {hand.torque_off_report}")


def calibrate_hand_eye(config: RigConfig, out: Path, say: Callable[[str], None] = print):
    """``T_hand_cam`` from fingertip presses on a sphere resting on the board (the sensors at the rig's mounts),
    written to ``out``; the press set is refused when it leaves an axis undetermined or fits worse than its noise
    explains."""
    from tacsplat.acquisition.devices import rig_mounts
    from tacsplat.acquisition.presses import SPHERE_RADIUS_M, hand_eye_plan
    from tacsplat.drivers.press_calibration import fit_presses, save_hand_eye

    if shadowing := inline_T_hand_cam(config):
        say(f"warning: {shadowing}")
    presses, T_hand_cam, mounts = _presses(config, hand_eye_plan, say)
    calibrated = rig_mounts(config, calibrating=True)  # the rig's mounts file's and its sensors' own
    fit = fit_presses(presses, SPHERE_RADIUS_M, T_hand_cam, mounts, "hand-eye", calibrated)
    save_hand_eye(out, fit.T_hand_cam, sum(fit.presses.values()), fit.rms_mm)
    say(
        f"T_hand_cam: {len(presses)} presses, rms {fit.rms_mm:.3f} mm; {pose_change(T_hand_cam, fit.T_hand_cam)} from the "
        "rig's previous value"
    )
    say(f"wrote {out} ({shadowing or _naming(config, out, config.camera.hand_eye, 'camera.hand_eye')})")
    return fit


def _naming(config: RigConfig, path: Path, name: str | None, key: str) -> str:
    """Whether the rig file's ``key`` (its value ``name``) names ``path`` already, or should."""
    if name and os.path.realpath(config.path(name)) == os.path.realpath(path):
        return f"the rig's {key}"
    return f"name it as {key} in the rig file"


def _hand_eye_file(config: RigConfig, out: Path, hand_eye_out: Path | None, say: Callable[[str], None]) -> Path:
    """Where calibrate mounts writes the ``T_hand_cam`` it solves: ``--hand-eye``, else the rig's ``camera.hand_eye``
    file (said), checked writable before any press. Solved with the mounts, it is the ``T_hand_cam`` they are right
    with: the mounts written beside an older one would be out of step with it (a capture's touches off the surface),
    and holding ``T_hand_cam`` at the older one would bend the mounts around its error. So a roboticist who
    calibrates the mounts gets the rig's hand-eye file updated with them, as the rig file names it; a rig that names
    none is refused, asking for ``--hand-eye``."""
    from tacsplat.datasets.outputs import ensure_output_dir
    from tacsplat.errors import ConfigError, UsageError

    if hand_eye_out is not None:
        return hand_eye_out
    if not config.camera.hand_eye:  # (an option the command line lacks: a usage error)
        raise UsageError(
            "--hand-eye",
            "calibrate mounts solves T_hand_cam with the mounts, and the rig file names no camera.hand_eye to write "
            "it to: give --hand-eye FILE (and name that file as camera.hand_eye in the rig file)",
        )
    path = config.path(config.camera.hand_eye)
    if path.is_dir():
        raise ConfigError("camera.hand_eye", f"{path} is a folder; give a .json file", config.source)
    if os.path.realpath(path) == os.path.realpath(out):
        raise ConfigError("camera.hand_eye", f"{path} is --out's file too: give --hand-eye another file", config.source)
    ensure_output_dir(path.parent, "camera.hand_eye")
    say(f"T_hand_cam is solved with the mounts: {path} (the rig's camera.hand_eye) will be written with them")
    return path


def _large(T_from: np.ndarray, T_to: np.ndarray) -> str:
    """A note when ``T_to`` is further from ``T_from`` than anything is mounted off by hand (kept: the fit's rms and
    undetermined parameters judge it); ``""`` if not."""
    from tacsplat.drivers.press_calibration import LARGE_CHANGE

    mm, deg = pose_gap(T_from, T_to)
    if mm > LARGE_CHANGE[0] or deg > LARGE_CHANGE[1]:
        return f" (a large change, over {LARGE_CHANGE[0]:g} mm or {LARGE_CHANGE[1]:g} deg: kept, as the presses fit it)"
    return ""


def calibrate_mounts(
    config: RigConfig,
    out: Path,
    hand_eye_out: Path | None = None,
    say: Callable[[str], None] = print,
    stand_height_m: float | None = None,
):
    """Each sensor's ``T_fingertip_sensor`` and ``T_hand_cam``, solved together (they are coupled: a hand-eye
    solved with the pads at their nominal mounts takes up part of their errors) from two press sets: every
    fingertip's centre on a sphere resting on the board, and six places of each pad (its two ends, two sides and two
    corners) on the sphere on a stand of known height (two bends, two spreads each); started at the rig's
    ``T_hand_cam`` (run calibrate hand-eye first) and mounts. ``stand_height_m``: the sphere's centre over the board
    on its stand, as measured (None: :data:`~tacsplat.acquisition.presses.STAND_HEIGHT_M`, the twin's and the
    emulator's). A line per sensor and one for ``T_hand_cam``; the mounts written to ``out``, ``T_hand_cam`` to
    ``hand_eye_out`` (None: the rig's ``camera.hand_eye`` file, :func:`_hand_eye_file`), both or neither. Presses
    that leave an axis undetermined, or a sensor of the rig without a usable press, are refused."""
    from tacsplat.acquisition.presses import SPHERE_RADIUS_M, STAND_HEIGHT_M, hand_eye_plan, mounts_plan
    from tacsplat.drivers.press_calibration import fit_mounts, save_mounts_and_hand_eye
    from tacsplat.errors import InvalidInputError

    def plan(*fingers):  # the hand-eye presses, then the pads' on the stand
        return hand_eye_plan(*fingers) + mounts_plan(*fingers)

    hand_eye_out = _hand_eye_file(config, out, hand_eye_out, say)
    for warning in (inline_T_hand_cam(config), inline_mounts(config)):
        if warning:
            say(f"warning: {warning}")
    stand = STAND_HEIGHT_M if stand_height_m is None else float(stand_height_m)
    where = f"resting on the board, then on a stand, its centre {1000 * stand:g} mm over the board"
    presses, T_hand_cam, mounts = _presses(config, plan, say, where)
    # every sensor of the rig (the keys of ``mounts``) needs its presses: a mounts file without one would leave it at
    # the identity in a capture, unnoticed
    if unpressed := [f for f in mounts if not any(p.finger == f for p in presses)]:
        raise InvalidInputError(
            f"calibrate mounts: no usable press of the {', '.join(unpressed)} sensor{'s' * (len(unpressed) > 1)} (each "
            "was skipped: no contact, or the wrist camera did not see the board); nothing written: take the presses "
            "again, the board in view"
        )
    fit = fit_mounts(presses, SPHERE_RADIUS_M, {0: SPHERE_RADIUS_M, 1: stand}, T_hand_cam, mounts, "calibrate mounts")
    for finger, T in fit.mounts.items():
        before = mounts.get(finger, np.eye(4))
        say(
            f"{finger}: {fit.presses[finger]} presses ({fit.dropped[finger]} dropped), rms {fit.rms_mm[finger]:.3f} mm; "
            f"{pose_change(before, T)} from the rig's previous mounting{_large(before, T)}"
        )
    change = f"{pose_change(T_hand_cam, fit.T_hand_cam)} from the rig's previous value"
    say(f"T_hand_cam: {change}{_large(T_hand_cam, fit.T_hand_cam)}")
    # both files or neither: a new mounts file beside an old hand-eye file would be out of step with it
    save_mounts_and_hand_eye(fit, out, hand_eye_out)
    named = _naming(config, hand_eye_out, config.camera.hand_eye, "camera.hand_eye")
    say(f"wrote {hand_eye_out} ({inline_T_hand_cam(config) or named})")
    said = inline_mounts(config) or _naming(config, out, config.tactile.mounts, "tactile.mounts")
    say(f"wrote {out} ({len(fit.mounts)} sensors; {said})")
    return fit
