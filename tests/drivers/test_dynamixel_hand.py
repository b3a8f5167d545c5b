"""The real DynamixelHand and the real dynamixel_sdk against the protocol 2.0 servo emulator on a pty."""

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

from tacsplat.drivers import DynamixelHand, Hand, HandCalibration
from tacsplat.drivers.calibration import RAD_PER_TICK
from tacsplat.drivers.dxl_emulator import DxlEmulator, crc16, stuff, unstuff
from tacsplat.drivers.dynamixel_hand import DynamixelHandConfig, ServoError
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


# replies within 100 ms: generous for an emulator thread on a loaded CI machine (a U2D2 answers in ~1 ms)
TEST_CONFIG = DynamixelHandConfig(min_packet_timeout_s=0.1, drain_s=0.1)
LATE_S = 0.15  # a reply this late is past the timeout, and inside the drain that follows it


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
    port, ph = dxl.PortHandler(emu.path), dxl.PacketHandler(2.0)
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


def test_sync_write_and_sync_read_with_calibration(emu, kinematics, tmp_path):
    names = kinematics.joint_names
    signs = np.where(np.arange(16) % 3 == 0, -1, 1)
    offsets = np.linspace(-0.4, 0.4, 16)
    path = tmp_path / "hand.json"
    path.write_text(json.dumps({
        "format": "tacsplat-hand-calibration", "version": 1,
        "joints": {n: {"sign": int(s), "offset_rad": float(o)} for n, s, o in zip(names, signs, offsets)},
    }))
    limits = kinematics.joint_limits
    target = limits[:, 0] + 0.3 * (limits[:, 1] - limits[:, 0])
    with make_hand(emu, kinematics, calibration=path) as hand:
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
    path.write_text(json.dumps({"format": "tacsplat-hand-calibration", "version": 1,
                                "joints": {n: {"sign": 1, "offset_rad": 0.0} for n in kinematics.joint_names}
                                | {"ring_2": {"sign": 0, "offset_rad": 0.0}}}))
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
        with pytest.raises(ServoError, match=r"servo 9 \(ring_1\): SYNC_READ .*COMM_RX_TIMEOUT.* after 3 attempts") as exc:
            hand.read_joint_positions()  # never the previous values
        assert exc.value.instruction.startswith("SYNC_READ")
        assert "torque disabled on servos [0, 1, 2, 3, 4, 5, 6, 7, 8, 10, 11, 12, 13, 14, 15], " \
               "not confirmed by 9 (ring_1)" in str(exc.value)
        assert_all_torque_off(emu, except_ids=[9])
        with pytest.raises(HandError, match="faulted"):
            hand.command_joint_positions(np.zeros(16))


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


def test_sigint_leaves_torque_off(emu, kinematics):
    previous = signal.getsignal(signal.SIGINT)
    reads = []
    with pytest.raises(KeyboardInterrupt):
        with make_hand(emu, kinematics) as hand:
            threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGINT)).start()
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:  # a capture loop, interrupted mid-exchange or between
                reads.append(hand.read_joint_positions())
    assert len(reads) > 1
    assert_all_torque_off(emu)
    assert signal.getsignal(signal.SIGINT) is previous
    assert hand._port is None  # port closed


def test_missing_port_is_a_clear_error(kinematics):
    with pytest.raises(HandError, match="cannot open serial port.*dialout"):
        with DynamixelHand("/dev/ttyUSB_tacsplat_missing", kinematics=kinematics, config=TEST_CONFIG):
            pass


def test_unplugged_adapter_is_a_clear_error(emu, kinematics):
    hand = make_hand(emu, kinematics)
    hand.connect()
    emu.stop()  # the U2D2 disappears: the pty's other end is gone
    with pytest.raises(HandError, match=r"port /dev/.*SYNC_READ.*serial port error.*no servo confirmed torque off"):
        hand.read_joint_positions()
    hand.close()  # never raises: it is what runs on the way out


def test_latched_hardware_error_at_connect_refuses(emu, kinematics):
    emu.set_hardware_error(14, HardwareError.INPUT_VOLTAGE)
    with pytest.raises(ServoError, match=r"servo 14 \(thumb_2\): PING .*input voltage"):
        with make_hand(emu, kinematics):
            pass
    assert_all_torque_off(emu)


def test_pose_outside_the_limits_at_connect_is_clamped_and_logged(kinematics, caplog):
    lower = kinematics.joint_limits[1, 0]  # index_1
    outside = 2048 + (lower - 0.2) / RAD_PER_TICK
    with DxlEmulator(initial_ticks={1: outside}) as emu:
        with caplog.at_level(logging.WARNING):
            with make_hand(emu, kinematics):
                goal = round(2048 + lower / RAD_PER_TICK)
                assert wait_for(lambda: emu.servos[1].get("goal_position") == goal)
    assert "present pose clamped to joint limits: index_1" in caplog.text
