"""Simulated capture through the same :class:`CaptureLogger` as the real rig.

The twin's planner decides *where* (the view camera on the hemisphere around
the object; the hand base from a sampled approach direction with each finger
preshaped so its pad faces the surface, from :mod:`tacsplat.sim.grasps`); the
logger does the rest exactly as on the real rig: it closes the hand with a
speed-limited ramp through ``command_joint_positions``, waits on the twin's
clock until the fingers settle or stall, reads the four pads, places them with
the hand pose, writes the touches and opens the hand.

The plan is deterministic in the seed: view ``i`` of a split is the same pose
on every run, and grasp ``g`` draws its approaches from a generator seeded
with ``(seed, g)`` on a freshly reset simulation, so ``--resume`` continues a
killed capture where its journal stopped (a grasp cut short is redone whole).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tacsplat.acquisition.capture_scene import open_scene
from tacsplat.acquisition.config import CapturePlan, GraspPlan, RigConfig, SimConfig, ViewPlan, validate
from tacsplat.acquisition.logger import CaptureLogger, GraspOutcome
from tacsplat.errors import ConfigError

log = logging.getLogger(__name__)

MAX_ATTEMPTS_PER_GRASP = 6  # approaches tried for one grasp before it is skipped


class TwinPlanner:
    """Places the twin's view camera and hand for the logger (the twin's stand-in for the operator)."""

    def __init__(self, twin, plan: CapturePlan, grasp_config=None, view_radius_m: float | None = None):
        from tacsplat.sim.grasps import GraspConfig
        from tacsplat.sim.views import ViewConfig, hemisphere_views

        self.twin = twin
        self.plan = plan
        self.grasp_config = grasp_config or GraspConfig()
        radius = twin.object.bounding_radius
        view_config = ViewConfig() if view_radius_m is None else ViewConfig(radius_factor=view_radius_m / radius)
        train, test = hemisphere_views(plan.views.train, plan.views.test, radius, twin.config.seed, view_config)
        self.view_poses = {"train": train, "test": test}
        self._table = None

    def before_view(self, split: str, index: int) -> None:
        self.twin.move_camera(self.view_poses[split][index])

    @property
    def table(self):
        if self._table is None:
            from tacsplat.sim.grasps import PreshapeTable

            c = self.grasp_config
            self._table = PreshapeTable(self.twin, c.preshape_grid, c.preshape_abduction)
        return self._table

    def approach(self, rng: np.random.Generator) -> np.ndarray:
        """Reset the simulation, place the hand on a sampled approach, preshape it; returns the close pose [16]."""
        import mujoco

        from tacsplat.sim.grasps import preshape_fingers, sample_hand_pose, tap_close_pose

        twin = self.twin
        mujoco.mj_resetData(twin.model, twin.data)
        twin.forward()
        T_world_hand = sample_hand_pose(twin, rng, self.grasp_config)
        q_pre, reachable = preshape_fingers(twin, self.table, T_world_hand, self.grasp_config)
        return tap_close_pose(q_pre, reachable, self.grasp_config)

    def grasp(self, logger: CaptureLogger, index: int) -> GraspOutcome | None:
        """Grasp number ``index``: approaches until a pad touches (an approach that touched nothing is undone
        and retried); fingers without contact in a kept grasp are recorded as no-contact touches."""
        rng = np.random.default_rng([self.plan.grasps.seed, index])
        for attempt in range(MAX_ATTEMPTS_PER_GRASP):
            q_close = self.approach(rng)
            outcome = logger.take_grasp(close_pose=q_close, open_pose=np.zeros(16), index=index)
            if outcome.fingers_in_contact:
                return outcome
            logger.undo()
            log.info("grasp %d, approach %d touched nothing; trying another", index, attempt)
        log.warning("grasp %d touched nothing in %d approaches; skipped", index, MAX_ATTEMPTS_PER_GRASP)
        return None


def sim_rig_config(object: str = "teapot", mesh: str | None = None, object_radius: float = 0.08, views: int = 5,
                   test_views: int = 24, grasps: int = 5, resolution: int = 200, seed: int = 0) -> RigConfig:
    """The ``rig: sim`` config of ``tacsplat sim-capture``'s options."""
    config = RigConfig(
        rig="sim",
        sim=SimConfig(object=object, mesh=mesh, object_radius=object_radius, resolution=resolution, seed=seed),
        plan=CapturePlan(ViewPlan(train=views, test=test_views, mode="hemisphere"),
                         GraspPlan(count=grasps, mode="random", seed=seed)),
    )
    validate(config)
    return config


def sim_capture(config: RigConfig, out: str | Path, resume: bool = False, progress: bool = True) -> dict:
    """Capture a scene on the twin, unattended: train views, test views with GT depth, grasps; returns timings
    in seconds (``setup_s``, ``views_s``, ``grasps_s``, ``total_s``). ``resume`` continues the scene in ``out``
    only if it was captured with the same settings (a ConfigError names each that differs)."""
    if config.rig != "sim":
        raise ConfigError("rig", f"sim_capture runs the twin; got rig: {config.rig}", config.source)
    t0 = time.perf_counter()
    with open_scene(config, Path(out), resume) as (rig, writer):
        logger = CaptureLogger(writer, rig.hand, rig.sensors, rig.camera, rig.clock, rig.poses, rig.control)
        planner = TwinPlanner(rig.twin, config.plan, view_radius_m=config.plan.views.radius_m)
        t_setup = time.perf_counter()
        counts, v = logger.counts(), config.plan.views
        todo = [("train", i) for i in range(counts.train, v.train)] + [("test", i) for i in range(counts.test, v.test)]
        for split, i in tqdm(todo, desc="views", unit="view", disable=not progress):
            planner.before_view(split, i)
            logger.take_view(split)
        t_views = time.perf_counter()
        start = logger.next_grasp_index()
        for g in tqdm(range(start, config.plan.grasps.count), desc="grasps", unit="grasp", disable=not progress):
            planner.grasp(logger, g)
        t_end = time.perf_counter()
    return {"setup_s": t_setup - t0, "views_s": t_views - t_setup, "grasps_s": t_end - t_views, "total_s": t_end - t0}
