"""``tacsplat simulate-touches``: simulated grasps of a mesh added to an existing scene (e.g. an import).

The grasps run on the twin through the same logger and grasp controller as
every capture (:class:`~tacsplat.acquisition.logger.CaptureLogger`, placed by
the :class:`~tacsplat.acquisition.twin_planner.TwinPlanner`): grasp ``g`` is
deterministic in ``(seed, g)``. The mesh is simulated at a graspable size; the
scene sees the twin through an adapter that expresses the hand pose and the
pads' readings in the scene's frame and units, as the paper did for Shiny
Blender and Glossy Synthetic. With ``touch_model="paper"`` the touches are
instead the paper's (:mod:`~tacsplat.acquisition.paper_touches`), four for each
grasp asked for, sampled on the same mesh at the same size and mapped into the
scene the same way.
"""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

import numpy as np

from tacsplat.acquisition.config import TouchPlan, validate_touches
from tacsplat.acquisition.devices import twin_rig
from tacsplat.acquisition.logger import CaptureLogger, PoseEstimate
from tacsplat.acquisition.paper_touches import TOUCHES_PER_GRASP, PaperTouches, write_paper_touches
from tacsplat.acquisition.twin_planner import TwinPlanner
from tacsplat.datasets import Scene, SceneMeta, SceneWriter, copy_scene
from tacsplat.errors import ConfigError, UsageError
from tacsplat.files import check_writable
from tacsplat.geometry import minimum_sphere
from tacsplat.progress import progress_bar
from tacsplat.sim.grasps import GraspConfig
from tacsplat.sim.objects import (
    DEFAULT_OBJECT_RADIUS,
    bounding_sphere,
    normalised_scale,
    object_radius_problem,
    read_mesh,
)
from tacsplat.sim.twin import SimTwin, TwinConfig, pad_sensor_model
from tacsplat.types import TactileReading

GT_POINTS = "gt/points.ply"  # scene.json's record of touches made on the scene's ground-truth points


class SceneUnits:
    """A scene whose world is the twin's scaled by ``1 / scale`` and moved to ``centre``:
    ``p_scene = centre + p_twin / scale`` (``scale``: twin metres per scene unit; rotations unchanged)."""

    def __init__(self, centre, scale: float):
        self.centre = np.asarray(centre, dtype=np.float64)
        self.scale = float(scale)

    def points(self, p_twin: np.ndarray) -> np.ndarray:
        """Points [N, 3] of the twin in the scene."""
        return self.centre + np.asarray(p_twin, dtype=np.float64) / self.scale

    def pose(self, T_twin: np.ndarray, anchored: bool = True) -> np.ndarray:
        """A pose of the twin in the scene; ``anchored=False`` for a pose relative to another (no ``centre``)."""
        T = np.array(T_twin, dtype=np.float64)
        T[:3, 3] = T[:3, 3] / self.scale + (self.centre if anchored else 0.0)
        return T


class ScaledPad:
    """A twin pad (``TactileSensor``) whose readings are in the scene's units."""

    def __init__(self, pad, units: SceneUnits):
        self.pad, self.units, self.name = pad, units, pad.name

    def read(self) -> TactileReading:
        r, s = self.pad.read(), self.units.scale
        return TactileReading(
            r.depth / s, r.pixel_size_m / s, self.units.pose(r.T_ref_sensor, anchored=False), r.frame, r.timestamp
        )


class ScenePoseSource:
    """The twin's ground-truth hand pose (the one pose a grasp asks its ``PoseSource`` for) in the scene's frame and
    units."""

    def __init__(self, twin: SimTwin, units: SceneUnits):
        self.twin, self.units = twin, units

    def hand_pose(self, image: np.ndarray) -> PoseEstimate:
        return PoseEstimate(self.units.pose(self.twin.hand_pose_from_wrist_camera()))


