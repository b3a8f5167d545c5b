"""An emulated bus of Dynamixel X-series servos speaking protocol 2.0 on a pseudo-terminal.

The emulator owns the master end of ``os.openpty()``; anything that opens
:attr:`DxlEmulator.path` with pyserial (the real ``dynamixel_sdk``, hence the
real :class:`~tacsplat.drivers.DynamixelHand`) talks to it exactly as it would
to a U2D2 adapter. It is written from the protocol specification, not from the
SDK: packets are parsed byte by byte (header ``FF FF FD 00``, id, length,
instruction, byte-stuffed parameters, CRC-16 of the protocol), and PING, READ,
WRITE, SYNC_READ and SYNC_WRITE are answered from an X-series control table per
servo, each servo moving toward its goal position while its torque is on.

The Bus Watchdog (address 98) is the firmware's: armed with 1..127 (unit 20 ms),
it watches the time between instruction packets that reach the servo while its
torque is on; past it, the servo stops where it stands and holds there (its goal
becomes its present position), the register reads -1 and the goal registers
refuse writes (Data Range error) until 0 is written.

A servo may have hard stops (a joint's ends) and be moved by a person's hand while its torque is off
(:meth:`move_by_hand`: the person of ``tacsplat calibrate hand --mock``).

Faults for tests: :meth:`disconnect` (a servo that never answers),
:meth:`inject` ``"bad_crc"`` (a status packet with a corrupted CRC) or
``"late"`` (a reply after the host's timeout), :meth:`slip_horn` (a joint that turns without its servo),
:meth:`inject_position_offset`
(an encoder that reads off by some ticks) and :meth:`set_hardware_error`
(the alert bit and Hardware Error Status, with the shutdown that the servo's
firmware applies). Tests and the mocked operator session use it; it is no
substitute for the hardware, but the bytes on the wire are real.

``python -m tacsplat.drivers.dxl_emulator`` runs it as a process of its own, so
that it outlives a process that dies while using the port (a killed capture):
it prints ``{"port": PATH}`` and answers commands on its standard input, one
JSON line each (:func:`main`); :class:`EmulatorProcess` starts and drives it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import select
import subprocess
import sys
import threading
import time
import tty
from dataclasses import dataclass, field

from tacsplat.drivers.dynamixel_table import (
    ALERT_BIT,
    BUS_WATCHDOG_TRIPPED,
    BUS_WATCHDOG_UNIT_S,
    CENTRE_TICK,
    CONTROL_TABLE_SIZE,
    EEPROM_END,
    GOAL_REGISTERS,
    REGISTERS,
    Instruction,
    OperatingMode,
    le_bytes,
    to_signed,
)

log = logging.getLogger(__name__)

HEADER = bytes([0xFF, 0xFF, 0xFD, 0x00])
BROADCAST_ID = 0xFE

# Status error numbers (protocol 2.0; dynamixel_table.STATUS_ERROR_NAMES names them)
ERR_INSTRUCTION, ERR_CRC, ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = range(2, 8)


def crc16(data: bytes | bytearray | list[int]) -> int:
    """CRC-16 of Dynamixel protocol 2.0 (polynomial 0x8005, initial value 0, not reflected)."""
    crc = 0
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005 if crc & 0x8000 else crc << 1) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert 0xFD after every ``FF FF FD`` in a packet body (instruction onwards, CRC excluded)."""
    return bytes(body).replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")  # the pattern cannot overlap itself


def unstuff(body: bytes) -> bytes:
    """Remove the 0xFD that :func:`stuff` inserted."""
    return bytes(body).replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")


def build_packet(servo_id: int, instruction: int, params: bytes | list[int]) -> bytes:
    """A complete protocol 2.0 packet: header, id, length, stuffed body, CRC."""
    body = stuff(bytes([instruction]) + bytes(params))
    length = len(body) + 2
    head = HEADER + bytes([servo_id, length & 0xFF, length >> 8])
    crc = crc16(head + body)
    return head + body + bytes([crc & 0xFF, crc >> 8])


