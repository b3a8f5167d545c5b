"""DynamixelHand: the real 16-DoF hand (LEAP-style) on Dynamixel X-series servos, protocol 2.0.

Implements the ``Hand`` Protocol of DESIGN.md on ``dynamixel_sdk``. What the
LEAP Hand API leaves to luck is done here on purpose:

* every status packet is checked: a comm failure is retried a bounded number of
  times (with a drain of the input so a late reply is never taken for the next
  one) and then raises; a read never returns the previous values silently;
* the status error byte is decoded, and a hardware alert is resolved by reading
  the servo's Hardware Error Status (overload, overheating, input voltage,
  electrical shock, encoder);
* a position reading farther outside its joint's limits than
  ``reading_tolerance_rad`` (what no finger can reach: an encoder glitch, a
  slipped horn) is a fault, not a pose. Ticks are read as the servos give
  them, within one turn after power-on: a joint whose calibrated range crosses
  the 4095/0 tick seam reads a turn off beyond it, and the refusal says so
  (``calibrate hand`` refuses such a joint; the fix is on the servo: its horn
  or its Homing Offset);
* any failure disables torque on every servo that still answers, records the
  fault (no further motion until a reconnect) and raises one :class:`ServoError`
  naming the servo, its joint, the instruction and the decoded error;
  :attr:`DynamixelHand.torque_off_report` says which servos confirmed torque off
  (at a fault, and again at close) and which did not;
* connect holds the present pose: before torque comes on, each servo's goal is
  where it stands, or, for a joint standing just outside its limits, the nearest
  limit if that is at most ``connect_tolerance_rad`` away; a calibration (or a
  finger) that puts a joint farther out is refused with torque off, naming the
  joint, its sign and offset. Only :meth:`DynamixelHand.command_joint_positions`
  moves the hand further;
* connect holds the port alone (a lock): a second process opening it, ``tacsplat
  rig check`` beside a capture, is refused instead of turning torque off under it;
* commands are checked (InvalidInputError before anything reaches the bus),
  clamped to the joint limits of the twin's model, and clamping is logged; a
  missing servo at connect time is a refusal to move.

What leaves the hand safe when the process ends, by how it ends:

* an exception, ``close()``, or SIGINT, SIGTERM, SIGHUP or SIGQUIT (the context
  manager): torque off, confirmed servo by servo. A signal arriving mid-packet is
  deferred until the exchange completes (the port is never left half-used), then
  raised as :class:`SignalInterrupt` (a KeyboardInterrupt; exit code 128 +
  signum), and one arriving while torque goes off waits until it is off;
* any death of the process, SIGKILL included (``guard``): a guard process started
  at connect holds a pipe from this one; when the pipe ends without the word that
  the hand was closed, the guard opens the port itself and turns torque off,
  confirming servo by servo. Connect waits for the guard to say it is ready, and
  refuses to go on without it;
* a host crash, a hung process, or a guard that cannot run (``bus_watchdog_s``):
  the servos' own Bus Watchdog, armed at connect and fed by a heartbeat thread
  while torque is on. With no instruction packet for that long, each servo stops
  where it stands and holds there, at its current limit, refusing new goals until
  the next connect clears it. It does not turn torque off; the heartbeat reports
  a tripped watchdog as a fault (a process that was stopped and continued), and
  one that a servo's reboot reset (a brown-out, which also turns its torque off).
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import json
import logging
import math
import numbers
import os
import select
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import dynamixel_sdk as dxl
import numpy as np
import serial

from tacsplat.drivers.calibration import (
    MAX_TOLERANCE_RAD,
    RAD_PER_TICK,
    HandCalibration,
    motor_angles_from_ticks,
    seam_advice,
    seam_crossing,
)
from tacsplat.drivers.dynamixel_table import (
    ALERT_BIT,
    BUS_WATCHDOG_TRIPPED,
    BUS_WATCHDOG_UNIT_S,
    REGISTERS,
    OperatingMode,
    decode_hardware_error,
    decode_status_error,
    le_bytes,
    to_signed,
)
from tacsplat.drivers.protocols import HandKinematics
from tacsplat.errors import ConfigError, HandError, InvalidInputError
from tacsplat.interrupts import END_SIGNALS, SignalInterrupt  # each leaves the hand with torque off

log = logging.getLogger(__name__)

try:  # what pyserial lets escape when the adapter disappears (termios.error is not an OSError)
    import termios

    PORT_ERRORS: tuple[type[BaseException], ...] = (OSError, termios.error)
except ImportError:  # Windows
    PORT_ERRORS = (OSError,)

COMM_RESULT_NAMES = {value: name for name, value in vars(dxl).items() if name.startswith("COMM_")}

# One sync read gets current, velocity and position (addresses 126..135), little-endian and signed.
_STATE_ADDRESS = REGISTERS["present_current"].address
_STATE_DTYPE = np.dtype([("current", "<i2"), ("velocity", "<i4"), ("position", "<i4")])
_STATE_SIZE = _STATE_DTYPE.itemsize
VELOCITY_UNIT_RAD_S = 0.229 * 2.0 * np.pi / 60.0  # Present Velocity unit: 0.229 rpm
MAX_BUS_WATCHDOG_S = 127 * BUS_WATCHDOG_UNIT_S
GUARD_CLOSED = b"closed\n"  # what the guard reads when the hand was closed: it then exits without a word
GUARD_READY = b"ready\n"  # what the guard says once it holds all it needs to turn torque off
GUARD_READY_S = 10.0  # connect refuses a guard not ready by then (it starts within a second or two)


def _is_int(value) -> bool:
    """An integer, numpy's included, but not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


