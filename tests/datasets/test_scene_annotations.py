"""Capture annotations (SceneWriter.annotate): journaled like every record, in scene.json's "annotations", the latest
value of a key winning, also after kill -9 and replay; anything but plain JSON refused."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import numpy as np
import pytest

from tacsplat.datasets import Scene, SceneWriter, check_scene
from tacsplat.datasets.inspect import summarise
from tacsplat.errors import InvalidInputError

# Resumes the scene, annotates "choice" with {"v": 2}, and SIGKILLs itself inside that record's k-th fsync
# (1: the journal line, 2: scene.json's temp file, 3: the folder after scene.json's rename).
CHILD = r"""
import os, sys
from tacsplat.datasets import SceneWriter

path, crash_at = sys.argv[1], int(sys.argv[2])
w = SceneWriter.resume(path)
real_fsync, calls = os.fsync, [0]
def fsync(fd):
    calls[0] += 1
    if calls[0] == crash_at:
        os.kill(os.getpid(), 9)
    real_fsync(fd)
os.fsync = fsync
w.annotate("choice", {"v": 2})
"""


def _scene_json(path) -> dict:
    return json.loads((path / "scene.json").read_text())


@pytest.mark.parametrize("crash_at", [1, 2, 3])
def test_an_annotation_survives_kill_9_inside_its_record(tmp_path, h, crash_at):
    path = h.build_scene(tmp_path / "s", n_frames=2, n_touches=2)
    with SceneWriter.resume(path) as w:
        w.annotate("choice", {"v": 1})
    proc = subprocess.run([sys.executable, "-c", CHILD, str(path), str(crash_at)], capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    scene, problems = check_scene(path)
    if crash_at < 3:  # journaled, scene.json one record behind: every reader refuses it until a resume
        assert scene.annotations == {"choice": {"v": 1}}
        assert [(p.path.name, p.field) for p in problems] == [("journal.jsonl", "annotations")], problems
        assert "a writer stopped between the two" in str(problems[0])
    else:
        assert problems == [] and scene.annotations == {"choice": {"v": 2}}
    with SceneWriter.resume(path) as w:
        assert w.annotations == {"choice": {"v": 2}}
    assert Scene.load(path).annotations == {"choice": {"v": 2}}
    assert _scene_json(path)["annotations"] == {"choice": {"v": 2}}
    assert [p for p in path.rglob("*") if p.name.endswith(".tmp")] == []


def test_the_latest_value_wins_live_and_on_replay(tmp_path, h):
    path = h.build_scene(tmp_path / "s", n_frames=2, n_touches=2)
    with SceneWriter.resume(path) as w:
        w.annotate("a", 1)
        w.annotate("b", {"grasps": [{"grasp": 0, "score_mm2": 1.25, "executed": None}]})
        w.annotate("a", [3, "x", True])
        w.remove_last()  # undo a touch: annotations are no frame or touch to undo
        assert w.annotations == {
            "a": [3, "x", True],
            "b": {"grasps": [{"grasp": 0, "score_mm2": 1.25, "executed": None}]},
        }
        live = dict(w.annotations)
    assert _scene_json(path)["annotations"] == live
    with SceneWriter.resume(path) as w:
        assert w.annotations == live and w.num_touches == 1
    assert Scene.load(path).annotations == live
    assert summarise(path)["annotations"] == ["a", "b"]


def test_a_torn_annotation_line_leaves_the_value_before_it(tmp_path, h):
    path = h.build_scene(tmp_path / "s", n_frames=2, n_touches=0)
    with SceneWriter.resume(path) as w:
        w.annotate("choice", {"v": 1})
        w.annotate("choice", {"v": 2})
    journal = path / "journal.jsonl"
    journal.write_bytes(journal.read_bytes()[:-10])  # the last record cut mid-write by a power cut
    with SceneWriter.resume(path) as w:
        assert w.annotations == {"choice": {"v": 1}}
    assert Scene.load(path).annotations == {"choice": {"v": 1}}


@pytest.mark.parametrize(
    "value, why",
    [
        ({"x": float("nan")}, "plain JSON"),
        ({"x": np.float32(1.0)}, "float32"),
        (object(), "object"),
        ((1, 2), "read back changed"),
        ({1: "a"}, "read back changed"),
    ],
)
def test_anything_but_plain_json_is_refused_naming_the_key(tmp_path, h, value, why):
    path = h.build_scene(tmp_path / "s", n_frames=2, n_touches=0)
    journal = (path / "journal.jsonl").read_bytes()
    with SceneWriter.resume(path) as w:
        with pytest.raises(InvalidInputError, match=why) as info:
            w.annotate("next_touch", value)
        assert "annotation 'next_touch'" in str(info.value)
        assert w.annotations == {}
        with pytest.raises(InvalidInputError, match="annotation key"):
            w.annotate("", 1)
    assert (path / "journal.jsonl").read_bytes() == journal and _scene_json(path)["annotations"] == {}


def test_a_scene_without_annotations_loads_and_a_malformed_one_is_named(scene_dir):
    data = _scene_json(scene_dir)
    del data["annotations"]  # as a scene written before annotations
    (scene_dir / "scene.json").write_text(json.dumps(data))
    assert Scene.load(scene_dir).annotations == {}
    (scene_dir / "scene.json").write_text(json.dumps({**data, "annotations": ["next_touch"]}))
    _, problems = check_scene(scene_dir)
    assert [(p.path.name, p.field) for p in problems] == [("scene.json", "annotations")], problems
