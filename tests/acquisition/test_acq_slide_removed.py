"""The slide (after each press, every finger in contact slid its pad across the surface and the pad was read as it
went) was removed: it did not beat more presses at equal robot time (docs/experiments.md). A rig file or a batch
file that still asks for it is one error naming the file and the key, and the options are gone; a scene captured
with it still loads, inspects and reconstructs, a grasp of it cut short is still removed whole, and a resume of it
is refused with one error; a twin scene captured before the removal without the slide still resumes."""

import dataclasses
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from tacsplat.acquisition import capture_scene
from tacsplat.acquisition.config import example_rig
from tacsplat.acquisition.logger import CaptureLogger
from tacsplat.acquisition.sim_capture import sim_capture, sim_rig_config
from tacsplat.apps.batch import load_batch
from tacsplat.cli import main
from tacsplat.datasets import Scene, SceneWriter, check_scene
from tacsplat.datasets.records import MOTION_PHASES
from tacsplat.errors import ConfigError
from tacsplat.geometry import make_pose

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import no_devices  # noqa: E402

pytestmark = pytest.mark.timeout(300)

SLIDE, OPEN = MOTION_PHASES.index("slide"), MOTION_PHASES.index("open")
# the grasp control's slide settings as twin captures recorded them before the removal (GraspControl's defaults)
SLIDE_SETTINGS = {"slide_m": 0.0, "slide_speed_m_s": 0.04, "slide_push_m": 0.001, "stream_period_s": 0.04}
TINY = ["--object", "bell", "--views", "2", "--test-views", "1", "--grasps", "1", "--resolution", "24", "--seed", "1"]
WHY = "the slide was removed (it did not beat more presses at equal robot time, docs/experiments.md)"