@dataclass(frozen=True)
class DynamixelHandConfig:
    """Servo settings written at connect, and the communication and safety policy."""

    operating_mode: int = OperatingMode.CURRENT_BASED_POSITION  # the LEAP Hand's mode: position with a current cap
    current_limit: int = 350  # Current Limit register units (XC330: 1 mA), LEAP's safe grip
    current_unit_a: float = 0.001  # amperes per Present Current unit (XC330: 1 mA; XM430: 2.69 mA)
    position_p_gain: int = 800
    position_i_gain: int = 0
    position_d_gain: int = 200
    min_packet_timeout_s: float = 0.05  # lower bound on the SDK's status-packet timeout (its own is ~34 ms)
    retries: int = 2  # extra attempts after a failed exchange, then raise
    drain_s: float = 0.1  # after a failed exchange: wait, then flush input, so late replies cannot be mistaken
    # SIGINT, SIGTERM, SIGHUP, SIGQUIT: deferred to the end of the packet exchange, then SignalInterrupt
    handle_signals: bool = True
    # how far connect may move a joint that stands just outside its limits onto the nearest limit; farther is refused
    connect_tolerance_rad: float = math.radians(5.0)
    # a reading farther outside its joint's limits is a fault (encoder glitch, slipped horn, wrong calibration), not
    # a pose. At least connect_tolerance_rad: a joint that connect accepted reads up to that far out until it is
    # on its limit; the controller's overshoot at a limit is a few ticks. 1500 ticks of glitch are 2.3 rad.
    reading_tolerance_rad: float = math.radians(5.0)
    # the servos' Bus Watchdog: with torque on and no instruction packet for this long, they stop and hold (0: off).
    # Unit 20 ms, at most 2.54 s. At least 2 (min_packet_timeout_s + drain_s), twice the silence of a retried
    # exchange (the heartbeat waits for the bus meanwhile), so that a retry never trips it. 1 s stops a hand whose
    # host died within a second; the heartbeat (every eighth of it) then rides out a host that stalls for 0.875 s
    # (a loaded machine, a long garbage collection), where a healthy loaded host's longest silence is ~0.16 s.
    bus_watchdog_s: float = 1.0
    guard: bool = True  # a guard process turns torque off when this one dies without closing the hand (SIGKILL too)

    def __post_init__(self):
        if not _is_int(self.retries) or self.retries < 0:
            raise ConfigError(
                "retries", f"must be an integer >= 0 (extra attempts after a failure), got {self.retries!r}"
            )
        for key in ("min_packet_timeout_s", "drain_s", "current_unit_a"):
            value, unit = getattr(self, key), "amperes" if key == "current_unit_a" else "seconds"
            positive = key != "drain_s"  # (drain_s 0: the input is flushed at once)
            if not (value > 0 if positive else value >= 0) or not math.isfinite(value):  # also NaN
                raise ConfigError(
                    key, f"must be a finite number of {unit} {'>' if positive else '>='} 0, got {value!r}"
                )
        for key in ("operating_mode", "current_limit", "position_p_gain", "position_i_gain", "position_d_gain"):
            value, top = getattr(self, key), (1 << (8 * REGISTERS[key].size)) - 1  # written to its register as is
            if not _is_int(value) or not 0 <= value <= top:
                raise ConfigError(key, f"must be an integer in [0, {top}] (its register's range), got {value!r}")
        for key in ("connect_tolerance_rad", "reading_tolerance_rad"):
            tol = getattr(self, key)
            if not 0.0 <= tol <= MAX_TOLERANCE_RAD:  # also NaN
                raise ConfigError(
                    key,
                    f"must be in [0, {MAX_TOLERANCE_RAD}] rad (how far outside its limits a joint may be), got {tol!r}",
                )
        if self.reading_tolerance_rad < self.connect_tolerance_rad:
            raise ConfigError(
                "reading_tolerance_rad",
                f"must be at least connect_tolerance_rad "
                f"({self.connect_tolerance_rad:g}): a joint connect accepted reads that far out, got "
                f"{self.reading_tolerance_rad:g}",
            )
        shortest = 2 * (self.min_packet_timeout_s + self.drain_s)
        wd = self.bus_watchdog_s
        if wd != 0 and not (shortest <= wd <= MAX_BUS_WATCHDOG_S and self.bus_watchdog_units >= 1):  # also NaN
            raise ConfigError(
                "bus_watchdog_s",
                f"must be 0 (off) or in [{shortest:g}, {MAX_BUS_WATCHDOG_S:g}] s "
                f"(at least 2 (min_packet_timeout_s + drain_s): a retried exchange must not trip it), "
                f"got {wd!r}",
            )

    @property
    def heartbeat_s(self) -> float:
        """The heartbeat's period: an eighth of ``bus_watchdog_s``, so that a host may stall for 7/8 of it."""
        return self.bus_watchdog_s / 8

    @property
    def bus_watchdog_units(self) -> int:
        """The Bus Watchdog register's value (20 ms units; 0 = off)."""
        return round(self.bus_watchdog_s / BUS_WATCHDOG_UNIT_S)


@dataclass(frozen=True)
class HandState:
    positions: np.ndarray  # [16] radians
    velocities: np.ndarray  # [16] radians / second
    currents: np.ndarray  # [16] amperes (signed like the joint)
    timestamp: float  # time.monotonic() when the sync read completed (as the video frames': never stepped)


@dataclass(frozen=True)
class TorqueOffReport:
    """What one torque-off confirmed: ``servos`` every servo as ``"ID (joint)"``, ``unconfirmed`` those that did not
    answer the write without error (their torque may still be on)."""

    servos: tuple[str, ...]
    unconfirmed: tuple[str, ...]

    @property
    def confirmed(self) -> bool:
        """Every servo confirmed torque off."""
        return not self.unconfirmed

    def __str__(self) -> str:
        n, bad = len(self.servos), self.unconfirmed
        if not bad:
            return f"torque off confirmed on all {n} servos"
        if len(bad) == n:
            return f"torque off NOT confirmed on any of the {n} servos: cut the servo power"
        which = f"servo {bad[0]}" if len(bad) == 1 else f"servos {', '.join(bad)}"
        return f"torque off NOT confirmed on {which}: cut the servo power (confirmed on the other {n - len(bad)})"


