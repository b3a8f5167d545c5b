"""The closed loop on the twin (`sim-capture --grasp-strategy next-best`): an ordinary scene with its decisions in
its scene.json, the strategy checked on resume, and a capture killed with SIGKILL in the middle of the loop that
resumes choosing and recording exactly the grasps of an uninterrupted capture."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tacsplat.acquisition.next_touch import DECISIONS_KEY
from tacsplat.acquisition.sim_capture import sim_capture, sim_rig_config
from tacsplat.cli import main
from tacsplat.datasets import Scene, check_scene

pytestmark = pytest.mark.timeout(300)

PLAN = dict(
    object="bell",
    views=2,
    test_views=1,
    grasps=3,
    resolution=40,
    seed=1,
    grasp_strategy="next-best",
    candidates=3,
    selection_steps=8,
)
ARGS = [
    "sim-capture",
    "--object",
    "bell",
    "--views",
    "2",
    "--test-views",
    "1",
    "--grasps",
    "3",
    "--resolution",
    "40",
    "--seed",
    "1",
    "--grasp-strategy",
    "next-best",
    "--candidates",
    "3",
    "--selection-steps",
    "8",
]


def _records(path: Path) -> list:
    scene = Scene.load(path)
    frames = [((path / f.file_path).read_bytes(), f.split, f.T_world_cam.tobytes()) for f in scene.frames]
    touches = [
        (scene.load_touch_depth(t).tobytes(), t.grasp, t.finger, t.T_world_sensor.tobytes()) for t in scene.touches
    ]
    return frames + touches


def _decisions(path: Path) -> list[dict]:
    """The decisions recorded in scene.json, less how long they took."""
    grasps = Scene.load(path).annotations[DECISIONS_KEY]["grasps"]
    return [{k: v for k, v in d.items() if k != "selection_seconds"} for d in grasps]


def _decided(path: Path, index: int) -> bool:
    """Whether grasp ``index`` is decided, from scene.json as a capture writes it (replaced whole, atomically)."""
    index_file = path / "scene.json"
    if not index_file.is_file():
        return False
    recorded = json.loads(index_file.read_text()).get("annotations", {}).get(DECISIONS_KEY, {"grasps": []})
    return any(d["grasp"] == index for d in recorded["grasps"])


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("loop") / "scene"
    sim_capture(sim_rig_config(**PLAN), out, progress=False)
    return out


def test_the_closed_loop_writes_an_ordinary_scene_and_its_decisions(uninterrupted):
    scene, problems = check_scene(uninterrupted)
    assert problems == []
    assert scene.meta.capture_plan["grasps"] == {
        "count": 3,
        "mode": "next-best",
        "seed": 1,
        "candidates": 3,
        "selection_steps": 8,
        "uncertainty": "depth-variance",
    }
    decisions = _decisions(uninterrupted)
    assert [d["grasp"] for d in decisions] == [0, 1, 2]
    for d in decisions:
        scores = {c["candidate"]: c["score_mm2"] for c in d["candidates"]}
        assert sorted(scores) == [0, 1, 2] and sorted(d["ranking"]) == [0, 1, 2]
        assert [scores[k] for k in d["ranking"]] == sorted(scores.values(), reverse=True)
        assert d["executed"] in d["ranking"] and d["scene"] == {"train_views": 2, "touches": 4 * d["grasp"]}
        assert d["reconstruction"]["steps"] == 8 and d["reconstruction"]["gaussians"] > 0
    assert sorted({t.grasp for t in scene.touches}) == [0, 1, 2]
    assert not list(uninterrupted.glob("next_touch*"))  # no side file: the scene is all there is


def test_a_resume_with_another_grasp_strategy_is_refused(uninterrupted, capsys):
    before = _records(uninterrupted)
    random_args = [a if a != "next-best" else "random" for a in ARGS]
    assert main(random_args + ["--out", str(uninterrupted), "--resume"]) == 1
    err = capsys.readouterr().err
    assert "--grasp-strategy" in err and "'next-best'" in err and "'random'" in err, err
    assert _records(uninterrupted) == before


def test_sigkill_in_the_loop_then_resume_chooses_the_same_grasps(uninterrupted, tmp_path):
    out = tmp_path / "scene"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "tacsplat.cli", *ARGS, "--out", str(out)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 200
        while not _decided(out, 1):
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "grasp 1 was never decided"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)  # grasp 1 decided: the hand is moving, or about to
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert len({t.grasp for t in Scene.load(out).touches}) < 3  # the kill left work to do

    sim_capture(sim_rig_config(**PLAN), out, resume=True, progress=False)
    assert _records(out) == _records(uninterrupted)
    assert _decisions(out) == _decisions(uninterrupted)
