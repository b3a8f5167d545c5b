"""The real DynamixelHand and the real dynamixel_sdk against the protocol 2.0 servo emulator on a pty."""

import dataclasses
import json
import logging
import os
import random
import signal
import threading
import time

import dynamixel_sdk as dxl
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from tacsplat.drivers import Hand
from tacsplat.drivers.calibration import RAD_PER_TICK, HandCalibration
from tacsplat.drivers.dxl_emulator import DxlEmulator, crc16, stuff, unstuff
from tacsplat.drivers.dynamixel_hand import DynamixelHand, DynamixelHandConfig, ServoError, _PortHandler
from tacsplat.drivers.dynamixel_table import REGISTERS, HardwareError, Instruction
from tacsplat.errors import ConfigError, HandError, InvalidInputError
from tacsplat.sim.hand import HandKinematics

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(scope="module")
def kinematics():
    return HandKinematics()


@pytest.fixture
def emu():
    with DxlEmulator() as e:
        yield e


# replies within 300 ms: an emulator thread on a loaded 2-core machine missed 100 ms (a U2D2 answers in ~1 ms)
TEST_CONFIG = DynamixelHandConfig(min_packet_timeout_s=0.3, drain_s=0.1)
LATE_S = 0.35  # a reply this late is past the timeout, and inside the drain that follows it


def make_hand(emu, kinematics, **kw):
    return DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG, **kw)


def wait_for(condition, timeout_s=3.0):
    """Poll ``condition`` (a SYNC_WRITE has no status packet, so the emulator applies it asynchronously)."""
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.005)
    return condition()


def assert_all_torque_off(emu, except_ids=()):
    state = emu.torque_enabled()
    assert not any(on for sid, on in state.items() if sid not in except_ids), state


# -- the wire protocol --------------------------------------------------------
def test_emulator_crc_and_stuffing_agree_with_the_sdk():
    ph = dxl.PacketHandler(2.0)
    rng = random.Random(0)
    for _ in range(50):
        data = [rng.randrange(256) for _ in range(rng.randrange(1, 40))]
        assert crc16(data) == ph.updateCRC(0, data, len(data))
    body = bytes([0x03, 0xFF, 0xFF, 0xFD, 0x01, 0xFF, 0xFF, 0xFD])
    stuffed = stuff(body)
    assert stuffed == bytes([0x03, 0xFF, 0xFF, 0xFD, 0xFD, 0x01, 0xFF, 0xFF, 0xFD, 0xFD])
    assert unstuff(stuffed) == body


def test_sdk_packets_with_byte_stuffing_round_trip(emu):
    port, ph = _PortHandler(emu.path, min_timeout_ms=1000.0), dxl.PacketHandler(2.0)  # a busy host's emulator
    assert port.openPort() and port.setBaudRate(4_000_000)  # pyserial accepts 4 Mbps on the pty
    try:
        value = 0xFFFDFFFF  # little endian FF FF FD FF: stuffed in the WRITE and in the READ's status
        assert ph.write4ByteTxRx(port, 3, REGISTERS["homing_offset"].address, value) == (dxl.COMM_SUCCESS, 0)
        assert ph.read4ByteTxRx(port, 3, REGISTERS["homing_offset"].address) == (value, dxl.COMM_SUCCESS, 0)
        assert ph.ping(port, 15) == (1240, dxl.COMM_SUCCESS, 0)
        assert ph.ping(port, 16)[1] == dxl.COMM_RX_TIMEOUT  # no such servo
        assert emu.crc_errors == 0
    finally:
        port.closePort()


# -- normal operation ----------------------------------------------------------
def test_connect_configures_servos_and_exit_disables_torque(emu, kinematics):
    hand = make_hand(emu, kinematics)
    assert isinstance(hand, Hand)
    with hand:
        assert all(emu.torque_enabled().values())
        for servo in emu.servos.values():
            assert servo.get("operating_mode") == 5  # current-based position
            assert servo.get("current_limit") == 350
            assert servo.get("position_p_gain") == 800 and servo.get("position_d_gain") == 200
        q = hand.read_joint_positions()
        np.testing.assert_allclose(q, 0.0, atol=RAD_PER_TICK)  # every servo starts at the centre tick
    assert_all_torque_off(emu)
    assert emu.crc_errors == 0
    pings = [sid for inst, sid in emu.instructions if inst == Instruction.PING]
    assert sorted(set(pings)) == list(range(16))


