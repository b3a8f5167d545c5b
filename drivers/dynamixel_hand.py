"""DynamixelHand: the real 16-DoF hand (LEAP-style) on Dynamixel X-series servos, protocol 2.0.

Implements the ``Hand`` Protocol of DESIGN.md on ``dynamixel_sdk``. What the
LEAP Hand API leaves to luck is done here on purpose:

* every status packet is checked: a comm failure is retried a bounded number of
  times (with a drain of the input so a late reply is never taken for the next
  one) and then raises; a read never returns the previous values silently;
* the status error byte is decoded, and a hardware alert is resolved by reading
  the servo's Hardware Error Status (overload, overheating, input voltage,
  electrical shock, encoder);
* any failure disables torque on every servo that still answers, records the
  fault (no further motion until a reconnect) and raises one :class:`ServoError`
  naming the servo, its joint, the instruction and the decoded error;
* the context manager disables torque on exit, on exception and on SIGINT (a
  Ctrl-C arriving mid-packet is deferred until the exchange completes, so the
  port is never left half-used);
* connect holds the present pose: before torque comes on, each servo's goal is
  where it stands, or, for a joint standing just outside its limits, the nearest
  limit if that is at most ``connect_tolerance_rad`` away; a calibration (or a
  finger) that puts a joint farther out is refused with torque off, naming the
  joint, its sign and offset. Only :meth:`DynamixelHand.command_joint_positions`
  moves the hand further;
* commands are checked (InvalidInputError before anything reaches the bus),
  clamped to the joint limits of the twin's model, and clamping is logged; a
  missing servo at connect time is a refusal to move.
"""

from __future__ import annotations

import atexit
import logging
import math
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import dynamixel_sdk as dxl
import numpy as np

from tacsplat.drivers.calibration import RAD_PER_TICK, HandCalibration
from tacsplat.drivers.protocols import HandKinematics
from tacsplat.drivers.dynamixel_table import (
    ALERT_BIT,
    REGISTERS,
    OperatingMode,
    decode_hardware_error,
    decode_status_error,
    le_bytes,
    to_signed,
)
from tacsplat.errors import ConfigError, HandError, InvalidInputError

log = logging.getLogger(__name__)

try:  # what pyserial lets escape when the adapter disappears (termios.error is not an OSError)
    import termios

    PORT_ERRORS: tuple[type[BaseException], ...] = (OSError, termios.error)
except ImportError:  # Windows
    PORT_ERRORS = (OSError,)

COMM_RESULT_NAMES = {
    dxl.COMM_SUCCESS: "COMM_SUCCESS",
    dxl.COMM_PORT_BUSY: "COMM_PORT_BUSY",
    dxl.COMM_TX_FAIL: "COMM_TX_FAIL",
    dxl.COMM_RX_FAIL: "COMM_RX_FAIL",
    dxl.COMM_TX_ERROR: "COMM_TX_ERROR",
    dxl.COMM_RX_WAITING: "COMM_RX_WAITING",
    dxl.COMM_RX_TIMEOUT: "COMM_RX_TIMEOUT",
    dxl.COMM_RX_CORRUPT: "COMM_RX_CORRUPT",
    dxl.COMM_NOT_AVAILABLE: "COMM_NOT_AVAILABLE",
}

# One sync read gets current, velocity and position (addresses 126..135).
_STATE_ADDRESS = REGISTERS["present_current"].address
_STATE_SIZE = REGISTERS["present_position"].address + 4 - _STATE_ADDRESS
VELOCITY_UNIT_RAD_S = 0.229 * 2.0 * np.pi / 60.0  # Present Velocity unit: 0.229 rpm
MAX_CONNECT_TOLERANCE_RAD = 0.2


