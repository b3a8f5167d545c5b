"""--resume continues only the capture that was started: the settings that change the data are recorded in
scene.json when a capture starts, and a resume asking for another value of any of them is refused before a device
opens, naming the option and both values; the scene is left byte for byte as it was."""

import io
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from tacsplat.acquisition.config import example_rig, load_rig  # noqa: E402
from tacsplat.acquisition.operator_session import run_capture  # noqa: E402
from tacsplat.cli import main  # noqa: E402
from tacsplat.datasets import Scene, SceneWriter  # noqa: E402
from tacsplat.errors import ConfigError  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import ScriptedKeys, write_mock_rig  # noqa: E402

pytestmark = pytest.mark.timeout(180)

TORUS = {
    "--object": "torus",
    "--object-radius": "0.08",
    "--views": "2",
    "--test-views": "1",
    "--grasps": "1",
    "--resolution": "32",
    "--seed": "0",
}


def _sim_capture(out: Path, changes: dict | None = None, resume: bool = False) -> int:
    options = {**TORUS, **(changes or {})}
    argv = ["sim-capture", *[x for pair in options.items() for x in pair], "--out", str(out)]
    return main(argv + (["--resume"] if resume else []))


def _files(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _records(path: Path) -> list:
    scene = Scene.load(path)
    frames = [((path / f.file_path).read_bytes(), f.split, f.T_world_cam.tobytes()) for f in scene.frames]
    touches = [
        (scene.load_touch_depth(t).tobytes(), t.grasp, t.finger, t.T_world_sensor.tobytes()) for t in scene.touches
    ]
    return frames + touches


@pytest.fixture(scope="module")
def torus(tmp_path_factory):
    """A complete small torus capture, and the same capture as a kill after its two train images leaves it."""
    root = tmp_path_factory.mktemp("torus")
    assert _sim_capture(root / "complete") == 0
    shutil.copytree(root / "complete", root / "killed")
    with SceneWriter.resume(root / "killed") as writer:  # drop grasp 0's four touches and the test view
        for _ in range(5):
            writer.remove_last()
    assert [f.split for f in Scene.load(root / "killed").frames] == ["train", "train"]
    return root


@pytest.fixture
def killed(torus, tmp_path):
    out = tmp_path / "S"
    shutil.copytree(torus / "killed", out)
    return out


def test_resume_with_another_object_is_refused_then_the_right_one_finishes_identically(torus, killed, capsys):
    before = _files(killed)
    assert _sim_capture(killed, {"--object": "teapot"}, resume=True) == 1
    err = capsys.readouterr().err
    assert (
        f"error: --object: {killed} was captured with 'torus', this run asks for 'teapot'; "
        "drop --resume to start a new scene"
    ) in err, err
    assert "Traceback" not in err
    assert _files(killed) == before
    assert _sim_capture(killed, resume=True) == 0
    assert _records(killed) == _records(torus / "complete")
    assert Scene.load(killed).meta.object == "torus"


@pytest.mark.parametrize(
    "option, value, recorded",
    [
        ("--object-radius", "0.1", "0.08"),
        ("--views", "3", "2"),
        ("--test-views", "2", "1"),
        ("--grasps", "2", "1"),
        ("--resolution", "48", "32"),
        ("--seed", "1", "0"),
    ],
)
def test_resume_with_another_sim_option_is_refused_naming_it(killed, capsys, option, value, recorded):
    before = _files(killed)
    assert _sim_capture(killed, {option: value}, resume=True) == 1
    err = capsys.readouterr().err
    assert f"error: {option}: {killed} was captured with {recorded}, this run asks for {value}" in err, err
    assert err.count(f"{option}:") == 1, err  # --seed seeds the twin and the grasps: named once
    assert err.rstrip().endswith("drop --resume to start a new scene"), err
    assert _files(killed) == before


def test_resume_with_another_mesh_file_or_changed_mesh_content_is_refused(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("TACSPLAT_CACHE", str(tmp_path / "cache"))
    mesh = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=2).export(mesh)
    out = tmp_path / "S"
    assert _sim_capture(out, {"--mesh": str(mesh), "--views": "1", "--test-views": "0", "--grasps": "0"}) == 0
    before = _files(out)
    (tmp_path / "copy").mkdir()
    elsewhere = str(shutil.copy(mesh, tmp_path / "copy" / "ball.ply"))
    assert (
        _sim_capture(out, {"--mesh": elsewhere, "--views": "1", "--test-views": "0", "--grasps": "0"}, resume=True) == 1
    )
    err = capsys.readouterr().err
    assert f"error: --mesh: {out} was captured with '{mesh}', this run asks for '{elsewhere}'" in err, err

    trimesh.creation.box(extents=(1.0, 0.6, 0.4)).export(mesh)  # same path, other content
    assert (
        _sim_capture(out, {"--mesh": str(mesh), "--views": "1", "--test-views": "0", "--grasps": "0"}, resume=True) == 1
    )
    err = capsys.readouterr().err
    assert f"error: --mesh: {out} was captured with a file of sha256 " in err and "this run's file has sha256" in err, (
        err
    )
    assert _files(out) == before


def _as_written_by_older_code(scene: Path) -> None:
    """Remove what this version records for resuming from the journal's header and scene.json (older scenes
    lack it)."""
    journal = scene / "journal.jsonl"
    lines = journal.read_text().splitlines(keepends=True)
    header = json.loads(lines[0])
    del header["meta"]["extra"]["capture_settings"]
    journal.write_text(json.dumps(header) + "\n" + "".join(lines[1:]))
    with SceneWriter.resume(scene):  # rewrites scene.json from the journal
        pass
    assert "capture_settings" not in json.loads((scene / "scene.json").read_text())["extra"]


@pytest.mark.parametrize(
    "option, value, recorded, asked",
    [
        ("--object", "teapot", "'torus'", "'teapot'"),
        ("--resolution", "48", "32", "48"),
        ("--object-radius", "0.1", "0.08", "0.1"),
        ("--grasps", "2", "1", "2"),
    ],
)
def test_a_scene_of_older_code_is_refused_on_the_settings_it_recorded(killed, capsys, option, value, recorded, asked):
    _as_written_by_older_code(killed)
    before = _files(killed)
    assert _sim_capture(killed, {option: value}, resume=True) == 1
    err = capsys.readouterr().err
    assert f"error: {option}: {killed} was captured with {recorded}, this run asks for {asked}" in err, err
    assert _files(killed) == before


def test_resume_with_another_texture_is_refused_and_a_scene_from_before_textures_resumes(torus, killed, capsys):
    before = _files(killed)
    assert _sim_capture(killed, {"--texture": "checker"}, resume=True) == 1
    err = capsys.readouterr().err
    assert f"error: --texture: {killed} was captured with 'none', this run asks for 'checker'" in err, err
    assert _files(killed) == before
    journal = killed / "journal.jsonl"  # a scene captured before the texture was a setting
    lines = journal.read_text().splitlines(keepends=True)
    header = json.loads(lines[0])
    del header["meta"]["extra"]["capture_settings"]["sim"]["texture"]
    journal.write_text(json.dumps(header) + "\n" + "".join(lines[1:]))
    assert _sim_capture(killed, {"--texture": "checker"}, resume=True) == 1  # it was a plain one
    assert "error: --texture: " in capsys.readouterr().err
    assert _sim_capture(killed, resume=True) == 0
    assert _records(killed) == _records(torus / "complete")


def test_a_scene_of_older_code_resumes_when_its_recorded_settings_agree(torus, killed):
    _as_written_by_older_code(killed)
    assert _sim_capture(killed, resume=True) == 0
    assert _records(killed) == _records(torus / "complete")


# --- a rig file (tacsplat capture --resume) ------------------------------------------------------


def _sensors_with_mount(index: int) -> list:
    sensors = yaml.safe_load(example_rig("mock").read_text())["tactile"]["sensors"]
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # the sensor turned 90 degrees on its pad
    sensors[index]["T_fingertip_sensor"] = T.tolist()
    return sensors


@pytest.mark.parametrize(
    "changes, key, recorded, asked",
    [
        ({"object": "cup"}, "object", "'mock-board'", "'cup'"),
        ({"plan": {"views": {"train": 3, "test": 1}, "grasps": {"count": 7}}}, "plan.grasps.count", "3", "7"),
        ({"board": {"square_length_m": 0.012, "marker_length_m": 0.009}}, "board.square_length_m", "0.015", "0.012"),
        (
            {"tactile": {"sensors": _sensors_with_mount(2)}},
            "tactile.sensors[2].T_fingertip_sensor",
            "None",
            "[[0.0, -1.0",
        ),
    ],
)
def test_resume_with_a_rig_file_of_another_object_or_plan_is_refused_naming_the_field(
    tmp_path, changes, key, recorded, asked
):
    out = tmp_path / "scene"
    assert (
        run_capture(load_rig(write_mock_rig(tmp_path), mock=True), out, keys=ScriptedKeys("\n"), output=io.StringIO())
        == 1
    )
    before = _files(out)
    (tmp_path / "other").mkdir()
    other = write_mock_rig(tmp_path / "other", **changes)
    with pytest.raises(ConfigError) as err:
        run_capture(load_rig(other, mock=True), out, resume=True, keys=ScriptedKeys(""), output=io.StringIO())
    message = str(err.value)
    assert err.value.key == key, message
    assert message.startswith(f"{other}: {key}: {out} was captured with {recorded}, this run asks for {asked}"), message
    assert message.endswith("drop --resume to start a new scene")
    assert _files(out) == before


def test_a_mock_capture_is_not_resumed_on_the_real_rig_and_no_device_opens(tmp_path):
    out = tmp_path / "scene"
    rig = write_mock_rig(tmp_path)
    assert run_capture(load_rig(rig, mock=True), out, keys=ScriptedKeys("\n"), output=io.StringIO()) == 1
    for name in (
        "wrist_camera.json",
        "tactile_index.npz",
        "tactile_middle.npz",
        "tactile_ring.npz",
        "tactile_thumb.npz",
    ):
        (tmp_path / "calibration").mkdir(exist_ok=True)
        (tmp_path / "calibration" / name).write_text("not a calibration: opening the devices would fail on it")
    with pytest.raises(ConfigError) as err:
        run_capture(load_rig(rig), out, resume=True, keys=ScriptedKeys(""), output=io.StringIO())
    assert err.value.key == "mock" and f"{out} was captured with True, this run asks for False" in str(err.value)


def _write_pose_files(folder: Path, offset_m: float) -> None:
    """A hand-eye file and a mounts file, both moved by ``offset_m`` (a recalibration)."""
    from tacsplat.drivers.press_calibration import MountsFit, save_hand_eye, save_mounts
    from tacsplat.sim.hand import nominal_T_hand_cam

    T = nominal_T_hand_cam()
    T[0, 3] += offset_m
    save_hand_eye(folder / "hand_eye.json", T, presses=16, rms_mm=0.1)
    M = np.eye(4)
    M[0, 3] = offset_m
    save_mounts(MountsFit(T, {"index": M}, {}, {"index": 0.1}, {"index": 12}, {"index": 0}), folder / "mounts.json")


@pytest.mark.parametrize(
    "changed, key", [("hand_eye.json", "camera.hand_eye_sha256"), ("mounts.json", "tactile.mounts_sha256")]
)
def test_resume_after_a_new_hand_eye_or_mounts_file_is_refused_naming_it(tmp_path, changed, key):
    """The hand-eye and mounts files place every touch: a scene is continued only with the files it began with
    (the mock uses the rig's, as a real rig does)."""
    out = tmp_path / "scene"
    rig = write_mock_rig(tmp_path, camera={"hand_eye": "hand_eye.json"}, tactile={"mounts": "mounts.json"})
    _write_pose_files(tmp_path, 0.0)
    assert run_capture(load_rig(rig, mock=True), out, keys=ScriptedKeys("\n"), output=io.StringIO()) == 1
    before = _files(out)
    (tmp_path / "new").mkdir()
    _write_pose_files(tmp_path / "new", 0.01)
    (tmp_path / changed).write_bytes((tmp_path / "new" / changed).read_bytes())  # the other file as it was
    with pytest.raises(ConfigError) as err:
        run_capture(load_rig(rig, mock=True), out, resume=True, keys=ScriptedKeys(""), output=io.StringIO())
    assert err.value.key == key, str(err.value)
    assert f"{out} was captured with a file of sha256 " in str(err.value)
    assert _files(out) == before


def test_a_scene_that_recorded_no_hand_eye_or_mounts_file_resumes_with_one(tmp_path):
    """A scene of an older version recorded neither file's sha256: it resumes on what it did record."""
    out = tmp_path / "scene"
    rig = write_mock_rig(tmp_path, camera={"hand_eye": "hand_eye.json"}, tactile={"mounts": "mounts.json"})
    _write_pose_files(tmp_path, 0.0)
    assert run_capture(load_rig(rig, mock=True), out, keys=ScriptedKeys("\n"), output=io.StringIO()) == 1
    journal = out / "journal.jsonl"
    header, *records = journal.read_text().splitlines(keepends=True)
    header = json.loads(header)
    settings = header["meta"]["extra"]["capture_settings"]
    assert settings["camera"].pop("hand_eye_sha256") and settings["tactile"].pop("mounts_sha256")
    journal.write_text(json.dumps(header) + "\n" + "".join(records))
    _write_pose_files(tmp_path, 0.01)
    keys = ScriptedKeys("\n")
    assert run_capture(load_rig(rig, mock=True), out, resume=True, keys=keys, output=io.StringIO()) == 1
    assert [f.split for f in Scene.load(out).frames] == ["train", "train"]