def test_sync_write_and_sync_read_with_calibration(kinematics, tmp_path):
    names = kinematics.joint_names
    signs = np.where(np.arange(16) % 3 == 0, -1, 1)
    offsets = np.linspace(-0.4, 0.4, 16)
    path = tmp_path / "hand.json"
    path.write_text(
        json.dumps(
            {
                "format": "tacsplat-hand-calibration",
                "version": 1,
                "joints": {n: {"sign": int(s), "offset_rad": float(o)} for n, s, o in zip(names, signs, offsets)},
            }
        )
    )
    limits = kinematics.joint_limits
    target = limits[:, 0] + 0.3 * (limits[:, 1] - limits[:, 0])
    at_zero = dict(enumerate(2048 + offsets / RAD_PER_TICK))  # every joint starts at its zero
    # the packets of each call are counted: no heartbeat (tests/drivers/test_hand_safety.py tests it) may slip in
    quiet = dataclasses.replace(TEST_CONFIG, bus_watchdog_s=0.0)
    with (
        DxlEmulator(initial_ticks=at_zero) as emu,
        DynamixelHand(emu.path, kinematics=kinematics, config=quiet, calibration=path) as hand,
    ):
        np.testing.assert_allclose(hand.read_joint_positions(), 0.0, atol=RAD_PER_TICK)
        n_before = len(emu.instructions)
        hand.command_joint_positions(target)
        expected_ticks = np.rint(2048 + (signs * target + offsets) / (2 * np.pi / 4096))
        goals = lambda: [emu.servos[i].get("goal_position") for i in range(16)]  # noqa: E731
        assert wait_for(lambda: np.array_equal(goals(), expected_ticks)), goals()
        assert [inst for inst, _ in emu.instructions[n_before:]] == [Instruction.SYNC_WRITE]
        deadline = time.monotonic() + 5
        while np.abs(hand.read_joint_positions() - target).max() > RAD_PER_TICK and time.monotonic() < deadline:
            time.sleep(0.05)
        state = hand.read_state()
        np.testing.assert_allclose(state.positions, target, atol=RAD_PER_TICK)
        n_before = len(emu.instructions)
        hand.read_joint_positions()
        assert [inst for inst, _ in emu.instructions[n_before:]] == [Instruction.SYNC_READ]
        poses = hand.fingertip_poses()
        ref = kinematics.fingertip_poses(hand.read_joint_positions())
        for finger in kinematics.finger_names:
            np.testing.assert_allclose(poses[finger], ref[finger])
        hand.close()
        assert_all_torque_off(emu)


def test_clamping_is_logged_not_silent(emu, kinematics, caplog):
    with make_hand(emu, kinematics) as hand:
        q = np.zeros(16)
        q[5] = 10.0  # middle_1 far above its limit
        with caplog.at_level(logging.WARNING):
            hand.command_joint_positions(q)
        assert "middle_1 +10.0000 -> +1.6100" in caplog.text
        hi_ticks = hand.calibration.ticks_from_radians(kinematics.joint_limits[:, 1])[5]
        assert wait_for(lambda: emu.servos[5].get("goal_position") == hi_ticks)
        with pytest.raises(InvalidInputError, match="index_2"):
            hand.command_joint_positions(np.where(np.arange(16) == 2, np.nan, 0.0))
        with pytest.raises(InvalidInputError, match="shape"):
            hand.command_joint_positions(np.zeros(15))


def test_calibration_file_round_trip_and_bad_file_names_the_key(tmp_path, kinematics, emu):
    names = kinematics.joint_names
    cal = HandCalibration(tuple(names), np.where(np.arange(16) < 8, 1.0, -1.0), np.linspace(-1, 1, 16))
    cal.save(tmp_path / "good.json")
    loaded = HandCalibration.load(tmp_path / "good.json", names)
    np.testing.assert_array_equal(loaded.signs, cal.signs)
    np.testing.assert_array_equal(loaded.offsets_rad, cal.offsets_rad)
    ticks = np.arange(1000, 3000, 125)
    np.testing.assert_array_equal(loaded.ticks_from_radians(loaded.radians_from_ticks(ticks)), ticks)
    path = tmp_path / "cal.json"
    path.write_text(
        json.dumps(
            {
                "format": "tacsplat-hand-calibration",
                "version": 1,
                "joints": {n: {"sign": 1, "offset_rad": 0.0} for n in kinematics.joint_names}
                | {"ring_2": {"sign": 0, "offset_rad": 0.0}},
            }
        )
    )
    with pytest.raises(ConfigError, match="joints.ring_2.sign"):
        make_hand(emu, kinematics, calibration=path)


