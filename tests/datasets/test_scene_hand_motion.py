"""A grasp's hand motion in the scene format: written with its touches, read back equal, undone and cleaned up
with them, copied with them; scenes written before it still load."""

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from tacsplat.datasets import HandMotion, Scene, SceneWriter, check_scene, copy_scene
from tacsplat.datasets.inspect import format_summary, summarise
from tacsplat.errors import InvalidInputError, SceneFormatError
from tacsplat.geometry import make_pose

OLD_SCENE = Path(__file__).parents[1] / "data" / "scene_before_hand_motion"  # written by tacsplat at a699bd7
NO_TOUCH_TIMES = Path(__file__).parents[1] / "data" / "scene_before_touch_times"  # written by tacsplat at 1ea25b2


def motion(grasp: int, samples: int = 5) -> HandMotion:
    rng = np.random.default_rng(grasp)
    q = np.cumsum(rng.uniform(0, 0.05, (samples, 16)), axis=0)
    poses = np.tile(np.eye(4), (samples, 3, 1, 1))
    poses[:, :, :3, 3] = rng.uniform(-0.1, 0.1, (samples, 3, 3))
    return HandMotion(
        grasp=grasp,
        joint_names=tuple(f"j{i}" for i in range(16)),
        t=np.linspace(0, 0.4, samples),
        phase=np.array([0] + [1] * (samples - 2) + [2]),
        q=q,
        q_target=q + 0.01,
        effort=rng.normal(size=(samples, 16)),
        effort_unit="N m",
        T_world_hand=make_pose(np.eye(3), [0.0, 0.0, 0.2]),
        link_names=("palm", "index_distal", "index_gel"),
        link_half_extents=np.array([[0.05, 0.04, 0.01], [0.02, 0.012, 0.01], [0.012, 0.0096, 0.001]]),
        link_poses=poses,
    )


@pytest.fixture
def old_scene(tmp_path) -> Path:
    path = tmp_path / "scene"
    shutil.copytree(OLD_SCENE, path)
    return path


def add_grasp(writer: SceneWriter, grasp: int) -> None:
    hand_file = writer.add_hand_motion(motion(grasp))
    depth = np.zeros((writer.sensor.height_px, writer.sensor.width_px), np.float32)
    depth[3:6, 4:8] = 3e-4
    for f, finger in enumerate(("index", "thumb")):
        writer.add_touch(depth * (f == 0), make_pose(np.eye(3), [0.0, 0.01 * f, 0.05]), grasp, finger, hand_file)


def test_a_scene_written_before_hand_motions_loads_without_them(old_scene):
    scene, problems = check_scene(old_scene)
    assert problems == []
    assert len(scene.touches) == 2 and all(t.hand_file is None for t in scene.touches)
    assert scene.hand_motions() == [] and scene.load_hand_motion(scene.touches[0]) is None
    assert summarise(old_scene)["hand_motion"] is None


def test_motions_round_trip_and_go_with_their_grasp(old_scene, tmp_path):
    with SceneWriter.resume(old_scene) as writer:  # an old scene continued by the new writer
        add_grasp(writer, 1)
        add_grasp(writer, 2)
    scene = Scene.load(old_scene)
    assert [t.hand_file for t in scene.touches] == [None, None] + ["grasps/000001.npz"] * 2 + ["grasps/000002.npz"] * 2
    for got, grasp in zip(scene.hand_motions(), (1, 2)):
        expected = motion(grasp).to_arrays()
        for key, value in got.to_arrays().items():
            assert np.array_equal(value, expected[key]), key
    text = format_summary(summarise(old_scene))
    assert "hand      2 grasps recorded (10 samples of 16 joints, 3 links)" in text

    copy = Scene.load(copy_scene(scene, tmp_path / "copy", touches=scene.touches[2:4]))
    assert [m.grasp for m in copy.hand_motions()] == [1]
    assert np.array_equal(copy.hand_motions()[0].link_poses, motion(1).link_poses)

    with SceneWriter.resume(old_scene) as writer:  # the operator's undo of grasp 2: its file goes with it
        writer.remove_last()
        assert (old_scene / "grasps/000002.npz").is_file()  # one of its touches is left
        writer.remove_last()
        assert not (old_scene / "grasps/000002.npz").exists()
        writer.add_hand_motion(motion(2))  # a crash after the motion, before its touches ...
    with SceneWriter.resume(old_scene):
        pass
    assert not (old_scene / "grasps/000002.npz").exists()  # ... leaves nothing behind
    assert (old_scene / "grasps/000001.npz").is_file()


@pytest.mark.parametrize("bad", [-1, 1.7, 4, "close"], ids=["negative", "fraction", "too large", "a name"])
def test_a_phase_the_file_cannot_hold_is_refused_naming_the_field(bad):
    """The file holds phases as uint8 indices: -1 would become 255 and 1.7 would become 1."""
    phase = np.array([0, 1, 1, bad, 2] if bad != "close" else ["preshape", "close", "close", "close", "open"])
    with pytest.raises(InvalidInputError, match=r"hand motion of grasp 3: phase must hold whole numbers 0 to 3"):
        dataclasses.replace(motion(3), phase=phase)
    whole = dataclasses.replace(motion(3), phase=np.array([0.0, 1.0, 1.0, 3.0, 2.0]))  # whole floats are indices
    assert whole.to_arrays()["phase"].tolist() == [0, 1, 1, 3, 2]


def test_a_damaged_motion_file_is_one_error_naming_it(old_scene):
    with SceneWriter.resume(old_scene) as writer:
        add_grasp(writer, 1)
    (old_scene / "grasps/000001.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(SceneFormatError, match=r"grasps/000001\.npz"):
        Scene.load(old_scene)


def test_a_scene_written_before_touch_times_loads_and_resumes_with_its_grasp_whole(tmp_path):
    from tacsplat.acquisition.logger import CaptureLogger

    path = tmp_path / "scene"
    shutil.copytree(NO_TOUCH_TIMES, path)
    scene, problems = check_scene(path)
    assert problems == []
    (m,) = scene.hand_motions()
    assert m.touch_t is None and len(m.t) == 4
    assert summarise(path)["hand_motion"]["slides"] == 0

    class Hand:
        joint_names = [f"{f}_{j}" for f in ("index", "thumb") for j in range(4)]

    class Sensor:
        def __init__(self, name):
            self.name = name

    with SceneWriter.resume(path) as writer:  # one touch per sensor: complete, kept
        logger = CaptureLogger(writer, Hand(), [Sensor("index"), Sensor("thumb")], None, None, None)
        assert logger.dropped_partial_grasp == 0 and writer.num_touches == 2
