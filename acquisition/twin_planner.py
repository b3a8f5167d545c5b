"""The twin's stand-in for the operator: it places the view camera and the hand; the logger does the rest.

Views: the view camera on the hemisphere around the object. Grasps: the hand
base on a sampled approach direction, each finger preshaped so its pad faces
the surface (:mod:`tacsplat.sim.grasps`); then the logger's grasp controller
(:meth:`~tacsplat.acquisition.logger.CaptureLogger.take_grasp`) closes the hand
through the Protocols until each finger stalls on the object, reads the pads
and opens the hand, exactly as on the real rig.

Grasp ``g`` is deterministic in ``(seed, g)``: its approaches come from a
generator seeded with both, each on a freshly reset simulation, so a capture
resumed at grasp ``g`` continues as if it had never stopped.
"""

from __future__ import annotations

import functools
import logging

import numpy as np

from tacsplat.acquisition.config import ViewPlan
from tacsplat.acquisition.logger import CaptureLogger, GraspOutcome
from tacsplat.sim.grasps import GraspConfig, PreshapeTable, preshape_fingers, sample_hand_pose, tap_close_pose
from tacsplat.sim.twin import SimTwin
from tacsplat.sim.views import ViewConfig, hemisphere_views

log = logging.getLogger(__name__)

MAX_ATTEMPTS_PER_GRASP = 6  # approaches tried for one grasp before it is skipped


class TwinPlanner:
    """Places the twin's view camera (``views``: the plan's, None for a grasps-only job) and its hand."""

    def __init__(
        self, twin: SimTwin, grasp_seed: int, views: ViewPlan | None = None, grasp_config: GraspConfig = GraspConfig()
    ):
        self.twin = twin
        self.grasp_seed = grasp_seed
        self.grasp_config = grasp_config
        self.view_poses = {"train": [], "test": []}
        if views is not None:
            radius = twin.object.bounding_radius
            view_config = ViewConfig() if views.radius_m is None else ViewConfig(radius_factor=views.radius_m / radius)
            train, test = hemisphere_views(views.train, views.test, radius, twin.config.seed, view_config)
            self.view_poses = {"train": train, "test": test}

    def before_view(self, split: str, index: int) -> None:
        self.twin.move_camera(self.view_poses[split][index])

    @functools.cached_property
    def table(self) -> PreshapeTable:
        c = self.grasp_config
        return PreshapeTable(self.twin, c.preshape_grid, c.preshape_abduction)

    def approach(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Reset the simulation, place the hand on a sampled approach, preshape it; returns the close pose [16] and
        the preshape [16] (the release goes back to it: the way the fingers came is free)."""
        twin, config = self.twin, self.grasp_config
        twin.reset()
        q_pre, reachable = preshape_fingers(twin, self.table, sample_hand_pose(twin, rng, config), config)
        return tap_close_pose(q_pre, reachable, config), q_pre

    def grasp(self, logger: CaptureLogger, index: int) -> GraspOutcome | None:
        """Grasp number ``index``: approach, let the logger grasp; an approach that touched nothing is undone and
        another tried, up to ``MAX_ATTEMPTS_PER_GRASP``; None when none touched. Fingers without contact in a kept
        grasp are recorded as no-contact touches."""
        rng = np.random.default_rng([self.grasp_seed, index])
        for attempt in range(MAX_ATTEMPTS_PER_GRASP):
            q_close, q_pre = self.approach(rng)
            outcome = logger.take_grasp(close_pose=q_close, open_pose=q_pre, index=index)
            if outcome.fingers_in_contact:
                return outcome
            logger.undo()
            log.info("grasp %d, approach %d touched nothing; trying another", index, attempt)
        log.warning("grasp %d touched nothing in %d approaches; skipped", index, MAX_ATTEMPTS_PER_GRASP)
        return None