@dataclass(frozen=True)
class DynamixelHandConfig:
    """Servo settings written at connect, and the communication policy."""

    operating_mode: int = OperatingMode.CURRENT_BASED_POSITION  # the LEAP Hand's mode: position with a current cap
    current_limit: int = 350  # Current Limit register units (XC330: 1 mA), LEAP's safe grip
    current_unit_a: float = 0.001  # amperes per Present Current unit (XC330: 1 mA; XM430: 2.69 mA)
    position_p_gain: int = 800
    position_i_gain: int = 0
    position_d_gain: int = 200
    min_packet_timeout_s: float = 0.05  # lower bound on the SDK's status-packet timeout (its own is ~34 ms)
    retries: int = 2  # extra attempts after a failed exchange, then raise
    drain_s: float = 0.1  # after a failed exchange: wait, then flush input, so late replies cannot be mistaken
    handle_sigint: bool = True  # defer Ctrl-C to the end of the packet exchange, then raise KeyboardInterrupt
    # how far connect may move a joint that stands just outside its limits onto the nearest limit; farther is refused
    connect_tolerance_rad: float = math.radians(5.0)

    def __post_init__(self):
        tol = self.connect_tolerance_rad
        if not 0.0 <= tol <= MAX_CONNECT_TOLERANCE_RAD:  # also NaN
            raise ConfigError("connect_tolerance_rad", f"must be in [0, {MAX_CONNECT_TOLERANCE_RAD}] rad (how far "
                                                       f"connect may move a servo), got {tol!r}")


@dataclass(frozen=True)
class HandState:
    positions: np.ndarray  # [16] radians
    velocities: np.ndarray  # [16] radians / second
    currents: np.ndarray  # [16] amperes (signed like the joint)
    timestamp: float  # time.time() when the sync read completed


class ServoError(HandError):
    """A servo failed, named with its joint, the instruction and the decoded error or comm result."""

    def __init__(self, device: str, message: str, *, servo_id: int | None = None, joint: str | None = None,
                 instruction: str | None = None, comm_result: int | None = None, status_error: int = 0,
                 hardware_error: int = 0):
        self.servo_id = servo_id
        self.joint = joint
        self.instruction = instruction
        self.comm_result = comm_result
        self.status_error = status_error
        self.hardware_error = hardware_error
        super().__init__(device, message)


class _PortHandler(dxl.PortHandler):
    """The SDK's port with a lower bound on the status-packet timeout."""

    def __init__(self, port_name: str, min_timeout_ms: float):
        super().__init__(port_name)
        self.min_timeout_ms = min_timeout_ms

    def setPacketTimeout(self, packet_length):
        super().setPacketTimeout(packet_length)
        self.packet_timeout = max(self.packet_timeout, self.min_timeout_ms)


class _Exchange:
    """One packet exchange: holds the bus lock and defers SIGINT until it ends."""

    def __init__(self, hand: "DynamixelHand"):
        self.hand = hand

    def __enter__(self):
        self.hand._lock.acquire()
        self.hand._depth += 1

    def __exit__(self, *exc):
        hand = self.hand
        hand._depth -= 1
        hand._lock.release()
        if hand._depth == 0 and hand._sigint_pending:
            hand._sigint_pending = False
            raise KeyboardInterrupt


