"""What stops the hand when its process cannot: the servos' Bus Watchdog (emulated as the firmware has it), the
driver's heartbeat that feeds it and notices it trip, the guard process after SIGKILL; a reading no joint can
reach is a fault; a signal during the torque-off waits for it. On the servo emulator over a pty (in this process,
or in its own where the hand's process is killed or stopped)."""

import json
import os
import re
import signal
import subprocess
import sys
import time

import dynamixel_sdk as dxl
import numpy as np
import pytest

from tacsplat.drivers import dynamixel_hand
from tacsplat.drivers.calibration import RAD_PER_TICK
from tacsplat.drivers.dxl_emulator import ERR_DATA_RANGE, DxlEmulator, EmulatorProcess
from tacsplat.drivers.dynamixel_hand import DynamixelHand, DynamixelHandConfig, ServoError, SignalInterrupt
from tacsplat.drivers.dynamixel_table import REGISTERS
from tacsplat.errors import ConfigError, HandError
from tacsplat.sim.hand import HandKinematics

pytestmark = pytest.mark.timeout(120)

# a status timeout of 0.4 s: the emulator shares a host that may be busy (a real servo answers in 1 ms)
TEST_CONFIG = DynamixelHandConfig(min_packet_timeout_s=0.4, drain_s=0.1)
WATCHDOG = REGISTERS["bus_watchdog"].address
GOAL = REGISTERS["goal_position"].address
TORQUE = REGISTERS["torque_enable"].address


@pytest.fixture(scope="module")
def kinematics():
    return HandKinematics()


@pytest.fixture
def emu():
    with DxlEmulator() as e:
        yield e


def poll(condition, what: str, timeout_s: float = 20.0):
    """``condition()`` once it is true, polled until a generous deadline (a loaded machine)."""
    deadline = time.monotonic() + timeout_s
    while not (value := condition()):
        assert time.monotonic() < deadline, f"not within {timeout_s} s: {what}"
        time.sleep(0.02)
    return value


def sdk_port(path: str):
    """The SDK on the emulator's pty, with a status timeout of 1 s: the emulator is a thread or process of a host
    that may be busy, where a servo answers within a millisecond (the SDK's own timeout is ~34 ms)."""
    port, ph = dynamixel_hand._PortHandler(path, min_timeout_ms=1000.0), dxl.PacketHandler(2.0)
    assert port.setBaudRate(4_000_000)
    return port, ph


# -- the emulated Bus Watchdog ------------------------------------------------------------------------------------
def test_emulated_bus_watchdog_stops_a_silent_servo_and_locks_its_goal(emu):
    port, ph = sdk_port(emu.path)
    try:
        assert ph.write1ByteTxRx(port, 1, WATCHDOG, 200) == (dxl.COMM_SUCCESS, ERR_DATA_RANGE)  # -56: not 0..127
        for sid in (1, 2):
            assert ph.write1ByteTxRx(port, sid, WATCHDOG, 5) == (dxl.COMM_SUCCESS, 0)  # 100 ms
            assert ph.write1ByteTxRx(port, sid, TORQUE, 1) == (dxl.COMM_SUCCESS, 0)
        assert ph.write4ByteTxRx(port, 1, GOAL, 3500) == (dxl.COMM_SUCCESS, 0)  # 0.36 s away at 4000 ticks/s
        # servo 2 hears from the host all along; servo 1 hears nothing more and trips while it is moving
        poll(
            lambda: ph.ping(port, 2)[1] == dxl.COMM_SUCCESS and emu.servos[1].get("bus_watchdog") == -1,
            "servo 1's watchdog trips",
        )
        assert emu.servos[2].get("bus_watchdog") == 5
        held = emu.servos[1].get("present_position")
        assert 2048 < held < 3500 and emu.servos[1].get("goal_position") == held  # stopped where it stood
        time.sleep(0.1)
        assert emu.servos[1].get("present_position") == held and emu.servos[1].torque_enabled  # holds, torque on
        assert ph.write4ByteTxRx(port, 1, GOAL, 3500) == (dxl.COMM_SUCCESS, ERR_DATA_RANGE)  # goals are read-only
        assert ph.write1ByteTxRx(port, 1, WATCHDOG, 5) == (dxl.COMM_SUCCESS, ERR_DATA_RANGE)  # cleared first ...
        assert ph.write1ByteTxRx(port, 1, WATCHDOG, 0) == (dxl.COMM_SUCCESS, 0)  # ... by writing 0
        assert ph.write4ByteTxRx(port, 1, GOAL, 3500) == (dxl.COMM_SUCCESS, 0)
        poll(lambda: emu.servos[1].get("present_position") == 3500, "servo 1 moves again")
    finally:
        port.closePort()


