"""The logger's grasp controller on a small simulated hand: speed-limited ramp, per-finger stall on an obstacle,
settling, the timeout, and the world placement of what the sensors read."""

import numpy as np
import pytest

from tacsplat.acquisition.config import GraspControl
from tacsplat.acquisition.logger import CaptureLogger, PoseEstimate
from tacsplat.datasets import SceneMeta, SceneWriter, SensorModel
from tacsplat.errors import InvalidInputError
from tacsplat.geometry import make_pose
from tacsplat.types import CameraIntrinsics, TactileReading

FINGERS = ("index", "middle", "ring", "thumb")
SENSOR = SensorModel("pad", 8, 6, 1e-3, 2e-3)


class ToyClock:
    def __init__(self, hand):
        self.t, self.hand = 0.0, hand

    def sleep(self, seconds):
        self.hand.advance(seconds)
        self.t += seconds

    @property
    def time(self):
        return self.t


class ToyHand:
    """Joints that move toward their targets at ``speed`` rad/s; joint 3 of each finger listed in ``blocked`` stops
    at an obstacle angle (the finger meets the object); ``jitter`` keeps one joint moving forever."""

    def __init__(self, blocked: dict[str, float] | None = None, speed: float = 3.0, jitter: bool = False):
        self.q = np.zeros(16)
        self.target = np.zeros(16)
        self.blocked = {FINGERS.index(f) * 4 + 3: a for f, a in (blocked or {}).items()}
        self.speed, self.jitter, self.commands, self._t = speed, jitter, [], 0.0

    joint_names = [f"{f}_{j}" for f in FINGERS for j in range(4)]
    joint_limits = np.tile([-0.5, 1.8], (16, 1))

    def advance(self, dt):
        self._t += dt
        self.q += np.clip(self.target - self.q, -self.speed * dt, self.speed * dt)
        for j, a in self.blocked.items():
            self.q[j] = min(self.q[j], a)
        if self.jitter:
            self.q[0] = 0.05 * np.sin(40 * self._t)

    def read_joint_positions(self):
        return self.q.copy()

    effort_unit = "A"
    link_names = ["palm"]

    def read_joint_state(self):
        return self.q.copy(), np.full(16, np.nan)

    def link_boxes(self, q):
        return np.eye(4)[None], np.array([[0.05, 0.04, 0.01]])

    def command_joint_positions(self, q):
        self.commands.append(np.array(q))
        self.target = np.array(q)

    def fingertip_poses(self):
        return {f: make_pose(np.eye(3), [0.01 * i, 0.0, 0.1 + self.q[4 * i + 3] * 0.01]) for i, f in enumerate(FINGERS)}


class PadSensor:
    """A pad that reads contact when its finger's distal joint is blocked (pressing on the object)."""

    def __init__(self, hand, finger):
        self.hand, self.name = hand, finger

    def read(self):
        i = FINGERS.index(self.name)
        depth = np.zeros((SENSOR.height_px, SENSOR.width_px), np.float32)
        if 4 * i + 3 in self.hand.blocked and self.hand.target[4 * i + 3] > self.hand.q[4 * i + 3]:
            depth[2:4, 3:5] = 5e-4
        return TactileReading(depth, SENSOR.pixel_size_m, self.hand.fingertip_poses()[self.name], "hand")


class BlankCamera:
    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    width, height = 16, 12

    def read(self):
        return np.zeros((12, 16, 3), np.uint8), 0.0


class FixedPoses:
    def __init__(self, T):
        self.T = T

    def camera_pose(self, image):
        return PoseEstimate(self.T)

    def hand_pose(self, image):
        return PoseEstimate(self.T)

    def ground_truth_depth(self):
        return None


def _logger(tmp_path, hand, control, T=np.eye(4)):
    camera = BlankCamera()
    writer = SceneWriter.create(
        tmp_path / "scene",
        CameraIntrinsics(camera.K, camera.width, camera.height),
        SceneMeta("real", "toy", {}, {}),
        SENSOR,
    )
    logger = CaptureLogger(
        writer,
        hand,
        [PadSensor(hand, f) for f in FINGERS],
        camera=camera,
        clock=ToyClock(hand),
        poses=FixedPoses(T),
        control=control,
    )
    return writer, logger


