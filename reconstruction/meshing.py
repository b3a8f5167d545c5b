"""A watertight mesh from a reconstruction, and the mesh metrics.

:func:`extract_mesh` renders the Gaussians' median depth (the paper's
evaluation depth) and colour from ``views`` cameras spread evenly on a sphere
around the object, fuses them into a truncated signed distance field (TSDF) on
a dense voxel grid, fuses the touches' contact points into the same field as
points along their normals (a tactile map is orthographic: no camera ray), and
runs marching cubes (scikit-image). Only the cameras within a cone around the
training cameras' directions are fused (:func:`fused_cameras`). A pixel where
the render shows no surface marks its whole ray as empty; voxels no view and no touch ever reaches (the
inside) stay inside, so the zero level set is closed: the mesh is watertight by
construction. A view that sees through a semi-transparent stretch of the shell
carves hollows into the object that open to the outside only through small
holes; they are sealed (:func:`seal_hollows`, a morphological closing of the
inside). Only the largest connected piece is kept (floaters go) unless
asked otherwise. Each vertex is flagged ``observed`` when a training camera sees
it (the mesh itself occluding) or a touch lies within a voxel of it.

The fusion is a dense grid (numpy, by slabs): Open3D's scalable TSDF would add
a C++ dependency that pulls a web framework with it, and it keeps only the
observed band, which leaves holes where no view looked. The default voxel is 1 %
of the object's radius (about 220^3 voxels): fine enough for an F-score at 1 %.

:func:`~.metrics.mesh_metrics` compares a mesh with the ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from tacsplat.errors import InvalidInputError
from tacsplat.files import atomic_write
from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction.metrics import finite_or_none, ground_truth_surface, mesh_metrics
from tacsplat.types import CameraIntrinsics

SLAB_VOXELS = 2_000_000  # voxels projected at once (memory: about 100 bytes each)


@dataclass
class MeshConfig:
    """How :func:`extract_mesh` makes a mesh."""

    voxel: float = 0.01  # voxel side, as a fraction of the object's radius
    views: int = 64  # virtual cameras spread evenly on a sphere around the object ...
    cone_deg: float = 30.0  # ... of which those within this angle of a training camera's direction are fused
    image_size: int = 256  # their image width and height, pixels
    truncation: float = 3.0  # the TSDF's truncation, in voxels
    touches: bool = True  # fuse the touches' contact points
    touch_weight: float = 1.0  # a touch point's weight, as a share of all the views' together
    seal: float = 0.1  # hollows open to the outside only through gaps narrower than twice this (of the radius) fill
    object_only: bool = True  # keep only the largest connected piece

    def validate(self) -> None:
        if not 0.001 <= self.voxel <= 0.2:
            raise InvalidInputError(f"voxel: must be in [0.001, 0.2] of the object's radius, got {self.voxel}")
        for key, least in (("views", 6), ("image_size", 16)):
            if getattr(self, key) < least:
                raise InvalidInputError(f"{key}: must be >= {least}, got {getattr(self, key)}")
        if not 0 < self.cone_deg <= 180:
            raise InvalidInputError(f"cone_deg: must be in (0, 180], got {self.cone_deg}")
        if not 0 <= self.seal <= 1:
            raise InvalidInputError(f"seal: must be in [0, 1] of the object's radius, got {self.seal}")
        if not self.truncation >= 1 or not self.touch_weight > 0:
            raise InvalidInputError("truncation must be >= 1 voxel and touch_weight > 0")


def object_sphere(means: np.ndarray, opacities: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre [3] and radius of the object: the opaque Gaussians' (opacity > 0.5) means inside the scene's bounds
    ``lo``..``hi``, their 0.5th to 99.5th percentile box (a stray Gaussian does not stretch it), grown by 5 %."""
    inside = np.all((means >= lo) & (means <= hi), axis=1) & (opacities > 0.5)
    points = means[inside] if inside.sum() >= 10 else means
    if not len(points):
        raise InvalidInputError("the reconstruction has no Gaussians to mesh")
    low, high = np.percentile(points, [0.5, 99.5], axis=0)
    centre = (low + high) / 2
    return centre, 1.05 * float(np.linalg.norm(high - low) / 2)