# -- the driver: watchdog armed and fed, cleared at connect, a trip noticed ------------------------------------
def test_an_idle_hand_keeps_its_watchdog_fed(emu, kinematics):
    with DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG) as hand:
        assert {s.get("bus_watchdog") for s in emu.servos.values()} == {50}  # 1 s, armed at connect
        time.sleep(2 * TEST_CONFIG.bus_watchdog_s)  # an operator thinking: no command, no read
        assert {s.get("bus_watchdog") for s in emu.servos.values()} == {50}  # the heartbeat fed it
        assert all(emu.torque_enabled().values())
        hand.command_joint_positions(np.full(16, 0.2))
        poll(lambda: np.allclose(hand.read_joint_positions(), 0.2, atol=RAD_PER_TICK), "the hand moves")
    assert not any(emu.torque_enabled().values())


def test_connect_clears_the_watchdog_a_crashed_process_tripped(emu, kinematics):
    for servo in emu.servos.values():  # what a host crash leaves: torque on, watchdog tripped, goals locked
        servo.set("torque_enable", 1)
        servo.set("bus_watchdog", -1)
    with DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG) as hand:
        hand.command_joint_positions(np.full(16, 0.2))
        poll(lambda: np.allclose(hand.read_joint_positions(), 0.2, atol=RAD_PER_TICK), "the hand moves")


def test_watchdog_and_tolerance_settings_are_checked():
    assert DynamixelHandConfig().bus_watchdog_units == 50  # 1 s in 20 ms units
    assert DynamixelHandConfig(bus_watchdog_s=0).bus_watchdog_units == 0  # off
    for bad in (0.2, 2.6, -1.0, np.nan):  # 0.2 s: shorter than a retried exchange (2 x (0.05 + 0.1) s)
        with pytest.raises(ConfigError, match=r"bus_watchdog_s: must be 0 \(off\) or in \[0\.3, 2\.54\] s"):
            DynamixelHandConfig(bus_watchdog_s=bad)
    with pytest.raises(ConfigError, match=r"bus_watchdog_s: must be 0 \(off\) or in \[1\.2, 2\.54\]"):
        DynamixelHandConfig(min_packet_timeout_s=0.5, drain_s=0.1)  # the default 1 s would trip on a retry
    with pytest.raises(ConfigError, match=r"reading_tolerance_rad: must be at least connect_tolerance_rad"):
        DynamixelHandConfig(reading_tolerance_rad=0.01)
    with pytest.raises(ConfigError, match=r"reading_tolerance_rad: must be in \[0, 0\.2\]"):
        DynamixelHandConfig(reading_tolerance_rad=0.5)


@pytest.mark.parametrize(
    "field, value, expected",
    [
        ("retries", -1, r"an integer >= 0"),
        ("retries", 1.5, r"an integer >= 0"),
        ("drain_s", -0.1, r"a finite number of seconds >= 0"),
        ("drain_s", np.nan, r"a finite number of seconds >= 0"),
        ("min_packet_timeout_s", 0.0, r"a finite number of seconds > 0"),
        ("min_packet_timeout_s", np.inf, r"a finite number of seconds > 0"),
        ("current_unit_a", -0.001, r"a finite number of amperes > 0"),
        ("current_limit", -350, r"an integer in \[0, 65535\]"),
        ("position_p_gain", 70000, r"an integer in \[0, 65535\]"),
        ("operating_mode", 300, r"an integer in \[0, 255\]"),
    ],
)
def test_communication_and_servo_settings_are_checked(field, value, expected):
    """A value that would crash later with a raw Python error (a negative retry count, a negative sleep) or reach a
    register it does not fit is one ConfigError naming the field and its range."""
    with pytest.raises(ConfigError, match=rf"^{field}: must be {expected}.*, got {value!r}$"):
        DynamixelHandConfig(bus_watchdog_s=0.0, **{field: value})


