"""Every kind of bad scene input raises one SceneFormatError naming the file and field at fault."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from tacsplat.datasets import Scene, check_scene
from tacsplat.errors import SceneFormatError


def _edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _transforms(edit):
    return lambda s: _edit_json(s / "transforms.json", edit)


def _touches(edit):
    return lambda s: _edit_json(s / "touches.json", edit)


def _scale_rotation(T, factor):
    T = np.array(T)
    T[:3, :3] *= factor
    return T.tolist()


def _reflect(T):
    T = np.array(T)
    T[:3, 0] *= -1
    return T.tolist()


def _save_npz(path, depth):
    buf = io.BytesIO()
    np.savez(buf, depth=depth)
    path.write_bytes(buf.getvalue())


def _truncate(path, keep=0.5):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _nan_patch(shape):
    d = np.zeros(shape, np.float32)
    d[1, 1] = np.nan
    return d


# (corruption, file the error names, field the error names, words of the message)
CASES = {
    "missing image": (lambda s: (s / "images/000002.png").unlink(),
                      "transforms.json", "frames[2].file_path", "missing"),
    "corrupt image": (lambda s: (s / "images/000001.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 20),
                      "000001.png", "frames[1].file_path", "corrupt"),
    "truncated image": (lambda s: _truncate(s / "images/000003.png"),
                        "000003.png", "frames[3].file_path", "corrupt or truncated"),
    "image size vs w, h": (_transforms(lambda d: d.update(w=17)),
                           "000000.png", "frames[0].file_path", "image is 16x12 but the camera says w x h = 17x12"),
    "truncated touch npz": (lambda s: _truncate(s / "touches/000001.npz"),
                            "000001.npz", "touch 1 depth", "truncated or corrupt npz"),
    "non-finite touch depth": (lambda s: _save_npz(s / "touches/000002.npz", _nan_patch((8, 10))),
                               "000002.npz", "touch 2 depth", "non-finite"),
    "negative touch depth": (lambda s: _save_npz(s / "touches/000000.npz", -np.ones((8, 10), np.float32)),
                             "000000.npz", "touch 0 depth", "negative depth"),
    "touch depth vs sensor model": (_touches(lambda d: d["sensor"].update(width_px=11)),
                                    "000000.npz", "touch 0 depth", "does not match the expected (8, 11)"),
    "non-finite gt depth": (lambda s: _save_npz(s / "gt/depth/000001.npz", _nan_patch((12, 16))),
                            "000001.npz", "gt depth of frame 1", "non-finite"),
    "gt depth vs image size": (lambda s: _save_npz(s / "gt/depth/000001.npz", np.ones((12, 15), np.float32)),
                               "000001.npz", "gt depth of frame 1", "does not match the expected (12, 16)"),
    "frame pose not orthonormal": (_transforms(lambda d: d["frames"][1].update(
                                       transform_matrix=_scale_rotation(d["frames"][1]["transform_matrix"], 1.1))),
                                   "transforms.json", "frames[1].transform_matrix", "not orthonormal"),
    "frame pose is a reflection": (_transforms(lambda d: d["frames"][2].update(
                                       transform_matrix=_reflect(d["frames"][2]["transform_matrix"]))),
                                   "transforms.json", "frames[2].transform_matrix", "determinant is -1"),
    "frame pose not 4x4": (_transforms(lambda d: d["frames"][0].update(transform_matrix=[[1, 0, 0], [0, 1, 0]])),
                           "transforms.json", "frames[0].transform_matrix", "expected a 4x4 matrix"),
    "touch pose not rigid": (_touches(lambda d: d["touches"][3].update(
                                 T_world_sensor=_scale_rotation(d["touches"][3]["T_world_sensor"], 0.5))),
                             "touches.json", "touches[3].T_world_sensor", "not orthonormal"),
    "unknown split": (_transforms(lambda d: d["frames"][3].update(split="val")),
                      "transforms.json", "frames[3].split", "unknown split 'val'"),
    "duplicate frame id": (_transforms(lambda d: d["frames"][2].update(id=0)),
                           "transforms.json", "frames[2].id", "duplicate frame id 0"),
    "duplicate touch id": (_touches(lambda d: d["touches"][3].update(id=1)),
                           "touches.json", "touches[3].id", "duplicate touch id 1"),
    "in_contact contradicts the depth": (_touches(lambda d: d["touches"][1].update(in_contact=True)),
                                         "touches.json", "touches[1].in_contact", "says True"),
    "missing transforms.json": (lambda s: (s / "transforms.json").unlink(), "transforms.json", None, "missing"),
    "corrupt scene.json": (lambda s: (s / "scene.json").write_text("{\"source\": "), "scene.json", None, "not valid JSON"),
    "wrong units": (lambda s: _edit_json(s / "scene.json", lambda d: d.update(units="mm")), "scene.json", "units", "'m'"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_raises_one_error_naming_file_and_field(scene_dir, case):
    corrupt, filename, field, words = CASES[case]
    corrupt(scene_dir)
    with pytest.raises(SceneFormatError) as info:
        Scene.load(scene_dir)
    err = info.value
    assert err.path.name == filename, str(err)
    assert err.field == field, str(err)
    assert words in str(err)
    assert str(err).startswith(str(err.path))


def test_check_scene_collects_every_problem_and_keeps_the_rest(scene_dir):
    CASES["missing image"][0](scene_dir)
    CASES["unknown split"][0](scene_dir)
    CASES["truncated touch npz"][0](scene_dir)
    scene, problems = check_scene(scene_dir)
    assert sorted(p.field for p in problems) == ["frames[2].file_path", "frames[3].split", "touch 1 depth"]
    assert [f.id for f in scene.frames] == [0, 1]
    assert [t.id for t in scene.touches] == [0, 2, 3]


def test_valid_scene_has_no_problems(scene_dir):
    assert check_scene(scene_dir)[1] == []
