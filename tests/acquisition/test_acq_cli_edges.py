"""The edges of `sim-capture` and `simulate-touches` as a command-line user meets them: two processes on one
scene are told about `--resume` and the other process's PID; an option value out of its range is a usage error
(exit 2) naming the option; and the documented ranges are the ones that work."""

import re
import subprocess
import sys

import pytest
import yaml

from tacsplat.cli import main
from tacsplat.datasets import Scene, check_scene

pytestmark = pytest.mark.timeout(180)

TINY = ["--object", "bell", "--views", "1", "--test-views", "1", "--grasps", "1", "--resolution", "16"]

# A process holding a scene open (as a capture in progress does) until its stdin closes.
HOLDER = r"""
import sys
from tacsplat.datasets import SceneMeta, SceneWriter
from tacsplat.types import CameraIntrinsics
import numpy as np

path = sys.argv[1]
K = np.array([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]])
with SceneWriter.create(path, CameraIntrinsics(K, 16, 16), SceneMeta("sim", "held")):
    print("holding", flush=True)
    sys.stdin.read()
"""


def _tacsplat(*args, **kw):
    return subprocess.Popen(
        [sys.executable, "-m", "tacsplat", "-q", *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        **kw,
    )


def test_a_resume_while_another_process_writes_the_scene_names_it_and_the_option(tmp_path):
    out = tmp_path / "scene"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline() == "holding\n"
        resumed = _tacsplat("sim-capture", *TINY, "--out", out, "--resume")
        _, err = resumed.communicate()
        assert resumed.returncode == 1
        assert err.splitlines() == [
            f"error: {out} is being written by another tacsplat process (PID {holder.pid}): "
            "wait for it to end, then continue the scene with --resume"
        ], err
    finally:
        holder.stdin.close()
        holder.wait()


def test_two_captures_into_one_new_folder_at_once_one_wins_and_the_other_is_told_what_to_do(tmp_path):
    out = tmp_path / "scene"
    runs = [_tacsplat("sim-capture", *TINY, "--out", out) for _ in range(2)]
    results = [(run.pid, *run.communicate(), run.returncode) for run in runs]
    assert sorted(code for *_, code in results) == [0, 1], results
    (winner, *_), (_, _, err, _) = sorted(results, key=lambda r: r[3])
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and "--resume" in err, err
    assert "SceneWriter" not in err, err
    if "another tacsplat process" in err:  # the loser found the winner at work, not done
        assert f"(PID {winner})" in err, err
    scene, problems = check_scene(out)
    assert problems == [] and len(scene.frames) == 2 and len(scene.touches) == 4


@pytest.mark.parametrize(
    "args, option, words",
    [
        (["--object-radius", "0.0005"], "--object-radius", "must be in [0.025, 0.3] m"),
        (["--object-radius", "0.02"], "--object-radius", "must be in [0.025, 0.3] m"),
        (["--object-radius", "0.31"], "--object-radius", "must be in [0.025, 0.3] m"),
        (["--views", "0"], "--views", "must be >= 1, got 0"),
        (["--test-views", "-1"], "--test-views", "must be >= 0, got -1"),
        (["--grasps", "-1"], "--grasps", "must be >= 0, got -1"),
        (["--resolution", "7"], "--resolution", "must be in [8, 4096] px, got 7"),
        (["--resolution", "4097"], "--resolution", "must be in [8, 4096] px, got 4097"),
        (["--seed", "-1"], "--seed", "must be >= 0, got -1"),
        (["--touch-model", "paper", "--surface-points", "49"], "--surface-points", "must be at least the 50 points"),
        (["--texture", "plaid"], "--texture", "must be one of 'none', 'checker'"),
    ],
)
def test_sim_capture_values_out_of_range_are_usage_errors(tmp_path, capsys, args, option, words):
    out = tmp_path / "scene"
    assert main(["sim-capture", *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"tacsplat sim-capture: error: {option}: {words}" in err and "--help" in err, err
    assert not out.exists()


@pytest.mark.parametrize(
    "args, option, words",
    [
        (["--object-radius", "0.0005"], "--object-radius", "must be in [0.025, 0.3] m"),
        (["--grasps", "0"], "--grasps", "must be an integer >= 1, got 0"),
        (["--seed", "-1"], "--seed", "must be an integer >= 0, got -1"),
        (["--touch-model", "paper", "--surface-points", "1"], "--surface-points", "must be at least the 50 points"),
        (["--touch-model", "nope"], "--touch-model", "must be one of 'gel', 'paper'"),
    ],
)
def test_simulate_touches_values_out_of_range_are_usage_errors(tmp_path, capsys, args, option, words):
    assert main(["simulate-touches", "--mesh", str(tmp_path / "m.ply"), str(tmp_path / "scene"), *args]) == 2
    err = capsys.readouterr().err
    assert f"tacsplat simulate-touches: error: {option}: {words}" in err, err


def test_a_rig_file_with_an_object_too_small_to_grasp_is_one_error_naming_the_radius(tmp_path):
    rig = tmp_path / "sim.yaml"
    rig.write_text(
        yaml.safe_dump(
            {
                "rig": "sim",
                "sim": {"object": "bell", "object_radius": 0.0005, "resolution": 16},
                "plan": {
                    "views": {"train": 1, "test": 0, "mode": "hemisphere"},
                    "grasps": {"count": 0, "mode": "random"},
                },
            }
        )
    )
    run = _tacsplat("capture", "--rig", rig, "--out", tmp_path / "scene")
    _, err = run.communicate()
    assert run.returncode == 1 and "Traceback" not in err, err
    assert f"{rig}: sim.object_radius: must be in [0.025, 0.3] m, got 0.0005" in err, err  # when the file loads


@pytest.mark.parametrize(
    "rig, args, code, words",
    [
        ("sim", ["--views", "3"], 2, "tacsplat sim-capture: error: --views: {rig} sets the capture with --rig"),
        ("real", [], 1, "{rig}: rig: this command runs a rig: sim file, got rig: real"),
    ],
)
def test_sim_capture_with_a_rig_file_takes_no_other_capture_option_and_no_real_rig(
    tmp_path, capsys, rig, args, code, words
):
    path = tmp_path / "rig.yaml"
    path.write_text(f"rig: {rig}\n")
    out = tmp_path / "scene"
    assert main(["sim-capture", "--rig", str(path), "--out", str(out), *args]) == code
    assert words.format(rig=path) in capsys.readouterr().err
    assert not out.exists()


def _documented_radii(command: str) -> tuple[str, str]:
    """The ends of ``--object-radius``'s range as the command's --help states it."""
    help_text = subprocess.run(
        [sys.executable, "-m", "tacsplat", command, "--help"], capture_output=True, text=True
    ).stdout
    found = re.search(r"\(([\d.]+) to ([\d.]+): the sizes the twin's hand grasps\)", " ".join(help_text.split()))
    assert found, f"{command} --help states no range of --object-radius"
    return found.group(1), found.group(2)


@pytest.mark.parametrize("end", [0, 1], ids=["smallest", "largest"])
def test_the_documented_object_radii_are_grasped_at_both_ends(tmp_path, end):
    radius = _documented_radii("sim-capture")[end]
    assert _documented_radii("simulate-touches")[end] == radius
    out = tmp_path / "scene"
    run = _tacsplat(
        "sim-capture",
        "--object",
        "torus",
        "--views",
        "1",
        "--test-views",
        "0",
        "--grasps",
        "2",
        "--resolution",
        "8",
        "--seed",
        "1",
        "--object-radius",
        radius,
        "--out",
        out,
    )
    _, err = run.communicate()
    assert run.returncode == 0, err
    scene = Scene.load(out)
    for grasp in (0, 1):  # every grasp touches the object, most with two pads or more
        assert any(t.in_contact for t in scene.touches if t.grasp == grasp)
    assert sum(t.in_contact for t in scene.touches) >= 3