def test_a_servo_that_rebooted_is_a_fault(emu, kinematics):
    """A brown-out under grip load reboots a servo: its RAM back to the factory values (torque off, Bus Watchdog 0,
    the goal where it stands). The heartbeat notices, and the fault turns torque off on every servo."""
    with DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG) as hand:
        with emu._lock:  # the reboot, all at once (the emulator's thread holds this lock while it answers)
            servo = emu.servos[1]
            for reg in REGISTERS.values():
                if reg.address >= REGISTERS["torque_enable"].address and reg.writable:
                    servo.set(reg.name, reg.initial)
            servo.set("goal_position", int(round(servo.position)))
        poll(lambda: not any(emu.torque_enabled().values()), "the fault turns torque off on every servo")
        with pytest.raises(
            HandError,
            match=r"faulted.*servo 1 \(index_1\): heartbeat failed: Bus Watchdog of servos 1 \(index_1\) = 0, not "
            r"the 50 armed at connect: a reboot.*torque off confirmed on all 16 servos",
        ):
            hand.command_joint_positions(np.full(16, 0.2))


# -- a reading no joint can reach ----------------------------------------------------------------------------------
def test_an_encoder_glitch_is_a_fault_not_a_pose(emu, kinematics):
    lo, hi = kinematics.joint_limits[5]  # middle_1: [-0.196, 1.61] rad
    with DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG) as hand:
        q = np.zeros(16)
        q[5] = hi
        hand.command_joint_positions(q)
        poll(lambda: abs(hand.read_joint_positions()[5] - hi) < 2 * RAD_PER_TICK, "middle_1 at its upper limit")
        emu.inject_position_offset(5, round(np.radians(3.0) / RAD_PER_TICK))  # 3 degrees past the limit: a pose
        assert hand.read_joint_positions()[5] == pytest.approx(hi + np.radians(3.0), abs=RAD_PER_TICK)
        emu.inject_position_offset(5, 1500)  # 2.3 rad past it: no finger stands there
        with pytest.raises(
            ServoError,
            match=r"servo 5 \(middle_1\): read present position failed: middle_1 "
            r"\(servo 5\) reads \+3\.9\d+ rad \(tick 4\d{3}\), 2\.3\d+ rad outside "
            r"its limits \[-0\.1960, \+1\.6100\].*encoder",
        ) as exc:
            hand.read_joint_positions()
        assert exc.value.servo_id == 5 and exc.value.joint == "middle_1"
        assert not any(emu.torque_enabled().values())
        assert hand.torque_off_report.confirmed and "torque off confirmed on all 16 servos" in str(exc.value)
        with pytest.raises(HandError, match="faulted"):
            hand.command_joint_positions(np.zeros(16))


# -- signals while the torque goes off -----------------------------------------------------------------------------
def test_a_signal_during_the_torque_off_waits_until_every_servo_is_off(emu, kinematics, monkeypatch):
    torque_off = dynamixel_hand.torque_off

    def signalled_midway(ph, port, ids, device):  # SIGTERM after the first servos, as a second Ctrl-C could be
        unconfirmed = torque_off(ph, port, ids[:3], device)
        os.kill(os.getpid(), signal.SIGTERM)
        return unconfirmed + torque_off(ph, port, ids[3:], device)

    previous = signal.getsignal(signal.SIGTERM)
    hand = DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG)
    with pytest.raises(SignalInterrupt) as exc:
        with hand:
            monkeypatch.setattr(dynamixel_hand, "torque_off", signalled_midway)
    assert exc.value.signum == signal.SIGTERM
    assert not any(emu.torque_enabled().values())
    assert hand.torque_off_report.confirmed and hand._port is None
    assert signal.getsignal(signal.SIGTERM) is previous


