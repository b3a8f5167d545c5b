"""The hand's joint calibration (``tacsplat calibrate hand``): each joint's sign, zero and range from its hard stops.

LeRobot's habit, torque off and each joint through its range, with the zero taken from the ends: the model's
joint limits (:data:`tacsplat.sim.hand.JOINT_LIMITS`, the Allegro hand's) are the hand's hard stops, so the motor
angle read with the joint held against its upper stop and against its lower stop gives the sign (which reads
higher) and the offset (the mean of the two stops' offsets, so that the stops' give, equal at both ends, cancels).
A hand posed by eye is not good to half a degree; its stops are.

The person's part (moving a joint, holding it against a stop) is a :class:`Person`: a person at the terminal on a
real rig, the twin or the servo emulator on a simulated one (so that the command runs to its end without keys).
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Callable, Protocol, Sequence, TextIO

import numpy as np

from tacsplat.drivers.calibration import MAX_TOLERANCE_RAD, HandCalibration, seam_advice, seam_crossing
from tacsplat.errors import HandError

STOP_READS = 5  # reads per stop; their median is the stop's motor angle
MIN_TRAVEL_FRACTION = 0.25  # a joint that moved less than this fraction of its model range between stops did not move
RANGE_TOLERANCE_RAD = math.radians(3.0)  # measured range vs the model's: farther off, a stop was not reached


class LimpHand(Protocol):
    """A hand with torque off whose servos are read raw: the real driver after ``connect(torque=False)``, the
    twin's hand after ``set_torque(False)``."""

    @property
    def joint_names(self) -> Sequence[str]: ...

    @property
    def joint_limits(self) -> np.ndarray:
        """[n, 2] the model's limits, radians: the hard stops."""

    def read_motor_angles(self) -> np.ndarray:
        """[n] radians, before any calibration."""


class Person(Protocol):
    """Whoever moves the joints: holds joint ``joint`` against its ``upper`` (the model's upper limit) or lower
    stop, returning once it is held there, and lets it go."""

    def hold_at_stop(self, joint: int, upper: bool, instruction: str) -> None: ...

    def let_go(self, joint: int) -> None: ...


