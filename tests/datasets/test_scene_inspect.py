"""`tacsplat inspect`: the text summary, --json and the exit code."""

from __future__ import annotations

import json

import cv2
import pytest

from tacsplat.datasets import Scene
from tacsplat.datasets.inspect import run_inspect
from tacsplat.errors import SceneFormatError


def test_inspect_text_summary_of_a_valid_scene(scene_dir, tmp_path, capsys):
    assert run_inspect(scene_dir, plot=tmp_path / "scene.png") == 0
    picture = cv2.imread(str(tmp_path / "scene.png"))
    assert picture.shape == (600, 700, 3) and picture.std() > 0
    out = capsys.readouterr().out
    assert "frames    4: 3 train, 1 test  [16x12]" in out
    assert "touches   4 (2 in contact) in 2 grasps" in out
    assert "per grasp   0: 2, 1: 2" in out
    assert "per finger  index: 2, thumb: 2" in out
    assert "sensor    gel 10x8 px, 0.5 mm/px, gel 2 mm" in out
    assert "bounds    (" in out
    assert "gt        mesh: none, depth maps: 1" in out
    assert "problems  none" in out


def test_inspect_json_of_a_valid_scene(scene_dir, capsys):
    assert run_inspect(scene_dir, as_json=True) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == {"train": 3, "test": 1}
    assert summary["touches"] == 4 and summary["grasps"] == 2
    assert summary["touches_per_grasp"] == {"0": 2, "1": 2}
    assert summary["problems"] == []
    lo, hi = summary["bounds"]["lo"], summary["bounds"]["hi"]
    assert all(a < b for a, b in zip(lo, hi))


def test_inspect_lists_every_problem_and_fails(scene_dir, capsys):
    from tacsplat.cli import main

    (scene_dir / "images" / "000002.png").unlink()
    (scene_dir / "touches" / "000003.npz").write_bytes(b"PK\x03\x04 not a zip")
    assert main(["inspect", str(scene_dir), "--json"]) == 1
    summary = json.loads(capsys.readouterr().out)
    assert len(summary["problems"]) == 2
    assert "frames[2].file_path" in summary["problems"][0] and "missing" in summary["problems"][0]
    assert "000003.npz" in summary["problems"][1] and "truncated or corrupt npz" in summary["problems"][1]
    assert summary["frames"] == {"train": 3, "test": 1}  # the frame is listed: counted, its missing image a problem
    assert summary["touches"] == 3  # the rest is still summarised
    assert run_inspect(scene_dir) == 1
    out = capsys.readouterr().out
    assert "problems  2" in out and "  - " in out


def test_inspect_counts_the_frames_listed_when_every_image_is_missing(scene_dir, capsys):
    for png in (scene_dir / "images").glob("*.png"):
        png.unlink()
    assert run_inspect(scene_dir) == 1
    out = capsys.readouterr().out
    assert "frames    4: 3 train, 1 test  [16x12]" in out
    assert "gt        mesh: none, depth maps: 1" in out
    assert "problems  4" in out and out.count("is missing") == 4 and "has no frames" not in out


def test_inspect_of_a_scene_without_touches(tmp_path, h, capsys):
    path = h.build_scene(tmp_path / "s", n_frames=2, n_touches=0, sensor=None)
    assert run_inspect(path) == 0
    out = capsys.readouterr().out
    assert "touches   0 (0 in contact) in 0 grasps" in out and "sensor    none" in out


def test_inspect_of_touches_too_shallow_for_a_contact_point_and_no_frames(tmp_path, h, capsys):
    """Before: "error: ...: no frames and no contact points: the scene has no bounds" and no summary; with --plot, a
    traceback (an empty picture)."""
    import numpy as np

    from tacsplat.cli import main
    from tacsplat.datasets import SceneMeta, SceneWriter

    path, sensor = tmp_path / "s", h.SENSOR
    with SceneWriter.create(path, h.intrinsics(), SceneMeta(source="sim", object="o", capture_plan={}), sensor) as w:
        w.add_touch(np.full((sensor.height_px, sensor.width_px), 5e-6, np.float32), h.touch_pose(0), 0, "index")
    assert main(["inspect", str(path), "--json"]) == 1
    summary = json.loads(capsys.readouterr().out)
    assert summary["touches_in_contact"] == 1 and summary["bounds"] is None
    assert summary["problems"] == [f"{path / 'transforms.json'} [frames]: the scene has no frames"]
    assert main(["inspect", str(path), "--plot", str(tmp_path / "p.png")]) == 1
    err = capsys.readouterr().err
    assert err == f"error: {path}: nothing to plot: no readable frames or contact points\n", err
    assert not (tmp_path / "p.png").exists()


