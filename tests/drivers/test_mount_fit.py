"""fit_mount on synthetic presses: contact patches generated from a known mount, T_hand_cam and sphere with no noise
are solved back exactly; a press set that leaves an axis undetermined is refused naming what to press."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tacsplat.drivers.press_calibration import Press, fit_mount
from tacsplat.errors import InvalidInputError
from tacsplat.geometry import invert_pose, make_pose

RADIUS = 0.0125
INDENT = 0.0006
PIXEL = 0.00015
SPOTS = ((0.006, 0.0), (-0.006, 0.0), (0.0, 0.005), (0.0, -0.005))


def _mount(rng, mm=2.0, deg=3.0) -> np.ndarray:
    t, r = rng.normal(size=3), rng.normal(size=3)
    return make_pose(Rotation.from_rotvec(np.radians(deg) * r / np.linalg.norm(r)).as_matrix(), mm / 1000 * t / 3)


def _press(rng, M, T_hand_cam, centre, spot, finger="index") -> Press:
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
    return Press(finger, T_hand_fingertip, points, T_world_hand @ T_hand_cam, "sphere", 0)


def _error(T, M) -> tuple[float, float]:
    D = invert_pose(M) @ T
    return 1000 * np.linalg.norm(D[:3, 3]), np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_known_mount_is_recovered_exactly_from_noiseless_presses(seed):
    rng = np.random.default_rng(seed)
    M, T_hand_cam = _mount(rng), _mount(rng, 50.0, 30.0)
    centre = np.array([0.03, -0.02, RADIUS])
    presses = [_press(rng, M, T_hand_cam, centre, spot) for spot in SPOTS for _ in range(2)]
    fit = fit_mount(presses, RADIUS, T_hand_cam)
    mm, deg = _error(fit.T_fingertip_sensor, M)
    assert mm < 1e-4 and deg < 1e-4
    assert np.allclose(fit.sphere_centres[0], centre, atol=1e-7)
    assert fit.rms_mm < 1e-4


def test_presses_at_one_spot_are_refused_naming_the_axes_and_the_spots_to_add():
    rng = np.random.default_rng(5)
    M, T_hand_cam = _mount(rng), _mount(rng, 50.0, 30.0)
    centre = np.array([0.03, -0.02, RADIUS])
    presses = [_press(rng, M, T_hand_cam, centre, (0.0, 0.0)) for _ in range(4)]
    with pytest.raises(InvalidInputError, match=r"undetermined: index mount rotation.*further apart along its x and y"):
        fit_mount(presses, RADIUS, T_hand_cam)
    line = [_press(rng, M, T_hand_cam, centre, spot) for spot in ((0.006, 0.0), (-0.006, 0.0)) for _ in range(2)]
    with pytest.raises(InvalidInputError, match=r"index mount rotation about x.*along its y axis"):
        fit_mount(line, RADIUS, T_hand_cam)


def test_a_press_with_a_flipped_board_pose_is_dropped_and_the_mount_still_recovered():
    rng = np.random.default_rng(3)
    M, T_hand_cam = _mount(rng), _mount(rng, 50.0, 30.0)
    centre = np.array([0.03, -0.02, 0.06])
    presses = [_press(rng, M, T_hand_cam, centre, spot) for spot in SPOTS for _ in range(2)]
    bad = presses[3]
    flipped = make_pose(Rotation.from_euler("y", 40, degrees=True).as_matrix(), [0.09, 0.0, 0.05]) @ bad.T_world_cam
    presses[3] = Press(bad.finger, bad.T_hand_fingertip, bad.points_sensor, flipped, "sphere", 0)
    fit = fit_mount(presses, RADIUS, T_hand_cam, centre_height_m=0.06)
    mm, deg = _error(fit.T_fingertip_sensor, M)
    assert fit.dropped == 1 and fit.presses == 7
    assert mm < 1e-4 and deg < 1e-4
