"""Dynamixel X-series control table (protocol 2.0), error bits and their decoding.

Addresses and sizes follow the ROBOTIS e-Manual for the X-series (XC330, XL330,
XM430, ...), which share one layout. Shared by the hand driver and the servo
emulator the tests drive it with, so that both speak the same table.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag

MODEL_XC330_M288 = 1240  # LEAP Hand servo


class OperatingMode(IntEnum):
    CURRENT = 0
    VELOCITY = 1
    POSITION = 3
    EXTENDED_POSITION = 4
    CURRENT_BASED_POSITION = 5
    PWM = 16


class HardwareError(IntFlag):
    """Bits of the Hardware Error Status register (address 70)."""

    INPUT_VOLTAGE = 1 << 0
    OVERHEATING = 1 << 2
    MOTOR_ENCODER = 1 << 3
    ELECTRICAL_SHOCK = 1 << 4
    OVERLOAD = 1 << 5


# the Shutdown register's factory value: the hardware errors that turn torque off
SHUTDOWN_FACTORY = int(HardwareError.OVERHEATING | HardwareError.ELECTRICAL_SHOCK | HardwareError.OVERLOAD)


@dataclass(frozen=True)
class Register:
    name: str
    address: int
    size: int  # bytes: 1, 2 or 4, little endian
    writable: bool = True  # (the EEPROM area, below EEPROM_END, only while torque is off)
    signed: bool = False
    initial: int = 0  # the factory value (the e-Manual's, an XC330-M288's where models differ)


REGISTERS = {
    r.name: r
    for r in (
        Register("model_number", 0, 2, writable=False, initial=MODEL_XC330_M288),
        Register("model_information", 2, 4, writable=False),
        Register("firmware_version", 6, 1, writable=False, initial=52),
        Register("id", 7, 1),
        Register("baud_rate", 8, 1, initial=6),
        Register("return_delay_time", 9, 1),
        Register("drive_mode", 10, 1),
        Register("operating_mode", 11, 1, initial=OperatingMode.POSITION),
        Register("secondary_id", 12, 1),
        Register("protocol_type", 13, 1, initial=2),
        Register("homing_offset", 20, 4, signed=True),
        Register("moving_threshold", 24, 4),
        Register("temperature_limit", 31, 1, initial=70),
        Register("max_voltage_limit", 32, 2, initial=70),
        Register("min_voltage_limit", 34, 2, initial=35),
        Register("pwm_limit", 36, 2, initial=885),
        Register("current_limit", 38, 2, initial=1750),
        Register("velocity_limit", 44, 4, initial=445),
        Register("max_position_limit", 48, 4, initial=4095),
        Register("min_position_limit", 52, 4),
        Register("shutdown", 63, 1, initial=SHUTDOWN_FACTORY),
        Register("torque_enable", 64, 1),
        Register("led", 65, 1),
        Register("status_return_level", 68, 1, initial=2),
        Register("registered_instruction", 69, 1, writable=False),
        Register("hardware_error_status", 70, 1, writable=False),
        Register("velocity_i_gain", 76, 2),
        Register("velocity_p_gain", 78, 2),
        Register("position_d_gain", 80, 2),
        Register("position_i_gain", 82, 2),
        Register("position_p_gain", 84, 2, initial=400),
        Register("bus_watchdog", 98, 1, signed=True),  # 0 off, 1..127 on (unit BUS_WATCHDOG_UNIT_S), -1 tripped
        Register("goal_pwm", 100, 2, signed=True),
        Register("goal_current", 102, 2, signed=True),
        Register("goal_velocity", 104, 4, signed=True),
        Register("profile_acceleration", 108, 4),
        Register("profile_velocity", 112, 4),
        Register("goal_position", 116, 4, signed=True),
        Register("realtime_tick", 120, 2, writable=False),
        Register("moving", 122, 1, writable=False),
        Register("moving_status", 123, 1, writable=False),
        Register("present_pwm", 124, 2, writable=False, signed=True),
        Register("present_current", 126, 2, writable=False, signed=True),
        Register("present_velocity", 128, 4, writable=False, signed=True),
        Register("present_position", 132, 4, writable=False, signed=True),
        Register("present_input_voltage", 144, 2, writable=False, initial=50),
        Register("present_temperature", 146, 1, writable=False, initial=30),
    )
}

CONTROL_TABLE_SIZE = 147  # bytes: addresses 0 .. 146
EEPROM_END = 64  # addresses below this are EEPROM

BUS_WATCHDOG_UNIT_S = 0.02  # Bus Watchdog (98): its unit, 20 ms; 1..127 arms it
BUS_WATCHDOG_TRIPPED = -1  # the Bus Watchdog Error state: goal values are read-only until 0 is written
GOAL_REGISTERS = ("goal_pwm", "goal_current", "goal_velocity", "goal_position")  # read-only while tripped

TICKS_PER_REV = 4096  # X-series position resolution
CENTRE_TICK = 2048  # the middle of one turn; motor angle 0 rad


# The status packet's error byte: bit 7 = alert (a hardware error is latched),
# bits 0-6 = the processing error number.
ALERT_BIT = 0x80
STATUS_ERROR_NAMES = {
    1: "result fail",
    2: "instruction error",
    3: "CRC error",
    4: "data range error",
    5: "data length error",
    6: "data limit error",
    7: "access error",
}


class Instruction(IntEnum):
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REBOOT = 0x08
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83


def decode_hardware_error(bits: int) -> list[str]:
    """Names of the bits set in a Hardware Error Status value (unknown bits as 'bit N')."""
    names = [flag.name.lower().replace("_", " ") for flag in HardwareError if bits & flag]
    return names + [f"bit {i}" for i in range(8) if bits & ~sum(HardwareError) & (1 << i)]


def decode_status_error(error: int) -> list[str]:
    """Names of the problems in a status packet's error byte."""
    number = error & ~ALERT_BIT
    alert = ["hardware alert"] if error & ALERT_BIT else []
    return alert + ([STATUS_ERROR_NAMES.get(number, f"unknown error {number}")] if number else [])


def to_signed(value: int, size: int) -> int:
    bits = 8 * size
    value = int(value) & ((1 << bits) - 1)
    return value - (1 << bits) if value >= 1 << (bits - 1) else value


def le_bytes(value: int, size: int) -> list[int]:
    """Little-endian bytes of ``value`` (two's complement for negatives)."""
    return list((int(value) & ((1 << (8 * size)) - 1)).to_bytes(size, "little"))
