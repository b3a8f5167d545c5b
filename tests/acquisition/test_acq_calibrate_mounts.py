"""tacsplat calibrate mounts: on twins hiding random mounting errors (up to 2 mm and 3 degrees per sensor) and a
hand-eye error (up to 5 mm and 3 degrees), after calibrate hand-eye (which the mounting errors throw off) it finds
each T_fingertip_sensor within 0.5 mm and 1 degree and T_hand_cam within 1 mm and 0.5 degree, solved together; it
runs with standard input closed, and a capture with its files puts the touches back on the mesh."""

import os
import sys

import numpy as np
import pytest
import trimesh
import yaml
from scipy.spatial.transform import Rotation

from tacsplat.acquisition.calibrate import calibrate_hand_eye, calibrate_mounts
from tacsplat.acquisition.config import load_rig
from tacsplat.cli import main
from tacsplat.drivers.press_calibration import load_hand_eye, load_mounts
from tacsplat.sim.hand import FINGER_NAMES, nominal_T_hand_cam

pytestmark = pytest.mark.timeout(300)

FINE_BOARD = {"squares_x": 14, "squares_y": 10, "square_length_m": 0.015, "marker_length_m": 0.011}


def _pose_error(rng, m: float, deg: float) -> dict:
    t, r = rng.normal(size=3), rng.normal(size=3)
    t *= m * rng.uniform(0.3, 1.0) / np.linalg.norm(t)
    r *= deg * rng.uniform(0.3, 1.0) / np.linalg.norm(r)
    return {"translation_m": t.tolist(), "rotation_deg": r.tolist()}


def _draw(seed: int) -> dict:
    """A mounting error up to 2 mm and 3 degrees for each sensor, a hand-eye error up to 5 mm and 3 degrees."""
    rng = np.random.default_rng(seed)
    mounts = {finger: _pose_error(rng, 0.002, 3.0) for finger in FINGER_NAMES}
    return {"mounts": mounts, "hand_eye": _pose_error(rng, 0.005, 3.0)}


def _matrix(e: dict) -> np.ndarray:
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(e["rotation_deg"], degrees=True).as_matrix()
    E[:3, 3] = e["translation_m"]
    return E


def _off(T: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    D = np.linalg.inv(truth) @ T
    return 1000 * float(np.linalg.norm(D[:3, 3])), float(np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()))


def _rig(tmp_path, errors: dict, **more) -> str:
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"rig": "sim", "board": FINE_BOARD, "sim": {"true_errors": errors}, **more}))
    return str(path)


def _recovery(tmp_path, seed: int) -> dict:
    """calibrate hand-eye, then calibrate mounts from its file: name: (mm, degrees) off the twin's truth, for
    T_hand_cam after each and for each mount."""
    errors = _draw(seed)
    calibrate_hand_eye(load_rig(_rig(tmp_path, errors)), tmp_path / "he.json", lambda s: 0)
    rig = _rig(tmp_path, errors, camera={"hand_eye": "he.json"})
    calibrate_mounts(load_rig(rig), tmp_path / "mounts.json", tmp_path / "he2.json", lambda s: 0)
    T_hand_cam = nominal_T_hand_cam() @ _matrix(errors["hand_eye"])
    mounts = load_mounts(tmp_path / "mounts.json", FINGER_NAMES)
    found = {f: _off(mounts[f], _matrix(e)) for f, e in errors["mounts"].items()}
    found["hand-eye alone"] = _off(load_hand_eye(tmp_path / "he.json"), T_hand_cam)
    found["hand-eye"] = _off(load_hand_eye(tmp_path / "he2.json"), T_hand_cam)
    print(f"seed {seed}: " + ", ".join(f"{f} {mm:.3f} mm {deg:.3f} deg" for f, (mm, deg) in found.items()))
    return found


def _good(found: dict) -> bool:
    mounts = all(mm < 0.5 and deg < 1.0 for f, (mm, deg) in found.items() if f in FINGER_NAMES)
    mm, deg = found["hand-eye"]
    return mounts and mm < 1.0 and deg < 0.5