# -- faults: each ends in a clear HandError and torque off on the servos that answer
def test_missing_servo_refuses_to_move(emu, kinematics):
    emu.disconnect(7)
    with pytest.raises(ServoError, match=r"servo 7 \(middle_3\).*PING.*COMM_RX_TIMEOUT.*refusing to move") as exc:
        with make_hand(emu, kinematics):
            pass
    assert exc.value.servo_id == 7 and exc.value.comm_result == dxl.COMM_RX_TIMEOUT
    assert_all_torque_off(emu)
    assert not any(inst == Instruction.SYNC_WRITE for inst, _ in emu.instructions)  # never commanded a goal


def test_servo_that_stops_answering_raises_and_disables_torque(emu, kinematics):
    with make_hand(emu, kinematics) as hand:
        emu.disconnect(9)
        with pytest.raises(
            ServoError, match=r"servo 9 \(ring_1\): SYNC_READ .*COMM_RX_TIMEOUT.* after 3 attempts"
        ) as exc:
            hand.read_joint_positions()  # never the previous values
        assert exc.value.instruction.startswith("SYNC_READ")
        assert "torque off NOT confirmed on servo 9 (ring_1): cut the servo power (confirmed on the other 15)" in str(
            exc.value
        )
        assert_all_torque_off(emu, except_ids=[9])
        with pytest.raises(HandError, match="faulted"):
            hand.command_joint_positions(np.zeros(16))


def test_torque_off_tries_a_silent_servo_twice_and_a_dead_bus_once_per_servo(emu, kinematics):
    """Each servo that does not confirm gets a second try, until two in a row have not: the bus is dead, and the
    rest get one try each (every try waits out the timeout)."""
    for silent, tries in [((3, 9), [2 if sid in (3, 9) else 1 for sid in range(16)]), (range(16), [2, 2] + [1] * 14)]:
        with make_hand(emu, kinematics) as hand:
            for sid in silent:
                emu.disconnect(sid)
            emu.instructions.clear()
            hand.close()
            writes = [sid for inst, sid in emu.instructions if inst == Instruction.WRITE]
            assert [writes.count(sid) for sid in range(16)] == tries
            assert hand.torque_off_report.unconfirmed == tuple(hand._names([sid]) for sid in silent)
        for sid in silent:
            emu.reconnect(sid)


def test_corrupted_crc_raises_after_retries(emu, kinematics):
    with make_hand(emu, kinematics) as hand:
        emu.inject(4, "bad_crc")
        with pytest.raises(ServoError, match=r"servo 4 \(middle_0\).*COMM_RX_CORRUPT") as exc:
            hand.read_joint_positions()
        assert exc.value.comm_result == dxl.COMM_RX_CORRUPT
        assert_all_torque_off(emu)  # the corrupted servo still obeyed the torque-off write


def test_transient_corrupted_crc_is_retried(emu, kinematics, caplog):
    with make_hand(emu, kinematics) as hand:
        emu.inject(4, "bad_crc", times=1)
        with caplog.at_level(logging.WARNING):
            q = hand.read_joint_positions()
        assert "COMM_RX_CORRUPT" in caplog.text and "attempt 1 of 3" in caplog.text
        np.testing.assert_allclose(q, 0.0, atol=RAD_PER_TICK)
        assert all(emu.torque_enabled().values())


def test_hardware_error_bits_are_decoded(emu, kinematics):
    with make_hand(emu, kinematics) as hand:
        emu.set_hardware_error(12, HardwareError.OVERLOAD | HardwareError.OVERHEATING)
        with pytest.raises(ServoError, match=r"servo 12 \(thumb_0\).*hardware alert.*overheating, overload") as exc:
            hand.read_joint_positions()
        assert exc.value.hardware_error == int(HardwareError.OVERLOAD | HardwareError.OVERHEATING)
        assert_all_torque_off(emu)


