"""Simulated touches for existing scenes: ``tacsplat simulate-touches``.

(``tacsplat sim-capture`` runs through the acquisition logger, as real
captures do: :mod:`tacsplat.acquisition.sim_capture`, built on this package's
views, preshape and tap.) Grasp ``g`` is deterministic in ``(seed, g)``: its
approaches come from a generator seeded with both, each on a freshly reset
simulation.
"""

from __future__ import annotations

import logging
from pathlib import Path

import mujoco
import numpy as np
from tqdm import tqdm

from tacsplat.datasets import Scene, SceneMeta, SceneWriter, SensorModel
from tacsplat.errors import ConfigError
from tacsplat.geometry import make_pose
from tacsplat.sim.grasps import GraspConfig, GraspResult, PreshapeTable, execute_grasp, sample_hand_pose
from tacsplat.sim.hand import FINGER_NAMES
from tacsplat.sim.objects import DEFAULT_OBJECT_RADIUS, bounding_sphere
from tacsplat.sim.twin import SimTwin, TwinConfig
from tacsplat.types import TactileReading

log = logging.getLogger(__name__)

SENSOR_NAME = "sim-digit"
MAX_ATTEMPTS_PER_GRASP = 6


def sensor_model(twin: SimTwin, scale: float = 1.0) -> SensorModel:
    """The scene's sensor model of the twin's pads (lengths divided by ``scale``)."""
    t = twin.config.tactile
    return SensorModel(SENSOR_NAME, t.width_px, t.height_px, t.pixel_size_m / scale, t.gel_thickness_m / scale)


def grasp_once(twin: SimTwin, table: PreshapeTable, seed: int, index: int, config: GraspConfig) -> GraspResult | None:
    """Grasp number ``index`` of a plan: deterministic in ``(seed, index)``; None if nothing was touched."""
    rng = np.random.default_rng([seed, index])
    for _ in range(MAX_ATTEMPTS_PER_GRASP):
        mujoco.mj_resetData(twin.model, twin.data)
        twin.forward()
        result = execute_grasp(twin, sample_hand_pose(twin, rng, config), config, table)
        if result.fingers_in_contact:
            return result
    log.warning("grasp %d touched nothing in %d attempts; skipped", index, MAX_ATTEMPTS_PER_GRASP)
    return None


def _scaled_reading(reading: TactileReading, T_scene_twin: np.ndarray, scale: float) -> TactileReading:
    """A twin reading expressed in a scene whose lengths are the twin's divided by ``scale``."""
    T = reading.T_world_sensor.copy()
    T = T_scene_twin @ T
    T[:3, :3] = reading.T_world_sensor[:3, :3]
    return TactileReading(reading.depth / scale, reading.pixel_size_m / scale, T, "world", reading.timestamp)


def simulate_touches(
    mesh_path: str | Path,
    scene_path: str | Path,
    grasps: int,
    out: str | Path | None = None,
    object_radius: float = DEFAULT_OBJECT_RADIUS,
    seed: int = 0,
    grasp_config: GraspConfig = GraspConfig(),
) -> Path:
    """Add simulated touches of ``mesh_path`` (in the scene's world frame and units) to a scene.

    The grasps run on the mesh scaled to a graspable bounding radius
    (``object_radius`` metres); touches are mapped back into the scene's frame
    and units (poses, indentations and pixel size divided by the scale), as the
    paper did for Shiny Blender and Glossy Synthetic. A scene written with this
    sensor model is extended in place; one without (an import) is copied with
    its frames into ``out`` first.
    """
    scene = Scene.load(scene_path)
    centre, radius = bounding_sphere(_raw_mesh(mesh_path))
    twin_cfg = TwinConfig(mesh_path=str(mesh_path), object_radius=object_radius, seed=seed)
    with SimTwin(twin_cfg) as twin:
        scale = twin.object.bounding_radius / radius  # twin metres per scene unit
        T_scene_twin = make_pose(np.eye(3), centre) @ np.diag([1 / scale, 1 / scale, 1 / scale, 1.0])
        sensor = sensor_model(twin, scale)
        if scene.sensor is not None:
            if out is not None:
                raise ConfigError("out", f"{scene_path} already holds touches; it is extended in place, drop --out")
            if not np.isclose(scene.sensor.pixel_size_m, sensor.pixel_size_m, rtol=1e-6):
                raise ConfigError("object_radius", f"the scene's sensor has {scene.sensor.pixel_size_m} pixels; "
                                  f"this mesh at radius {object_radius} gives {sensor.pixel_size_m}")
            writer = SceneWriter.resume(scene_path)
            target = Path(scene_path)
        else:
            if out is None:
                raise ConfigError("out", f"{scene_path} has no tactile sensor model (an import): pass --out NEW_SCENE")
            target = Path(out)
            meta = SceneMeta(
                source=scene.meta.source,
                object=scene.meta.object,
                capture_plan={**scene.meta.capture_plan, "simulated_touches": {"mesh": str(mesh_path), "grasps": grasps, "seed": seed}},
                extra={**scene.meta.extra, "touch_scale": scale, "object_bounding_radius_m": object_radius},
            )
            writer = SceneWriter.create(target, scene.intrinsics or scene.frames[0].intrinsics, meta, sensor)
            for frame in tqdm(scene.frames, desc="copy frames", unit="frame"):
                image = np.rint(scene.load_image(frame) * 255).astype(np.uint8)
                writer.add_frame(image, frame.T_world_cam, frame.split, scene.gt_depth(frame), frame.intrinsics)
            writer.set_gt_mesh(scene.gt_mesh_path or mesh_path)
        with writer:
            first = writer.num_grasps
            table = PreshapeTable(twin, grasp_config.preshape_grid, grasp_config.preshape_abduction)
            for g in tqdm(range(first, first + grasps), desc="grasps", unit="grasp"):
                result = grasp_once(twin, table, seed, g, grasp_config)
                if result is None:
                    continue
                for finger in FINGER_NAMES:
                    writer.add_reading(_scaled_reading(result.readings[finger], T_scene_twin, scale), g, finger)
    return target


def _raw_mesh(path: str | Path):
    """The mesh file as the twin loads it, before centring and scaling."""
    import trimesh

    if not Path(path).is_file():
        raise ConfigError("mesh", f"file not found: {path}")
    return trimesh.load(Path(path), force="mesh", process=True)
