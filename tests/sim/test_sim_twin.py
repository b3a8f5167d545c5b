"""The MuJoCo twin: Protocols, cameras against the ground-truth mesh, touches on the surface, stable physics."""

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import trimesh  # noqa: E402

from tacsplat.drivers.protocols import Camera, Hand, TactileSensor  # noqa: E402
from tacsplat.errors import InvalidInputError, SimulationError  # noqa: E402
from tacsplat.geometry import look_at, project_points, unproject_depth  # noqa: E402
from tacsplat.sim.grasps import GraspConfig, PreshapeTable, preshape_fingers, sample_hand_pose, tap_close_pose  # noqa: E402
from tacsplat.sim.hand import ActuatorGains, HandGeometry, HandKinematics  # noqa: E402
from tacsplat.sim.twin import MAX_SERVO_OMEGA_DT, SimTwin, TwinConfig, check_physics, servo_omega_dt  # noqa: E402

_TWINS: dict = {}


def twin_of(name: str, **kw) -> SimTwin:
    key = (name, tuple(sorted(kw.items())))
    if key not in _TWINS:
        _TWINS[key] = SimTwin(TwinConfig(object=name, **kw))
    return _TWINS[key]


@pytest.fixture(scope="module", autouse=True)
def _close_twins():
    yield
    for twin in _TWINS.values():
        twin.close()
    _TWINS.clear()


def test_twin_implements_the_device_protocols():
    twin = twin_of("car")
    assert isinstance(twin.hand, Hand)
    assert [s.name for s in twin.tactile_sensors] == ["index", "middle", "ring", "thumb"]
    assert all(isinstance(s, TactileSensor) for s in twin.tactile_sensors)
    assert isinstance(twin.wrist_camera, Camera) and isinstance(twin.view_camera, Camera)
    image, stamp = twin.wrist_camera.read()
    assert image.shape == (200, 200, 3) and image.dtype == np.uint8 and stamp == twin.time


def test_hand_kinematics_match_the_twin_and_readings_are_in_the_hand_frame():
    twin = twin_of("car")
    twin.set_hand_base_pose(look_at([0.3, 0.1, 0.4], [0, 0, 0]))
    q = np.random.default_rng(1).uniform(twin.hand.joint_limits[:, 0], twin.hand.joint_limits[:, 1])
    twin.hand.set_joint_positions(q)
    reference = HandKinematics().fingertip_poses(q)
    poses = twin.hand.fingertip_poses()
    for sensor in twin.tactile_sensors:
        assert np.allclose(poses[sensor.name], reference[sensor.name], atol=1e-9)
        reading = sensor.read()
        assert reading.frame == "hand" and np.allclose(reading.T_ref_sensor, reference[sensor.name], atol=1e-9)
    assert np.allclose(twin.hand.read_joint_positions(), q)


def test_sleep_advances_the_clock_and_commands_are_checked():
    twin = twin_of("car")
    t0 = twin.time
    twin.sleep(0.1)
    assert twin.time == pytest.approx(t0 + 0.1)
    with pytest.raises(InvalidInputError, match="shape"):
        twin.hand.command_joint_positions(np.zeros(3))
    with pytest.raises(InvalidInputError, match="NaN"):
        twin.hand.command_joint_positions(np.full(16, np.nan))
    twin.hand.command_joint_positions(np.full(16, 10.0))  # clamped to the upper limits
    assert np.allclose(twin.hand.read_joint_targets(), twin.hand.joint_limits[:, 1])