@dataclass
class EmulatedServo:
    """One X-series servo: its control table and a first-order motion model."""

    servo_id: int
    speed_ticks_per_s: float = 4000.0  # about 6 rad/s
    initial_ticks: float = CENTRE_TICK
    table: bytearray = field(default_factory=lambda: bytearray(CONTROL_TABLE_SIZE))
    position: float = 0.0  # ticks, continuous
    offset_ticks: int = 0  # what the encoder reads on top of the position (a fault)
    last_instruction: float = field(default_factory=time.monotonic)  # when an instruction packet last reached it
    stops: tuple[float, float] | None = None  # the joint's hard stops (ticks): nothing moves it past them
    hand_goal: float | None = None  # where a person's hand moves it while its torque is off (None: let go)
    hand_speed_ticks_per_s: float = 10000.0
    horn_slipped: bool = False  # a fault: the joint turns without the servo, so a hand no longer moves it

    def __post_init__(self):
        for reg in REGISTERS.values():
            self.set(reg.name, reg.initial)
        self.set("id", self.servo_id)
        self.position = float(self.initial_ticks)
        self.set("goal_position", int(round(self.position)))
        self._sync_present()

    def get(self, name: str) -> int:
        reg = REGISTERS[name]
        value = int.from_bytes(self.table[reg.address : reg.address + reg.size], "little")
        return to_signed(value, reg.size) if reg.signed else value

    def set(self, name: str, value: int) -> None:
        reg = REGISTERS[name]
        self.table[reg.address : reg.address + reg.size] = bytes(le_bytes(value, reg.size))

    @property
    def torque_enabled(self) -> bool:
        return bool(self.get("torque_enable"))

    def write(self, address: int, data: bytes) -> int:
        """Apply a WRITE the way the firmware does; returns the status error number (0 = ok)."""
        end = address + len(data)
        if address < 0 or end > CONTROL_TABLE_SIZE or not data:
            return ERR_ACCESS
        touched = [r for r in REGISTERS.values() if r.address < end and address < r.address + r.size]
        if not touched or any(not r.writable for r in touched):
            return ERR_ACCESS
        if any(r.address < address or r.address + r.size > end for r in touched):
            return ERR_DATA_LENGTH  # partial register
        if address < EEPROM_END and self.torque_enabled:
            return ERR_ACCESS  # EEPROM is locked while torque is on
        tripped = self.get("bus_watchdog") == BUS_WATCHDOG_TRIPPED
        if tripped and any(r.name in GOAL_REGISTERS for r in touched):
            return ERR_DATA_RANGE  # goal values are read-only until the Bus Watchdog Error is cleared
        new = bytearray(self.table)
        new[address:end] = data
        watchdog = REGISTERS["bus_watchdog"].address
        if address <= watchdog < end:
            value = to_signed(new[watchdog], 1)
            if not 0 <= value <= 127 or tripped and value:
                return ERR_DATA_RANGE  # 0 clears and disarms, 1..127 arms; a tripped watchdog is cleared first
        goal = REGISTERS["goal_position"]
        # the position limits apply in position mode only
        if address <= goal.address < end and self.get("operating_mode") == OperatingMode.POSITION:
            value = to_signed(int.from_bytes(new[goal.address : goal.address + 4], "little"), 4)
            if not self.get("min_position_limit") <= value <= self.get("max_position_limit"):
                return ERR_DATA_LIMIT
        torque = REGISTERS["torque_enable"].address
        if address <= torque < end and new[torque] and self.get("hardware_error_status"):
            return ERR_ACCESS  # a latched hardware error keeps torque off until reboot
        self.table[:] = new
        return 0

    def step(self, dt: float) -> None:
        """Move toward the goal at the servo's speed while torque is on."""
        present = {"present_current": 0, "present_velocity": 0, "moving": 0}  # torque off: still, no current
        if self.torque_enabled:
            error = self.get("goal_position") - self.position
            move = max(-self.speed_ticks_per_s * dt, min(self.speed_ticks_per_s * dt, error))
            self.position += move
            current = max(-self.get("current_limit"), min(self.get("current_limit"), 2.0 * (error - move)))
            present["present_current"] = int(round(current))
            present["present_velocity"] = int(round(move / max(dt, 1e-6) / 4096 * 60 / 0.229))
            present["moving"] = int(abs(error - move) > self.get("moving_threshold"))
        elif self.hand_goal is not None and not self.horn_slipped:
            step = self.hand_speed_ticks_per_s * dt
            self.position += max(-step, min(step, self.hand_goal - self.position))
        for name, value in present.items():
            self.set(name, value)
        if self.stops is not None:
            self.position = min(max(self.position, self.stops[0]), self.stops[1])
        self._sync_present()

    def check_watchdog(self, now: float) -> None:
        """Trip the Bus Watchdog when armed, torque on, and no instruction packet came within its period: the servo
        stops and holds where it stands."""
        units, silent = self.get("bus_watchdog"), now - self.last_instruction
        if units > 0 and self.torque_enabled and silent > units * BUS_WATCHDOG_UNIT_S:
            self.set("bus_watchdog", BUS_WATCHDOG_TRIPPED)
            self.set("goal_position", int(round(self.position)))
            log.debug("servo %d: Bus Watchdog Error after %.3f s without an instruction", self.servo_id, silent)

    def _sync_present(self) -> None:
        self.set("present_position", int(round(self.position)) + self.offset_ticks)

    def status_error(self, number: int = 0) -> int:
        return number | (ALERT_BIT if self.get("hardware_error_status") else 0)