def test_reply_after_the_timeout(emu, kinematics):
    with make_hand(emu, kinematics) as hand:
        # once: retried after a drain, and the read recovers
        emu.inject(2, "late", times=1, delay_s=LATE_S)
        q = np.full(16, 0.2)
        hand.command_joint_positions(q)
        time.sleep(0.3)
        np.testing.assert_allclose(hand.read_joint_positions(), 0.2, atol=RAD_PER_TICK)
        # always late: a clear error
        emu.inject(2, "late", delay_s=LATE_S)
        with pytest.raises(ServoError, match=r"servo 2 \(index_2\).*COMM_RX_TIMEOUT"):
            hand.read_joint_positions()
        assert_all_torque_off(emu)


def test_exception_inside_the_block_leaves_torque_off(emu, kinematics):
    with pytest.raises(RuntimeError, match="operator error"):
        with make_hand(emu, kinematics) as hand:
            hand.command_joint_positions(np.full(16, 0.1))
            raise RuntimeError("operator error")
    assert_all_torque_off(emu)


def _signal_reached_the_test(signum, frame):
    raise RuntimeError(f"{signal.Signals(signum).name} reached the test: the hand did not handle it")


@pytest.mark.parametrize(
    "signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT], ids=lambda s: signal.Signals(s).name
)
def test_an_ending_signal_leaves_torque_off(emu, kinematics, signum):
    previous = {s: signal.signal(s, _signal_reached_the_test) for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)}
    try:
        before = {s: signal.getsignal(s) for s in (signal.SIGINT, *previous)}
        reads = []
        with pytest.raises(KeyboardInterrupt) as exc:
            with make_hand(emu, kinematics) as hand:
                threading.Timer(0.2, os.kill, (os.getpid(), signum)).start()
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline:  # a capture loop, interrupted mid-exchange or between
                    reads.append(hand.read_joint_positions())
        assert exc.value.signum == signum  # SignalInterrupt: the exit code is 128 + signum
        assert len(reads) > 1
        assert_all_torque_off(emu)
        assert hand.torque_off_report.confirmed
        assert {s: signal.getsignal(s) for s in before} == before  # every handler restored
        assert hand._port is None  # port closed
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def test_missing_port_is_a_clear_error(kinematics):
    with pytest.raises(HandError, match="cannot open serial port.*dialout"):
        with DynamixelHand("/dev/ttyUSB_tacsplat_missing", kinematics=kinematics, config=TEST_CONFIG):
            pass


def test_unplugged_adapter_is_a_clear_error(emu, kinematics):
    hand = make_hand(emu, kinematics)
    hand.connect()
    emu.stop()  # the U2D2 disappears: the pty's other end is gone
    with pytest.raises(
        HandError,
        match=r"port /dev/.*SYNC_READ.*serial port error.*"
        r"torque off NOT confirmed on any of the 16 servos: cut the servo power",
    ):
        hand.read_joint_positions()
    hand.close()  # never raises: it is what runs on the way out


def test_latched_hardware_error_at_connect_refuses(emu, kinematics):
    emu.set_hardware_error(14, HardwareError.INPUT_VOLTAGE)
    with pytest.raises(ServoError, match=r"servo 14 \(thumb_2\): PING .*input voltage"):
        with make_hand(emu, kinematics):
            pass
    assert_all_torque_off(emu)


# -- connect holds the present pose: it never moves a servo more than the tolerance
TOLERANCE_RAD = TEST_CONFIG.connect_tolerance_rad


def write_hand_json(path, names, signs, offsets):
    path.write_text(
        json.dumps(
            {
                "format": "tacsplat-hand-calibration",
                "version": 1,
                "joints": {n: {"sign": s, "offset_rad": o} for n, s, o in zip(names, signs, offsets)},
            }
        )
    )
    return path


def goal_ticks(emu):
    return {sid: servo.get("goal_position") for sid, servo in emu.servos.items()}


def test_connect_tolerance_is_a_few_degrees_and_checked():
    assert 0 < DynamixelHandConfig().connect_tolerance_rad <= np.radians(10)
    for bad in (-0.01, np.nan, 1.0):
        with pytest.raises(ConfigError, match=r"connect_tolerance_rad: .*\[0, 0\.2\]"):
            DynamixelHandConfig(connect_tolerance_rad=bad)