class ServoError(HandError):
    """A servo failed, named with its joint, the instruction and the decoded error or comm result (the keyword
    arguments, each an attribute; those not given keep the defaults here)."""

    servo_id: int | None = None
    joint: str | None = None
    instruction: str | None = None
    comm_result: int | None = None
    status_error: int = 0
    hardware_error: int = 0

    def __init__(self, device: str, message: str, **details):
        vars(self).update(details)
        super().__init__(device, message)


class PortInUse(OSError):
    """The port is locked by another process (an ``exclusive`` :class:`_PortHandler` there)."""


class _PortHandler(dxl.PortHandler):
    """The SDK's port with a lower bound on the status-packet timeout, opened ``exclusive`` (a flock: a second
    process, say ``tacsplat rig check`` beside a capture, would reconfigure the servos under it) or not."""

    def __init__(self, port_name: str, min_timeout_ms: float, exclusive: bool = True):
        super().__init__(port_name)
        self.min_timeout_ms = min_timeout_ms
        self.exclusive = exclusive
        self._serial = serial.Serial  # resolved now: the guard proves it can open a port before it says it is ready

    def setupPort(self, cflag_baud):
        """The SDK's, with the lock taken before the port is touched (pyserial flushes its input at open)."""
        if self.is_open:
            self.closePort()
        try:
            self.ser = self._serial(
                self.port_name, self.baudrate, bytesize=serial.EIGHTBITS, timeout=0, exclusive=self.exclusive or None
            )
        except serial.SerialException as exc:
            if self.exclusive and exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK):
                raise PortInUse(exc.errno, f"{self.port_name} is in use by another process") from None
            raise
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True

    def setPacketTimeout(self, packet_length):
        super().setPacketTimeout(packet_length)
        self.packet_timeout = max(self.packet_timeout, self.min_timeout_ms)


def torque_off(ph: dxl.PacketHandler, port: dxl.PortHandler, ids: Sequence[int], device: str) -> list[int]:
    """Broadcast torque off, then confirm servo by servo: two tries each, one once two servos in a row have not
    answered (the bus is likely dead, and each try waits out the timeout); returns the ids that did not confirm."""
    address = REGISTERS["torque_enable"].address
    try:
        port.is_using = False
        port.clearPort()
        ph.write1ByteTxOnly(port, dxl.BROADCAST_ID, address, 0)
    except PORT_ERRORS as exc:
        log.error("%s: broadcast torque off failed: %s", device, exc)
    unconfirmed, silent = [], 0  # silent: servos in a row that did not confirm
    for sid in ids:
        for _ in range(1 if silent >= 2 else 2):
            port.is_using = False
            try:
                result, error = ph.write1ByteTxRx(port, sid, address, 0)
            except PORT_ERRORS:
                result, error = dxl.COMM_TX_FAIL, 0
            if result == dxl.COMM_SUCCESS and not error & ~ALERT_BIT:  # a latched alert does not refuse the write
                silent = 0
                break
        else:
            unconfirmed.append(sid)
            silent += 1
    return unconfirmed


class _Exchange:
    """One packet exchange (or a torque-off): holds the bus lock and, in the main thread, defers the ending signals
    until it ends."""

    def __init__(self, hand: "DynamixelHand"):
        self.hand = hand
        self.main = threading.current_thread() is threading.main_thread()

    def __enter__(self):
        if self.main:
            self.hand._depth += 1  # before waiting for the lock: a signal meanwhile is deferred too
        self.hand._lock.acquire()

    def __exit__(self, *exc):
        self.hand._lock.release()
        if self.main:
            self.hand._depth -= 1
            self.hand._raise_pending_signal()