# -- the hand's process killed or stopped: the emulator in a process of its own --------------------------------
def _drive(port: str, guard: bool) -> int:
    """The hand's process of the tests below: close the hand slowly, reading all along, until killed or faulted."""
    kinematics = HandKinematics()
    config = DynamixelHandConfig(min_packet_timeout_s=0.1, drain_s=0.1, guard=guard)
    with DynamixelHand(port, kinematics=kinematics, config=config) as hand:
        hand.command_joint_positions(0.9 * kinematics.joint_limits[:, 1])
        print("moving", flush=True)
        try:
            while True:
                hand.read_joint_positions()
                time.sleep(0.01)
        except HandError as exc:
            print(f"fault: {exc}", flush=True)
            return 3


def _start_driving(emu: EmulatorProcess, guard: bool) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, __file__, emu.path, "guard" if guard else "no-guard"], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline() == "moving\n"
    return proc


def test_a_host_that_stalls_for_longer_than_half_a_second_keeps_the_hand(kinematics):
    # a loaded host or a long garbage collection: no thread of this process runs for 0.6 s (the main thread keeps
    # the GIL), so the heartbeat sends nothing; the servos, in a process of their own, keep time meanwhile
    with EmulatorProcess() as emu, DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG) as hand:
        interval = sys.getswitchinterval()
        sys.setswitchinterval(10.0)
        try:
            deadline = time.monotonic() + 0.6
            while time.monotonic() < deadline:
                pass
        finally:
            sys.setswitchinterval(interval)
        time.sleep(2 * TEST_CONFIG.heartbeat_s)  # the heartbeat's next read
        hand.check()
        assert {s["bus_watchdog"] for s in emu.status().values()} == {TEST_CONFIG.bus_watchdog_units}
        hand.command_joint_positions(np.full(16, 0.2))


def test_killed_without_a_guard_the_watchdog_stops_the_hand_where_it_is(kinematics):
    goal = np.rint(0.9 * kinematics.joint_limits[:, 1] / RAD_PER_TICK + 2048).astype(int)
    with EmulatorProcess(speed_ticks_per_s=200.0) as emu:  # 5 s from open to closed
        proc = _start_driving(emu, guard=False)
        try:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(20)
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
            proc.stdout.close()

        def tripped():
            status = emu.status()
            return status if all(s["bus_watchdog"] == -1 for s in status.values()) else None

        status = poll(tripped, "every servo's watchdog trips")
        time.sleep(0.2)
        assert emu.status() == status  # it stays: stopped and holding (torque on, at the current limit)
        for sid, servo in status.items():
            assert servo["torque"] and servo["goal_position"] == servo["present_position"] != goal[sid], (sid, servo)
        port, ph = sdk_port(emu.path)
        try:
            assert ph.write4ByteTxRx(port, 5, GOAL, int(goal[5])) == (dxl.COMM_SUCCESS, ERR_DATA_RANGE)
        finally:
            port.closePort()


def test_a_stopped_process_trips_the_watchdog_and_continues_into_a_fault():
    with EmulatorProcess(speed_ticks_per_s=200.0) as emu:
        proc = _start_driving(emu, guard=True)
        try:
            os.kill(proc.pid, signal.SIGSTOP)  # Ctrl-Z, or a debugger: the heartbeat stops with the process
            poll(lambda: all(s["bus_watchdog"] == -1 for s in emu.status().values()), "every servo's watchdog trips")
            os.kill(proc.pid, signal.SIGCONT)
            out, _ = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
        assert proc.returncode == 3, out
        assert (
            "heartbeat failed: Bus Watchdog Error on servos 0 (index_0)" in out
            and "torque off confirmed on all 16 servos" in out
        ), out
        assert not any(emu.torque_enabled().values())


# -- the guard starts clear of the caller's folder, and connect waits for it; one process per port ------------------
def _python_path(folder, serial_py: str) -> str:
    """A PYTHONPATH with a module ``serial`` (the text ``serial_py``) first, before pyserial."""
    folder.mkdir(exist_ok=True)
    (folder / "serial.py").write_text(serial_py)
    return os.pathsep.join(filter(None, [str(folder), os.environ.get("PYTHONPATH")]))


