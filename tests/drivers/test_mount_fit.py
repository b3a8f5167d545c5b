"""fit_mounts on synthetic presses: contact patches generated from known mounts, T_hand_cam and sphere with no noise
are solved back exactly from a start off by the largest errors; a press with a flipped board pose is dropped; a press
set that leaves an axis undetermined is refused naming what to press."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tacsplat.drivers.press_calibration import Press, fit_mounts
from tacsplat.errors import InvalidInputError
from tacsplat.geometry import invert_pose, make_pose

RADIUS = 0.0125
INDENT = 0.0006
PIXEL = 0.00015
SPOTS = ((0.006, 0.0), (-0.006, 0.0), (0.0, 0.005), (0.0, -0.005))


def _mount(rng, mm=2.0, deg=3.0) -> np.ndarray:
    t, r = rng.normal(size=3), rng.normal(size=3)
    return make_pose(Rotation.from_rotvec(np.radians(deg) * r / np.linalg.norm(r)).as_matrix(), mm / 1000 * t / 3)


def _press(rng, M, T_hand_cam, centre, spot, finger="index", placement=1) -> Press:
    """A press of the pad's ``spot`` on the sphere at ``centre``, the fingertip in a random pose on the hand and
    the sphere reached from a random direction above the board."""
    d = rng.normal(size=3)
    d[2] = abs(d[2]) + 0.3
    d /= np.linalg.norm(d)
    z = -d
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    R = (
        np.column_stack([x, np.cross(z, x), z])
        @ Rotation.from_euler("z", rng.uniform(0, 360), degrees=True).as_matrix()
    )
    T_world_sensor = make_pose(R, centre + (RADIUS - INDENT) * d - R @ np.array([*spot, 0.0]))
    T_hand_fingertip = make_pose(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-0.1, 0.1, 3))
    T_world_hand = T_world_sensor @ invert_pose(T_hand_fingertip @ M)
    c = (invert_pose(T_world_sensor) @ np.r_[centre, 1.0])[:3]  # the sphere's centre in the sensor frame
    gx, gy = np.meshgrid(np.arange(-64, 64) * PIXEL, np.arange(-80, 80) * PIXEL)
    inside = (gx - c[0]) ** 2 + (gy - c[1]) ** 2 < RADIUS**2
    zs = c[2] - np.sqrt(np.clip(RADIUS**2 - (gx - c[0]) ** 2 - (gy - c[1]) ** 2, 0, None))
    hit = inside & (zs < 0)
    points = np.stack([gx[hit], gy[hit], zs[hit]], axis=1)
    return Press(finger, T_hand_fingertip, points, T_world_hand @ T_hand_cam, "sphere", placement)


def _error(T, M) -> tuple[float, float]:
    D = invert_pose(M) @ T
    return 1000 * np.linalg.norm(D[:3, 3]), np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude())


BOARD_CENTRE = np.array([0.025, -0.025, RADIUS])  # placement 0: resting on the board
STAND_CENTRE = np.array([0.1, -0.07, 0.06])  # placement 1: on a stand
HEIGHTS = {0: RADIUS, 1: 0.06}
FINGERS = ("index", "thumb")


def _presses(rng, mounts, T_hand_cam, spots=SPOTS) -> list:
    """Each finger's pad centre on the sphere on the board twice, and ``spots`` of it on the stand's twice."""
    out = []
    for f in FINGERS:
        out += [_press(rng, mounts[f], T_hand_cam, BOARD_CENTRE, (0.0, 0.0), f, 0) for _ in range(2)]
        out += [_press(rng, mounts[f], T_hand_cam, STAND_CENTRE, spot, f, 1) for spot in spots for _ in range(2)]
    return out


def _truth(seed):
    rng = np.random.default_rng(seed)
    mounts = {f: _mount(rng) for f in FINGERS}
    T_hand_cam = make_pose(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-0.05, 0.05, 3))
    return rng, mounts, T_hand_cam, T_hand_cam @ _mount(rng, 5.0, 3.0)  # the start: off by 5 mm, 3 degrees


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_known_mounts_and_hand_eye_are_recovered_exactly_from_noiseless_presses(seed):
    rng, mounts, T_hand_cam, start = _truth(seed)
    fit = fit_mounts(_presses(rng, mounts, T_hand_cam), RADIUS, HEIGHTS, start)
    for f in FINGERS:
        mm, deg = _error(fit.mounts[f], mounts[f])
        assert mm < 1e-4 and deg < 1e-4 and fit.rms_mm[f] < 1e-4
    mm, deg = _error(fit.T_hand_cam, T_hand_cam)
    assert mm < 1e-4 and deg < 1e-4
    assert np.allclose(fit.sphere_centres[0], BOARD_CENTRE, atol=1e-7)
    assert np.allclose(fit.sphere_centres[1], STAND_CENTRE, atol=1e-7)


def test_a_press_with_a_flipped_board_pose_is_dropped_and_the_mounts_still_recovered():
    rng, mounts, T_hand_cam, start = _truth(3)
    presses = _presses(rng, mounts, T_hand_cam)
    bad = presses[5]
    flipped = make_pose(Rotation.from_euler("y", 40, degrees=True).as_matrix(), [0.09, 0.0, 0.05]) @ bad.T_world_cam
    presses[5] = Press(bad.finger, bad.T_hand_fingertip, bad.points_sensor, flipped, "sphere", bad.placement)
    fit = fit_mounts(presses, RADIUS, HEIGHTS, start)
    assert fit.dropped == {"index": 1, "thumb": 0} and fit.presses == {"index": 9, "thumb": 10}
    for f in FINGERS:
        mm, deg = _error(fit.mounts[f], mounts[f])
        assert mm < 1e-4 and deg < 1e-4


def test_presses_that_leave_an_axis_undetermined_are_refused_naming_the_axes_and_the_spots_to_add():
    rng, mounts, T_hand_cam, start = _truth(5)
    with pytest.raises(InvalidInputError, match=r"undetermined: index mount rotation.*further apart along its x and y"):
        fit_mounts(_presses(rng, mounts, T_hand_cam, [(0.0, 0.0)]), RADIUS, HEIGHTS, start)
    line = _presses(rng, mounts, T_hand_cam, [(0.006, 0.0), (-0.006, 0.0)])
    with pytest.raises(InvalidInputError, match=r"index mount rotation about x.*along its y axis"):
        fit_mounts(line, RADIUS, HEIGHTS, start)
