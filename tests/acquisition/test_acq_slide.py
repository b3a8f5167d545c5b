"""The slide after a press (``GraspControl.slide_m``): each finger in contact moves its pad across the surface under
a light contact and the pads are read as they go. On the twin the stream's contact points lie on a box's flat faces
and reach beyond the pressed patch; the grasp's hand motion lists when each touch was read, so a grasp cut short
while its stream was written is redone whole; the real hand's path runs it through the Dynamixel emulator."""

import dataclasses
import io
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tacsplat.acquisition.config import load_rig
from tacsplat.acquisition.devices import TWIN_CONTROL, twin_rig
from tacsplat.acquisition.logger import CaptureLogger
from tacsplat.acquisition.operator_session import run_capture
from tacsplat.acquisition.twin_planner import TwinPlanner
from tacsplat.datasets import Scene, SceneMeta, SceneWriter
from tacsplat.datasets.inspect import format_summary, summarise
from tacsplat.datasets.records import MOTION_PHASES
from tacsplat.sim.twin import SimTwin, TwinConfig

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import ScriptedKeys, write_mock_rig  # noqa: E402

SLIDE = MOTION_PHASES.index("slide")


@pytest.fixture(scope="module")
def box_scene(tmp_path_factory):
    """Two grasps with slides on a box (flat faces), its mesh in the world frame, and the rig's sensor count."""
    folder = tmp_path_factory.mktemp("slide")
    mesh_file = folder / "box.ply"
    trimesh.creation.box((0.1, 0.08, 0.06)).export(mesh_file)
    control = dataclasses.replace(TWIN_CONTROL, slide_m=0.008)
    config = TwinConfig(mesh_path=str(mesh_file), object_radius=0.07, camera_width=16, camera_height=16)
    with SimTwin(config) as twin:
        rig = twin_rig(twin, control)
        with SceneWriter.create(folder / "scene", rig.intrinsics, SceneMeta("sim", "box"), rig.sensor_model) as w:
            logger = CaptureLogger(w, rig.hand, rig.sensors, rig.camera, rig.clock, rig.poses, rig.control)
            planner = TwinPlanner(twin, 0)
            logger.take_view("train")
            outcomes = [planner.grasp(logger, g) for g in range(2)]
        mesh = twin.object_mesh.copy()
    assert all(outcomes), "a grasp touched nothing"
    return Scene.load(folder / "scene"), mesh, len(rig.sensors)


def test_a_slide_over_flat_faces_reads_contact_points_within_0_2_mm_of_them(box_scene):
    scene, mesh, sensors = box_scene
    streamed = [t for t in scene.touches if sum(u.grasp == t.grasp for u in scene.touches) > sensors]
    assert streamed, "no grasp recorded a slide's frames"
    points = scene.touch_points()
    _, distance, _ = trimesh.proximity.closest_point(mesh, points)
    assert distance.max() < 2e-4, distance.max()


def test_the_slide_reaches_beyond_the_pressed_patch(box_scene):
    scene, _, sensors = box_scene
    grasp0 = [t for t in scene.touches if t.grasp == 0]
    pressed = {t.finger: t for t in grasp0[:sensors] if t.in_contact}
    for finger, press in pressed.items():
        pads = np.array([t.T_world_sensor[:3, 3] for t in grasp0[sensors:] if t.finger == finger])
        if len(pads):
            travel = np.linalg.norm(pads - press.T_world_sensor[:3, 3], axis=1).max()
            assert travel > 0.004, (finger, travel)  # more than a quarter of the pad's width
            return
    pytest.fail("no pressed finger streamed frames")


def test_the_hand_motion_lists_when_each_touch_of_the_grasp_was_read(box_scene):
    scene, _, sensors = box_scene
    for motion in scene.hand_motions():
        touches = [t for t in scene.touches if t.grasp == motion.grasp]
        assert len(motion.touch_t) == len(touches) > sensors
        assert np.all(np.diff(motion.touch_t) >= 0)  # in the order they were read
        for finger in {t.finger for t in touches}:
            stream = [tt for tt, t in zip(motion.touch_t[sensors:], touches[sensors:]) if t.finger == finger]
            assert np.all(np.diff(stream) > 0)  # one frame of a pad per read
        slide = motion.t[motion.phase == SLIDE]
        assert len(slide) and slide.min() <= motion.touch_t[sensors] and motion.touch_t[-1] <= motion.t.max()
        assert np.all(motion.touch_t[:sensors] <= slide.min())  # the press is read before the slide
    assert "2 slid their pads along the surface" in format_summary(summarise(scene.path))


def test_a_grasp_cut_short_while_writing_its_stream_is_removed_whole(box_scene, tmp_path):
    scene, _, sensors = box_scene
    copy = tmp_path / "scene"
    shutil.copytree(scene.path, copy)
    with SceneWriter.resume(copy) as writer:
        writer.remove_last()  # a kill while the last of grasp 1's stream frames was written
        have = sum(t.grasp == 1 for t in writer.touches)
        assert have > sensors  # more touches than sensors: only the motion's touch_t tells it is short
        logger = CaptureLogger(
            writer, _NoHand(), [_Named(f) for f in ("index", "middle", "ring", "thumb")], *[None] * 3
        )
        assert logger.dropped_partial_grasp == have
        assert {t.grasp for t in writer.touches} == {0}


class _NoHand:
    joint_names = [f"{f}_{j}" for f in ("index", "middle", "ring", "thumb") for j in range(4)]


class _Named:
    def __init__(self, name):
        self.name = name


def test_the_real_hand_path_slides_through_the_dynamixel_emulator(tmp_path):
    rig = write_mock_rig(
        tmp_path,
        plan={"views": {"train": 1, "test": 0}, "grasps": {"count": 1}},
        grasp={"slide_m": 0.004},
    )
    out = tmp_path / "scene"
    output = io.StringIO()
    assert run_capture(load_rig(rig, mock=True), out, keys=ScriptedKeys("\ng"), output=output) == 0, output.getvalue()
    scene = Scene.load(out)
    (motion,) = scene.hand_motions()
    slide = motion.phase == SLIDE
    assert slide.any(), "no slide was recorded"
    assert len(motion.touch_t) == len(scene.touches)
    moving = np.abs(np.diff(motion.q_target[slide], axis=0)).max()
    assert moving > 1e-3, moving  # the slide commanded the servos through the emulated bus