def _run_folder(path):
    """The files `tacsplat reconstruct` leaves in its run folder (only their names tell a run from a scene)."""
    path.mkdir()
    for name in ("config.json", "checkpoint.pt", "splat.ply", "metrics.json"):
        (path / name).write_text("{}\n")
    return path


NOT_SCENES = {  # what a user may pass instead of a scene -> the words of its one error line
    "missing path": (lambda p: p, ["does not exist"]),
    "a file": (lambda p: p.write_text("x\n"), ["a file, not a scene directory"]),
    "an empty folder": (lambda p: p.mkdir(), ["not a scene directory", "scene.json"]),
    "a random folder": (lambda p: (p.mkdir(), (p / "notes.txt").write_text("x\n")), ["not a scene directory"]),
    "a reconstruction run": (_run_folder, ["a reconstruction run, not a scene", "tacsplat view", "tacsplat evaluate"]),
}


@pytest.mark.parametrize("kind", NOT_SCENES)
@pytest.mark.parametrize("as_json", [False, True])
def test_inspect_of_what_is_no_scene_is_one_error_line(kind, as_json, tmp_path, capsys):
    from tacsplat.cli import main

    make, words = NOT_SCENES[kind]
    path = tmp_path / "given"
    make(path)
    assert main(["inspect", str(path), *(["--json"] if as_json else [])]) == 1
    out, err = capsys.readouterr()
    assert out == "" and "Traceback" not in err, out + err  # no summary of zeros
    (line,) = err.splitlines()
    assert line.startswith(f"error: {path}: "), line
    assert all(word in line for word in words), line
    with pytest.raises(SceneFormatError) as info:  # reconstruct, evaluate, ... refuse it with the same words
        Scene.load(path)
    assert f"error: {info.value}" == line


BAD_SENSORS = {  # a damaged sensor field of touches.json -> words of its problem
    "a key missing": (lambda s: s.pop("pixel_size_m"), "missing keys ['pixel_size_m']"),
    "a key of the wrong type": (lambda s: s.update(width_px="10"), "width_px must be a positive integer"),
    "a non-finite number": (lambda s: s.update(gel_thickness_m=float("nan")), "gel_thickness_m must be positive"),
}


@pytest.mark.parametrize("damage", [*BAD_SENSORS, "no sensor"])
def test_a_bad_sensor_is_listed_beside_every_touch_problem(damage, scene_dir, capsys):
    index = scene_dir / "touches.json"
    data = json.loads(index.read_text())
    if damage == "no sensor":
        data["sensor"], words = None, "4 touches but no sensor model"
    else:
        BAD_SENSORS[damage][0](data["sensor"])
        words = BAD_SENSORS[damage][1]
    data["touches"][1]["finger"] = 5
    index.write_text(json.dumps(data))
    (scene_dir / "touches" / "000003.npz").write_bytes(b"PK\x03\x04 not a zip")
    assert run_inspect(scene_dir, as_json=True) == 1
    summary = json.loads(capsys.readouterr().out)
    assert len(summary["problems"]) == 3, summary["problems"]
    assert summary["problems"][0].startswith(f"{index} [sensor]: ") and words in summary["problems"][0]
    assert "[touches[1].finger]: expected a finger name, got 5" in summary["problems"][1]
    assert "000003.npz [touch 3 depth]: truncated or corrupt npz" in summary["problems"][2]
    assert summary["touches"] == 2 and summary["touches_per_grasp"] == {"0": 1, "1": 1}  # the other touches count
    assert summary["sensor"] is None and summary["bounds"] is not None  # (the cameras' bounds)
    with pytest.raises(SceneFormatError, match=r"\[sensor\]"):  # (what every other command reads first)
        Scene.load(scene_dir)


def test_inspect_notices_an_index_behind_its_journal(scene_dir, capsys):
    transforms = scene_dir / "transforms.json"
    data = json.loads(transforms.read_text())
    data["frames"].pop()  # as if the writer died after journaling frame 3, before rewriting the index
    transforms.write_text(json.dumps(data))
    assert run_inspect(scene_dir, as_json=True) == 1
    problems = json.loads(capsys.readouterr().out)["problems"]
    assert len(problems) == 1 and "records 4 frames and 4 touches but the index files hold 3 and 4" in problems[0]
    from tacsplat.datasets import SceneWriter

    SceneWriter.resume(scene_dir).close()
    assert run_inspect(scene_dir) == 0