class DynamixelHand:
    """The real hand. ``with DynamixelHand("/dev/ttyUSB0") as hand:`` connects, configures, enables torque.

    ``ids[i]`` is the servo of joint ``joint_names[i]`` (the twin's joint order:
    index, middle, ring, thumb, four joints each). ``calibration`` is a
    :class:`HandCalibration`, the path of a calibration file, or None (sign +1,
    offset 0: joint zero at the centre tick). ``kinematics`` gives the joint
    names, limits and fingertip poses (the twin's model, passed in by the rig
    assembly: :class:`tacsplat.sim.hand.HandKinematics`).
    """

    def __init__(self, port: str, baudrate: int = 4_000_000, ids: Iterable[int] = range(16),
                 calibration: HandCalibration | str | Path | None = None, *,
                 config: DynamixelHandConfig | None = None, kinematics: HandKinematics):
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
        self._depth = 0
        self._sigint_pending = False
        self._previous_sigint = None
        self._fault: str | None = None
        self._torque_on = False

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

    def connect(self) -> None:
        """Open the port, ping every servo, configure them with torque off, hold the present pose, enable torque.

        On a faulted hand this reconnects from scratch: the goal is again where each servo stands now.
        """
        if self._port is not None:
            if not self._fault:
                return
            self.close()
        port = _PortHandler(self.port_name, 1000.0 * self.config.min_packet_timeout_s)
        try:
            opened = port.setBaudRate(self.baudrate)  # opens the port at this rate (openPort would open at 1 Mbps first)
        except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
            raise HandError(self.device, f"cannot open serial port: {exc} (is the U2D2 plugged in, "
                                         "and is this user in the dialout group?)") from None
        if not opened:
            raise HandError(self.device, f"baud rate {self.baudrate} is not one the Dynamixel SDK supports")
        self._port = port
        self._fault = None
        self._install_sigint()
        atexit.register(self.close)
        try:
            self._ping_all()
            for sid in self.ids:
                self._write(sid, "torque_enable", 0)
                self._write(sid, "operating_mode", int(self.config.operating_mode))
                self._write(sid, "current_limit", self.config.current_limit)
                self._write(sid, "position_p_gain", self.config.position_p_gain)
                self._write(sid, "position_i_gain", self.config.position_i_gain)
                self._write(sid, "position_d_gain", self.config.position_d_gain)
            # hold where the hand is before torque comes on: no jump (acknowledged writes, not an unanswered sync write)
            for sid, tick in zip(self.ids, self._holding_goal(self._read_raw_state()[0])):
                self._write(sid, "goal_position", int(tick))
            for sid in self.ids:
                self._write(sid, "torque_enable", 1)
            self._torque_on = True
            log.info("%s: %d servos connected, torque on", self.device, len(self.ids))
        except BaseException:
            self.close()
            raise

    def read_state(self) -> HandState:
        """Positions, velocities and currents of every joint by one sync read (retried, then raises)."""
        ticks, vel, cur = self._read_raw_state()
        signs = self.calibration.signs
        return HandState(
            positions=self.calibration.radians_from_ticks(ticks),
            velocities=signs * vel * VELOCITY_UNIT_RAD_S,
            currents=signs * cur * self.config.current_unit_a,
            timestamp=time.time(),
        )

    def read_joint_positions(self) -> np.ndarray:
        """[16] radians."""
        return self.read_state().positions

    def read_joint_currents(self) -> np.ndarray:
        """[16] amperes."""
        return self.read_state().currents

    def command_joint_positions(self, q) -> None:
        """Goal positions [16] radians by one sync write, clamped to the joint limits (clamping logged).

        The one motion command: bad ``q`` (not 16 real finite numbers) raises InvalidInputError, writing nothing.
        """
        self._check_usable()
        if not self._torque_on:
            raise HandError(self.device, "torque is off: connect first (use the hand as a context manager)")
        self._sync_write_goal(self._clamp(self._joint_vector(q), "command"))

    def fingertip_poses(self) -> dict[str, np.ndarray]:
        """``{finger: T_hand_sensor [4, 4]}`` by forward kinematics of the twin's model at the present joints."""
        return self._kinematics.fingertip_poses(self.read_joint_positions())

    def close(self) -> None:
        """Disable torque on every servo that answers and close the port (idempotent)."""
        if self._port is None:
            return
        with self._lock:
            unconfirmed = self._torque_off_all()
            if unconfirmed:
                log.error("%s: torque off not confirmed by servos %s", self.device, self._names(unconfirmed))
            self._torque_on = False
            try:
                self._port.closePort()
            except PORT_ERRORS as exc:
                log.error("%s: closing the port: %s", self.device, exc)
            self._port = None
        self._restore_sigint()
        atexit.unregister(self.close)

    # -- internals ---------------------------------------------------------
    def _names(self, ids: Sequence[int]) -> str:
        return ", ".join(f"{s} ({self._joint_of.get(s, '?')})" for s in ids)

    def _check_usable(self) -> None:
        if self._port is None:
            raise HandError(self.device, "not connected (use `with DynamixelHand(...) as hand:`)")
        if self._fault:
            raise HandError(self.device, f"hand is faulted, reconnect to continue: {self._fault}")

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
        lo, hi = self._joint_limits[:, 0], self._joint_limits[:, 1]
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
            self._fail(self.ids[too_far[0]], "hold present pose",
                       f"{joints}; that is more than connect_tolerance_rad = {tol:.4f} rad, so the hand will not "
                       f"move there: check the sign and offset_rad of {names} in "
                       f"{cal.source or 'the hand calibration'}, or move the finger by hand into its range")
        nudged = np.flatnonzero(goal != ticks)
        if nudged.size:
            log.warning("%s: present pose clamped to joint limits: %s", self.device, ", ".join(
                f"{self._joint_names[i]} {q[i]:+.4f} -> {inside[i]:+.4f} rad" for i in nudged))
        return goal

    def _clamp(self, q: np.ndarray, what: str) -> np.ndarray:
        lo, hi = self._joint_limits[:, 0], self._joint_limits[:, 1]
        clamped = np.clip(q, lo, hi)
        moved = np.flatnonzero(clamped != q)
        if moved.size:
            log.warning(
                "%s: %s clamped to joint limits: %s", self.device, what,
                ", ".join(f"{self._joint_names[i]} {q[i]:+.4f} -> {clamped[i]:+.4f} rad" for i in moved),
            )
        return clamped

    def _install_sigint(self) -> None:
        if not self.config.handle_sigint or threading.current_thread() is not threading.main_thread():
            return

        def on_sigint(signum, frame):
            if self._depth:
                self._sigint_pending = True  # let the packet exchange finish, then stop
            else:
                raise KeyboardInterrupt

        self._previous_sigint = signal.signal(signal.SIGINT, on_sigint)

    def _restore_sigint(self) -> None:
        if self._previous_sigint is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, self._previous_sigint)
            self._previous_sigint = None

    def _drain(self) -> None:
        """After a failed exchange: let late replies arrive, then discard them."""
        time.sleep(self.config.drain_s)
        self._port.is_using = False
        try:
            self._port.clearPort()
        except PORT_ERRORS:
            pass  # the next exchange reports the port error

    def _comm_text(self, result: int) -> str:
        text = self._ph.getTxRxResult(result).replace("[TxRxResult] ", "").rstrip("!")
        return f"{COMM_RESULT_NAMES.get(result, result)} ({text})"

    def _attempt(self, instruction: str, exchange):
        """Run ``exchange()`` (returns ``(failed_servo, comm_result)`` or None) with bounded retries."""
        attempts = self.config.retries + 1
        for k in range(attempts):
            try:
                with _Exchange(self):
                    failure = exchange()
            except PORT_ERRORS as exc:
                self._fail(None, instruction, f"serial port error: {exc} (adapter unplugged?)")
            if failure is None:
                return
            servo_id, result = failure
            log.warning("%s: %s, servo %s: %s (attempt %d of %d)", self.device, instruction,
                        self._names([servo_id]), self._comm_text(result), k + 1, attempts)
            self._drain()
        self._fail(servo_id, instruction, f"{self._comm_text(result)} after {attempts} attempts",
                   comm_result=result)

    def _fail(self, servo_id: int | None, instruction: str, detail: str, *, comm_result: int | None = None,
              status_error: int = 0, hardware_error: int = 0):
        """Make the hand safe, record the fault and raise a ServoError."""
        unconfirmed = self._torque_off_all()
        self._torque_on = False
        answered = [s for s in self.ids if s not in unconfirmed]
        who = f"servo {self._names([servo_id])}" if servo_id is not None else f"port {self.port_name}"
        if not unconfirmed:
            safety = "torque disabled on all servos"
        elif answered:
            safety = f"torque disabled on servos {answered}, not confirmed by {self._names(unconfirmed)}"
        else:
            safety = "no servo confirmed torque off: cut the servo power"
        message = f"{who}: {instruction} failed: {detail}; {safety}"
        self._fault = message
        raise ServoError(self.device, message, servo_id=servo_id, joint=self._joint_of.get(servo_id, None),
                         instruction=instruction, comm_result=comm_result, status_error=status_error,
                         hardware_error=hardware_error)

    def _status_fail(self, servo_id: int, instruction: str, error: int):
        """Raise for a status packet whose error byte is set, decoding a hardware alert."""
        detail = ", ".join(decode_status_error(error))
        hw = 0
        if error & ALERT_BIT:
            try:
                with _Exchange(self):
                    data, result, _ = self._ph.readTxRx(self._port, servo_id,
                                                        REGISTERS["hardware_error_status"].address, 1)
            except PORT_ERRORS:
                data, result = [], dxl.COMM_TX_FAIL
            if result == dxl.COMM_SUCCESS and data:
                hw = data[0]
                detail += f": Hardware Error Status 0x{hw:02x} = {', '.join(decode_hardware_error(hw)) or 'none'}"
            else:
                detail += " (Hardware Error Status unreadable)"
        self._fail(servo_id, instruction, f"status error 0x{error:02x} ({detail})", status_error=error,
                   hardware_error=hw)

    def _torque_off_all(self) -> list[int]:
        """Broadcast torque off, then confirm servo by servo; returns the ids that did not confirm."""
        port, address = self._port, REGISTERS["torque_enable"].address
        unconfirmed = []
        with self._lock:
            try:
                port.is_using = False
                port.clearPort()
                self._ph.write1ByteTxOnly(port, dxl.BROADCAST_ID, address, 0)
            except PORT_ERRORS as exc:
                log.error("%s: broadcast torque off failed: %s", self.device, exc)
            for sid in self.ids:
                for _ in range(2):
                    port.is_using = False
                    try:
                        result, _ = self._ph.write1ByteTxRx(port, sid, address, 0)
                    except PORT_ERRORS:
                        result = dxl.COMM_TX_FAIL
                    if result == dxl.COMM_SUCCESS:
                        break
                else:
                    unconfirmed.append(sid)
        return unconfirmed

    def _ping_all(self) -> None:
        missing, comm = [], {}
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
                missing.append(sid)
                comm[sid] = result
            elif error:
                self._status_fail(sid, "PING", error)
        if missing:
            first = missing[0]
            self._fail(first, "PING", f"servos {self._names(missing)} did not answer ({self._comm_text(comm[first])}); "
                                      "refusing to move with a servo missing", comm_result=comm[first])

    def _write(self, servo_id: int, name: str, value: int) -> None:
        reg = REGISTERS[name]
        instruction = f"WRITE {name}={value}"
        status = {}

        def exchange():
            result, error = self._ph.writeTxRx(self._port, servo_id, reg.address, reg.size, le_bytes(value, reg.size))
            if result != dxl.COMM_SUCCESS:
                return servo_id, result
            status["error"] = error

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
        self._check_usable()
        raw = self._sync_read(_STATE_ADDRESS, _STATE_SIZE, "SYNC_READ present current/velocity/position")
        ticks = np.array([to_signed(int.from_bytes(raw[s][6:10], "little"), 4) for s in self.ids])
        vel = np.array([to_signed(int.from_bytes(raw[s][2:6], "little"), 4) for s in self.ids])
        cur = np.array([to_signed(int.from_bytes(raw[s][0:2], "little"), 2) for s in self.ids])
        return ticks, vel, cur

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


__all__ = ["DynamixelHand", "DynamixelHandConfig", "HandState", "ServoError"]