@pytest.mark.parametrize("offset", [45.0, 1e9])
def test_reported_calibration_is_refused_before_the_bus(emu, kinematics, tmp_path, offset):
    """The issue: offset_rad 45 (or 1e9) for index_0 wrote goal tick 31077 (or a wrapped int32) at connect."""
    offsets = np.where(np.arange(16) == 0, offset, 0.0)
    path = write_hand_json(tmp_path / "hand.json", kinematics.joint_names, [1] * 16, offsets.tolist())
    with pytest.raises(ConfigError, match=r"hand\.json: joints\.index_0\.offset_rad: .*\[-pi, pi\]"):
        make_hand(emu, kinematics, calibration=path).connect()
    assert emu.instructions == []  # nothing reached the bus
    assert set(goal_ticks(emu).values()) == {2048}


def test_calibration_that_maps_the_pose_outside_the_limits_is_refused_with_torque_off(emu, kinematics, tmp_path):
    """A wrong offset (index_0) or sign (index_1) inside +-pi: the hand stands still, torque off, one clear error."""
    signs, offsets = np.ones(16, dtype=int), np.zeros(16)
    offsets[0] = 1.0  # index_0 at the centre tick reads -1.0 rad, 0.53 rad below its limit
    emu.servos[1].position = 2048 + 1.0 / RAD_PER_TICK  # index_1 really at +1.0 rad ...
    signs[1] = -1  # ... read as -1.0 rad
    path = write_hand_json(tmp_path / "hand.json", kinematics.joint_names, signs.tolist(), offsets.tolist())
    hand = make_hand(emu, kinematics, calibration=path)
    with pytest.raises(ServoError) as exc:
        with hand:
            pass
    message = str(exc.value)
    assert exc.value.joint == "index_0" and exc.value.servo_id == 0
    for expected in (
        "index_0",
        "offset_rad +1.0000",
        "sign +1",
        "index_1",
        "sign -1",
        str(path),
        "check the sign and offset_rad",
        "move the finger by hand",
        "torque off confirmed on all 16 servos",
    ):
        assert expected in message, (expected, message)
    assert_all_torque_off(emu)
    assert set(goal_ticks(emu).values()) == {2048}  # nothing written
    assert emu.servos[0].position == 2048 and emu.servos[1].position == 2048 + 1.0 / RAD_PER_TICK  # nothing moved
    assert not any(inst == Instruction.SYNC_WRITE for inst, _ in emu.instructions)
    assert hand._port is None


def test_finger_far_outside_its_range_at_connect_is_refused(kinematics):
    lower = kinematics.joint_limits[1, 0]  # index_1, 0.2 rad below its range with the identity calibration
    with DxlEmulator(initial_ticks={1: 2048 + (lower - 0.2) / RAD_PER_TICK}) as emu:
        with pytest.raises(ServoError, match=r"index_1 .*outside its limits.*move the finger by hand"):
            with make_hand(emu, kinematics):
                pass
        assert_all_torque_off(emu)
        assert goal_ticks(emu)[1] == round(2048 + (lower - 0.2) / RAD_PER_TICK)


SEAM_OFFSET_RAD = 2.6  # index_1's zero at tick ~3743: its range [-0.196, 1.61] rad spans ticks ~3615..4794


def _one_turn_tick(motor_rad: float) -> int:
    """What an X-series servo reports after power-on: its position within one turn, ticks 0..4095."""
    return round(motor_rad / RAD_PER_TICK + 2048) % 4096


@pytest.mark.parametrize("q", [0.3, 1.0])
def test_a_calibration_across_the_tick_seam_is_refused_naming_the_seam(kinematics, q):
    """index_1's range crosses the 4095/0 seam: resting at q = 0.3 it reads right, at q = 1.0 (beyond the seam,
    read a turn off after power-on) the refusal names the seam as a cause and what to do, with torque off."""
    offsets = np.where(np.arange(16) == 1, SEAM_OFFSET_RAD, 0.0)
    calibration = HandCalibration(tuple(kinematics.joint_names), np.ones(16), offsets)
    tick = _one_turn_tick(q + SEAM_OFFSET_RAD)
    with DxlEmulator(initial_ticks={1: tick}) as emu:
        hand = make_hand(emu, kinematics, calibration=calibration)
        if q < 0.5:
            with hand:
                assert abs(hand.read_joint_positions()[1] - q) < 0.01
            return
        with pytest.raises(ServoError) as exc:
            with hand:
                pass
        assert_all_torque_off(emu)
    message = str(exc.value)
    for expected in ("index_1", f"tick {tick}", "4095/0 tick seam", "a turn off", "Homing Offset", "re-seat"):
        assert expected in message, (expected, message)