class DynamixelHand:
    """The real hand. ``with DynamixelHand("/dev/ttyUSB0") as hand:`` connects, configures, enables torque.

    ``ids[i]`` is the servo of joint ``joint_names[i]`` (the twin's joint order:
    index, middle, ring, thumb, four joints each). ``calibration`` is a
    :class:`HandCalibration`, the path of a calibration file, or None (sign +1,
    offset 0: joint zero at the centre tick). ``kinematics`` gives the joint
    names, limits and fingertip poses (the twin's model, passed in by the rig
    assembly: :class:`tacsplat.sim.hand.HandKinematics`).
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 4_000_000,
        ids: Iterable[int] = range(16),
        calibration: HandCalibration | str | Path | None = None,
        *,
        config: DynamixelHandConfig | None = None,
        kinematics: HandKinematics,
    ):
        self._kinematics = kinematics
        self._joint_names = list(kinematics.joint_names)
        self._joint_limits = np.asarray(kinematics.joint_limits, dtype=np.float64)
        self.ids = [int(i) for i in ids]
        if len(self.ids) != len(self._joint_names):
            raise InvalidInputError(f"ids: {len(self.ids)} servo ids for {len(self._joint_names)} joints")
        if len(set(self.ids)) != len(self.ids) or not all(0 <= i <= dxl.MAX_ID for i in self.ids):
            raise InvalidInputError(f"ids: must be distinct integers in 0..{dxl.MAX_ID}, got {self.ids}")
        if calibration is None:
            calibration = HandCalibration.identity(self._joint_names)
        elif isinstance(calibration, (str, Path)):
            calibration = HandCalibration.load(calibration, self._joint_names)
        calibration.check_joints(self._joint_names)
        self.calibration = calibration
        self.config = config or DynamixelHandConfig()
        self.port_name = str(port)
        self.baudrate = int(baudrate)
        self.device = f"Dynamixel hand on {self.port_name}"
        self._joint_of = dict(zip(self.ids, self._joint_names))
        self._ph = dxl.PacketHandler(2.0)
        self._port: _PortHandler | None = None
        self._lock = threading.RLock()
        self._depth = 0  # exchanges of the main thread in progress: its ending signals wait for them
        self._pending_signal: int | None = None
        self._previous_handlers: dict[int, object] = {}
        self._fault: str | None = None
        self._torque_on = False
        self._heartbeat: threading.Thread | None = None
        self._heartbeat_stop = threading.Event()
        self._guard: subprocess.Popen | None = None
        self.torque_off_report: TorqueOffReport | None = None  # the last torque-off's (a fault's, a close's)

    # -- Hand Protocol ----------------------------------------------------
    @property
    def joint_names(self) -> list[str]:
        return list(self._joint_names)

    @property
    def joint_limits(self) -> np.ndarray:
        """[16, 2] radians, from the twin's model."""
        return self._joint_limits.copy()

    def __enter__(self) -> "DynamixelHand":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def connect(self, torque: bool = True) -> None:
        """Open the port, ping every servo, configure them with torque off, hold the present pose, arm the Bus
        Watchdog, enable torque.

        ``torque=False`` stops after the configuration: the joints move freely by hand (``calibrate hand``), only
        :meth:`read_motor_angles` reads them (no calibration needed), and closing confirms torque off as ever.
        On a faulted hand this reconnects from scratch: the goal is again where each servo stands now.
        """
        if self._port is not None:
            if not self._fault:
                return
            self.close()
        port = _PortHandler(self.port_name, 1000.0 * self.config.min_packet_timeout_s)
        try:  # setBaudRate opens the port at this rate (openPort would open at 1 Mbps first)
            opened = port.setBaudRate(self.baudrate)
        except PortInUse:
            raise HandError(
                self.device,
                f"port in use by another process (a capture, or `tacsplat rig check` in another terminal? "
                f"`fuser {self.port_name}` names it); not connecting, which would reconfigure its servos",
            ) from None
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise HandError(
                self.device,
                f"cannot open serial port: {exc} (is the U2D2 plugged in, and is this user in the dialout group?)",
            ) from None
        if not opened:
            raise HandError(self.device, f"baud rate {self.baudrate} is not one the Dynamixel SDK supports")
        self._port = port
        self._fault = None
        self._install_signal_handlers()
        atexit.register(self.close)
        try:
            self._start_guard()
            self._ping_all()
            # bus_watchdog 0 clears a tripped one: the goal registers take writes again
            settings = {"torque_enable": 0, "bus_watchdog": 0, "operating_mode": int(self.config.operating_mode)}
            settings |= {k: getattr(self.config, k) for k in ("current_limit", *(f"position_{g}_gain" for g in "pid"))}
            for sid in self.ids:
                for name, value in settings.items():
                    self._write(sid, name, value)
            if not torque:
                log.info("%s: %d servos connected, torque off", self.device, len(self.ids))
                return
            # hold where the hand is before torque comes on: no jump (acknowledged writes, not an unanswered sync write)
            for sid, tick in zip(self.ids, self._holding_goal(self._read_raw_state()[0])):
                self._write(sid, "goal_position", int(tick))
            # the Bus Watchdog of every servo (it watches once torque is on), then torque on every servo
            for name, value in (("bus_watchdog", self.config.bus_watchdog_units), ("torque_enable", 1)):
                for sid in self.ids:
                    self._write(sid, name, value)
            self._torque_on = True
            self._start_heartbeat()
            log.info("%s: %d servos connected, torque on", self.device, len(self.ids))
        except BaseException:
            self.close()
            raise

    def read_state(self) -> HandState:
        """Positions, velocities and currents of every joint by one sync read (retried, then raises).

        A position farther outside its joint's limits than ``reading_tolerance_rad`` is a fault (ServoError)."""
        ticks, vel, cur = self._read_raw_state()
        positions, signs = self.calibration.radians_from_ticks(ticks), self.calibration.signs
        self._check_reachable(ticks, positions)
        return HandState(
            positions, signs * vel * VELOCITY_UNIT_RAD_S, signs * cur * self.config.current_unit_a, time.monotonic()
        )

    def read_motor_angles(self) -> np.ndarray:
        """[16] the servos' motor angles in radians (0 at the centre tick), before the calibration and its checks."""
        return motor_angles_from_ticks(self._read_raw_state()[0])

    def read_joint_positions(self) -> np.ndarray:
        """[16] radians."""
        return self.read_state().positions

    effort_unit = "A"  # the servos' present current

    def read_joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        """``(positions [16] radians, currents [16] amperes)`` by one sync read."""
        state = self.read_state()
        return state.positions, state.currents

    def command_joint_positions(self, q) -> None:
        """Goal positions [16] radians by one sync write, clamped to the joint limits (clamping logged).

        The one motion command: bad ``q`` (not 16 real finite numbers) raises InvalidInputError, writing nothing.
        """
        self.check()
        if not self._torque_on:
            raise HandError(self.device, "torque is off: connect first (use the hand as a context manager)")
        self._sync_write_goal(self._clamp(self._joint_vector(q), "command"))

    def fingertip_poses(self) -> dict[str, np.ndarray]:
        """``{finger: T_hand_sensor [4, 4]}`` by forward kinematics of the twin's model at the present joints."""
        return self._kinematics.fingertip_poses(self.read_joint_positions())

    @property
    def link_names(self) -> list[str]:
        return list(self._kinematics.link_names)

    def link_boxes(self, q) -> tuple[np.ndarray, np.ndarray]:
        """The hand's solid shape at joint positions ``q`` [16] (the twin's model): boxes [L, 4, 4], [L, 3]."""
        return self._kinematics.link_boxes(q)

    def check(self) -> None:
        """Raise the fault that stopped the hand (HandError), such as one the heartbeat found while nothing else used
        the hand (a dead bus, a tripped Bus Watchdog); nothing when it is connected and well."""
        if self._port is None:
            raise HandError(self.device, "not connected (use `with DynamixelHand(...) as hand:`)")
        if self._fault:
            raise HandError(self.device, f"hand is faulted, reconnect to continue: {self._fault}")

    def close(self) -> None:
        """Disable torque on every servo that answers (:attr:`torque_off_report` says which did) and close the port
        (idempotent). An ending signal that arrives meanwhile is raised once torque is off."""
        if self._port is None:
            return
        main = threading.current_thread() is threading.main_thread()
        if main:
            self._depth += 1  # nothing interrupts the way out
        try:
            self._stop_heartbeat()
            with self._lock:
                self._torque_off_all()
                if not self.torque_off_report.confirmed:
                    log.error("%s: %s", self.device, self.torque_off_report)
                self._torque_on = False
                try:
                    self._port.closePort()
                except PORT_ERRORS as exc:
                    log.error("%s: closing the port: %s", self.device, exc)
                self._port = None
            self._release_guard()
        finally:
            if main:
                self._depth -= 1
            self._restore_signal_handlers()
            atexit.unregister(self.close)
        self._raise_pending_signal()

    # -- internals ---------------------------------------------------------
    def _names(self, ids: Sequence[int]) -> str:
        return ", ".join(f"{s} ({self._joint_of.get(s, '?')})" for s in ids)

    def _joint_vector(self, q) -> np.ndarray:
        """``q`` as [16] float64 radians, or InvalidInputError naming the argument."""
        n = len(self.ids)
        expected = f"command_joint_positions: q must be {n} finite joint angles in radians"
        try:
            array = np.asarray(q)
        except (ValueError, TypeError) as exc:  # ragged nested sequences
            raise InvalidInputError(f"{expected}: {exc}") from None
        if array.dtype.kind not in "iuf":
            raise InvalidInputError(f"{expected}, got {type(q).__name__} of dtype {array.dtype}")
        if array.shape != (n,):
            raise InvalidInputError(f"{expected} (shape ({n},)), got shape {array.shape}")
        array = array.astype(np.float64)
        if not np.all(np.isfinite(array)):
            bad = [self._joint_names[i] for i in np.flatnonzero(~np.isfinite(array))]
            raise InvalidInputError(f"command_joint_positions: q is NaN or infinite for joints {bad}")
        return array

    def _holding_goal(self, ticks: np.ndarray) -> np.ndarray:
        """Goal ticks that hold the present pose: ``ticks``, or the nearest joint limit if within the tolerance.

        Refuses (torque off, one ServoError) when a joint reads farther outside its limits than
        ``connect_tolerance_rad``: the calibration is wrong, or the finger was bent out of its range.
        """
        cal, tol = self.calibration, self.config.connect_tolerance_rad
        q = cal.radians_from_ticks(ticks)
        lo, hi = self._joint_limits.T
        inside = np.clip(q, lo, hi)
        goal = np.where(inside == q, ticks, cal.ticks_from_radians(inside))
        too_far = np.flatnonzero(np.abs(goal - ticks) * RAD_PER_TICK > tol)
        if too_far.size:
            joints = "; ".join(
                f"{self._joint_names[i]} (servo {self.ids[i]}) stands at tick {ticks[i]}, which sign "
                f"{int(cal.signs[i]):+d} and offset_rad {cal.offsets_rad[i]:+.4f} read as {q[i]:+.4f} rad, "
                f"{abs(q[i] - inside[i]):.4f} rad outside its limits [{lo[i]:+.4f}, {hi[i]:+.4f}]"
                for i in too_far
            )
            names = ", ".join(self._joint_names[i] for i in too_far)
            self._fail(
                self.ids[too_far[0]],
                "hold present pose",
                f"{joints}; that is more than connect_tolerance_rad = {tol:.4f} rad, so the hand will not "
                f"move there: check the sign and offset_rad of {names} in "
                f"{cal.source or 'the hand calibration'}, or move the finger by hand into its range"
                + self._seam_notes(too_far),
            )
        self._clamp(q, "present pose", np.where(goal != ticks, inside, q))  # (logs the joints nudged)
        return goal

    def _check_reachable(self, ticks: np.ndarray, q: np.ndarray) -> None:
        """A fault (torque off, ServoError) when a joint reads farther outside its limits than
        ``reading_tolerance_rad``: no finger stands there, so the reading is wrong."""
        tol = self.config.reading_tolerance_rad
        lo, hi = self._joint_limits.T
        out = np.flatnonzero((q < lo - tol) | (q > hi + tol))
        if out.size:
            joints = "; ".join(
                f"{self._joint_names[i]} (servo {self.ids[i]}) reads {q[i]:+.4f} rad (tick {ticks[i]}), "
                f"{max(lo[i] - q[i], q[i] - hi[i]):.4f} rad outside its limits [{lo[i]:+.4f}, {hi[i]:+.4f}]"
                for i in out
            )
            self._fail(
                self.ids[out[0]],
                "read present position",
                f"{joints}; farther than reading_tolerance_rad = {tol:.4f} rad, where the joint cannot be: "
                "an encoder fault, a slipped horn or a wrong calibration" + self._seam_notes(out),
            )

    def _seam_notes(self, joints: Iterable[int]) -> str:
        """Why each of ``joints`` whose calibrated range crosses its servo's 4095/0 tick seam may read a turn off
        (the servo reads within one turn after power-on), and what to do; empty when none does."""
        cal, margin = self.calibration, self.config.reading_tolerance_rad
        notes = []
        for i in joints:
            lower, upper = self._joint_limits[i]
            across = seam_crossing(cal.signs[i], cal.offsets_rad[i], lower, upper, margin)
            if across:
                name = self._joint_names[i]
                notes.append(
                    f"; a possible cause: {name}'s range spans servo ticks {across[0]} to {across[1]} with this "
                    f"calibration, across the servo's 4095/0 tick seam, and a servo reads within one turn after "
                    f"power-on, so {name} reads a turn off wherever the finger rests across the seam: "
                    f"{seam_advice(name)}"
                )
        return "".join(notes)

    def _clamp(self, q: np.ndarray, what: str, clamped: np.ndarray | None = None) -> np.ndarray:
        """``q`` clamped to the joint limits (or ``clamped``, where it differs from ``q``), the clamping logged."""
        clamped = np.clip(q, *self._joint_limits.T) if clamped is None else clamped
        moved = ", ".join(
            f"{self._joint_names[i]} {q[i]:+.4f} -> {clamped[i]:+.4f} rad" for i in np.flatnonzero(clamped != q)
        )
        if moved:
            log.warning("%s: %s clamped to joint limits: %s", self.device, what, moved)
        return clamped

    # -- the ways out: signals, the guard process, the Bus Watchdog and its heartbeat
    def _install_signal_handlers(self) -> None:
        if not self.config.handle_signals or threading.current_thread() is not threading.main_thread():
            return

        def on_signal(signum, frame):
            if self._depth:
                self._pending_signal = self._pending_signal or signum  # let the exchange finish, then stop
            else:
                raise SignalInterrupt(signum)

        self._previous_handlers = {s: signal.signal(s, on_signal) for s in END_SIGNALS}

    def _restore_signal_handlers(self) -> None:
        if self._previous_handlers and threading.current_thread() is threading.main_thread():
            for s, handler in self._previous_handlers.items():  # (None: a handler installed outside Python)
                signal.signal(s, signal.SIG_DFL if handler is None else handler)
            self._previous_handlers = {}

    def _raise_pending_signal(self) -> None:
        if self._depth == 0 and self._pending_signal is not None:
            signum, self._pending_signal = self._pending_signal, None
            raise SignalInterrupt(signum)

    def _start_guard(self) -> None:
        """The guard process (``python -P -m tacsplat.drivers.dynamixel_hand``, :func:`guard_main`): ``-P`` keeps the
        working folder off its sys.path (a ``serial.py`` there would shadow pyserial); in a session of its own, so
        that the terminal's signals reach this process only; it outlives this one. A guard that does not say it is
        ready within ``GUARD_READY_S`` is killed, and connect refused: the hand never runs unguarded."""
        if not self.config.guard:
            return
        args = {"port": self.port_name, "baudrate": self.baudrate, "timeout_s": self.config.min_packet_timeout_s}
        args |= {"drain_s": self.config.drain_s, "servos": [(sid, self._names([sid])) for sid in self.ids]}
        command = [sys.executable, "-P", "-m", "tacsplat.drivers.dynamixel_hand", json.dumps(args)]
        what = "the guard process (it turns torque off should this process die)"
        try:
            self._guard = subprocess.Popen(
                command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, start_new_session=True
            )
        except OSError as exc:
            raise HandError(self.device, f"cannot start {what}: {exc}") from None
        if (why := self._guard_not_ready()) is None:
            return
        guard, self._guard = self._guard, None
        guard.kill()  # (nothing when it has ended)
        guard.wait()
        guard.stdin.close()
        raise HandError(self.device, f"{what} {why}: not connecting without it")

    def _guard_not_ready(self) -> str | None:
        """Wait for the guard's word that it is ready (anything it prints before is skipped); None once it said it,
        or why it did not."""
        deadline, said = time.monotonic() + GUARD_READY_S, b""
        with self._guard.stdout as out:
            while not said.endswith(GUARD_READY):
                if not select.select([out], [], [], max(0.0, deadline - time.monotonic()))[0]:
                    return f"was not ready within {GUARD_READY_S:g} s"
                if not (chunk := os.read(out.fileno(), 4096)):
                    return f"ended (exit code {self._guard.wait()}) before it was ready (its error is above)"
                said += chunk
        return None

    def _release_guard(self) -> None:
        """Tell the guard that the hand was closed (it exits without a word); reaped by a thread, never waited for."""
        guard, self._guard = self._guard, None
        if guard is None:
            return
        with contextlib.suppress(OSError):  # (the guard is gone)
            guard.stdin.write(GUARD_CLOSED)
            guard.stdin.close()
        threading.Thread(target=guard.wait, name="hand-guard-reaper", daemon=True).start()

    def _start_heartbeat(self) -> None:
        if not self.config.bus_watchdog_units:
            return
        self._heartbeat_stop = threading.Event()
        self._heartbeat = threading.Thread(
            target=self._feed_watchdog, args=(self._heartbeat_stop,), name="hand-heartbeat", daemon=True
        )
        self._heartbeat.start()

    def _stop_heartbeat(self) -> None:
        self._heartbeat_stop.set()
        if self._heartbeat is not None and self._heartbeat is not threading.current_thread():
            self._heartbeat.join()
        self._heartbeat = None

    def _feed_watchdog(self, stop: threading.Event) -> None:
        """Heartbeat thread: every eighth of ``bus_watchdog_s``, read every servo's Bus Watchdog (an instruction
        packet feeds it); one that is not the value armed at connect is a fault (torque off), which the next use of
        the hand raises: tripped (-1), or reset by a reboot (a brown-out), which also turned its torque off."""
        address, armed = REGISTERS["bus_watchdog"].address, self.config.bus_watchdog_units
        while not stop.wait(self.config.heartbeat_s):
            try:
                with self._lock:
                    if stop.is_set() or not self._torque_on or self._fault:
                        continue
                    values = self._sync_read(address, 1, "SYNC_READ bus_watchdog (heartbeat)")
                    values = {sid: to_signed(values[sid][0], 1) for sid in self.ids}
                    tripped = [sid for sid in self.ids if values[sid] == BUS_WATCHDOG_TRIPPED]
                    reset = [sid for sid in self.ids if values[sid] not in (armed, BUS_WATCHDOG_TRIPPED)]
                    if tripped:
                        self._fail(
                            tripped[0],
                            "heartbeat",
                            f"Bus Watchdog Error on servos {self._names(tripped)}: no "
                            f"instruction reached them for bus_watchdog_s = {self.config.bus_watchdog_s:g} s "
                            "(was this process stopped?), so they stopped and held",
                        )
                    if reset:
                        found = ", ".join(f"{self._names([sid])} = {values[sid]}" for sid in reset)
                        self._fail(
                            reset[0],
                            "heartbeat",
                            f"Bus Watchdog of servos {found}, not the {armed} armed at connect: a reboot (a "
                            "brown-out under load? check the servo power and cabling) reset it and turned torque off",
                        )
            except HandError as exc:  # recorded in self._fault, torque off
                log.error("%s", exc)
                return

    # -- the bus -----------------------------------------------------------
    def _drain(self) -> None:
        """After a failed exchange: let late replies arrive, then discard them."""
        time.sleep(self.config.drain_s)
        self._port.is_using = False
        with contextlib.suppress(*PORT_ERRORS):  # the next exchange reports the port error
            self._port.clearPort()

    def _comm_text(self, result: int) -> str:
        text = self._ph.getTxRxResult(result).replace("[TxRxResult] ", "").rstrip("!")
        return f"{COMM_RESULT_NAMES.get(result, result)} ({text})"

    def _attempt(self, instruction: str, exchange):
        """Run ``exchange()`` (returns ``(failed_servo, comm_result)`` or None) with bounded retries, holding the bus
        through the drains too (the heartbeat never takes a late reply for its own)."""
        attempts = self.config.retries + 1
        with self._lock:
            if self._fault:  # faulted by the heartbeat meanwhile
                raise HandError(self.device, f"hand is faulted, reconnect to continue: {self._fault}")
            for k in range(attempts):
                try:
                    with _Exchange(self):
                        failure = exchange()
                except PORT_ERRORS as exc:
                    self._fail(None, instruction, f"serial port error: {exc} (adapter unplugged?)")
                if failure is None:
                    return
                servo_id, result = failure
                failed = f"{self.device}: {instruction}, servo {self._names([servo_id])}"
                log.warning("%s: %s (attempt %d of %d)", failed, self._comm_text(result), k + 1, attempts)
                self._drain()
            self._fail(
                servo_id, instruction, f"{self._comm_text(result)} after {attempts} attempts", comm_result=result
            )

    def _fail(self, servo_id: int | None, instruction: str, detail: str, **codes):
        """Make the hand safe, record the fault and raise a ServoError (an ending signal meanwhile wins); ``codes``:
        ServoError's comm_result, status_error, hardware_error."""
        with _Exchange(self):
            self._torque_off_all()
            who = f"servo {self._names([servo_id])}" if servo_id is not None else f"port {self.port_name}"
            message = f"{who}: {instruction} failed: {detail}; {self.torque_off_report}"
            self._fault = message
            joint = self._joint_of.get(servo_id)
            error = ServoError(self.device, message, servo_id=servo_id, joint=joint, instruction=instruction, **codes)
        raise error

    def _status_fail(self, servo_id: int, instruction: str, error: int):
        """Raise for a status packet whose error byte is set, decoding a hardware alert."""
        detail = ", ".join(decode_status_error(error))
        hw, address = 0, REGISTERS["hardware_error_status"].address
        if error & ALERT_BIT:
            try:
                with _Exchange(self):
                    data, result, _ = self._ph.readTxRx(self._port, servo_id, address, 1)
            except PORT_ERRORS:
                data, result = [], dxl.COMM_TX_FAIL
            if result == dxl.COMM_SUCCESS and data:
                hw = data[0]
                detail += f": Hardware Error Status 0x{hw:02x} = {', '.join(decode_hardware_error(hw)) or 'none'}"
            else:
                detail += " (Hardware Error Status unreadable)"
        detail = f"status error 0x{error:02x} ({detail})"
        self._fail(servo_id, instruction, detail, status_error=error, hardware_error=hw)

    def _torque_off_all(self) -> None:
        """Torque off on every servo, confirmed one by one, into :attr:`torque_off_report`."""
        with _Exchange(self):
            unconfirmed = torque_off(self._ph, self._port, self.ids, self.device)
            self._torque_on = False
            self.torque_off_report = TorqueOffReport(
                tuple(self._names([s]) for s in self.ids), tuple(self._names([s]) for s in unconfirmed)
            )

    def _ping_all(self) -> None:
        missing = {}  # servo -> the comm result of its last try
        for sid in self.ids:
            for _ in range(self.config.retries + 1):
                try:
                    with _Exchange(self):
                        model, result, error = self._ph.ping(self._port, sid)
                except PORT_ERRORS as exc:
                    self._fail(None, "PING", f"serial port error: {exc} (adapter unplugged?)")
                if result == dxl.COMM_SUCCESS:
                    break
                self._drain()
            if result != dxl.COMM_SUCCESS:
                missing[sid] = result
            elif error:
                self._status_fail(sid, "PING", error)
        if missing:
            first, result = next(iter(missing.items()))
            why = f"servos {self._names(list(missing))} did not answer ({self._comm_text(result)})"
            self._fail(first, "PING", f"{why}; refusing to move with a servo missing", comm_result=result)

    def _write(self, servo_id: int, name: str, value: int) -> None:
        reg = REGISTERS[name]
        instruction = f"WRITE {name}={value}"
        status = {}

        def exchange():
            result, status["error"] = self._ph.writeTxRx(
                self._port, servo_id, reg.address, reg.size, le_bytes(value, reg.size)
            )
            return None if result == dxl.COMM_SUCCESS else (servo_id, result)

        self._attempt(instruction, exchange)
        if status["error"]:
            self._status_fail(servo_id, instruction, status["error"])

    def _sync_read(self, address: int, size: int, instruction: str) -> dict[int, bytes]:
        """One SYNC_READ of ``size`` bytes at ``address`` from every servo; status errors raise."""
        group = dxl.GroupSyncRead(self._port, self._ph, address, size)
        for sid in self.ids:
            group.addParam(sid)
        replies: dict[int, tuple[bytes, int]] = {}

        def exchange():
            replies.clear()
            result = group.txPacket()
            if result != dxl.COMM_SUCCESS:
                return self.ids[0], result
            # read each status ourselves: GroupSyncRead.rxPacket drops the error byte and the failing id
            for sid in self.ids:
                data, result, error = self._ph.readRx(self._port, sid, size)
                if result != dxl.COMM_SUCCESS:
                    return sid, result
                replies[sid] = (bytes(data), error)

        self._attempt(instruction, exchange)
        for sid in self.ids:
            data, error = replies[sid]
            if error:
                self._status_fail(sid, instruction, error)
            if len(data) != size:
                self._fail(sid, instruction, f"status packet has {len(data)} data bytes, expected {size}")
        return {sid: replies[sid][0] for sid in self.ids}

    def _read_raw_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Present (position ticks, velocity units, current units) of every servo by one sync read."""
        self.check()
        raw = self._sync_read(_STATE_ADDRESS, _STATE_SIZE, "SYNC_READ present current/velocity/position")
        state = np.frombuffer(b"".join(raw[s] for s in self.ids), _STATE_DTYPE)
        return tuple(state[key].astype(np.int64) for key in ("position", "velocity", "current"))

    def _sync_write_goal(self, q: np.ndarray) -> None:
        ticks = self.calibration.ticks_from_radians(q)
        reg = REGISTERS["goal_position"]
        group = dxl.GroupSyncWrite(self._port, self._ph, reg.address, reg.size)
        for sid, t in zip(self.ids, ticks):
            group.addParam(sid, le_bytes(int(t), reg.size))

        def exchange():
            result = group.txPacket()
            self._port.is_using = False
            return None if result == dxl.COMM_SUCCESS else (self.ids[0], result)

        self._attempt("SYNC_WRITE goal_position", exchange)


# -- the guard process ------------------------------------------------------------------------------------------
def guard_main(argv: list[str] | None = None) -> int:
    """``python -P -m tacsplat.drivers.dynamixel_hand JSON``: the guard of one connected hand (``JSON``: its ``port``,
    ``baudrate``, ``timeout_s`` and ``drain_s``, and ``servos``: ``[[ID, "ID (joint)"], ...]``).

    Started by :meth:`DynamixelHand.connect`; says ``ready`` on standard output once it holds all it needs (its
    imports, pyserial's port class), then reads its standard input (a pipe from the hand's process) to the end.
    ``closed`` there: the hand was closed, exit without a word. Anything else (the process died: its end of the pipe
    closed with it, SIGKILL included): open the port, turn torque off on every servo, confirm each, and say so on
    standard error; any failure there says that torque off is not confirmed. The ending signals are ignored: it ends
    when the hand's process does.
    """
    for s in END_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    args = json.loads((sys.argv[1:] if argv is None else argv)[0])
    names = {int(sid): name for sid, name in args["servos"]}  # in the hand's order
    parent = os.getppid()
    # not exclusive: the lock went with the dead process's descriptors, and nothing may keep torque on
    port = _PortHandler(args["port"], 1000.0 * args["timeout_s"], exclusive=False)
    ph = dxl.PacketHandler(2.0)
    with contextlib.suppress(OSError):  # (a hand's process that died meanwhile: the torque-off below is needed)
        os.write(sys.stdout.fileno(), GUARD_READY)
    if sys.stdin.buffer.read() == GUARD_CLOSED:
        return 0
    device = f"hand guard of {args['port']}"
    what = f"{device}: the process {parent} ended without closing the hand"
    try:
        if not port.setBaudRate(args["baudrate"]):
            raise ValueError(f"baud rate {args['baudrate']} is not supported")
        time.sleep(args["drain_s"])  # status packets meant for the dead process arrive, and are dropped
        unconfirmed = torque_off(ph, port, list(names), device)
    except Exception as exc:  # whatever it is, the servos may still hold torque: say so
        _say(
            f"{what}; cannot turn torque off ({type(exc).__name__}: {exc}): torque off NOT confirmed on any of the "
            f"{len(names)} servos: cut the servo power"
        )
        return 1
    finally:
        if port.is_open:
            with contextlib.suppress(Exception):
                port.closePort()
    report = TorqueOffReport(tuple(names.values()), tuple(names[s] for s in unconfirmed))
    _say(f"{what}; {report}")
    return 0 if report.confirmed else 1


def _say(line: str) -> None:
    with contextlib.suppress(OSError):  # (the terminal went with the process)
        print(line, file=sys.stderr, flush=True)


__all__ = ["DynamixelHand", "DynamixelHandConfig", "HandState", "ServoError", "SignalInterrupt", "TorqueOffReport"]

if __name__ == "__main__":
    sys.exit(guard_main())
