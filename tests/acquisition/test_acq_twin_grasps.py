"""Grasps on the twin through the one grasp controller (the logger's, placed by the twin planner): touches on the
object's surface for every library object, and a bounded penetration of the collision geometry, also when the hand
closes fast with the stiffest gains the twin allows."""

import dataclasses

import numpy as np
import pytest
import trimesh

from tacsplat.acquisition.config import GraspControl
from tacsplat.acquisition.devices import TWIN_CONTROL, twin_rig
from tacsplat.acquisition.logger import CaptureLogger
from tacsplat.acquisition.twin_planner import TwinPlanner
from tacsplat.datasets import Scene, SceneMeta, SceneWriter
from tacsplat.sim.grasps import GraspConfig
from tacsplat.sim.hand import ActuatorGains
from tacsplat.sim.objects import OBJECT_NAMES
from tacsplat.sim.twin import MAX_SERVO_OMEGA_DT, SimTwin, TwinConfig, servo_omega_dt

# Stated bounds on the penetration of hand and object collision geometry in a grasp (soft contacts, solref time
# constant 5 ms at 2 ms steps). Measured with the logger's controller: 0.04-0.11 mm at the twin's gains and grasp
# control (one grasp of each library object); 0.6-1.8 mm closing at 4 rad/s with the stiffest gains check_physics
# allows (a stalled finger is held at a lag of stall_error_rad behind its target, so the squeeze grows with kp).
PENETRATION_BOUND_M = 0.0025  # any allowed gains and closing speeds up to 4 rad/s
DEFAULT_PENETRATION_BOUND_M = 0.0005  # the twin's gains and grasp control


def twin_grasps(
    twin: SimTwin,
    folder,
    count: int,
    seed: int,
    control: GraspControl = TWIN_CONTROL,
    config: GraspConfig = GraspConfig(),
) -> tuple[Scene, list[float]]:
    """``count`` grasps (and a view, which a valid scene needs) written to a scene in ``folder``, and the peak
    penetration of each grasp kept."""
    rig = twin_rig(twin, control)
    peaks = []
    with SceneWriter.create(folder, rig.intrinsics, SceneMeta("sim", "test"), rig.sensor_model) as writer:
        logger = CaptureLogger(writer, rig.hand, rig.sensors, rig.camera, rig.clock, rig.poses, rig.control)
        planner = TwinPlanner(twin, seed, grasp_config=config)
        logger.take_view("train")
        for g in range(count):
            if planner.grasp(logger, g) is not None:
                peaks.append(twin.peak_penetration_m)
    return Scene.load(folder), peaks


def assert_touches_on_the_surface(scene: Scene, mesh: trimesh.Trimesh) -> None:
    points = scene.touch_points()
    assert len(points) > 0
    _, distance, _ = trimesh.proximity.closest_point(mesh, points)
    assert distance.mean() < 3e-4 and distance.max() < 1e-3, (distance.mean(), distance.max())


@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_touch_points_lie_on_the_object_surface(name, tmp_path):
    with SimTwin(TwinConfig(object=name, camera_width=32, camera_height=32)) as twin:
        scene, peaks = twin_grasps(twin, tmp_path / "scene", 1, seed=0)
        assert peaks, f"no grasp touched the {name}"
        assert_touches_on_the_surface(scene, twin.object_mesh)
        assert all(0 < p < DEFAULT_PENETRATION_BOUND_M for p in peaks), peaks


@pytest.mark.parametrize("name,radius", [("torus", 0.05), ("teapot", 0.15)])
def test_fast_closing_with_the_stiffest_allowed_gains_stays_stable(name, radius, tmp_path):
    with SimTwin(TwinConfig(object=name, object_radius=radius, camera_width=32, camera_height=32)) as probe:
        kp_max = 0.999 * (MAX_SERVO_OMEGA_DT / servo_omega_dt(probe.model, 1.0)) ** 2
    gains = ActuatorGains(kp=kp_max, kv=0.05)
    fast = dataclasses.replace(TWIN_CONTROL, close_speed_rad_s=4.0, poll_s=0.005)
    config = TwinConfig(object=name, object_radius=radius, gains=gains, camera_width=32, camera_height=32)
    with SimTwin(config) as twin:
        scene, peaks = twin_grasps(
            twin, tmp_path / "scene", 2, seed=1, control=fast, config=GraspConfig(max_tap_rad=1.2)
        )
        assert peaks
        assert all(0 < p < PENETRATION_BOUND_M for p in peaks), peaks
        assert all(int(w.number) == 0 for w in twin.data.warning)
        assert np.all(np.isfinite(twin.data.qpos)) and np.all(np.isfinite(twin.data.qacc))
        assert_touches_on_the_surface(scene, twin.object_mesh)


@pytest.mark.slow
@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_many_grasps_touch_the_surface(name, tmp_path):
    with SimTwin(TwinConfig(object=name, camera_width=32, camera_height=32)) as twin:
        scene, peaks = twin_grasps(twin, tmp_path / "scene", 8, seed=11)
        assert len(peaks) == 8
        assert_touches_on_the_surface(scene, twin.object_mesh)
        assert max(peaks) < DEFAULT_PENETRATION_BOUND_M
