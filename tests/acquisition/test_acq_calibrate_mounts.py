"""tacsplat calibrate mounts: on twins hiding random mounting errors (up to 2 mm and 3 degrees per sensor) it finds
each T_fingertip_sensor within 0.5 mm and 1 degree from presses of four places of each pad on a sphere on a stand,
runs with standard input closed, and a capture with its file puts the touches back on the mesh."""

import os
import sys

import numpy as np
import pytest
import trimesh
import yaml
from scipy.spatial.transform import Rotation

from tacsplat.acquisition.calibrate import calibrate_mounts
from tacsplat.acquisition.config import load_rig
from tacsplat.cli import main
from tacsplat.drivers.press_calibration import load_mounts
from tacsplat.sim.hand import FINGER_NAMES

pytestmark = pytest.mark.timeout(300)

FINE_BOARD = {"squares_x": 14, "squares_y": 10, "square_length_m": 0.015, "marker_length_m": 0.011}


def _draw(seed: int) -> dict:
    """A mounting error up to 2 mm and 3 degrees for each sensor."""
    rng = np.random.default_rng(seed)
    out = {}
    for finger in FINGER_NAMES:
        t, r = rng.normal(size=3), rng.normal(size=3)
        t *= 0.002 * rng.uniform(0.3, 1.0) / np.linalg.norm(t)
        r *= 3.0 * rng.uniform(0.3, 1.0) / np.linalg.norm(r)
        out[finger] = {"translation_m": t.tolist(), "rotation_deg": r.tolist()}
    return {"mounts": out}


def _rig(tmp_path, errors: dict, **more) -> str:
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"rig": "sim", "board": FINE_BOARD, "sim": {"true_errors": errors}, **more}))
    return str(path)


def _errors(mounts: dict, errors: dict) -> dict:
    """finger: (mm, degrees) between a calibrated T_fingertip_sensor and the twin's true one."""
    out = {}
    for finger, e in errors["mounts"].items():
        E = np.eye(4)
        E[:3, :3] = Rotation.from_rotvec(e["rotation_deg"], degrees=True).as_matrix()
        E[:3, 3] = e["translation_m"]
        D = np.linalg.inv(E) @ mounts[finger]
        out[finger] = (1000 * np.linalg.norm(D[:3, 3]), np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude()))
    return out


def _recovery(tmp_path, seed: int) -> dict:
    errors = _draw(seed)
    calibrate_mounts(load_rig(_rig(tmp_path, errors)), tmp_path / "mounts.json", lambda s: 0)
    found = _errors(load_mounts(tmp_path / "mounts.json", FINGER_NAMES), errors)
    print(f"seed {seed}: " + ", ".join(f"{f} {mm:.3f} mm {deg:.3f} deg" for f, (mm, deg) in found.items()))
    return found


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_it_recovers_each_hidden_mounting_error_within_half_a_mm_and_a_degree(tmp_path, seed):
    found = _recovery(tmp_path, seed)
    assert set(found) == set(FINGER_NAMES)
    assert all(mm < 0.5 and deg < 1.0 for mm, deg in found.values())


@pytest.mark.slow
def test_ten_draws_recover_within_half_a_mm_and_a_degree(tmp_path):
    """The issue's measurement: 10 draws (40 sensors); prints the worst and median errors."""
    found = [_recovery(tmp_path / str(seed), seed) for seed in range(10, 20)]
    mm = [m for f in found for m, _ in f.values()]
    deg = [d for f in found for _, d in f.values()]
    print(
        f"10 draws, 40 sensors: max {max(mm):.3f} mm, {max(deg):.3f} deg; median {np.median(mm):.3f} mm, "
        f"{np.median(deg):.3f} deg"
    )
    assert max(mm) < 0.5 and max(deg) < 1.0


def _touch_median_mm(tmp_path, rig: str) -> float:
    from tacsplat.acquisition.sim_capture import sim_capture
    from tacsplat.datasets import Scene

    sim_capture(load_rig(rig), tmp_path / "scene", progress=False)
    scene = Scene.load(tmp_path / "scene")
    mesh = trimesh.load(scene.gt_mesh_path, force="mesh")
    _, distance, _ = trimesh.proximity.closest_point(mesh, scene.touch_points())
    return 1000 * float(np.median(distance))


def test_the_command_runs_with_stdin_closed_and_a_capture_with_its_file_touches_the_mesh(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys, "stdin", open(os.devnull))
    errors = _draw(7)  # a draw where one index press has a flipped board pose (6 corners), dropped
    out = tmp_path / "calibration" / "mounts.json"
    assert main(["calibrate", "mounts", "--rig", _rig(tmp_path, errors), "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(line.startswith("press 1/64: index on the sphere (placement 2)") for line in lines)
    assert [line.split(":")[0] for line in lines[-5:-1]] == FINGER_NAMES
    assert lines[-1].startswith(f"wrote {out} (4 sensors")
    scene = {"object": "bell", "resolution": 32, "seed": 3, "true_errors": errors}
    plan = {"views": {"train": 1, "test": 0, "mode": "hemisphere"}, "grasps": {"count": 2, "mode": "random"}}
    nominal = _touch_median_mm(tmp_path / "nominal", _scene_rig(tmp_path / "nominal", scene, plan))
    calibrated = _touch_median_mm(
        tmp_path, _scene_rig(tmp_path, scene, plan, tactile={"mounts": "calibration/mounts.json"})
    )
    print(f"median touch distance to the mesh: {nominal:.3f} mm nominal mounts, {calibrated:.3f} mm calibrated")
    assert calibrated < 0.3 < nominal


def _scene_rig(tmp_path, sim: dict, plan: dict, **more) -> str:
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "scene_rig.yaml"
    path.write_text(yaml.safe_dump({"rig": "sim", "sim": sim, "plan": plan, **more}))
    return str(path)
