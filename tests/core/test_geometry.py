import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from tacsplat import geometry as g
from tacsplat.errors import InvalidInputError
from tacsplat.types import TactileReading

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
quats = arrays(np.float64, 4, elements=st.floats(-1, 1, allow_nan=False)).filter(lambda q: np.linalg.norm(q) > 0.1)
vec3 = arrays(np.float64, 3, elements=finite)


@st.composite
def poses(draw):
    return g.make_pose(Rotation.from_quat(draw(quats), scalar_first=True).as_matrix(), draw(vec3))


@given(poses())
def test_inverse_round_trip(T):
    assert np.allclose(g.compose(T, g.invert_pose(T)), np.eye(4), atol=1e-9)
    assert g.rigidity_problem(T) is None


@given(poses(), poses(), vec3)
def test_compose_is_sequential_transform(A, B, p):
    direct = g.transform_points(g.compose(A, B), p)
    stepwise = g.transform_points(A, g.transform_points(B, p))
    assert np.allclose(direct, stepwise, atol=1e-9)


@given(poses())
def test_opencv_opengl_round_trip_and_axes(T):
    gl = g.opencv_to_opengl(T)
    assert np.allclose(g.opengl_to_opencv(gl), T)
    # same centre; OpenGL looks down -z, OpenCV down +z: same viewing direction
    assert np.allclose(gl[:3, 3], T[:3, 3])
    assert np.allclose(-gl[:3, 2], T[:3, 2])
    assert np.allclose(-gl[:3, 1], T[:3, 1])


@settings(max_examples=50)
@given(poses(), st.integers(4, 40), st.integers(4, 40))
def test_project_unproject_round_trip(T, h, w):
    K = g.intrinsics_matrix(30.0, 35.0, w / 2, h / 2)
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 3.0, size=(h, w))
    pts = g.unproject_depth(depth, K, T)
    uv, z = g.project_points(pts, K, T)
    u, v = g.pixel_centres(h, w)
    assert np.allclose(uv[:, 0], u.ravel(), atol=1e-6)
    assert np.allclose(uv[:, 1], v.ravel(), atol=1e-6)
    assert np.allclose(z, depth.ravel(), atol=1e-9)


def test_unproject_skips_empty_and_masked_pixels():
    depth = np.array([[1.0, 0.0], [np.nan, 2.0]])
    mask = np.array([[True, True], [True, False]])
    pts = g.unproject_depth(depth, g.intrinsics_matrix(1, 1, 1, 1), np.eye(4), mask=mask)
    assert pts.shape == (1, 3)


def test_project_behind_camera_is_nan():
    uv, z = g.project_points([[0, 0, -1.0]], np.eye(3), np.eye(4))
    assert np.isnan(uv).all() and z[0] == -1


def test_look_at_points_optical_axis_at_target():
    T = g.look_at([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])
    assert g.rigidity_problem(T) is None
    uv, z = g.project_points([[0, 0, 0]], g.intrinsics_matrix(100, 100, 50, 40), T)
    assert np.allclose(uv, [[50, 40]]) and z[0] > 0
    # image "up" (-y in OpenCV) points towards world +z
    assert T[2, 1] < 0
    assert g.rigidity_problem(g.look_at([0, 0, 2.0], [0, 0, 0])) is None  # along `up`


@pytest.mark.parametrize(
    "T, words",
    [
        (np.diag([1.0, 1.0, -1.0, 1.0]), "determinant"),
        (np.diag([2.0, 1.0, 1.0, 1.0]), "orthonormal"),
        (np.full((4, 4), np.nan), "NaN"),
        (np.eye(3), "4x4"),
    ],
)
def test_non_rigid_is_named(T, words):
    assert words in g.rigidity_problem(T)
    with pytest.raises(InvalidInputError, match="T_test"):
        g.check_rigid(T, "T_test")


def test_tactile_lifting_follows_the_design_convention():
    depth = np.zeros((4, 6), np.float32)
    depth[1, 4] = 0.001
    T_world_sensor = g.make_pose(np.diag([1.0, -1.0, -1.0]), [0.1, 0.2, 0.3])  # x-axis flip (quaternion 0 1 0 0)
    pts = g.tactile_depth_to_points(depth, 0.0002, T_world_sensor)
    x = (4 + 0.5 - 3) * 0.0002
    y = (1 + 0.5 - 2) * 0.0002
    assert np.allclose(pts, [[0.1 + x, 0.2 - y, 0.3 + 0.001]])
    reading = TactileReading(depth, 0.0002, np.eye(4), frame="hand")
    with pytest.raises(InvalidInputError, match="hand"):
        reading.contact_points()
    assert np.allclose(reading.to_world(T_world_sensor).contact_points(), pts)


def test_tactile_reading_rejects_bad_depth():
    with pytest.raises(InvalidInputError, match="depth"):
        TactileReading(np.full((2, 2), -1.0), 0.001, np.eye(4))
    with pytest.raises(InvalidInputError, match="depth"):
        TactileReading(np.full((2, 2), np.nan), 0.001, np.eye(4))


def test_tactile_normals_of_a_sphere_press_point_along_its_radius():
    """A ball of radius 4 mm pressed 1 mm into the gel: the normal at each inner contact pixel, lifted to the
    world, is the sphere's outward normal there (within 2 degrees), i.e. along the radius."""
    pixel, radius, press = 1e-4, 4e-3, 1e-3
    x, y = g.tactile_pixel_grid(81, 81, pixel)
    centre_z = radius - press  # the ball's centre in front of the gel
    depth = np.clip(press - (radius - np.sqrt(np.clip(radius**2 - x**2 - y**2, 0, None))), 0, None)
    T = g.make_pose(Rotation.from_euler("xyz", [0.3, -0.5, 1.1]).as_matrix(), [0.1, 0.2, 0.3])
    points = g.tactile_depth_to_points(depth, pixel, T)
    normals = g.tactile_depth_to_normals(depth, pixel, T)
    assert normals.shape == points.shape
    known = np.isfinite(normals).all(axis=1)
    assert 0.6 < known.mean() < 1.0  # the rim's pixels have no known slope
    centre_world = g.transform_points(T, [[0.0, 0.0, centre_z]])[0]
    radial = points[known] - centre_world
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    cos = np.einsum("ij,ij->i", normals[known], radial)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 2.0