def touch_settings(
    grasps: int,
    object_radius: float,
    seed: int,
    touch_model: str = "gel",
    surface_points: int = TouchPlan.surface_points,
) -> TouchPlan:
    """The touch plan of :func:`simulate_touches`'s settings, each checked against its range (a ConfigError
    naming it: ``grasps``, ``object_radius``, ``seed``, ``model``, ``surface_points``)."""
    touches = TouchPlan(model=touch_model, surface_points=surface_points)
    validate_touches(touches)
    for key, value, least in (("grasps", grasps, 1), ("seed", seed, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise ConfigError(key, f"must be an integer >= {least}, got {value!r}")
    if problem := object_radius_problem(object_radius):
        raise ConfigError("object_radius", problem)
    return touches


def _existing_folder(path: Path) -> Path:
    """``path``, or its nearest parent that exists: where a new folder ``path`` would be made."""
    return next(p for p in (path, *path.parents) if p.exists())


def simulate_touches(
    mesh_path: str | Path | None,
    scene_path: str | Path,
    grasps: int,
    out: str | Path | None = None,
    object_radius: float = DEFAULT_OBJECT_RADIUS,
    seed: int = 0,
    grasp_config: GraspConfig = GraspConfig(),
    touch_model: str = "gel",
    surface_points: int = TouchPlan.surface_points,
) -> Path:
    """Add ``grasps`` simulated grasps of ``mesh_path`` (in the scene's world frame and units; None: the scene's
    ground-truth mesh, else, for the paper's touches only, its ground-truth points) to a scene.

    The grasps run on the mesh scaled to a graspable bounding radius
    (``object_radius`` metres); touches are mapped back into the scene's frame
    and units (poses, indentations and pixel size divided by the scale). With
    ``touch_model="paper"``, ``4 * grasps`` of the paper's touches (from
    ``surface_points`` samples) take the grasps' place. A scene written with this
    sensor model is extended in place, numbering grasps on; one without (an
    import) is copied with its frames into ``out`` first. Returns the scene
    written. The settings (:func:`touch_settings`) and the folder to write (it
    must be writable) are checked before the twin starts.
    """
    touches = touch_settings(grasps, object_radius, seed, touch_model, surface_points)
    scene = Scene.load(scene_path)
    if scene.sensor is not None and out is not None:
        raise UsageError("out", f"{scene_path} already holds touches; it is extended in place, drop --out")
    if scene.sensor is None and out is None:
        raise UsageError("out", f"{scene_path} has no tactile sensor model (an import): pass --out NEW_SCENE")
    check_writable(Path(scene_path) if out is None else _existing_folder(Path(out)))
    with ExitStack() as stack:
        if mesh_path is None and scene.gt_mesh_path is None:  # the paper's touches on the ground-truth points
            points = _gt_points(scene, touches)
            centre, radius, _ = minimum_sphere(points)
            scale = object_radius / radius  # to object_radius, as a mesh would be
            _check_size(scene, radius, scale, object_radius, None)
            units = SceneUnits(centre, scale)
            twin, surface, source = None, (points - centre) * scale, GT_POINTS
            sensor = pad_sensor_model(TwinConfig().tactile, units.scale)
        else:
            mesh_path = scene.gt_mesh_path if mesh_path is None else mesh_path
            centre, radius = bounding_sphere(read_mesh(mesh_path))
            _check_size(scene, radius, normalised_scale(radius, object_radius), object_radius, mesh_path)
            settings = TwinConfig(mesh_path=str(mesh_path), object_radius=object_radius, seed=seed)
            twin = stack.enter_context(SimTwin(settings))
            units = SceneUnits(centre, twin.object.bounding_radius / radius)
            surface, source = twin.object_mesh, str(mesh_path)
            sensor = twin.sensor_model(units.scale)
        if scene.sensor is None:
            target = _copy_with_sensor(scene, out, sensor, source, grasps, seed, touches, units, object_radius)
        else:  # (_check_size matched the scene's pixels)
            target = Path(scene_path)
        with SceneWriter.resume(target) as writer:
            first = max((t.grasp for t in writer.touches), default=-1) + 1
            if touch_model == "paper":
                todo = range(TOUCHES_PER_GRASP * first, TOUCHES_PER_GRASP * (first + grasps))
                touches_made = PaperTouches(surface, seed, touches)  # (before the bar: it samples the surface)
                bar = progress_bar(todo, desc="touches", unit="touch")
                write_paper_touches(writer, touches_made, bar, units.points)
            else:
                rig = twin_rig(twin)
                pads = [ScaledPad(p, units) for p in rig.sensors]  # the scene sees the twin in its frame and units
                poses = ScenePoseSource(twin, units)
                logger = CaptureLogger(
                    writer, rig.hand, pads, rig.camera, rig.clock, poses, rig.control, redo_partial_grasp=False
                )
                planner = TwinPlanner(twin, seed, grasp_config=grasp_config)
                for g in progress_bar(range(first, first + grasps), desc="grasps", unit="grasp"):
                    planner.grasp(logger, g)
    return target


# units a file may be in, in metres, for guessing which two a mesh and a scene of other sizes are in
_UNITS = {"metres": 1.0, "centimetres": 0.01, "millimetres": 0.001, "inches": 0.0254}


def _check_size(scene: Scene, radius: float, scale: float, object_radius: float, mesh_path) -> None:
    """Before the twin starts: whether the mesh (``mesh_path``; None: the scene's ground-truth points) of bounding
    radius ``radius`` in the scene's units, simulated ``scale`` times larger, touches with the pads of the scene's
    sensor model (a scene that has one). If not, a UsageError naming ``--object-radius`` when another radius in the
    twin's range does, else ``--mesh``: its units are not the scene's."""
    if scene.sensor is None:
        return
    pad = TwinConfig().tactile.pixel_size_m
    if np.isclose(scene.sensor.pixel_size_m, pad / scale, rtol=1e-6):
        return
    scene_scale = pad / scene.sensor.pixel_size_m  # twin metres per scene unit, as the scene's touches were made
    needed = radius * scene_scale  # the radius in the twin that gives the scene's pixels
    if mesh_path is None or object_radius_problem(needed) is None:
        raise UsageError(
            "--object-radius",
            f"the scene's touches were simulated at {scene_scale:.3g} twin metres a scene unit: "
            f"{'this mesh' if mesh_path else 'its ground-truth points'} (bounding radius {radius:.3g} in the "
            f"scene's units) match them at --object-radius {needed:.3g} (m), not {object_radius:.3g} m",
        )
    objects = object_radius / scene_scale  # a mesh in the scene's units would be about this size
    ratio = radius / objects
    error, mesh_units, scene_units = min(
        (abs(np.log(ratio * a / b)), a_name, b_name)
        for a_name, a in _UNITS.items()
        for b_name, b in _UNITS.items()
        if a != b
    )
    fix = "give the mesh in the scene's units"
    if error < np.log(2):
        fix = f"is the mesh in {mesh_units} and the scene in {scene_units}? {fix.capitalize()}"
    times = f"{ratio:.3g} times larger" if ratio > 1 else f"{1 / ratio:.3g} times smaller"
    raise UsageError(
        "--mesh",
        f"{mesh_path}'s bounding radius is {radius:.3g} in its file's units, the scene's objects are ~{objects:.3g} "
        f"in its units ({times}): {fix}",
    )


def _gt_points(scene: Scene, touches: TouchPlan) -> np.ndarray:
    """The ground-truth points [N, 3] of a scene with no ground-truth mesh, for the paper's touches."""
    points = scene.gt_points()
    if points is None:
        raise UsageError("mesh", f"{scene.path} has no ground-truth mesh or points: pass --mesh")
    if touches.model != "paper":
        raise UsageError(
            "mesh",
            f"{scene.path}'s ground truth is points ({scene.gt_points_file}), and the hand needs a mesh to grasp: "
            "pass --mesh, or make the paper's touches (--touch-model paper)",
        )
    return points


def _copy_with_sensor(
    scene: Scene, out, sensor, surface: str, grasps: int, seed: int, touches: TouchPlan, units, object_radius: float
) -> Path:
    """Copy an import into ``out`` with the pads' sensor model, recording where its touches come from."""
    plan = {
        **scene.meta.capture_plan,
        "simulated_touches": {"mesh": surface, "grasps": grasps, "seed": seed, "touches": touches.to_json()},
    }
    extra = {**scene.meta.extra, "touch_scale": units.scale, "object_bounding_radius_m": object_radius}
    gt_mesh = scene.gt_mesh_path or (None if surface == GT_POINTS else surface)
    meta = SceneMeta(scene.meta.source, scene.meta.object, plan, extra)
    return copy_scene(scene, out, meta=meta, sensor=sensor, gt_mesh=gt_mesh, progress=True)
