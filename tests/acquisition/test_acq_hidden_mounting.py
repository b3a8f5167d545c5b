"""The twin hides the rig file's hand-eye and mounting errors as a miscalibrated real rig does: the wrist camera and
the pads sit off their nominal poses, and a capture that computes poses with the nominal calibration puts its
touches off the surface by the error; with no error, on it."""

import numpy as np
import pytest
import trimesh
import yaml

from tacsplat.acquisition.config import load_rig
from tacsplat.acquisition.devices import twin_config
from tacsplat.acquisition.sim_capture import sim_capture
from tacsplat.datasets import Scene
from tacsplat.geometry import invert_pose
from tacsplat.sim.hand import FINGER_NAMES, nominal_T_hand_cam
from tacsplat.sim.twin import SimTwin

pytestmark = pytest.mark.timeout(300)


def _rig(tmp_path, true_errors: dict) -> str:
    data = {
        "rig": "sim",
        "sim": {"object": "bell", "resolution": 32, "seed": 3, "true_errors": true_errors},
        "plan": {"views": {"train": 1, "test": 0, "mode": "hemisphere"}, "grasps": {"count": 2, "mode": "random"}},
    }
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def _touch_distances_mm(tmp_path, true_errors: dict) -> np.ndarray:
    out = tmp_path / "scene"
    sim_capture(load_rig(_rig(tmp_path, true_errors)), out, progress=False)
    scene = Scene.load(out)
    mesh = trimesh.load(scene.gt_mesh_path, force="mesh")
    _, distance, _ = trimesh.proximity.closest_point(mesh, scene.touch_points())
    return 1000 * distance


MOUNT_2MM = {"translation_m": [0.0, 0.0, 0.002], "rotation_deg": [0.0, 0.0, 0.0]}  # the pad sits 2 mm proud


def test_a_capture_with_the_nominal_mounting_puts_touches_off_the_mesh_by_the_hidden_error(tmp_path):
    exact = _touch_distances_mm(tmp_path / "exact", {})
    off = _touch_distances_mm(tmp_path / "off", {"mounts": dict.fromkeys(FINGER_NAMES, MOUNT_2MM)})
    print(f"median touch distance to the mesh: {np.median(exact):.3f} mm exact, {np.median(off):.3f} mm off")
    assert np.median(exact) < 0.3
    assert 1.5 < np.median(off) < 2.5


def test_the_twins_camera_and_pads_sit_off_nominal_and_the_rig_computes_poses_from_nominal(tmp_path):
    errors = {
        "hand_eye": {"translation_m": [0.004, -0.002, 0.001], "rotation_deg": [1.0, -2.0, 0.5]},
        "mounts": {"ring": {"translation_m": [0.001, 0.0, -0.0015], "rotation_deg": [0.0, 3.0, 0.0]}},
    }
    config = load_rig(_rig(tmp_path, errors))
    E_cam = config.sim.true_errors.hand_eye.matrix()
    E_ring = config.sim.true_errors.mounts["ring"].matrix()
    with SimTwin(twin_config(config)) as twin:
        T_world_hand = twin.T_world_hand()
        T_hand_cam_true = invert_pose(T_world_hand) @ twin.wrist_camera.pose()
        assert np.allclose(T_hand_cam_true, nominal_T_hand_cam() @ E_cam, atol=1e-6)
        N = nominal_T_hand_cam()
        assert np.allclose(twin.hand_pose_from_wrist_camera(), T_world_hand @ N @ E_cam @ invert_pose(N), atol=1e-6)
        for pad in twin.tactile_sensors:
            reading = pad.read()
            E = E_ring if pad.name == "ring" else np.eye(4)
            assert np.allclose(invert_pose(T_world_hand) @ pad.T_world_sensor(), reading.T_ref_sensor @ E, atol=1e-6)
