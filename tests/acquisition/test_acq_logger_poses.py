"""take_grasp checks its close and open poses against the hand's joints before anything moves: a user's own hand
(here 4 joints) with a pose of the wrong length, or with the default 16-joint GraspControl, is one
InvalidInputError naming the pose and both counts; the hand is not commanded and nothing is recorded."""

import numpy as np
import pytest

from tacsplat.acquisition.config import GraspControl
from tacsplat.acquisition.logger import CaptureLogger, PoseEstimate
from tacsplat.datasets import SceneMeta, SceneWriter, SensorModel
from tacsplat.datasets.records import MOTION_PHASES
from tacsplat.errors import InvalidInputError
from tacsplat.types import CameraIntrinsics, TactileReading

JOINTS = ["index_0", "index_1", "thumb_0", "thumb_1"]
NAMED = "a hand of 4 joints (index_0, index_1, thumb_0, thumb_1)"
SENSOR = SensorModel("pad", 8, 6, 1e-3, 2e-3)
CLOSE4, OPEN4 = np.array([0.5, 1.0, 0.5, 1.0]), np.zeros(4)


class FourJointHand:
    """A user's own hand whose joints go where commanded; like DynamixelHand it refuses a command of another
    length (after which a grasp would be left closed)."""

    joint_names = JOINTS
    joint_limits = np.array([[-1.0, 1.5]] * 4)
    link_names = ["palm"]
    effort_unit = "A"

    def __init__(self):
        self.q, self.commands = np.zeros(4), []

    def link_boxes(self, q):
        return np.eye(4)[None], np.array([[0.05, 0.05, 0.01]])

    def read_joint_positions(self):
        return self.q.copy()

    def read_joint_state(self):
        return self.q.copy(), np.zeros(4)

    def command_joint_positions(self, q):
        q = np.asarray(q, float)
        if q.shape != (4,):
            raise InvalidInputError(f"q: expected 4 joints, got {q.shape}")
        self.commands.append(q)
        self.q = q

    def fingertip_poses(self):
        return {}


class Pad:
    def __init__(self, name):
        self.name = name

    def read(self):
        depth = np.zeros((SENSOR.height_px, SENSOR.width_px), np.float32)
        depth[2:4, 2:4] = 3e-4
        return TactileReading(depth, SENSOR.pixel_size_m, np.eye(4), "hand")


class Camera:
    K = np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]])
    width, height = 16, 12

    def read(self):
        return np.zeros((12, 16, 3), np.uint8), 0.0


class Poses:
    def camera_pose(self, image):
        return PoseEstimate(np.eye(4))

    def hand_pose(self, image):
        return PoseEstimate(np.eye(4))

    def ground_truth_depth(self):
        return None


class Clock:
    t = 0.0

    def sleep(self, seconds):
        self.t += seconds

    @property
    def time(self):
        return self.t


CONTROL = GraspControl(poll_s=0.01, max_close_s=1.0, open_s=0.05)  # its poses are the default 16-joint ones


@pytest.fixture
def rig(tmp_path):
    hand = FourJointHand()
    camera = Camera()
    intrinsics = CameraIntrinsics(camera.K, camera.width, camera.height)
    writer = SceneWriter.create(tmp_path / "scene", intrinsics, SceneMeta("real", "cup", {}, {}), SENSOR)
    logger = CaptureLogger(writer, hand, [Pad("index"), Pad("thumb")], camera, Clock(), Poses(), CONTROL)
    with writer:
        yield hand, writer, logger


def _nothing_moved_or_recorded(hand, writer, logger):
    assert hand.commands == [] and logger.hand_state == "open"
    assert writer.num_touches == 0 and writer.last_record is None
    assert not any((writer.path / "grasps").glob("*"))  # no hand motion file either


@pytest.mark.parametrize(
    "kwargs, told",
    [
        (dict(close_pose=CLOSE4, open_pose=np.zeros(3)), f"open_pose: 3 joint positions for {NAMED}"),
        (dict(close_pose=np.zeros(5), open_pose=OPEN4), f"close_pose: 5 joint positions for {NAMED}"),
        (dict(close_pose=CLOSE4, open_pose=np.zeros((2, 2))), f"open_pose: an array of shape (2, 2) for {NAMED}"),
        (dict(close_pose=[0.5, np.nan, 0.5, 1.0], open_pose=OPEN4), "close_pose: expected finite joint positions"),
        (dict(close_pose=CLOSE4, open_pose=[0.0, np.inf, 0.0, 0.0]), "open_pose: expected finite joint positions"),
    ],
)
def test_a_pose_that_does_not_fit_the_hand_is_refused_before_the_hand_moves(rig, kwargs, told):
    hand, writer, logger = rig
    with pytest.raises(InvalidInputError) as info:
        logger.take_grasp(**kwargs)
    assert str(info.value).startswith(told)
    _nothing_moved_or_recorded(hand, writer, logger)


@pytest.mark.parametrize("given", ["open_pose", "close_pose"])
def test_the_default_16_joint_poses_on_a_hand_of_4_joints_say_to_give_poses_for_this_hand(rig, given):
    hand, writer, logger = rig
    missing = {"open_pose": "close_pose", "close_pose": "open_pose"}[given]
    with pytest.raises(InvalidInputError) as info:
        logger.take_grasp(**{given: CLOSE4})
    assert str(info.value) == (
        f"grasp.{missing}: 16 joint positions for {NAMED}; give take_grasp a close_pose and an open_pose of 4 for "
        "this hand"
    )
    _nothing_moved_or_recorded(hand, writer, logger)


def test_open_with_a_pose_that_does_not_fit_leaves_the_hand_and_its_state(rig):
    hand, writer, logger = rig
    with pytest.raises(InvalidInputError, match=r"^grasp\.open_pose: 16 joint positions"):
        logger.open()
    with pytest.raises(InvalidInputError, match=r"^open_pose: 2 joint positions"):
        logger.open([0.0, 0.0])
    _nothing_moved_or_recorded(hand, writer, logger)


def test_poses_that_fit_the_hand_close_it_record_the_grasp_and_open_it(rig):
    hand, writer, logger = rig
    outcome = logger.take_grasp(close_pose=CLOSE4, open_pose=OPEN4)
    assert writer.num_touches == 2 and len(outcome.touches) == 2 and logger.hand_state == "open"
    assert np.allclose(hand.q, OPEN4) and np.allclose(np.max(hand.commands, axis=0), CLOSE4)
    assert MOTION_PHASES.index("open") in outcome.motion.phase  # the release recorded