@pytest.mark.slow  # (draw 7 runs in make test: the command test)
@pytest.mark.parametrize("seed", [0])
def test_it_recovers_each_hidden_mounting_error_and_the_hand_eye_together(tmp_path, seed):
    found = _recovery(tmp_path, seed)
    assert _good(found)


@pytest.mark.slow
def test_ten_draws_recover_within_half_a_mm_and_a_degree(tmp_path):
    """The issue's measurement: 10 draws (40 sensors); prints the worst and median errors."""
    found = [_recovery(tmp_path / str(seed), seed) for seed in range(10, 20)]
    for names in (FINGER_NAMES, ["hand-eye alone"], ["hand-eye"]):
        mm = [f[n][0] for f in found for n in names]
        deg = [f[n][1] for f in found for n in names]
        print(
            f"10 draws, {names if len(names) == 1 else 'mounts'}: max {max(mm):.3f} mm, {max(deg):.3f} deg; "
            f"median {np.median(mm):.3f} mm, {np.median(deg):.3f} deg"
        )
    assert all(_good(f) for f in found)


def _touch_median_mm(tmp_path, rig: str) -> float:
    """The median distance (mm) of a ``sim-capture --rig`` capture's touches to the object's mesh."""
    from tacsplat.datasets import Scene

    assert main(["sim-capture", "--rig", rig, "--out", str(tmp_path / "scene")]) == 0
    scene = Scene.load(tmp_path / "scene")
    mesh = trimesh.load(scene.gt_mesh_path, force="mesh")
    _, distance, _ = trimesh.proximity.closest_point(mesh, scene.touch_points())
    return 1000 * float(np.median(distance))