@dataclass
class _Fault:
    kind: str  # "bad_crc" | "late"
    remaining: int | None  # None = forever
    delay_s: float = 0.0


class DxlEmulator:
    """Servos on a pseudo-terminal; use as a context manager, connect to :attr:`path`."""

    def __init__(
        self,
        ids=range(16),
        *,
        speed_ticks_per_s: float = 4000.0,
        initial_ticks: dict[int, float] | None = None,
        stops: dict[int, tuple[float, float]] | None = None,
    ):
        initial_ticks, stops = initial_ticks or {}, stops or {}
        self.servos = {
            i: EmulatedServo(i, speed_ticks_per_s, initial_ticks.get(i, CENTRE_TICK), stops=stops.get(i)) for i in ids
        }
        self.crc_errors = 0  # instruction packets that arrived with a bad CRC
        self.instructions: list[tuple[int, int]] = []  # (instruction, id) received, in order
        self._disconnected: set[int] = set()
        self._faults: dict[int, _Fault] = {}
        self._lock = threading.RLock()
        self._outbox: list[tuple[float, bytes]] = []
        self._buffer = bytearray()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._received = time.monotonic()
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no newline translation: bytes pass unchanged
        self.path = os.ttyname(self._slave)
        self._last_step = time.monotonic()

    # -- fault injection -------------------------------------------------
    def disconnect(self, servo_id: int) -> None:
        """The servo neither processes nor answers anything (a cut cable, a dead servo)."""
        with self._lock:
            self._disconnected.add(servo_id)

    def reconnect(self, servo_id: int) -> None:
        with self._lock:
            self._disconnected.discard(servo_id)

    def inject(self, servo_id: int, kind: str, times: int | None = None, delay_s: float = 0.2) -> None:
        """Corrupt the next ``times`` status packets of a servo (None: all of them).

        ``kind`` is ``"bad_crc"`` (the CRC bytes are flipped) or ``"late"`` (the
        packet is sent ``delay_s`` after it was due, past the host's timeout).
        """
        if kind not in ("bad_crc", "late"):
            raise ValueError(f"unknown fault kind {kind!r}")
        with self._lock:
            self._faults[servo_id] = _Fault(kind, times, delay_s)

    def inject_position_offset(self, servo_id: int, ticks: int) -> None:
        """The servo's encoder reads ``ticks`` off (a glitch): Present Position reports position + ticks."""
        with self._lock:
            servo = self.servos[servo_id]
            servo.offset_ticks = int(ticks)
            servo._sync_present()

    def move_by_hand(self, servo_id: int, ticks: float | None) -> None:
        """A person's hand moves the servo toward ``ticks`` (as far as its hard stops let it) while its torque is
        off, and holds it there; None lets go. A servo with torque on holds against the hand."""
        with self._lock:
            self.servos[servo_id].hand_goal = None if ticks is None else float(ticks)

    def slip_horn(self, servo_id: int) -> None:
        """Fault: the servo's horn slips on its joint, so moving the joint by hand no longer turns the servo."""
        with self._lock:
            self.servos[servo_id].horn_slipped = True

    def position(self, servo_id: int) -> float:
        """Where the servo stands, in ticks (without an injected encoder offset)."""
        with self._lock:
            return self.servos[servo_id].position

    def set_hardware_error(self, servo_id: int, bits: int) -> None:
        """Latch Hardware Error Status bits; the shutdown bits turn torque off, as the firmware does."""
        with self._lock:
            servo = self.servos[servo_id]
            servo.set("hardware_error_status", int(bits))
            if int(bits) & servo.get("shutdown"):
                servo.set("torque_enable", 0)

    # -- lifecycle -------------------------------------------------------
    def start(self) -> "DxlEmulator":
        self._thread = threading.Thread(target=self._run, name="dxl-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():  # (blocked writing to a full terminal): a descriptor it still holds, once
                return  # closed, could be reused by a file it would then read or write; the daemon ends with us
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> "DxlEmulator":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def torque_enabled(self) -> dict[int, bool]:
        with self._lock:
            return {i: s.torque_enabled for i, s in self.servos.items()}

    def status(self) -> dict[int, dict[str, int | bool]]:
        """Per servo: torque, present and goal position (ticks), Bus Watchdog register."""
        names = ("present_position", "goal_position", "bus_watchdog")
        with self._lock:
            return {i: {"torque": s.torque_enabled} | {n: s.get(n) for n in names} for i, s in self.servos.items()}

    # -- the bus ---------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                due = min((t for t, _ in self._outbox), default=None)
            timeout = 0.005 if due is None else max(0.0, min(0.005, due - time.monotonic()))
            try:
                readable, _, _ = select.select([self._master], [], [], timeout)
                if readable:
                    self._buffer += os.read(self._master, 4096)
            except OSError:
                if self._stop.is_set():
                    return
                time.sleep(0.005)  # no client has the port open yet
                continue
            with self._lock:
                self._advance()
                self._received = time.monotonic()  # the bytes just read count as arrived now
                while self._parse_one():
                    pass
                for servo in self.servos.values():  # after the packets that arrived: a late emulator trips nothing
                    servo.check_watchdog(self._received)
                self._flush()

    def _advance(self) -> None:
        now = time.monotonic()
        dt, self._last_step = now - self._last_step, now
        for servo in self.servos.values():
            servo.step(dt)

    def _flush(self) -> None:
        now = time.monotonic()
        for t, data in self._outbox:
            if t <= now:
                os.write(self._master, data)
        self._outbox = [(t, data) for t, data in self._outbox if t > now]

    def _parse_one(self) -> bool:
        """Consume one packet (or garbage) from the buffer; False when more bytes are needed."""
        buf = self._buffer
        start = buf.find(HEADER)
        if start < 0:
            del buf[: max(0, len(buf) - 3)]  # keep a possible partial header
            return False
        del buf[:start]
        if len(buf) < 7:
            return False
        servo_id, length = buf[4], buf[5] | (buf[6] << 8)
        if length < 3 or length > 1024:
            del buf[:1]
            return True
        if len(buf) < 7 + length:
            return False
        packet = bytes(buf[: 7 + length])
        del buf[: 7 + length]
        if crc16(packet[:-2]) != (packet[-2] | (packet[-1] << 8)):
            self.crc_errors += 1
            servo = self.servos.get(servo_id)
            if servo is not None and servo_id not in self._disconnected:
                self._reply(servo, servo.status_error(ERR_CRC), b"")
            return True
        body = unstuff(packet[7:-2])
        self._handle(servo_id, body[0], body[1:])
        return True

    def _reply(self, servo: EmulatedServo, error: int, params: bytes) -> None:
        packet = bytearray(build_packet(servo.servo_id, Instruction.STATUS, bytes([error]) + bytes(params)))
        when = time.monotonic()
        fault = self._faults.get(servo.servo_id)
        if fault is not None:
            if fault.kind == "bad_crc":
                packet[-1] ^= 0xFF
                packet[-2] ^= 0x5A
            else:
                when += fault.delay_s
            if fault.remaining is not None:
                fault.remaining -= 1
                if fault.remaining <= 0:
                    del self._faults[servo.servo_id]
        # status packets leave the bus in order
        when = max([when] + [t for t, _ in self._outbox])
        self._outbox.append((when, bytes(packet)))

    def _handle(self, servo_id: int, instruction: int, params: bytes) -> None:
        self.instructions.append((instruction, servo_id))
        group = {Instruction.SYNC_WRITE: self._sync_write, Instruction.SYNC_READ: self._sync_read}.get(instruction)
        if group is not None:
            return group(params)
        targets = list(self.servos) if servo_id == BROADCAST_ID else [servo_id]
        for target in targets:
            if (servo := self._reached(target)) is None:  # (reaching a servo feeds its Bus Watchdog)
                continue
            error, reply = self._unicast(servo, instruction, params)
            if servo_id != BROADCAST_ID or instruction == Instruction.PING:
                self._reply(servo, error, reply)

    def _reached(self, servo_id: int) -> EmulatedServo | None:
        """The servo an instruction packet reaches (its Bus Watchdog fed), or None: no such servo, or disconnected."""
        servo = self.servos.get(servo_id)
        if servo is None or servo_id in self._disconnected:
            return None
        servo.last_instruction = self._received
        return servo

    def _unicast(self, servo: EmulatedServo, instruction: int, params: bytes) -> tuple[int, bytes]:
        if instruction == Instruction.PING:
            return servo.status_error(), bytes(le_bytes(servo.get("model_number"), 2) + [servo.get("firmware_version")])
        if instruction == Instruction.READ:
            if len(params) != 4:
                return servo.status_error(ERR_DATA_LENGTH), b""
            address, size = params[0] | params[1] << 8, params[2] | params[3] << 8
            if address + size > CONTROL_TABLE_SIZE or size == 0:
                return servo.status_error(ERR_ACCESS), b""
            return servo.status_error(), bytes(servo.table[address : address + size])
        if instruction == Instruction.WRITE:
            if len(params) < 3:
                return servo.status_error(ERR_DATA_LENGTH), b""
            number = servo.write(params[0] | params[1] << 8, params[2:])
            return servo.status_error(number), b""
        if instruction == Instruction.REBOOT:
            servo.set("hardware_error_status", 0)
            servo.set("torque_enable", 0)
            return servo.status_error(), b""
        return servo.status_error(ERR_INSTRUCTION), b""

    def _sync_write(self, params: bytes) -> None:
        if len(params) < 4:
            return
        address, size = params[0] | params[1] << 8, params[2] | params[3] << 8
        data = params[4:]
        for k in range(0, len(data) - size + 1, size + 1):
            servo = self._reached(data[k])
            if servo is not None and (number := servo.write(address, data[k + 1 : k + 1 + size])):
                log.debug("servo %d rejected SYNC_WRITE at %d: error %d", data[k], address, number)

    def _sync_read(self, params: bytes) -> None:
        if len(params) < 5:
            return
        address, size = params[0] | params[1] << 8, params[2] | params[3] << 8
        for target in params[4:]:
            if (servo := self._reached(target)) is None:
                continue
            if address + size > CONTROL_TABLE_SIZE:
                self._reply(servo, servo.status_error(ERR_ACCESS), b"")
            else:
                self._reply(servo, servo.status_error(), bytes(servo.table[address : address + size]))


# -- the emulator as a process of its own --------------------------------------------------------------------------
def _parse_ids(text: str) -> list[int]:
    """``0-15`` or ``0,1,5``."""
    if "-" in text:
        first, last = text.split("-", 1)
        return list(range(int(first), int(last) + 1))
    return [int(i) for i in text.split(",")]


def _command(emu: DxlEmulator, line: str) -> dict:
    """One command of :func:`main`'s standard input; its JSON reply."""
    name, *args = line.split() or [""]
    try:
        if name == "status" and not args:
            return {"servos": emu.status()}
        if name in ("disconnect", "reconnect") and len(args) == 1:
            for sid in emu.servos if args[0] == "all" else [int(args[0])]:
                getattr(emu, name)(sid)
            return {"ok": True}
        if name == "offset" and len(args) == 2:
            emu.inject_position_offset(int(args[0]), int(args[1]))
            return {"ok": True}
    except (KeyError, ValueError) as exc:
        return {"error": f"{line.strip()!r}: {exc!r}"}
    usage = "status | disconnect ID|all | reconnect ID|all | offset ID TICKS"
    return {"error": f"unknown command {line.strip()!r} ({usage})"}


def main(argv: list[str] | None = None) -> int:
    """``python -m tacsplat.drivers.dxl_emulator``: servos on a pty until standard input ends.

    Prints ``{"port": PATH}`` (the pty to connect to, e.g. ``mock_devices.servo_port`` of a rig file), then answers
    each command line with one JSON line: ``status`` (per servo: torque, present and goal position, Bus Watchdog),
    ``disconnect ID|all``, ``reconnect ID|all``, ``offset ID TICKS``.
    """
    parser = argparse.ArgumentParser(prog="python -m tacsplat.drivers.dxl_emulator", description=main.__doc__)
    parser.add_argument("--ids", default="0-15", help="servo ids: FIRST-LAST or a comma-separated list")
    parser.add_argument("--speed", type=float, default=4000.0, help="ticks per second toward the goal")
    args = parser.parse_args(argv)
    try:
        with DxlEmulator(_parse_ids(args.ids), speed_ticks_per_s=args.speed) as emu:
            print(json.dumps({"port": emu.path}), flush=True)
            for line in sys.stdin:
                print(json.dumps(_command(emu, line)), flush=True)
    except KeyboardInterrupt:
        return 130
    return 0


class EmulatorProcess:
    """:func:`main` in a child process (``with EmulatorProcess() as emu:``): :attr:`path` is its port; leaving the
    block kills it (the adapter unplugged)."""

    def __init__(self, ids=range(16), speed_ticks_per_s: float = 4000.0):
        self.ids = [int(i) for i in ids]
        self.speed = float(speed_ticks_per_s)
        self.proc: subprocess.Popen | None = None
        self.path = ""

    def __enter__(self) -> "EmulatorProcess":
        ids = ",".join(map(str, self.ids))
        command = [sys.executable, "-m", "tacsplat.drivers.dxl_emulator", "--ids", ids, "--speed", str(self.speed)]
        self.proc = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            self.path = self._reply()["port"]
        except BaseException:
            self.kill()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.kill()

    def kill(self) -> None:
        """End the process at once (SIGKILL: the pty closes as when the adapter is unplugged)."""
        if self.proc is not None:
            self.proc.kill()  # (nothing when it has ended)
            self.proc.wait()
            self.proc.stdin.close()
            self.proc.stdout.close()

    def _reply(self) -> dict:
        if not (line := self.proc.stdout.readline()):
            raise RuntimeError(f"the servo emulator process ended (exit code {self.proc.wait()})")
        return json.loads(line)

    def send(self, command: str) -> dict:
        """One command of :func:`main`; its reply (an ``error`` raises RuntimeError)."""
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        reply = self._reply()
        if "error" in reply:
            raise RuntimeError(reply["error"])
        return reply

    def status(self) -> dict[int, dict]:
        return {int(i): s for i, s in self.send("status")["servos"].items()}

    def torque_enabled(self) -> dict[int, bool]:
        return {i: s["torque"] for i, s in self.status().items()}


if __name__ == "__main__":
    sys.exit(main())