def test_a_calibration_clear_of_the_seam_gets_no_seam_note(emu, kinematics, tmp_path):
    signs, offsets = np.ones(16, dtype=int), np.zeros(16)
    offsets[0] = 1.0  # wrong, but index_0's range stays within one turn
    path = write_hand_json(tmp_path / "hand.json", kinematics.joint_names, signs.tolist(), offsets.tolist())
    with pytest.raises(ServoError) as exc:
        with make_hand(emu, kinematics, calibration=path):
            pass
    assert "seam" not in str(exc.value)


def test_pose_just_outside_the_limits_is_nudged_within_the_tolerance_and_logged(kinematics, caplog):
    lower = kinematics.joint_limits[1, 0]  # index_1
    present = round(2048 + (lower - 0.5 * TOLERANCE_RAD) / RAD_PER_TICK)
    with DxlEmulator(initial_ticks={1: present}) as emu:
        with caplog.at_level(logging.WARNING):
            with make_hand(emu, kinematics):
                goals = goal_ticks(emu)
                assert all(emu.torque_enabled().values())
        assert goals == {sid: (round(2048 + lower / RAD_PER_TICK) if sid == 1 else 2048) for sid in range(16)}
        assert abs(goals[1] - present) * RAD_PER_TICK <= TOLERANCE_RAD
    assert "present pose clamped to joint limits: index_1" in caplog.text


def test_reconnect_after_a_fault_holds_where_the_fingers_now_are(emu, kinematics):
    """After a fault the goal registers still hold the last command; reconnecting must not go back there."""
    with make_hand(emu, kinematics) as hand:
        hand.command_joint_positions(np.full(16, 0.3))
        assert wait_for(lambda: all(abs(s.position - (2048 + 0.3 / RAD_PER_TICK)) < 1 for s in emu.servos.values()))
        emu.disconnect(9)
        with pytest.raises(ServoError):
            hand.read_joint_positions()
        emu.reconnect(9)
        emu.servos[5].position = 2048 + 1.2 / RAD_PER_TICK  # torque off: the operator bends middle_1 to 1.2 rad
        hand.connect()  # reconnect
        assert all(emu.torque_enabled().values())
        present = {sid: round(servo.position) for sid, servo in emu.servos.items()}
        assert goal_ticks(emu) == present
        time.sleep(0.1)
        np.testing.assert_allclose(hand.read_joint_positions()[5], 1.2, atol=RAD_PER_TICK)
    assert_all_torque_off(emu)


def test_command_refuses_bad_input_without_touching_the_bus(emu, kinematics):
    bad_inputs = {
        "a string": "0.1",
        "strings": ["0.1"] * 16,
        "an object array": np.full(16, 0.1, dtype=object),
        "a ragged list": [[0.1] * 8, [0.1] * 7],
        "15 values": np.zeros(15),
        "a matrix": np.zeros((4, 4)),
        "NaN": np.where(np.arange(16) == 3, np.nan, 0.0),
        "inf": np.where(np.arange(16) == 3, -np.inf, 0.0),
        "booleans": [True] * 16,
        "complex numbers": np.full(16, 0.1 + 0.1j),
        "None": None,
    }
    with make_hand(emu, kinematics) as hand:
        goals, n_before = goal_ticks(emu), len(emu.instructions)
        for what, q in bad_inputs.items():
            with pytest.raises(InvalidInputError, match=r"^command_joint_positions: q "):
                hand.command_joint_positions(q)
        assert len(emu.instructions) == n_before
        assert goal_ticks(emu) == goals and all(emu.torque_enabled().values())
        hand.command_joint_positions([0.1] * 16)  # a list of floats is fine, and the hand still works


