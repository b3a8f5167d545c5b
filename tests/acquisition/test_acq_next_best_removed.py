"""Next-best touch was removed (it did not beat random grasps, docs/experiments.md): a rig file that still asks for
it is one error naming the file and the field; a scene captured with it still loads, inspects and reconstructs, and a
resume of it is refused with one error."""

import json

import pytest
import yaml

from tacsplat.acquisition import capture_scene
from tacsplat.acquisition.config import example_rig
from tacsplat.acquisition.sim_capture import sim_capture, sim_rig_config
from tacsplat.cli import main
from tacsplat.datasets import SceneWriter, check_scene

pytestmark = pytest.mark.timeout(300)

NEXT_BEST = {"count": 1, "mode": "next-best", "seed": 1, "candidates": 3, "selection_steps": 8}
DECISIONS = {"grasps": [{"grasp": 0, "executed": 2, "ranking": [2, 0, 1], "scene": {"train_views": 2, "touches": 0}}]}
TINY = ["--object", "bell", "--views", "2", "--test-views", "1", "--grasps", "1", "--resolution", "24", "--seed", "1"]


@pytest.mark.parametrize(
    "grasps, field",
    [
        ({"mode": "next-best"}, "plan.grasps.mode"),
        ({**NEXT_BEST, "uncertainty": "fisher"}, "plan.grasps.mode"),
        ({"mode": "random", "selection_steps": 300}, "plan.grasps.selection_steps"),
        ({"mode": "random", "candidates": 16}, "plan.grasps.candidates"),
    ],
)
@pytest.mark.parametrize("command", [["sim-capture", "--rig"], ["capture", "--rig"]])
def test_a_rig_file_asking_for_next_best_is_one_error_naming_file_and_field(tmp_path, capsys, grasps, field, command):
    data = yaml.safe_load(example_rig("sim").read_text())
    data["plan"]["grasps"] = grasps
    rig = tmp_path / "old.yaml"
    rig.write_text(yaml.safe_dump(data))
    out = tmp_path / "scene"
    assert main([*command, str(rig), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    assert str(rig) in err and field in err and "next-best touch was removed" in err and "'random'" in err, err
    assert "Traceback" not in err and not out.exists()


@pytest.fixture(scope="module")
def next_best_scene(tmp_path_factory):
    """A scene as a next-best capture wrote it: its plan in scene.json and its decisions under annotations."""
    out = tmp_path_factory.mktemp("old") / "scene"
    with pytest.MonkeyPatch.context() as mp:
        settings = capture_scene.capture_settings
        mp.setattr(
            capture_scene,
            "capture_settings",
            lambda c: {**settings(c), "plan": {**settings(c)["plan"], "grasps": NEXT_BEST}},
        )
        config = sim_rig_config(object="bell", views=2, test_views=1, grasps=1, resolution=24, seed=1)
        sim_capture(config, out, progress=False)
    with SceneWriter.resume(out) as writer:
        writer.annotate("next_touch", DECISIONS)
    return out


def test_a_scene_captured_with_next_best_still_loads_inspects_and_reconstructs(next_best_scene, tmp_path, capsys):
    scene, problems = check_scene(next_best_scene)
    assert problems == [] and scene.meta.capture_plan["grasps"] == NEXT_BEST
    assert scene.annotations == {"next_touch": DECISIONS} and len(scene.touches) == 4
    assert main(["inspect", str(next_best_scene)]) == 0
    assert "next_touch" in capsys.readouterr().out
    run = tmp_path / "run"
    assert main(["reconstruct", str(next_best_scene), "--out", str(run), "--iterations", "3", "--device", "cpu"]) == 0
    assert (run / "splat.ply").is_file()


def test_a_resume_of_a_next_best_scene_is_one_error(next_best_scene, capsys):
    before = (next_best_scene / "scene.json").read_text()
    assert main(["sim-capture", *TINY, "--out", str(next_best_scene), "--resume"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after the writer's log line
    assert err.startswith("error: plan.grasps.mode: ") and "'next-best'" in err and "--resume" in err, err
    assert json.loads((next_best_scene / "scene.json").read_text()) == json.loads(before)