def sphere_cameras(centre: np.ndarray, radius: float, count: int, size: int, fov_deg: float = 40.0) -> list:
    """``count`` cameras on a Fibonacci sphere around ``centre``, each looking at it and seeing the whole sphere of
    ``radius`` (scene frames of ``size`` square pixels)."""
    from tacsplat.datasets.records import Frame

    half = np.radians(fov_deg) / 2
    f = size / 2 / np.tan(half)
    K = np.array([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    distance = 1.1 * radius / np.sin(half)
    i = np.arange(count) + 0.5
    z, a = 1 - 2 * i / count, np.pi * (1 + 5**0.5) * i
    directions = np.stack([np.sqrt(1 - z**2) * np.cos(a), np.sqrt(1 - z**2) * np.sin(a), z], axis=1)
    frames = []
    for k, d in enumerate(directions):
        up = (0.0, 0.0, 1.0) if abs(d[2]) < 0.99 else (1.0, 0.0, 0.0)
        pose = look_at(centre + distance * d, centre, up=up)
        frames.append(Frame(k, f"virtual/{k}", pose, "test", CameraIntrinsics(K, size, size)))
    return frames


def fused_cameras(centre: np.ndarray, radius: float, train_frames: list, config: MeshConfig) -> list:
    """The virtual cameras whose renders are fused: those of :func:`sphere_cameras` within ``config.cone_deg`` of a
    training camera's direction from ``centre``. A render from where no training camera looked shows the inside
    of the surface the cameras saw (3DGS has no back faces) and would carve the object's inside away; what no
    fused view sees stays closed, and flagged unobserved."""
    seen = np.array([f.T_world_cam[:3, 3] - centre for f in train_frames])  # [T, 3]
    seen /= np.linalg.norm(seen, axis=1, keepdims=True)
    cameras = []
    for frame in sphere_cameras(centre, radius, config.views, config.image_size):
        direction = frame.T_world_cam[:3, 3] - centre
        cosine = seen @ (direction / np.linalg.norm(direction))
        if cosine.max() >= np.cos(np.radians(config.cone_deg)):
            cameras.append(frame)
    return cameras


class TSDFVolume:
    """A dense truncated signed distance field: positive outside, weighted sums per voxel (``sdf``, ``weight``,
    ``color``); a voxel nothing reached reads -1 (inside)."""

    def __init__(self, lo: np.ndarray, voxel: float, shape: tuple[int, int, int], truncation: float):
        self.lo, self.voxel, self.shape, self.truncation = np.asarray(lo, np.float64), float(voxel), shape, truncation
        self.sdf = np.zeros(shape, np.float32)
        self.weight = np.zeros(shape, np.float32)
        self.color = np.zeros(shape + (3,), np.float32)
        self.color_weight = np.zeros(shape, np.float32)

    def centres(self, x: slice) -> np.ndarray:
        """World centres [n, 3] of the voxels of the slab ``x`` (all y, z), in C order."""
        axes = [np.arange(self.shape[0])[x], np.arange(self.shape[1]), np.arange(self.shape[2])]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        return self.lo + (grid + 0.5) * self.voxel

    def integrate_depth(self, depth: np.ndarray, rgb: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> None:
        """Fuse one view's z-depth [H, W] (0 where no surface: its ray is empty) and colour [H, W, 3]."""
        h, w = depth.shape
        world_to_cam = invert_pose(T_world_cam)
        step = max(1, SLAB_VOXELS // (self.shape[1] * self.shape[2]))
        for start in range(0, self.shape[0], step):
            x = slice(start, min(start + step, self.shape[0]))
            p = self.centres(x) @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]  # [n, 3] camera frame
            z = p[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = np.floor(p[:, 0] / z * K[0, 0] + K[0, 2])
                v = np.floor(p[:, 1] / z * K[1, 1] + K[1, 2])
            inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            index = np.flatnonzero(inside)
            ui, vi = u[index].astype(np.int64), v[index].astype(np.int64)
            d = depth[vi, ui]
            sdf = np.where(d > 0, d - z[index], np.inf)  # no surface: the voxel is empty
            use = sdf >= -self.truncation  # (far behind the surface: occluded, unknown)
            # weight 1 each, into flat views of the slab (C-contiguous rows: its centres are in C order); each voxel
            # at most once per view
            flat = index[use]
            self.sdf[x].reshape(-1)[flat] += np.clip(sdf[use] / self.truncation, -1.0, 1.0)
            self.weight[x].reshape(-1)[flat] += 1.0
            band = np.abs(sdf[use]) < self.truncation
            self.color[x].reshape(-1, 3)[flat[band]] += rgb[vi[use][band], ui[use][band]]
            self.color_weight[x].reshape(-1)[flat[band]] += 1.0

    def integrate_points(self, points: np.ndarray, normals: np.ndarray, weight: float) -> None:
        """Fuse surface points [N, 3] with outward unit normals [N, 3]: each voxel within the truncation of a point
        gets the signed distance along that point's normal."""
        reach = int(np.ceil(self.truncation / self.voxel))
        offsets = np.stack(np.meshgrid(*[np.arange(-reach, reach + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
        for chunk in range(0, len(points), 2000):
            p, n = points[chunk : chunk + 2000], normals[chunk : chunk + 2000]
            cells = np.floor((p - self.lo) / self.voxel).astype(np.int64)[:, None] + offsets  # [N, O, 3]
            valid = np.all((cells >= 0) & (cells < np.array(self.shape)), axis=-1)
            centres = self.lo + (cells + 0.5) * self.voxel
            sdf = np.einsum("nod,nd->no", centres - p[:, None], n)
            near = valid & (np.linalg.norm(centres - p[:, None], axis=-1) <= self.truncation)
            flat = np.ravel_multi_index(tuple(cells[near].T), self.shape)
            np.add.at(self.sdf.reshape(-1), flat, weight * np.clip(sdf[near] / self.truncation, -1.0, 1.0))
            np.add.at(self.weight.reshape(-1), flat, weight)

    def field(self) -> np.ndarray:
        """The signed distance [X, Y, Z] in truncations: the weighted mean, -1 where nothing reached."""
        return np.where(self.weight > 0, self.sdf / np.maximum(self.weight, 1e-12), -1.0).astype(np.float32)

    def mesh(self, seal_voxels: float = 0.0) -> trimesh.Trimesh:
        """The zero level set (marching cubes on the field, sealed by :func:`seal_hollows`, padded with empty space:
        closed), outward faces, vertex colours from the nearest voxel."""
        from skimage.measure import marching_cubes

        field = np.pad(seal_hollows(self.field(), seal_voxels), 1, constant_values=1.0)
        field[field == 0] = 1e-6  # (a vertex exactly on a voxel corner would be shared by faces of several cells)
        if field.min() >= 0 or field.max() <= 0:
            raise InvalidInputError("the fused field has no surface (nothing inside the object's box)")
        vertices, faces, normals, _ = marching_cubes(field, level=0.0, spacing=(self.voxel,) * 3)
        vertices = vertices + self.lo - 0.5 * self.voxel  # padded voxel 1 is voxel 0, whose centre is lo + voxel / 2
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        trimesh.repair.fix_normals(mesh)
        # vertex normals along the field's gradient, which scikit-image gives pointing to lower values: inward
        # here (a vertex among the tiny faces near a voxel corner has no face normal to average)
        mesh.vertex_normals = -normals
        cells = np.clip(np.floor((mesh.vertices - self.lo) / self.voxel).astype(np.int64), 0, np.array(self.shape) - 1)
        w = self.color_weight[tuple(cells.T)]
        color = np.where(w[:, None] > 0, self.color[tuple(cells.T)] / np.maximum(w, 1e-12)[:, None], 0.5)
        mesh.visual.vertex_colors = np.concatenate(
            [np.clip(np.rint(color * 255), 0, 255), np.full((len(color), 1), 255)], axis=1
        ).astype(np.uint8)
        return mesh


def seal_hollows(field: np.ndarray, reach: float) -> np.ndarray:
    """``field`` [X, Y, Z] (negative inside) with every hollow that opens to the outside only through gaps narrower
    than ``2 reach`` voxels made inside (-1): a morphological closing of the inside (grown by ``reach``, the
    holes that encloses filled, shrunk back by ``reach``). Crevices of the outer surface narrower than that fill
    too. Outside the box is outside."""
    from scipy import ndimage

    if reach <= 0:
        return field
    pad = int(np.ceil(reach)) + 1
    solid = np.pad(field < 0, pad)  # [X + 2 pad, ...]
    grown = ndimage.distance_transform_edt(~solid) <= reach
    closed = ndimage.distance_transform_edt(ndimage.binary_fill_holes(grown)) > reach
    hollow = (closed & ~solid)[pad:-pad, pad:-pad, pad:-pad]
    return np.where(hollow, -1.0, field).astype(np.float32)


@dataclass
class ExtractedMesh:
    mesh: trimesh.Trimesh  # metres, the scene's frame, outward normals, vertex colours
    observed: np.ndarray  # [V] bool: a training camera sees the vertex, or a touch lies within a voxel of it
    voxel: float  # metres


@torch.no_grad()
def extract_mesh(gaussians, scene, train_frames: list, backend: str, look=None, config: MeshConfig | None = None):
    """:class:`ExtractedMesh` of a reconstruction (module docstring); ``look`` the Gaussians' appearance."""
    from tacsplat.reconstruction.evaluation import render_frame, render_median_depth, seen_by_cameras

    config = config or MeshConfig()
    config.validate()
    lo, hi = scene.bounds()
    means = gaussians.means.detach().cpu().numpy().astype(np.float64)
    opacities = gaussians.opacities.detach().cpu().numpy().reshape(-1)
    centre, radius = object_sphere(means, opacities, lo, hi)
    voxel = config.voxel * radius
    shape = tuple([int(np.ceil(2 * radius / voxel))] * 3)
    volume = TSDFVolume(centre - radius, voxel, shape, config.truncation * voxel)
    background = torch.zeros(config.image_size, config.image_size, 3)
    for frame in fused_cameras(centre, radius, train_frames, config):
        view = render_frame(gaussians, frame, background, backend, with_depth=False, look=look)
        median = view.median_depth if view.median_depth is not None else render_median_depth(gaussians, frame, backend)
        volume.integrate_depth(median.astype(np.float64), view.rgb, frame.intrinsics.K, frame.T_world_cam)
    touch_points = np.zeros((0, 3))
    if config.touches and any(t.in_contact for t in scene.touches):
        touch_points, normals = scene.touch_points(), scene.touch_normals()
        known = np.isfinite(normals).all(axis=1)
        volume.integrate_points(touch_points[known], normals[known], config.touch_weight * config.views)
    mesh = volume.mesh(config.seal / config.voxel)
    if config.object_only:
        pieces = mesh.split(only_watertight=False)
        if len(pieces) > 1:
            whole, mesh = mesh, max(pieces, key=lambda m: len(m.faces))
            mesh.vertex_normals = whole.vertex_normals[cKDTree(whole.vertices).query(mesh.vertices)[1]]  # (the field's)
    seen = seen_by_cameras(mesh, {0: np.asarray(mesh.vertices)}, train_frames, radius)[0]
    if len(touch_points):
        seen |= cKDTree(touch_points).query(mesh.vertices, distance_upper_bound=voxel)[0] <= voxel
    return ExtractedMesh(mesh, seen, voxel)


def save_mesh_ply(extracted: ExtractedMesh, path: str | Path) -> Path:
    """A binary PLY: vertices with normals, colours and ``observed`` (0/1), triangles."""
    from plyfile import PlyData, PlyElement

    mesh = extracted.mesh
    dtype = [(k, "f4") for k in ("x", "y", "z", "nx", "ny", "nz")]
    dtype += [(k, "u1") for k in ("red", "green", "blue", "observed")]
    columns = [*mesh.vertices.T, *mesh.vertex_normals.T, *mesh.visual.vertex_colors[:, :3].T, extracted.observed]
    vertex = np.rec.fromarrays(columns, dtype=dtype)
    faces = np.empty(len(mesh.faces), dtype=[("vertex_indices", "i4", (3,))])
    faces["vertex_indices"] = mesh.faces
    return atomic_write(
        path, PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(faces, "face")]).write
    )


def export_mesh(
    run_dir: str | Path, out: str | Path | None = None, config: MeshConfig | None = None, record: str | None = None
) -> dict:
    """Extract a run's mesh (its last checkpoint) into ``out`` (default ``RUN/mesh.ply``); returns a summary: the
    file, vertex and face counts, the share of vertices observed, and the mesh metrics where the scene has a
    ground truth. The metrics go into ``RUN/metrics.json`` too, as ``mesh_*`` for ``RUN/mesh.ply``, or under the
    prefix ``record`` (``mesh_untouched``: ``mesh_untouched_fscore_5``, ...)."""
    import json

    from tacsplat.datasets import Scene
    from tacsplat.reconstruction.evaluation import seen_by_training_views
    from tacsplat.reconstruction.run_dir import load_run
    from tacsplat.reconstruction.views import scene_at, training_frames

    run_dir = Path(run_dir)
    run = load_run(run_dir)
    scene = scene_at(Scene.load(run.scene_path), run.config.downscale)
    out = run_dir / "mesh.ply" if out is None else Path(out)
    frames = training_frames(scene, run.config.train_views)
    extracted = extract_mesh(run.gaussians, scene, frames, run.config.backend, run.look, config)
    save_mesh_ply(extracted, out)
    summary = {
        "mesh": str(out),
        "vertices": len(extracted.mesh.vertices),
        "faces": len(extracted.mesh.faces),
        "observed_fraction": float(extracted.observed.mean()),
        "voxel_m": extracted.voxel,
        "mesh_watertight": bool(extracted.mesh.is_watertight),
    }
    truth = ground_truth_surface(scene)
    if truth is not None:
        summary.update(
            finite_or_none(mesh_metrics(extracted.mesh, *truth, seen_by=seen_by_training_views(*truth, frames)))
        )
        metrics_path = run_dir / "metrics.json"
        default = out.resolve() == (run_dir / "mesh.ply").resolve()
        if (record is not None or default) and metrics_path.is_file():
            prefix = record or "mesh"
            metrics = json.loads(metrics_path.read_text())
            metrics.update({prefix + k[len("mesh") :]: v for k, v in summary.items() if k.startswith("mesh_")})
            atomic_write(metrics_path, json.dumps(metrics, indent=2).encode())
    return summary


def export_meshes(run_dir: str | Path) -> None:
    """A run's ``mesh.ply`` with its touches fused and ``mesh-untouched.ply`` without (``mesh_untouched_*`` in its
    metrics.json): what touching buys the mesh (``bench paper --mesh``)."""
    run_dir = Path(run_dir)
    export_mesh(run_dir, run_dir / "mesh-untouched.ply", MeshConfig(touches=False), record="mesh_untouched")
    export_mesh(run_dir)  # last: its file marks the run's meshes done
