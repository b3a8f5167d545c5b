"""A resume that is refused changes nothing in the scene: the settings, and the files the journal's records refer
to, are checked on the journal read-only before any device opens and before the scene is resumed (its index
rewritten, files it does not list removed). A scene whose record files are missing (a partial copy) is refused, so
that no lost view or grasp counts as taken."""

import io
import json
import shutil
import sys
from pathlib import Path

import pytest

from tacsplat.acquisition import capture_scene
from tacsplat.acquisition.config import load_rig
from tacsplat.acquisition.logger import CaptureLogger
from tacsplat.acquisition.operator_session import run_capture
from tacsplat.datasets import Scene, SceneWriter
from tacsplat.datasets.writer import journaled_state
from tacsplat.errors import ConfigError, SceneFormatError
from tacsplat.sim.hand import JOINT_NAMES

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import ScriptedKeys, no_devices, write_mock_rig  # noqa: E402

pytestmark = pytest.mark.timeout(180)


def _files(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """A mock capture stopped after one view and one grasp (grasps/000000.npz, touches 0-3), and its rig file."""
    root = tmp_path_factory.mktemp("captured")
    rig = write_mock_rig(root)
    assert run_capture(load_rig(rig, mock=True), root / "scene", keys=ScriptedKeys("\ng"), output=io.StringIO()) == 1
    assert len(Scene.load(root / "scene").touches) == 4
    return root


@pytest.fixture
def scene(captured, tmp_path):
    return Path(shutil.copytree(captured / "scene", tmp_path / "scene"))


@pytest.fixture
def no_device(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a device opened")

    monkeypatch.setattr(capture_scene, "open_rig", refuse)


def _resume(rig: str, out: Path) -> int:
    return run_capture(load_rig(rig, mock=True), out, resume=True, keys=ScriptedKeys(""), output=io.StringIO())


def test_a_resume_refused_for_its_settings_keeps_hand_edits_and_files_the_scene_does_not_list(
    captured, scene, tmp_path, no_device
):
    index = json.loads((scene / "transforms.json").read_text())
    (scene / "transforms.json").write_text(json.dumps({**index, "note": "my edit"}))
    shutil.copy(scene / "images" / "000000.png", scene / "images" / "000005.png")
    journal = scene / "journal.jsonl"
    journal.write_bytes(journal.read_bytes() + b'{"op": "frame", "fra')  # a torn last line: left as it is too
    before = _files(scene)
    (tmp_path / "other").mkdir()
    other = write_mock_rig(tmp_path / "other", board={"square_length_m": 0.012, "marker_length_m": 0.009})
    with pytest.raises(ConfigError) as err:
        _resume(other, scene)
    assert err.value.key == "board.square_length_m", str(err.value)
    assert _files(scene) == before


@pytest.mark.parametrize(("key", "value", "recorded"), [("joint_offsets_rad", 0.05, 0), ("joint_signs", -1, 1)])
def test_a_mock_resume_with_other_servo_errors_is_refused_naming_them(
    captured, scene, tmp_path, no_device, key, value, recorded
):
    """--mock's servos read off by sim.true_errors, so the joint angles a scene records depend on them; a difference
    is named by the rig file's own key and its joint (the scene's file gave none: each joint's default)."""
    (tmp_path / "other").mkdir()
    other = write_mock_rig(tmp_path / "other", sim={"true_errors": {key: {JOINT_NAMES[1]: value}}})
    before = _files(scene)
    with pytest.raises(ConfigError) as err:
        _resume(other, scene)
    dotted = f"sim.true_errors.{key}.{JOINT_NAMES[1]}"
    assert err.value.key == dotted, str(err.value)
    told = f"{other}: {dotted}: {scene} was captured with {recorded}, this run asks for {value}; drop --resume"
    assert str(err.value).startswith(told), str(err.value)
    assert _files(scene) == before


@pytest.mark.parametrize("lost", ["images/000000.png", "touches/000002.npz", "grasps/000000.npz"])
def test_a_resume_of_a_scene_missing_record_files_is_refused_naming_them_and_nothing_is_deleted(
    captured, scene, no_device, lost
):
    (scene / lost).unlink()
    shutil.copy(scene / "touches" / "000003.npz", scene / "touches" / "000009.npz")  # a file no record lists
    before = _files(scene)
    with pytest.raises(SceneFormatError) as err:
        _resume(str(captured / "rig.yaml"), scene)
    message = str(err.value)
    assert message.startswith(f"{scene / 'journal.jsonl'}: records 1 file(s) that are missing ({lost}): "), message
    assert "restore them" in message and "\n" not in message
    assert _files(scene) == before


def test_a_resume_with_the_last_grasps_hand_motion_cut_off_is_refused_naming_it(captured, scene, no_device):
    hand_file = scene / "grasps" / "000000.npz"
    hand_file.write_bytes(hand_file.read_bytes()[:300])
    before = _files(scene)
    with pytest.raises(SceneFormatError) as err:
        _resume(str(captured / "rig.yaml"), scene)
    assert err.value.path == hand_file and "truncated, corrupt or incomplete npz" in str(err.value)
    assert _files(scene) == before


def test_a_logger_on_a_scene_whose_last_hand_motion_is_cut_off_names_the_file(scene):
    hand_file = scene / "grasps" / "000000.npz"
    hand_file.write_bytes(hand_file.read_bytes()[:300])
    with SceneWriter.resume(scene) as writer:
        with pytest.raises(SceneFormatError) as err:
            CaptureLogger(writer, *no_devices())
    assert err.value.path == hand_file


def test_a_resume_after_a_view_that_followed_the_grasp_does_not_read_its_hand_motion(captured, scene):
    rig = str(captured / "rig.yaml")
    assert run_capture(load_rig(rig, mock=True), scene, resume=True, keys=ScriptedKeys("\n"), output=io.StringIO()) == 1
    assert Scene.load(scene).frames[-1].id == 1  # a view after the grasp: the resume redoes no grasp
    hand_file = scene / "grasps" / "000000.npz"
    hand_file.write_bytes(hand_file.read_bytes()[:300])
    assert _resume(rig, scene) == 1  # not refused (stopped: no keys)
    state = journaled_state(scene)
    assert (len(state.frames), len(state.touches)) == (2, 4)
    with pytest.raises(SceneFormatError) as err:  # loading the scene still reports it
        Scene.load(scene)
    assert err.value.path == hand_file