@pytest.mark.parametrize(
    "grasp, field",
    [
        ({"slide_m": 0.01}, "grasp.slide_m"),
        ({"slide_m": 0.0}, "grasp.slide_m"),
        ({"close_speed_rad_s": 1.0, "slide_push_m": 0.001}, "grasp.slide_push_m"),
        ({"stream_period_s": 0.04}, "grasp.stream_period_s"),
    ],
)
@pytest.mark.parametrize("command", [["sim-capture", "--rig"], ["capture", "--rig"]])
def test_a_rig_file_asking_for_the_slide_is_one_error_naming_file_and_key(tmp_path, capsys, grasp, field, command):
    data = yaml.safe_load(example_rig("sim").read_text())
    data["grasp"] = grasp
    rig = tmp_path / "old.yaml"
    rig.write_text(yaml.safe_dump(data))
    out = tmp_path / "scene"
    assert main([*command, str(rig), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"error: {rig}: {field}: {WHY}: remove the key", err
    assert not out.exists()


def test_a_batch_capture_job_asking_for_the_slide_is_one_error_naming_the_job_and_key(tmp_path):
    path = tmp_path / "b.yaml"
    path.write_text("jobs:\n  - {kind: capture, out: a, grasps: 2}\n  - {kind: capture, out: b, slide_m: 0.01}\n")
    with pytest.raises(ConfigError) as info:
        load_batch(path, tmp_path / "out")
    assert str(info.value) == f"{path}: jobs[1].slide_m: {WHY}: remove the key"


@pytest.mark.parametrize("command", [["sim-capture", *TINY], ["bench", "paper", "--quick"]])
def test_the_slide_options_are_gone(tmp_path, capsys, command):
    assert main([*command, "--out", str(tmp_path / "out"), "--slide-m", "0.01"]) == 2
    assert "error: --slide-m: not an option of tacsplat " in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def _capture_as_before(out, slide_m: float) -> None:
    """A tiny twin capture (TINY's options) whose scene.json records the grasp control's slide settings as
    captures recorded them before the removal, with ``slide_m``."""
    with pytest.MonkeyPatch.context() as mp:
        settings = capture_scene.capture_settings

        def recorded_as_before(config):
            s = settings(config)
            s["twin"]["grasp_control"].update(SLIDE_SETTINGS, slide_m=slide_m)
            return s

        mp.setattr(capture_scene, "capture_settings", recorded_as_before)
        config = sim_rig_config(object="bell", views=2, test_views=1, grasps=1, resolution=24, seed=1)
        sim_capture(config, out, progress=False)


def _add_slid_grasp(out) -> int:
    """Append grasp 1 as a capture with the slide wrote one: grasp 0's press, then its hand motion's samples in
    the slide phase before the release, and a frame of each pad in contact read while it slid (2 mm across the
    pad), listed in the motion's touch_t. Returns the grasp's touch count."""
    scene = Scene.load(out)
    (motion,) = scene.hand_motions()
    press = [t for t in scene.touches if t.grasp == 0]
    streamed = [t for t in press if t.in_contact]
    assert streamed, "the press touched nothing"
    opening = int(np.flatnonzero(motion.phase == OPEN)[0])
    k, poll = 6, 0.01  # slide samples, one per poll, between the press's read and the release
    index = np.r_[np.arange(opening), np.full(k, opening - 1), np.arange(opening, len(motion.t))]
    later = np.r_[np.zeros(opening), poll * np.arange(1, k + 1), np.full(len(motion.t) - opening, poll * k)]
    slid = dataclasses.replace(
        motion,
        grasp=1,
        t=motion.t[index] + later,
        phase=np.r_[motion.phase[:opening], np.full(k, SLIDE), motion.phase[opening:]],
        q=motion.q[index],
        q_target=motion.q_target[index],
        effort=motion.effort[index],
        link_poses=motion.link_poses[index],
        touch_t=np.r_[motion.touch_t, np.full(len(streamed), motion.t[opening - 1] + poll * k / 2)],
    )
    across = make_pose(np.eye(3), [0.0, 0.002, 0.0])
    with SceneWriter.resume(out) as writer:
        hand_file = writer.add_hand_motion(slid)
        for t, T in [*((t, t.T_world_sensor) for t in press), *((t, t.T_world_sensor @ across) for t in streamed)]:
            writer.add_touch(scene.load_touch_depth(t), T, grasp=1, finger=t.finger, hand_file=hand_file)
    return len(press) + len(streamed)


@pytest.fixture(scope="module")
def slid_scene(tmp_path_factory):
    """A twin scene captured with the slide (slide_m 8 mm recorded): grasp 0 pressed, grasp 1 slid its pads."""
    out = tmp_path_factory.mktemp("old") / "scene"
    _capture_as_before(out, slide_m=0.008)
    touches = _add_slid_grasp(out)
    return out, touches


def test_a_scene_captured_with_the_slide_still_loads_inspects_and_reconstructs(slid_scene, tmp_path, capsys):
    path, touches = slid_scene
    scene, problems = check_scene(path)
    assert problems == [], problems
    slid = scene.hand_motions()[1]
    assert (slid.phase == SLIDE).any() and len(slid.touch_t) == touches == sum(t.grasp == 1 for t in scene.touches)
    assert touches > 4  # more touches than sensors: the slide's frames
    assert main(["inspect", str(path)]) == 0
    assert "2 grasps recorded" in (out := capsys.readouterr().out) and "1 slid their pads along the surface" in out
    run = tmp_path / "run"
    assert main(["reconstruct", str(path), "--out", str(run), "--iterations", "2", "--device", "cpu"]) == 0
    assert (run / "splat.ply").is_file()


def test_a_slid_grasp_cut_short_is_removed_whole(slid_scene, tmp_path):
    copy = tmp_path / "scene"
    shutil.copytree(slid_scene[0], copy)
    with SceneWriter.resume(copy) as writer:
        writer.remove_last()  # a kill while the last of grasp 1's frames was written
        have = sum(t.grasp == 1 for t in writer.touches)
        assert have >= 4  # as many touches as sensors: only the motion's touch_t tells it is short
        logger = CaptureLogger(writer, *no_devices())
        assert logger.dropped_partial_grasp == have
        assert {t.grasp for t in writer.touches} == {0}


def test_a_resume_of_a_scene_captured_with_the_slide_is_one_error(slid_scene, capsys):
    path, _ = slid_scene
    before = (path / "scene.json").read_text()
    assert main(["sim-capture", *TINY, "--out", str(path), "--resume"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the writer's log line
    assert err.startswith(f"error: twin.grasp_control.slide_m: {path} was captured with the slide (slide_m 0.008) "), (
        err
    )
    assert WHY in err and "drop --resume" in err and "slide_speed_m_s" not in err, err
    assert json.loads((path / "scene.json").read_text()) == json.loads(before)


def test_a_twin_scene_captured_before_the_removal_without_the_slide_resumes(tmp_path):
    out = tmp_path / "scene"
    _capture_as_before(out, slide_m=0.0)
    with SceneWriter.resume(out) as writer:
        while writer.last_record[0] == "touch":  # a kill before the grasp's touches were written
            writer.remove_last()
    assert main(["sim-capture", *TINY, "--out", str(out), "--resume"]) == 0
    scene = Scene.load(out)
    assert len(scene.touches) == 4 and scene.meta.extra["capture_settings"]["twin"]["grasp_control"]["slide_m"] == 0
