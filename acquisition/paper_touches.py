"""The paper's touches (``--touch-model paper``): the touches the official code of Comi et al. gives its trainer,
recorded as touches of a scene.

The official code (maurock/Dynamic3DGaussians, branch depth_diff,
``data_making/simulate_local_depth.py``) samples ``pc_num`` points evenly on
the object's surface (``trimesh.sample.sample_surface_even``: 20000 for Glossy
Synthetic, 10000 for Shiny Blender). For each touch it casts one ray from the
mesh's centroid in a random direction, polar angle theta ~ U(0, pi) from +z and
azimuth phi ~ U(0, 2 pi) (so not uniform over the sphere: the poles get more),
again until one hits, keeps the hit furthest from the centroid, and takes the
50 samples nearest to it. No hand, no gel: a touch is 50 surface points.

Here the samples come from their own stream of ``seed`` and touch ``t``'s rays
from a generator seeded with ``(seed, t)``, so a resumed capture makes the same
touches; rays meet the mesh in trimesh's exact triangle intersector (not Embree:
the same hits on every machine). Touch ``t`` is recorded as grasp ``t // 4``,
finger ``FINGER_NAMES[t % 4]``: the scene format groups touches in grasps of
four, though no grasp is executed.

Encoding (:func:`encode_touch`): a touch is stored like any other, as an
indentation map of the scene's pad with its pose. The pad faces the plane fitted
to the points (its z axis is their smallest principal direction, pointing into
the object: against the ray, which leaves the object at its furthest hit; x and
y as :func:`~tacsplat.geometry.look_at` puts them); its origin is on that axis
through the points' centroid, the gel pressed flat onto the points until the
shallowest is ``MIN_INDENTATION_GELS`` gel thicknesses deep. Each point is
written at the pixel that holds it, with the indentation that lifts back to its
exact depth: a lifted point differs from its sample only along the pad, by at
most half a pixel diagonal (``pixel_size / sqrt(2)``, 0.11 mm on the twin's
pad). Where two points fall on one pixel, the deeper keeps it (a gel shows the
surface pressed furthest into it) and the other takes the nearest free pixel:
within ``COLLISION_TOLERANCE_PX`` pixels when one of the eight around it is free.
A point outside the pad, or deeper than the sensor records, is not written (a
warning says how many). Measured on the six library objects at the default
radius and sample count (seeds 0-2, 20 touches each, 360 touches): no point is
lost (a touch spans at most 16 mm of the 19.2 x 24 mm pad and 6.3 mm of the
20 mm of depth the scene accepts), two points moved to a neighbouring pixel,
and no lifted point lies more than 0.15 mm from its sample.
"""

from __future__ import annotations

import logging
from typing import Callable, Iterable

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from tacsplat.acquisition.config import TouchPlan
from tacsplat.datasets import SceneWriter, SensorModel
from tacsplat.datasets.records import touch_depth_limit
from tacsplat.errors import InvalidInputError
from tacsplat.geometry import look_at
from tacsplat.sim.hand import FINGER_NAMES

log = logging.getLogger(__name__)

TOUCHES_PER_GRASP = len(FINGER_NAMES)
MIN_INDENTATION_GELS = 0.05  # the shallowest point of a touch, in gel thicknesses (0.1 mm on the twin's pad)
COLLISION_TOLERANCE_PX = 1.5 * np.sqrt(2.0)  # a point moved off a taken pixel: at most this far, in pixels
MAX_RAYS = 1000  # rays cast for one touch before the mesh is declared unhittable
_SAMPLES_STREAM, _TOUCH_STREAM = 0, 1  # SeedSequence spawn keys: (0,) the surface samples, (1, t) touch t


