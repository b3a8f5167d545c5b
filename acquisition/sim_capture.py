"""``tacsplat sim-capture``: a whole scene captured on the twin, unattended, through the same
:class:`~tacsplat.acquisition.logger.CaptureLogger` as the real rig.

The :class:`~tacsplat.acquisition.twin_planner.TwinPlanner` decides *where*
(the view camera on the hemisphere, the hand on sampled approaches); the logger
does the rest exactly as on the real rig: it closes the hand with a
speed-limited ramp through ``command_joint_positions``, waits on the twin's
clock until the fingers settle or stall, reads the four pads, places them with
the hand pose, writes the touches and opens the hand.

With ``touch_model="paper"`` no grasp is executed: the touches are the
paper's (:mod:`~tacsplat.acquisition.paper_touches`), four for each planned
grasp (touch ``t`` recorded as grasp ``t // 4``, finger ``t % 4``), so the two
models compare at the same count of touches.

The plan is deterministic in the seed: view ``i`` of a split is the same pose
on every run, grasp ``g`` the same approaches and paper touch ``t`` the same points, so
``--resume`` continues a killed capture where its journal stopped (a grasp cut
short is redone whole).
"""

from __future__ import annotations

import time
from pathlib import Path

from tacsplat.acquisition.capture_scene import open_scene
from tacsplat.acquisition.config import CapturePlan, GraspPlan, RigConfig, SimConfig, TouchPlan, ViewPlan, validate
from tacsplat.acquisition.logger import CaptureLogger
from tacsplat.acquisition.paper_touches import TOUCHES_PER_GRASP, PaperTouches, write_paper_touches
from tacsplat.acquisition.twin_planner import TwinPlanner
from tacsplat.errors import ConfigError
from tacsplat.progress import progress_bar
from tacsplat.sim.objects import object_radius_problem


def sim_rig_config(
    object: str = "teapot",
    mesh: str | None = None,
    object_radius: float = 0.08,
    views: int = 5,
    test_views: int = 24,
    grasps: int = 5,
    resolution: int = 200,
    seed: int = 0,
    touch_model: str = "gel",
    surface_points: int = TouchPlan.surface_points,
    texture: str = "none",
) -> RigConfig:
    """The ``rig: sim`` config of ``tacsplat sim-capture``'s options (``surface_points``: the paper model's); a
    value out of its range is a ConfigError naming its key (``sim.object_radius``)."""
    if problem := object_radius_problem(object_radius):  # (before the rig config's check, with what it means)
        raise ConfigError("sim.object_radius", problem)
    sim = SimConfig(
        object=object, mesh=mesh, object_radius=object_radius, resolution=resolution, seed=seed, texture=texture
    )
    plan = CapturePlan(
        ViewPlan(train=views, test=test_views, mode="hemisphere"),
        GraspPlan(count=grasps, mode="random", seed=seed),
        TouchPlan(model=touch_model, surface_points=surface_points),
    )
    config = RigConfig(rig="sim", sim=sim, plan=plan)
    validate(config)
    return config


def sim_capture(config: RigConfig, out: str | Path, resume: bool = False, progress: bool = True) -> dict:
    """Capture a scene on the twin, unattended: train views, test views with GT depth, grasps (or the paper's
    touches); returns timings in seconds (``setup_s``, ``views_s``, ``grasps_s``: the touches', ``total_s``).
    ``resume`` continues the scene in ``out`` only if it was captured with the same settings (a ConfigError names
    each that differs)."""
    if config.rig != "sim":
        raise ConfigError("rig", f"sim_capture runs the twin; got rig: {config.rig}", config.source)
    t0 = time.perf_counter()
    with open_scene(config, Path(out), resume) as (rig, writer):
        _record_mesh_frame(rig.twin.object, writer)
        logger = CaptureLogger(writer, rig.hand, rig.sensors, rig.camera, rig.clock, rig.poses, rig.control)
        planner = TwinPlanner(rig.twin, config.plan.grasps.seed, config.plan.views)
        t_setup = time.perf_counter()
        counts, v = logger.counts(), config.plan.views
        todo = [("train", i) for i in range(counts.train, v.train)] + [("test", i) for i in range(counts.test, v.test)]
        for split, i in progress_bar(todo, desc="views", unit="view", enabled=progress):
            planner.before_view(split, i)
            logger.take_view(split)
        t_views = time.perf_counter()
        if config.plan.touches.model == "paper":
            touches = PaperTouches(rig.twin.object_mesh, config.plan.grasps.seed, config.plan.touches)
            todo = range(writer.num_touches, TOUCHES_PER_GRASP * config.plan.grasps.count)
            write_paper_touches(writer, touches, progress_bar(todo, desc="touches", unit="touch", enabled=progress))
        else:
            todo = range(logger.next_grasp_index(), config.plan.grasps.count)
            for g in progress_bar(todo, desc="grasps", unit="grasp", enabled=progress):
                planner.grasp(logger, g)
        t_end = time.perf_counter()
    return {"setup_s": t_setup - t0, "views_s": t_views - t_setup, "grasps_s": t_end - t_views, "total_s": t_end - t0}


MESH_FRAME = "mesh_frame"  # scene.json's annotation: where the scene (the twin's world) has a --mesh file's points


def _record_mesh_frame(obj, writer) -> None:
    """Annotate the scene (:data:`MESH_FRAME`) with how the twin placed a mesh file's points: ``p_scene = scale *
    p_file + translation_m`` (the mesh is centred on its bounding sphere, and scaled unless ``--keep-size``)."""
    if obj.from_file is None:  # a library object
        return
    scale, translation = obj.from_file
    value = {"scale": float(scale), "translation_m": [float(x) for x in translation]}
    if writer.annotations.get(MESH_FRAME) != value:
        writer.annotate(MESH_FRAME, value)