def test_the_command_runs_with_stdin_closed_and_a_capture_with_its_file_touches_the_mesh(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    errors = _draw(7)
    out, he = tmp_path / "calibration" / "mounts.json", tmp_path / "calibration" / "hand_eye.json"
    assert main(["calibrate", "hand-eye", "--rig", _rig(tmp_path, errors), "--out", str(he)]) == 0
    rig = _rig(tmp_path, errors, camera={"hand_eye": "calibration/hand_eye.json"})
    assert main(["calibrate", "mounts", "--rig", rig, "--out", str(out), "--hand-eye", str(he)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(line.startswith("press 17/") and "index on the sphere (placement 2)" in line for line in lines)
    assert [line.split(":")[0] for line in lines[-7:-2]] == [*FINGER_NAMES, "T_hand_cam"]
    assert lines[-2].startswith(f"wrote {he}") and lines[-1].startswith(f"wrote {out} (4 sensors")
    mounts = load_mounts(out, FINGER_NAMES)
    found = {f: _off(mounts[f], _matrix(e)) for f, e in errors["mounts"].items()}
    found["hand-eye"] = _off(load_hand_eye(he), nominal_T_hand_cam() @ _matrix(errors["hand_eye"]))
    assert _good(found), found  # each hidden error recovered
    scene = {"object": "bell", "resolution": 32, "seed": 3, "true_errors": errors}
    plan = {"views": {"train": 1, "test": 0, "mode": "hemisphere"}, "grasps": {"count": 2, "mode": "random"}}
    nominal = _touch_median_mm(tmp_path / "nominal", _scene_rig(tmp_path / "nominal", scene, plan))
    files = {"camera": {"hand_eye": "calibration/hand_eye.json"}, "tactile": {"mounts": "calibration/mounts.json"}}
    calibrated = _touch_median_mm(tmp_path, _scene_rig(tmp_path, scene, plan, **files))
    print(f"median touch distance to the mesh: {nominal:.3f} mm nominal, {calibrated:.3f} mm calibrated")
    assert calibrated < 0.3 < nominal


def _scene_rig(tmp_path, sim: dict, plan: dict, **more) -> str:
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "scene_rig.yaml"
    path.write_text(yaml.safe_dump({"rig": "sim", "sim": sim, "plan": plan, **more}))
    return str(path)


@pytest.mark.parametrize("given, found", [("58", True), (None, False)])
def test_the_stand_height_given_as_measured_is_the_one_the_mounts_are_solved_with(
    tmp_path, capsys, monkeypatch, given, found
):
    """A twin whose stand holds the sphere's centre 58 mm over the board: given as measured (--stand-height-mm 58)
    every mount is found within 0.5 mm and 1 degree; left at the 60 mm default, the mounts come out about 2 mm off."""
    from tacsplat.acquisition import presses

    board_place, (x, y, _) = presses.SPHERE_PLACEMENTS
    monkeypatch.setattr(presses, "SPHERE_PLACEMENTS", (board_place, (x, y, 0.058)))
    errors = _draw(7)
    out = tmp_path / "mounts.json"
    option = ["--stand-height-mm", given] if given else []
    args = ["--out", str(out), "--hand-eye", str(tmp_path / "hand_eye.json"), *option]
    assert main(["calibrate", "mounts", "--rig", _rig(tmp_path, errors), *args]) == 0
    assert f"its centre {given or 60} mm over the board" in capsys.readouterr().out
    mounts = load_mounts(out, FINGER_NAMES)
    off = {f: _off(mounts[f], _matrix(e)) for f, e in errors["mounts"].items()}  # (mm, degrees)
    assert all(mm < 0.5 and deg < 1.0 for mm, deg in off.values()) == found, off


@pytest.mark.parametrize("value", ["0", "-60", "nan", "inf"])
def test_a_stand_height_that_is_not_a_positive_finite_number_is_a_usage_error(tmp_path, capsys, value):
    out = tmp_path / "mounts.json"
    code = main(
        ["calibrate", "mounts", "--rig", _rig(tmp_path, _draw(7)), "--out", str(out), f"--stand-height-mm={value}"]
    )
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and not out.exists()
    assert "--stand-height-mm: must be a positive, finite height in mm, got " in err.splitlines()[-1], err


def test_a_hand_eye_file_that_is_a_folder_is_refused_before_any_press(tmp_path, capsys):
    (tmp_path / "calibration").mkdir()
    out = tmp_path / "mounts.json"
    args = ["--out", str(out), "--hand-eye", str(tmp_path / "calibration")]
    assert main(["calibrate", "mounts", "--rig", _rig(tmp_path, _draw(7)), *args]) == 1
    stdout, err = capsys.readouterr()
    assert "press" not in stdout and not out.exists()
    assert err.splitlines()[-1] == f"error: --hand-eye: {tmp_path / 'calibration'} is a folder; give a .json file"


@pytest.mark.parametrize("failing", ["hand_eye.json", "mounts.json"])
def test_the_mounts_and_hand_eye_files_are_both_written_or_neither(tmp_path, capsys, failing):
    """A write that fails (here: its temporary name taken by a folder) leaves both old files as they were: never a new
    mounts file beside an old hand-eye file, or the other way round."""
    out, he = tmp_path / "mounts.json", tmp_path / "hand_eye.json"
    out.write_text("old mounts\n")
    he.write_text("old hand-eye\n")
    (tmp_path / f"{failing}.tmp").mkdir()
    args = ["--out", str(out), "--hand-eye", str(he)]
    assert main(["calibrate", "mounts", "--rig", _rig(tmp_path, _draw(7)), *args]) == 1
    err = capsys.readouterr().err
    assert err.splitlines()[-1].startswith(f"error: {tmp_path / failing}: "), err
    assert out.read_text() == "old mounts\n" and he.read_text() == "old hand-eye\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([out.name, he.name, f"{failing}.tmp", "rig.yaml"])


@pytest.mark.parametrize(
    "out, hand_eye", [("sub/../mounts.json", "mounts.json"), ("link/mounts.json", "sub/mounts.json")]
)
def test_a_hand_eye_file_that_is_out_under_another_name_is_refused_before_any_press(
    tmp_path, capsys, monkeypatch, out, hand_eye
):
    """Through '..' or a symbolic link, one file: both would be written to it (the hand-eye file's write then fails
    after every press), so it is refused as the same name is."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "sub")
    rig = _rig(tmp_path, _draw(7))
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", "mounts", "--rig", rig, "--out", out, "--hand-eye", hand_eye]) == 2
    stdout, err = capsys.readouterr()
    assert "press" not in stdout and not (tmp_path / out).exists()
    assert f"--hand-eye: {hand_eye} is --out's file too: give the hand-eye file another name" in err.splitlines()[-1]
