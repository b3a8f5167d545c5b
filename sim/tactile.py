"""Simulated optical tactile sensing: depth maps from ray casting and synthetic tactile RGB images.

Depth (DESIGN.md): the sensor is an orthographic depth camera behind its gel.
Parallel rays start behind the gel and travel along the gel's outward normal
(sensor +z); the first hit on the object's surface at sensor height ``z < 0``
is an indentation ``d = -z``, clamped to the gel thickness; 0 is no contact.
Rays are cast against the object's exact triangle mesh only (trimesh with the
Embree backend, float64 hit positions), never against the hand or the convex
collision hulls.

RGB: a DIGIT/GelSight-like image by a Lambertian model of three coloured
lights (red, green, blue) grazing the gel from azimuths 90, 210 and 330
degrees; each channel is lit by the slope of the indented gel surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
import trimesh.ray.ray_pyembree

from tacsplat.errors import ConfigError, InvalidInputError
from tacsplat.geometry import check_rigid, invert_pose, tactile_pixel_grid, transform_points
from tacsplat.sim.objects import bounding_sphere

# Unit directions (sensor frame, pointing from the gel towards each light) of the
# red, green and blue lights; rows are channels.
_LIGHT_ELEVATION = np.deg2rad(35.0)
_LIGHT_AZIMUTHS = np.deg2rad([90.0, 210.0, 330.0])
_LIGHT_XY = np.cos(_LIGHT_ELEVATION)  # the length of each light direction's horizontal (x, y) part
TACTILE_LIGHT_DIRECTIONS = np.column_stack(
    [_LIGHT_XY * np.cos(_LIGHT_AZIMUTHS), _LIGHT_XY * np.sin(_LIGHT_AZIMUTHS), np.full(3, np.sin(_LIGHT_ELEVATION))]
)  # [3 channels, 3 xyz]
TACTILE_RGB_GAIN = 180.0  # grey levels per unit of (n . l - n_flat . l)


def default_tactile_background(height: int, width: int) -> np.ndarray:
    """The image of the untouched gel [h, w, 3] uint8: a smooth bluish grey with a soft vignette."""
    v, u = np.meshgrid(np.linspace(-1, 1, height), np.linspace(-1, 1, width), indexing="ij")
    shade = 1.0 - 0.12 * (u**2 + v**2)
    base = np.array([118.0, 128.0, 140.0])
    return np.clip(base * shade[..., None], 0, 255).astype(np.uint8)


def tactile_surface_normals(depth: np.ndarray, pixel_size_m: float) -> np.ndarray:
    """Outward unit normals [h, w, 3] of the indented gel surface ``z = -depth`` (sensor frame)."""
    dd_dy, dd_dx = np.gradient(depth.astype(np.float64), pixel_size_m)
    n = np.stack([dd_dx, dd_dy, np.ones_like(dd_dx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def render_tactile_rgb(depth: np.ndarray, pixel_size_m: float, background: np.ndarray | None = None) -> np.ndarray:
    """Synthetic tactile image [h, w, 3] uint8 of a depth map [h, w] float32 metres.

    ``I_c = background_c + TACTILE_RGB_GAIN * (n . l_c - n_flat . l_c)`` for the
    three light directions ``TACTILE_LIGHT_DIRECTIONS`` (n from the depth
    gradient by central differences), so an untouched gel is the background.
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise InvalidInputError(f"render_tactile_rgb: depth must be [h, w], got shape {depth.shape}")
    if not np.all(np.isfinite(depth)):
        raise InvalidInputError("render_tactile_rgb: depth contains NaN or infinite values")
    if not (np.isfinite(pixel_size_m) and pixel_size_m > 0):
        raise InvalidInputError(f"render_tactile_rgb: pixel_size_m must be positive, got {pixel_size_m}")
    h, w = depth.shape
    background = default_tactile_background(h, w) if background is None else np.asarray(background)
    if background.shape != (h, w, 3):
        raise InvalidInputError(f"render_tactile_rgb: background must be [{h}, {w}, 3], got {background.shape}")
    shading = tactile_surface_normals(depth, pixel_size_m) @ TACTILE_LIGHT_DIRECTIONS.T  # [h, w, 3]
    flat = TACTILE_LIGHT_DIRECTIONS[:, 2]  # n_flat = (0, 0, 1)
    image = background.astype(np.float64) + TACTILE_RGB_GAIN * (shading - flat)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class TactileConfig:
    """A DIGIT/GelSight-like pad: 128 x 160 pixels of 0.15 mm (19.2 x 24 mm), 2 mm of gel."""

    height_px: int = 128
    width_px: int = 160
    pixel_size_m: float = 1.5e-4
    gel_thickness_m: float = 0.002
    ray_margin_m: float = 0.01  # rays start this far behind the back of the gel

    def __post_init__(self):
        for key in ("height_px", "width_px"):
            if int(getattr(self, key)) < 1:
                raise ConfigError(f"tactile.{key}", f"must be a positive integer, got {getattr(self, key)}")
        for key in ("pixel_size_m", "gel_thickness_m", "ray_margin_m"):
            value = getattr(self, key)
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"tactile.{key}", f"must be a positive number of metres, got {value}")

    @property
    def pad_size_m(self) -> tuple[float, float]:
        """(width along x, height along y) of the pad in metres."""
        return self.width_px * self.pixel_size_m, self.height_px * self.pixel_size_m