class PaperTouches:
    """The paper's touches of one surface, in its frame and units: the surface samples drawn once (``seed``), touch
    ``t`` on demand.

    ``surface`` is a mesh, or points on the object's surface [N, 3] where a dataset ships no mesh (Glossy
    Synthetic's ``eval_pts.ply``, Shiny Blender's depth back-projected). On points, the samples are
    ``surface_points`` of them drawn at random, the rays start at their centroid, and a ray "meets" the samples
    within one sample spacing (the median distance between nearest samples) of it. A cloud of fewer points is
    used whole, and a touch takes proportionally fewer of them (at least one), so that it covers the share of the
    surface the paper's touch covers (``points_per_touch / surface_points``).
    """

    def __init__(self, surface: trimesh.Trimesh | np.ndarray, seed: int, plan: TouchPlan = TouchPlan()):
        self.seed = seed
        self.plan = plan
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(_SAMPLES_STREAM,)))
        if isinstance(surface, trimesh.Trimesh):
            self.samples = trimesh.sample.sample_surface_even(surface, plan.surface_points, seed=rng)[0]
            self.rays = trimesh.ray.ray_triangle.RayMeshIntersector(surface)
            self.centroid = np.asarray(surface.centroid, dtype=np.float64)
        else:
            points = np.asarray(surface, dtype=np.float64)
            if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2 or not np.isfinite(points).all():
                raise InvalidInputError(f"surface: expected finite points [N >= 2, 3], got shape {points.shape}")
            if len(points) > plan.surface_points:
                points = points[rng.choice(len(points), plan.surface_points, replace=False)]
            self.samples, self.rays, self.centroid = points, None, points.mean(axis=0)
        share = min(1.0, len(self.samples) / plan.surface_points)
        self.points_per_touch = max(1, round(plan.points_per_touch * share))
        self.tree = cKDTree(self.samples)
        if self.rays is None:
            self.spacing = float(np.median(self.tree.query(self.samples, k=2)[0][:, 1]))

    def _hits(self, direction: np.ndarray) -> np.ndarray:
        """Where the ray from the centroid along ``direction`` [3] meets the surface: points [K, 3]."""
        if self.rays is not None:
            return self.rays.intersects_location(self.centroid[None], direction[None])[0]
        offsets = self.samples - self.centroid  # [N, 3]
        along = offsets @ direction
        across = np.linalg.norm(offsets - along[:, None] * direction, axis=1)
        return self.samples[(along > 0) & (across <= self.spacing)]

    def ray(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Touch ``index``'s hit [3] (the furthest from the centroid along the first ray that meets the mesh) and
        that ray's unit direction [3]."""
        rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(_TOUCH_STREAM, index)))
        for _ in range(MAX_RAYS):
            theta, phi = rng.uniform(0.0, np.pi), rng.uniform(0.0, 2.0 * np.pi)
            direction = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
            hits = self._hits(direction)
            if len(hits):
                return hits[np.argmax(np.linalg.norm(hits - self.centroid, axis=1))], direction
        raise InvalidInputError(f"surface: no ray from its centroid met it in {MAX_RAYS} tries (touch {index})")

    def touch(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Touch ``index``: its points [k, 3] (the samples nearest to its hit) and its ray's direction [3]."""
        hit, direction = self.ray(index)
        k = min(self.points_per_touch, len(self.samples))
        _, nearest = self.tree.query(hit, k=k)
        return self.samples[np.atleast_1d(nearest)], direction


def encode_touch(points: np.ndarray, direction: np.ndarray, sensor: SensorModel) -> tuple[np.ndarray, np.ndarray]:
    """A touch's points [k, 3] (surface points around where a ray along ``direction`` [3] left the object) as an
    indentation map [h, w] float32 of ``sensor`` and its pose ``T_world_sensor`` [4, 4] (module docstring)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][-1]  # of the plane fitted to the points
    normal = normal if normal @ direction > 0 else -normal  # outward: the ray leaves the object there
    heights = (points - centre) @ normal
    origin = centre - (MIN_INDENTATION_GELS * sensor.gel_thickness_m - heights.min()) * normal
    T_world_sensor = look_at(origin, origin - normal)  # z into the object, towards the touched surface
    local = (points - origin) @ T_world_sensor[:3, :3]
    h, w, size = sensor.height_px, sensor.width_px, sensor.pixel_size_m
    cols = np.floor(local[:, 0] / size + w / 2).astype(np.int64)
    rows = np.floor(local[:, 1] / size + h / 2).astype(np.int64)
    depths = -local[:, 2]
    recordable = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h) & (depths <= touch_depth_limit(sensor)[0])
    if not recordable.all():
        log.warning(
            "%d of a touch's %d points lie outside the pad (%.3g x %.3g) or deeper than it records; not written",
            int((~recordable).sum()),
            len(points),
            w * size,
            h * size,
        )
    depth = np.zeros((h, w), dtype=np.float32)
    for i in np.flatnonzero(recordable)[np.argsort(-depths[recordable], kind="stable")]:  # the deepest first
        r, c = rows[i], cols[i]
        if depth[r, c] > 0:
            r, c = _nearest_free_pixel(depth, local[i, :2], size)
        depth[r, c] = depths[i]
    return depth, T_world_sensor


def _nearest_free_pixel(depth: np.ndarray, xy: np.ndarray, size: float) -> tuple[int, int]:
    """The (row, column) of the free pixel (indentation 0) whose centre is nearest to ``xy`` on the pad."""
    free = np.argwhere(depth == 0)
    h, w = depth.shape
    centres = (free[:, ::-1] + 0.5 - np.array([w / 2, h / 2])) * size
    r, c = free[np.argmin(np.sum((centres - xy) ** 2, axis=1))]
    return int(r), int(c)


def write_paper_touches(
    writer: SceneWriter,
    touches: PaperTouches,
    indices: Iterable[int],
    to_scene: Callable[[np.ndarray], np.ndarray] | None = None,
) -> None:
    """Append touches ``indices`` to ``writer``'s scene as grasp ``t // 4``, finger ``FINGER_NAMES[t % 4]``;
    ``to_scene`` maps the mesh's points into the scene's frame and units (a uniform scale and a translation;
    default: the same)."""
    for t in indices:
        points, direction = touches.touch(t)
        depth, T_world_sensor = encode_touch(points if to_scene is None else to_scene(points), direction, writer.sensor)
        writer.add_touch(
            depth, T_world_sensor, grasp=t // TOUCHES_PER_GRASP, finger=FINGER_NAMES[t % TOUCHES_PER_GRASP]
        )