CONTROL = GraspControl(
    close_pose=(0.0, 0.5, 0.5, 1.5) * 4,
    open_pose=(0.0,) * 16,
    close_speed_rad_s=1.0,
    poll_s=0.01,
    stall_error_rad=0.1,
    settle_tol_rad=1e-3,
    settle_polls=3,
    max_close_s=4.0,
    open_s=0.1,
)


def test_blocked_finger_stalls_with_a_bounded_squeeze_others_reach_and_the_touches_are_placed(tmp_path):
    hand = ToyHand(blocked={"middle": 0.6, "thumb": 1.0})
    T_world_hand = make_pose(np.eye(3), [0.3, -0.2, 0.5])
    writer, logger = _logger(tmp_path, hand, CONTROL, T_world_hand)
    with writer:
        outcome = logger.take_grasp()
    assert outcome.stopped_by == {"index": "reached", "middle": "stalled", "ring": "reached", "thumb": "stalled"}
    assert outcome.settled
    assert 1.5 <= outcome.close_seconds < 2.0  # 1.5 rad at 1 rad/s, then a few polls to settle
    commanded = np.array(hand.commands[:-1])  # the last command opens the hand
    assert np.abs(np.diff(commanded, axis=0)).max() <= 1.0 * 0.01 + 1e-12  # the ramp's speed limit
    for finger, obstacle in (("middle", 0.6), ("thumb", 1.0)):  # squeeze at most stall_error past the obstacle
        assert commanded[:, FINGERS.index(finger) * 4 + 3].max() <= obstacle + 0.1 + 1e-9
    assert [t.in_contact for t in outcome.touches] == [False, True, False, True]  # no-contact touches kept
    assert np.allclose(hand.target, 0.0)  # opened again
    for t in outcome.touches:
        i = FINGERS.index(t.finger)
        distal = {"middle": 0.6, "thumb": 1.0}.get(t.finger, 1.5)
        assert np.allclose(t.T_world_sensor[:3, 3], [0.3 + 0.01 * i, -0.2, 0.6 + distal * 0.01], atol=2e-3)


def test_fingers_that_never_settle_are_read_at_the_timeout(tmp_path, caplog):
    hand = ToyHand(jitter=True)
    control = GraspControl(**{**CONTROL.__dict__, "max_close_s": 2.0})
    writer, logger = _logger(tmp_path, hand, control)
    with writer:
        outcome = logger.take_grasp()
    assert not outcome.settled and 2.0 <= outcome.close_seconds < 2.1
    assert "did not settle" in caplog.text
    assert len(outcome.touches) == 4 and writer.num_touches == 4


def test_undo_removes_a_whole_grasp_and_the_next_grasp_reuses_its_number(tmp_path):
    hand = ToyHand(blocked={"index": 0.5})
    writer, logger = _logger(tmp_path, hand, CONTROL)
    with writer:
        logger.take_grasp()
        logger.take_grasp()
        assert logger.undo() == "grasp 1 (4 touches)"
        assert logger.counts().grasps == 1 and logger.next_grasp_index() == 1
        with pytest.raises(Exception, match="already recorded"):
            logger.take_grasp(index=0)
        assert logger.take_grasp().index == 1


def test_an_open_pose_that_is_not_numbers_fails_before_the_hand_moves(tmp_path):
    hand = ToyHand()
    writer, logger = _logger(tmp_path, hand, CONTROL)
    with writer:
        with pytest.raises(ValueError):
            logger.take_grasp(open_pose=[0.0] * 15 + ["half open"])
    assert hand.commands == [] and writer.num_touches == 0


class WorldPad(PadSensor):
    """A driver that places its pad in the world frame, which the logger cannot place in the scene."""

    def read(self):
        r = super().read()
        return TactileReading(r.depth, r.pixel_size_m, r.T_ref_sensor, "world")


def test_a_reading_outside_the_hand_frame_is_refused_naming_the_sensor(tmp_path):
    hand = ToyHand(blocked={"index": 0.5})
    writer, logger = _logger(tmp_path, hand, CONTROL)
    logger.sensors = [WorldPad(hand, f) for f in FINGERS]
    with writer:
        with pytest.raises(
            InvalidInputError, match="sensor 'index': expected a reading in the hand frame, got 'world'"
        ):
            logger.take_grasp()
        assert writer.num_touches == 0