class TactileDepthRenderer:
    """Indentation maps of one object mesh (world frame) seen by a pad at any pose.

    Parallel rays along the sensor's +z from behind the gel against the exact
    mesh (Embree via trimesh; hit heights recomputed in float64 from the hit
    triangle's plane). A ray whose first hit is a back face started inside the
    object (it sank deeper than the gel and the margin): full indentation, when
    a ray cast the other way confirms it; else it missed its entry through an
    edge, and reads no contact.
    """

    def __init__(self, mesh_world: trimesh.Trimesh, config: TactileConfig = TactileConfig()):
        self.config = config
        self.mesh = mesh_world
        self.intersector = trimesh.ray.ray_pyembree.RayMeshIntersector(mesh_world)
        self._centre, self._radius = bounding_sphere(mesh_world)
        x, y = tactile_pixel_grid(config.height_px, config.width_px, config.pixel_size_m)
        z0 = -(config.gel_thickness_m + config.ray_margin_m)
        self._origins_sensor = np.stack([x.ravel(), y.ravel(), np.full(x.size, z0)], axis=1)  # [h*w, 3]
        self._z0 = z0

    def inside(self, origins: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """[N] bool: whether each origin is inside the mesh, by a ray from it along ``-direction`` leaving it through
        a back face (the renderer's check of a ray along ``direction`` whose first hit was a back face: a ray through
        an edge can miss its entry there, and its first hit is then its exit)."""
        inside = np.zeros(len(origins), dtype=bool)
        if len(origins):
            tri, ray = self.intersector.intersects_id(
                origins, np.broadcast_to(-direction, origins.shape), multiple_hits=False, return_locations=False
            )
            inside[ray] = self.mesh.face_normals[tri] @ -direction >= 0
        return inside

    def render(self, T_world_sensor: np.ndarray) -> np.ndarray:
        """Indentation [h, w] float32 metres (0 = no contact, at most the gel thickness)."""
        cfg = self.config
        T = check_rigid(T_world_sensor, "T_world_sensor")
        depth = np.zeros(cfg.height_px * cfg.width_px, dtype=np.float64)
        c = invert_pose(T)[:3, :3] @ self._centre + invert_pose(T)[:3, 3]  # object centre, sensor frame
        half_w, half_h = cfg.pad_size_m[0] / 2, cfg.pad_size_m[1] / 2
        if c[2] - self._radius > 0 or abs(c[0]) > half_w + self._radius or abs(c[1]) > half_h + self._radius:
            return depth.reshape(cfg.height_px, cfg.width_px).astype(np.float32)  # object out of reach
        origins = transform_points(T, self._origins_sensor)
        direction = T[:3, 2]
        directions = np.broadcast_to(direction, origins.shape)
        tri, ray = self.intersector.intersects_id(origins, directions, multiple_hits=False, return_locations=False)
        normals = self.mesh.face_normals[tri]
        denom = normals @ direction
        t = np.einsum("ij,ij->i", self.mesh.triangles[tri, 0] - origins[ray], normals) / np.where(denom == 0, 1, denom)
        z_hit = self._z0 + t
        indentation = np.clip(-z_hit, 0.0, cfg.gel_thickness_m)
        back = np.flatnonzero(denom >= 0)  # first hit a back face: the ray started inside, or missed its entry
        indentation[back] = np.where(self.inside(origins[ray[back]], direction), cfg.gel_thickness_m, 0.0)
        depth[ray] = indentation
        return depth.reshape(cfg.height_px, cfg.width_px).astype(np.float32)
