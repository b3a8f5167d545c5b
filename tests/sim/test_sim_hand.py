"""The hand model and its forward kinematics (tacsplat.sim.hand)."""

import subprocess
import sys

import numpy as np
import pytest

from tacsplat.errors import InvalidInputError
from tacsplat.geometry import rigidity_problem
from tacsplat.sim.hand import FINGER_NAMES, HandGeometry, HandKinematics, build_hand_mjcf


@pytest.fixture(scope="module")
def kin():
    return HandKinematics()


def test_hand_model_compiles_with_sixteen_actuated_joints():
    import mujoco

    model = mujoco.MjModel.from_xml_string(build_hand_mjcf())
    assert model.njnt == 16 and model.nu == 16
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    for f in FINGER_NAMES:
        model.site(f"{f}_tactile")
        model.geom(f"{f}_pad")
    model.camera("wrist")


def test_names_and_limits(kin):
    assert kin.finger_names == ["index", "middle", "ring", "thumb"]
    assert kin.joint_names[:4] == ["index_0", "index_1", "index_2", "index_3"]
    assert kin.joint_names[12:] == ["thumb_0", "thumb_1", "thumb_2", "thumb_3"]
    lim = kin.joint_limits
    assert lim.shape == (16, 2) and np.all(lim[:, 0] < lim[:, 1])
    assert np.allclose(lim[1], [-0.196, 1.61])  # Allegro index flexion


def test_open_hand_pads_face_palm_normal(kin):
    g = HandGeometry()
    poses = kin.fingertip_poses(np.zeros(16))
    pad_x = g.palm_half_length + g.knuckle_length + g.proximal_length + g.middle_length + g.pad_centre_from_joint
    assert np.allclose(poses["index"][:3, 3], [pad_x, g.finger_spacing, g.gel_thickness], atol=1e-9)
    thumb_x = g.palm_half_length + g.knuckle_length + g.thumb_proximal_length + g.thumb_middle_length
    assert np.allclose(poses["thumb"][:3, 3], [-(thumb_x + g.pad_centre_from_joint), 0, g.gel_thickness], atol=1e-9)
    for T in poses.values():
        assert rigidity_problem(T) is None
        assert np.allclose(T[:3, 2], [0, 0, 1], atol=1e-9)


def test_flexion_turns_pads_towards_the_grasp_centre(kin):
    q = np.zeros(16)
    q[1] = np.pi / 2  # index first flexion joint
    q[13] = np.pi / 2 * 0.7
    poses = kin.fingertip_poses(q)
    assert np.allclose(poses["index"][:3, 2], [-1, 0, 0], atol=1e-9)  # pad looks back over the palm
    assert poses["index"][2, 3] > 0.05
    assert poses["thumb"][0, 2] > 0.5  # thumb pad turns towards the fingers (+x)
    assert np.allclose(poses["middle"][:3, 2], [0, 0, 1])


def test_bad_joint_vectors_are_rejected(kin):
    with pytest.raises(InvalidInputError, match="shape"):
        kin.fingertip_poses(np.zeros(15))
    q = np.zeros(16)
    q[3] = np.nan
    with pytest.raises(InvalidInputError, match="NaN"):
        kin.fingertip_poses(q)


def test_importing_the_hand_module_does_not_load_mujoco():
    code = "import sys, tacsplat.sim.hand, tacsplat.sim.tactile; print('mujoco' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", out.stderr