def test_projected_mesh_lands_on_the_rendered_silhouette_and_depth_lies_on_the_mesh():
    twin = twin_of("teapot", camera_width=160, camera_height=120)  # non-square: catches fx/fy and cx/cy mix-ups
    K = twin.view_camera.K
    assert K[0, 2] == 80 and K[1, 2] == 60 and K[0, 0] == K[1, 1]
    mesh = twin.object_mesh
    for eye in ([0.25, -0.12, 0.1], [-0.1, 0.2, 0.2]):
        twin.move_camera(look_at(eye, [0.01, 0, 0]))
        T = twin.camera_pose()
        assert np.allclose(T, look_at(eye, [0.01, 0, 0]), atol=1e-6)
        image, depth = twin.view_camera.read()[0], twin.view_camera.read_depth()
        rendered = depth > 0
        uv, _ = project_points(mesh.vertices, K, T)
        raster = np.zeros_like(rendered, dtype=np.uint8)
        shift = 4  # sub-pixel vertices; OpenCV puts pixel centres at integers, we at +0.5
        for tri in np.round((uv[mesh.faces] - 0.5) * 2**shift).astype(np.int32):
            cv2.fillConvexPoly(raster, tri, 1, lineType=cv2.LINE_8, shift=shift)
        kernel = np.ones((3, 3), np.uint8)
        assert rendered.sum() > 500
        assert not (rendered & ~cv2.dilate(raster, kernel).astype(bool)).any()
        assert not (cv2.erode(raster, kernel).astype(bool) & ~rendered).any()
        # the background shows where nothing was hit
        assert (image[~rendered].reshape(-1, 3).std(axis=0) < 40).all()
        points = unproject_depth(depth, K, T)
        _, distance, _ = trimesh.proximity.closest_point(mesh, points[:: max(1, len(points) // 1500)])
        assert distance.max() < 3e-4


def test_a_checker_texture_paints_the_object_in_its_color_and_a_contrasting_grey():
    """The "checker" texture (a cube map MuJoCo projects onto the mesh) shows the helmet's blue and a light grey in
    alternating patches; without it the helmet is one hue."""
    from tacsplat.sim.objects import make_object

    blue = np.array(make_object("helmet").material.rgba[:3])
    hues = {}
    for texture in ("none", "checker"):
        twin = twin_of("helmet", texture=texture, camera_width=96, camera_height=96)
        twin.move_camera(look_at([0.2, -0.15, 0.15], [0.0, 0.0, 0.0]))
        image, depth = twin.view_camera.read()[0], twin.view_camera.read_depth()
        pixels = image[depth > 0].astype(np.float64) / 255.0  # [P, 3] RGB
        blueness = pixels[:, 2] - pixels[:, :2].mean(axis=1)  # the blue channel's lead over red and green
        hues[texture] = blueness
    assert (hues["none"] > 0.1).mean() > 0.9  # blue (shaded, highlights aside) almost everywhere
    grey = np.abs(hues["checker"]) < 0.08
    assert 0.25 < grey.mean() < 0.75 and (hues["checker"] > 0.2).mean() > 0.25  # both colours, in patches
    assert blue[2] > blue[:2].mean() + 0.3


def test_an_unknown_texture_is_one_error_naming_it():
    from tacsplat.errors import ConfigError

    with pytest.raises(ConfigError, match="texture.*'plaid'"):
        SimTwin(TwinConfig(object="torus", texture="plaid"))


def test_reset_returns_to_the_initial_state_and_restarts_the_penetration_peak():
    twin = twin_of("car")
    twin.reset()
    T0, q0, ctrl0 = twin.T_world_hand(), twin.hand.read_joint_positions(), twin.hand.read_joint_targets()
    config = GraspConfig()
    table = PreshapeTable(twin, config.preshape_grid, config.preshape_abduction)
    q_pre, reachable = preshape_fingers(twin, table, sample_hand_pose(twin, np.random.default_rng(0)), config)
    assert reachable and twin.max_penetration() == 0.0
    twin.hand.set_joint_positions(tap_close_pose(q_pre, reachable, config))  # the pads teleported into the object
    assert twin.max_penetration() > 1e-3 and twin.peak_penetration_m == 0.0  # a peak is seen only by sleep()
    twin.sleep(0.004)
    assert twin.peak_penetration_m > 1e-3
    twin.reset()
    assert twin.time == 0.0 and twin.peak_penetration_m == 0.0 and twin.max_penetration() == 0.0
    assert np.array_equal(twin.T_world_hand(), T0)
    assert np.array_equal(twin.hand.read_joint_positions(), q0) and np.array_equal(
        twin.hand.read_joint_targets(), ctrl0
    )


def test_the_sensor_model_of_the_pads_in_a_scene_of_other_units():
    twin = twin_of("car")
    t = twin.config.tactile
    model = twin.sensor_model()
    assert (model.name, model.width_px, model.height_px) == ("sim-digit", t.width_px, t.height_px)
    assert (model.pixel_size_m, model.gel_thickness_m) == (t.pixel_size_m, t.gel_thickness_m)
    scaled = twin.sensor_model(scale=0.08)
    assert scaled.pixel_size_m == pytest.approx(t.pixel_size_m / 0.08)
    assert scaled.gel_thickness_m == pytest.approx(t.gel_thickness_m / 0.08)


def test_stiff_settings_are_rejected_with_a_clear_error():
    with pytest.raises(SimulationError, match="contact_timeconst"):
        check_physics(TwinConfig(timestep=0.002, contact_timeconst=0.003))
    with pytest.raises(SimulationError, match="timestep"):
        check_physics(TwinConfig(timestep=0.05))
    model = twin_of("car").model
    too_stiff = 1.1 * (MAX_SERVO_OMEGA_DT / servo_omega_dt(model, 1.0)) ** 2
    with pytest.raises(SimulationError, match="gains.kp"):
        check_physics(TwinConfig(gains=ActuatorGains(kp=too_stiff)), model)


def test_sleeps_that_are_not_whole_steps_add_up_on_the_twin_clock():
    """At a 6 ms timestep a 10 ms poll is 1.67 steps: the clock keeps what it owes, so 100 polls advance 1 s (not
    2 steps each, 1.2 s) and sleeps shorter than half a step advance it too (not nothing, forever)."""
    twin = twin_of("bell", timestep=0.006, contact_timeconst=0.015, camera_width=16, camera_height=16)
    twin.reset()
    for _ in range(100):
        twin.sleep(0.01)
    assert twin.time == pytest.approx(1.0, abs=0.006)
    t0 = twin.time
    for _ in range(3):
        twin.sleep(0.002)
    assert twin.time >= t0 + 0.006
    twin.reset()
    assert twin.time == 0.0
    twin.sleep(0.002)  # the reset also forgets what the clock owed
    assert twin.time == 0.0


@pytest.mark.timeout(120)
def test_a_grasp_finishes_at_a_timestep_that_does_not_divide_the_polls(tmp_path):
    """The logger opens the hand by sleeping out the rest of its open time in polls; at a 6 ms timestep a remainder
    under 3 ms advanced nothing, and the grasp never ended."""
    from tacsplat.acquisition.devices import twin_rig
    from tacsplat.acquisition.logger import CaptureLogger
    from tacsplat.acquisition.twin_planner import TwinPlanner
    from tacsplat.datasets import SceneMeta, SceneWriter

    config = TwinConfig(object="bell", timestep=0.006, contact_timeconst=0.015, camera_width=16, camera_height=16)
    check_physics(config)
    twin = twin_of("bell", timestep=0.006, contact_timeconst=0.015, camera_width=16, camera_height=16)
    check_physics(config, twin.model)
    rig = twin_rig(twin)
    with SceneWriter.create(tmp_path / "scene", rig.intrinsics, SceneMeta("sim", "bell"), rig.sensor_model) as writer:
        logger = CaptureLogger(writer, rig.hand, rig.sensors, rig.camera, rig.clock, rig.poses, rig.control)
        outcome = TwinPlanner(twin, 0).grasp(logger, 0)
    assert outcome is not None and outcome.fingers_in_contact


def test_closing_the_hand_holds_the_joints_where_they_are_whatever_the_servos_read():
    """close() holds the true joint angles: a servo mounted off (an offset the rig has not calibrated) or reversed
    reads another angle, and commanding that reading would move the finger."""
    offsets, signs = [0.0] * 16, [1] * 16
    offsets[1], signs[2] = 0.3, -1
    twin = twin_of(
        "bell", camera_width=16, camera_height=16, servo_offsets_rad=tuple(offsets), servo_signs=tuple(signs)
    )
    twin.reset()
    twin.set_hand_base_pose(look_at([0.0, 0.0, 1.0], [0.0, 0.0, 2.0]))  # far from the object
    q = np.zeros(16)
    q[1:3] = 0.5, 0.6
    twin.hand.set_joint_positions(q)
    twin.sleep(0.5)
    before = twin.hand.read_motor_angles()  # the true angles, through the servos' fixed offsets and signs
    twin.hand.close()
    twin.sleep(0.5)
    assert np.abs(twin.hand.read_motor_angles() - before).max() < 1e-3


@pytest.mark.parametrize(
    "setting, kw",
    [
        ("contact_solimp", dict(contact_solimp=(1.5, -1.0, 0.0))),
        ("contact_solimp", dict(contact_solimp=(float("nan"), 0.99, 0.001))),
        ("contact_solimp", dict(contact_solimp=(0.95, 0.99))),
        ("contact_dampratio", dict(contact_dampratio=1e-6)),
        ("hand_geometry.link_mass", dict(hand_geometry=HandGeometry(link_mass=0.0))),
    ],
)
def test_contact_and_mass_settings_that_break_the_simulation_are_refused_by_name(setting, kw):
    """Each made the twin fail later (unstable at the first grasp, or MuJoCo's compiler), naming no setting."""
    with pytest.raises(SimulationError, match=f"^{setting}:"):
        check_physics(TwinConfig(**kw))
