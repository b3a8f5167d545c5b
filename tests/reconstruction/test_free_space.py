"""Free space from the hand's recorded motion: the voxel grid is exact, carves what the boxes swept and nothing
else, gives back the neighbourhood of contacts, and training takes the opacity of Gaussians in it."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from tacsplat.datasets import HandMotion
from tacsplat.datasets.records import MOTION_PHASES
from tacsplat.geometry import make_pose
from tacsplat.reconstruction.free_space import _fill_boxes, carving_boxes, free_space, free_space_loss

GEL = np.array([0.012, 0.0096, 0.001])  # half extents of a pad's gel, metres


def gel_motion(z_stops, phases=None, grasp=0) -> HandMotion:
    """One gel, face up (+z), moved along +z so that its outer surface goes through ``z_stops``."""
    S = len(z_stops)
    poses = np.stack([make_pose(np.eye(3), [0.0, 0.0, z - GEL[2]]) for z in z_stops])[:, None]  # [S, 1, 4, 4]
    phases = np.full(S, MOTION_PHASES.index("close")) if phases is None else np.asarray(phases)
    return HandMotion(
        grasp=grasp,
        joint_names=("j",),
        t=np.arange(S) * 0.02,
        phase=phases,
        q=np.zeros((S, 1)),
        q_target=np.zeros((S, 1)),
        effort=np.full((S, 1), np.nan),
        effort_unit="A",
        T_world_hand=np.eye(4),
        link_names=("index_gel",),
        link_half_extents=GEL[None],
        link_poses=poses,
    )


def test_the_grid_holds_exactly_the_voxel_centres_inside_the_boxes():
    rng = np.random.default_rng(0)
    R = Rotation.random(30, random_state=1).as_matrix()
    t = rng.uniform(-0.03, 0.03, (30, 3))
    h = rng.uniform(0.002, 0.012, (30, 3))
    origin, voxel = np.full(3, -0.045), 0.0015
    free = np.zeros((60, 60, 60), bool)
    _fill_boxes(free, origin, voxel, R, t, h)
    centres = origin + (np.argwhere(np.ones(free.shape, bool)) + 0.5) * voxel
    inside = np.zeros(len(centres), bool)
    for b in range(len(R)):
        inside |= np.all(np.abs((centres - t[b]) @ R[b]) <= h[b], axis=1)
    assert free.any() and np.array_equal(free.reshape(-1), inside)


def test_a_gel_that_closed_on_nothing_carves_what_it_swept_and_nothing_beyond_or_behind():
    margin, voxel = 0.0002, 0.0002
    stops = np.linspace(0.0, 0.02, 41)  # its surface from z = 0 to 20 mm, 0.5 mm a sample
    space = free_space([gel_motion(stops)], np.zeros((0, 3)), 0.0, margin, voxel)
    swept = np.array([[0.0, 0.0, z] for z in np.linspace(-0.0015, 0.0195, 30)])
    assert space.contains(swept).all()
    assert space.contains(np.array([[0.01, 0.008, 0.01]])).all()  # off the axis, inside the swept prism
    beyond = np.array([[0.0, 0.0, 0.0201], [0.0, 0.0, 0.021], [0.0, 0.0, 0.05]])  # past its final surface
    behind = np.array([[0.0, 0.0, -0.0021], [0.0, 0.0, -0.01]])  # behind where it started
    beside = np.array([[0.0125, 0.0, 0.01], [0.0, 0.0101, 0.01]])  # outside its sides
    assert not space.contains(np.concatenate([beyond, behind, beside])).any()


def test_the_release_and_the_shrunk_margin_carve_nothing():
    close, release = MOTION_PHASES.index("close"), MOTION_PHASES.index("open")
    motion = gel_motion([0.0, 0.05], phases=[close, release])
    T, h = carving_boxes([motion], margin=0.0)
    assert len(T) == 1 and np.allclose(T[0, 2, 3], -GEL[2])  # only the close sample
    assert free_space([motion], np.zeros((0, 3)), 0.0, margin=0.0011) is None  # a 2 mm gel shrunk by 1.1 mm


def test_the_neighbourhood_of_a_contact_is_given_back():
    space_without = free_space([gel_motion(np.linspace(0, 0.02, 41))], np.zeros((0, 3)), 0.0, 0.0002, 0.0002)
    contact = np.array([[0.0, 0.0, 0.02]])  # where the gel stopped
    space = free_space([gel_motion(np.linspace(0, 0.02, 41))], contact, 0.001, 0.0002, 0.0002)
    near = np.array([[0.0, 0.0, 0.019], [0.0005, 0.0, 0.0195]])  # within 1.2 mm of the contact
    far = np.array([[0.0, 0.0, 0.017]])
    assert space_without.contains(near).all() and not space.contains(near).any()
    assert space.contains(far).all()


def test_gaussians_in_free_space_lose_their_opacity_and_the_others_keep_it():
    space = free_space([gel_motion(np.linspace(0, 0.02, 41))], np.zeros((0, 3)), 0.0, 0.0002, 0.0005)
    means = torch.tensor([[0.0, 0.0, 0.01], [0.0, 0.0, 0.03], [0.05, 0.0, 0.0]])  # swept, beyond, elsewhere
    logits = torch.zeros(3, requires_grad=True)
    optimizer = torch.optim.Adam([logits], lr=0.05)
    for _ in range(100):
        loss = free_space_loss(means, logits, space)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    opacity = torch.sigmoid(logits).detach()
    assert opacity[0] < 0.05
    assert torch.equal(opacity[1:], torch.full((2,), 0.5))


@pytest.mark.parametrize("bad", ["t", "link_poses"])
def test_a_motion_with_nan_is_refused_naming_the_array(bad):
    motion = gel_motion([0.0, 0.01])
    arrays = motion.to_arrays()
    arrays[bad] = np.where(True, np.nan, arrays[bad])
    with pytest.raises(Exception, match=bad):
        HandMotion.from_arrays(arrays)
