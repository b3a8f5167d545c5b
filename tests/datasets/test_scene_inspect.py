"""`tacsplat inspect`: the text summary, --json and the exit code."""

from __future__ import annotations

import json

import cv2

from tacsplat.datasets.inspect import run_inspect


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
    assert summary["frames"] == {"train": 2, "test": 1} and summary["touches"] == 3  # the rest is still summarised
    assert run_inspect(scene_dir) == 1
    out = capsys.readouterr().out
    assert "problems  2" in out and "  - " in out


def test_inspect_of_a_scene_without_touches_and_of_a_non_scene(tmp_path, h, capsys):
    path = h.build_scene(tmp_path / "s", n_frames=2, n_touches=0, sensor=None)
    assert run_inspect(path) == 0
    out = capsys.readouterr().out
    assert "touches   0 (0 in contact) in 0 grasps" in out and "sensor    none" in out
    assert run_inspect(tmp_path / "nothing", as_json=True) == 1
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == {"train": 0, "test": 0} and "does not exist" in summary["problems"][0]
    (tmp_path / "file.txt").write_text("x\n")
    assert run_inspect(tmp_path / "file.txt", as_json=True) == 1
    assert "a file, not a scene directory" in json.loads(capsys.readouterr().out)["problems"][0]


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