def test_a_serial_py_in_the_working_folder_does_not_disarm_the_guard(tmp_path):
    """A user's own scratch serial.py in the folder the capture runs from is not the guard's pyserial."""
    (tmp_path / "serial.py").write_text('print("my serial port test")\n')
    with EmulatorProcess(speed_ticks_per_s=200.0) as emu:
        proc = subprocess.Popen(
            [sys.executable, __file__, emu.path, "guard"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        try:
            assert proc.stdout.readline() == b"moving\n"
            os.kill(proc.pid, signal.SIGKILL)
            _, err = proc.communicate(timeout=60)  # to the end of the guard's too (it shares the pipe)
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
        err = err.decode()
        assert f"the process {proc.pid} ended without closing the hand; torque off confirmed on all 16 servos" in err
        assert not any(emu.torque_enabled().values())


def test_connect_refuses_a_guard_that_ends_before_it_is_ready(emu, kinematics, tmp_path, monkeypatch):
    """The guard ends on its start (here a ``serial`` without pyserial's port class): connect refuses, naming the
    port, and leaves torque off."""
    monkeypatch.setenv("PYTHONPATH", _python_path(tmp_path, '"""pyserial\'s name, not pyserial."""\n'))
    hand = DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG)
    with pytest.raises(
        HandError,
        match=rf"^Dynamixel hand on {re.escape(emu.path)}: the guard process \(it turns torque off should this process "
        r"die\) ended \(exit code 1\) before it was ready \(its error is above\): not connecting without it$",
    ):
        hand.connect()
    assert not any(emu.torque_enabled().values()) and hand._port is None


def test_connect_refuses_a_guard_that_is_not_ready_in_time(emu, kinematics, tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONPATH", _python_path(tmp_path, "import time\n\ntime.sleep(600)\n"))  # hangs on import
    monkeypatch.setattr(dynamixel_hand, "GUARD_READY_S", 1.0)
    hand = DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG)
    with pytest.raises(HandError, match=rf"on {re.escape(emu.path)}: the guard process .* was not ready within 1 s"):
        hand.connect()
    assert not any(emu.torque_enabled().values()) and hand._port is None


def test_the_guard_says_to_cut_the_power_whatever_stops_its_torque_off(tmp_path):
    """Any error of the guard's torque-off (here pyserial's port class failing) ends in the words that matter."""
    python_path = _python_path(
        tmp_path,
        "EIGHTBITS = 8\n\n\nclass SerialException(OSError):\n    pass\n\n\nclass Serial:\n"
        "    def __init__(self, *args, **kwargs):\n        raise RuntimeError('a bug')\n",
    )
    args = {"port": "/dev/null", "baudrate": 4_000_000, "timeout_s": 0.1, "drain_s": 0.0}
    args["servos"] = [[0, "0 (index_0)"], [1, "1 (index_1)"]]
    command = [sys.executable, "-P", "-m", "tacsplat.drivers.dynamixel_hand", json.dumps(args)]
    env = {**os.environ, "PYTHONPATH": python_path}
    done = subprocess.run(command, input=b"", capture_output=True, env=env, timeout=60)  # stdin ends: its process died
    err = done.stderr.decode()
    assert done.returncode == 1 and "Traceback" not in err, err
    assert (
        "hand guard of /dev/null: the process" in err
        and "ended without closing the hand; cannot turn torque off (RuntimeError: a bug): torque off NOT confirmed "
        "on any of the 2 servos: cut the servo power"
        in err
    ), err


def test_a_second_process_on_the_port_is_refused(emu, kinematics):
    """`tacsplat rig check` in another terminal, beside a capture: its connect (torque off) is refused, and the
    capture's hand keeps its torque and goes on."""
    with DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG) as hand:
        other = DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG)
        with pytest.raises(
            HandError,
            match=rf"on {re.escape(emu.path)}: port in use by another process .*`fuser {re.escape(emu.path)}`",
        ):
            other.connect(torque=False)
        assert all(emu.torque_enabled().values())
        hand.command_joint_positions(np.full(16, 0.2))
        poll(lambda: np.allclose(hand.read_joint_positions(), 0.2, atol=RAD_PER_TICK), "the hand moves")
    with DynamixelHand(emu.path, kinematics=kinematics, config=TEST_CONFIG) as again:  # the lock went with close
        again.check()


if __name__ == "__main__":
    sys.exit(_drive(sys.argv[1], guard=sys.argv[2] == "guard"))