def _wrap(angle: float) -> float:
    """An angle in [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


def stop_instruction(name: str, upper: bool) -> str:
    """What the person is asked to do for joint ``name`` (``finger_k``): k = 0 swings the finger sideways (positive:
    the fingertip towards the index finger's side, the thumb's towards the ring finger's), k > 0 curls it
    (positive: towards the palm)."""
    finger, k = name.rsplit("_", 1)
    if k == "0":
        side = ("index" if finger != "thumb" else "ring") if upper else ("ring" if finger != "thumb" else "index")
        motion = f"swing the {finger} finger sideways, towards the {side} finger's side,"
    else:
        motion = f"{'curl' if upper else 'straighten'} joint {k} of the {finger} finger{'' if upper else ' back'}"
    return f"{name}: {motion} until it stops; hold it there and press Enter"


@dataclass(frozen=True)
class JointResult:
    """One joint's calibration: its motor angles at the lower and upper stops, the sign and offset they give."""

    name: str
    servo: str
    motor_at_lower: float
    motor_at_upper: float
    model_range_rad: float

    @property
    def sign(self) -> int:
        return 1 if _wrap(self.motor_at_upper - self.motor_at_lower) > 0 else -1

    @property
    def measured_range_rad(self) -> float:
        return abs(_wrap(self.motor_at_upper - self.motor_at_lower))

    def offset_rad(self, lower: float, upper: float) -> float:
        """The motor angle at joint zero: the mean of what each stop says (the limits ``lower``, ``upper``)."""
        s = self.sign
        a, b = self.motor_at_lower - s * lower, self.motor_at_upper - s * upper
        return _wrap(a + _wrap(b - a) / 2)

    def problem(self) -> str | None:
        """Why this joint cannot be calibrated, saying what to do; None when it can."""
        travel, model = math.degrees(self.measured_range_rad), math.degrees(self.model_range_rad)
        if self.measured_range_rad < MIN_TRAVEL_FRACTION * self.model_range_rad:
            return (
                f"{self.name} ({self.servo}) did not move: it read {travel:.1f} degrees apart at its two stops, its "
                f"range is {model:.1f} degrees. Check that you moved {self.name} and not another joint, that the "
                "servo's horn is fastened to the joint and the servo answers, then calibrate again"
            )
        if abs(self.measured_range_rad - self.model_range_rad) > RANGE_TOLERANCE_RAD:
            return (
                f"{self.name} ({self.servo}) moved {travel:.1f} degrees between its stops, but its range is "
                f"{model:.1f} degrees (more than {math.degrees(RANGE_TOLERANCE_RAD):g} off): push it fully against "
                "both stops and hold it there while you press Enter; if it does, the hand's stops differ from the "
                "model's joint limits and this calibration cannot find its zero"
            )
        return None


def calibrate_joints(
    hand: LimpHand,
    person: Person,
    servos: Sequence[str] | None = None,
    say: Callable[[str], None] = print,
    device: str = "hand",
) -> tuple[HandCalibration, list[JointResult]]:
    """Every joint held against its upper, then its lower stop by ``person``; one status line per joint through
    ``say``. ``servos`` names each joint's servo in messages (default: ``joint k``). Refuses (HandError naming the
    joint and what to do) a joint that did not move, whose measured range is not the model's, or whose range
    (widened by the most a driver's reading tolerance may be) crosses its servo's 4095/0 tick seam: the servo reads
    within one turn after power-on, so the driver would read that joint a turn off wherever the finger rests across
    the seam (:func:`~tacsplat.drivers.calibration.seam_crossing`)."""
    names = list(hand.joint_names)
    limits = np.asarray(hand.joint_limits, dtype=np.float64)
    servos = list(servos) if servos is not None else [f"joint {k}" for k in range(len(names))]
    results, offsets = [], []
    for j, name in enumerate(names):
        lower, upper = limits[j]
        at = {}
        for is_upper in (True, False):
            person.hold_at_stop(j, is_upper, stop_instruction(name, is_upper))
            reads = [hand.read_motor_angles() for _ in range(STOP_READS)]  # their median: the stop's motor angle
            at[is_upper] = float(np.median(np.stack(reads), axis=0)[j])
        person.let_go(j)
        result = JointResult(name, servos[j], at[False], at[True], float(upper - lower))
        if problem := result.problem():
            raise HandError(device, f"calibration refused: {problem}")
        offset = result.offset_rad(lower, upper)
        if across := seam_crossing(result.sign, offset, lower, upper, MAX_TOLERANCE_RAD):
            raise HandError(
                device,
                f"calibration refused: {name} ({servos[j]}) with sign {result.sign:+d} and offset {offset:+.4f} rad "
                f"spans servo ticks {across[0]} to {across[1]} over its range (with "
                f"{math.degrees(MAX_TOLERANCE_RAD):.1f} degrees to spare at each end), across the servo's "
                f"4095/0 tick seam: after power-on the servo reads within one turn, so the driver would read "
                f"{name} a turn off: {seam_advice(name)}",
            )
        say(
            f"{name:<9} {servos[j]:<9} sign {result.sign:+d}  offset {offset:+.4f} rad ({math.degrees(offset):+7.2f} "
            f"deg)  range {math.degrees(result.measured_range_rad):6.1f} deg (model "
            f"{math.degrees(result.model_range_rad):.1f})  ok"
        )
        results.append(result)
        offsets.append(offset)
    return HandCalibration(tuple(names), np.array([r.sign for r in results], float), np.array(offsets)), results


class TerminalPerson:
    """A person at the terminal: each instruction is printed, Enter says the joint is held there."""

    def __init__(self, stdin: TextIO | None = None, out: TextIO | None = None):
        self.stdin = stdin or sys.stdin
        self.out = out or sys.stdout

    def hold_at_stop(self, joint: int, upper: bool, instruction: str) -> None:
        print(instruction, file=self.out, flush=True)
        if not self.stdin.readline():
            raise HandError(
                "calibrate hand",
                "standard input is closed: on a real rig a person moves each joint and presses Enter "
                "(run it at a terminal; --mock or a rig: sim file play the person themselves)",
            )

    def let_go(self, joint: int) -> None:
        """Nothing to do: the next instruction tells the person what to hold."""