@st.composite
def hand_calibration_cases(draw):
    """A true calibration with every joint inside its range, and up to three faults in the file or the pose."""
    n = 16
    true_signs = draw(st.lists(st.sampled_from([1, -1]), min_size=n, max_size=n))
    true_offsets = draw(st.lists(st.floats(-np.pi, np.pi), min_size=n, max_size=n))
    fractions = draw(st.lists(st.floats(0.0, 1.0), min_size=n, max_size=n))  # where each joint stands in its range
    file_signs, file_offsets, edge_excess, moved_ticks = list(true_signs), list(true_offsets), {}, {}
    for joint in draw(st.lists(st.integers(0, n - 1), max_size=3, unique=True)):
        fault = draw(st.sampled_from(["offset", "sign", "edge", "moved"]))
        if fault == "offset":
            file_offsets[joint] = draw(
                st.floats(-np.pi, np.pi)
                | st.floats(allow_nan=True, allow_infinity=True)
                | st.sampled_from([45.0, 1e9, -4.0])
            )
        elif fault == "sign":
            file_signs[joint] = draw(st.sampled_from([-true_signs[joint], 0, 2, True, "1", 1.0]))
        elif fault == "edge":  # just outside the range, either side: inside or beyond the tolerance
            edge_excess[joint] = draw(st.floats(-0.2, 0.2))
        else:  # moved by hand while torque was off: anywhere in the servo's turn
            moved_ticks[joint] = draw(st.integers(0, 4095))
    return true_signs, true_offsets, fractions, file_signs, file_offsets, edge_excess, moved_ticks


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(case=hand_calibration_cases())
def test_connect_refuses_with_torque_off_or_moves_no_servo_beyond_the_tolerance(kinematics, tmp_path_factory, case):
    true_signs, true_offsets, fractions, file_signs, file_offsets, edge_excess, moved_ticks = case
    lo, hi = kinematics.joint_limits.T
    q = lo + np.asarray(fractions) * (hi - lo)
    for joint, excess in edge_excess.items():
        q[joint] = hi[joint] + excess if excess > 0 else lo[joint] + excess
    ticks = np.rint((np.asarray(true_signs) * q + np.asarray(true_offsets)) / RAD_PER_TICK + 2048).astype(int)
    ticks = ticks % 4096  # after power-up a servo reports its position within one turn
    for joint, t in moved_ticks.items():
        ticks[joint] = t
    path = write_hand_json(
        tmp_path_factory.mktemp("cal") / "hand.json", kinematics.joint_names, file_signs, file_offsets
    )

    file_is_valid = all(not isinstance(s, (bool, str)) and s in (1, -1) for s in file_signs) and all(
        np.isfinite(o) and abs(o) <= np.pi for o in file_offsets
    )
    if file_is_valid:  # the calibration's reading of where each joint stands, and how far outside its range
        read = np.asarray(file_signs) * ((ticks - 2048) * RAD_PER_TICK - np.asarray(file_offsets))
        excess = np.maximum(np.maximum(lo - read, read - hi), 0.0).max()

    with DxlEmulator(initial_ticks=dict(enumerate(ticks.tolist()))) as emu:
        try:
            with make_hand(emu, kinematics, calibration=path):
                goals = np.array([emu.servos[sid].get("goal_position") for sid in range(16)])
                assert all(emu.torque_enabled().values())
        except ConfigError:
            event("refused: bad calibration file")
            assert not file_is_valid, file_signs
            assert emu.instructions == []  # refused before the bus
        except HandError:
            event("refused at connect")
            assert file_is_valid and excess > TOLERANCE_RAD - RAD_PER_TICK, excess
            assert_all_torque_off(emu)
            assert [emu.servos[sid].get("goal_position") for sid in range(16)] == ticks.tolist()
        else:
            event("connected" + (", a joint clamped" if excess > 0 else ""))
            assert file_is_valid and excess < TOLERANCE_RAD + RAD_PER_TICK, excess
            assert np.abs(goals - ticks).max() * RAD_PER_TICK <= TOLERANCE_RAD
            assert_all_torque_off(emu)


def test_hand_state_timestamps_are_monotonic_a_wall_clock_step_does_not_move(emu, kinematics, monkeypatch):
    with make_hand(emu, kinematics) as hand:
        first = hand.read_state().timestamp
        wall = time.time
        monkeypatch.setattr(time, "time", lambda: wall() - 5.0)  # NTP steps the wall clock back
        before = time.monotonic()
        later = hand.read_state().timestamp
        assert first <= before <= later <= time.monotonic()
