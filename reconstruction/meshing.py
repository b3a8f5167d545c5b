"""A watertight mesh from a reconstruction, and the mesh metrics.

:func:`extract_mesh` renders the Gaussians' median depth (the paper's evaluation depth) and colour from ``views``
cameras spread evenly on a sphere around the object, fuses them into a truncated signed distance field (TSDF) on a
dense voxel grid, fuses the touches' contact points into the same field as points along their normals (a tactile
map is orthographic: no camera ray), and runs marching cubes (scikit-image). Only the cameras within a cone around
the training cameras' directions are fused (:func:`fused_cameras`; none is an error). A pixel where the render shows
no surface marks its whole ray as empty; voxels no view and no touch ever reaches (the inside) stay inside, so the
zero level set is closed: the mesh is watertight by construction. A view that sees through a semi-transparent
stretch of the shell carves hollows into the object that open to the outside only through small holes; they are
sealed (:func:`seal_hollows`, a morphological closing of the inside). Only the largest connected piece is kept
(floaters go) unless asked otherwise; then a piece of the inside that nothing reached and that lies wholly beyond
the object's sphere (a corner of the grid that no fused view covers, or that only ever lies behind the object) is
outside (:meth:`TSDFVolume.clear_blobs`), not a blob of its own. Each vertex is flagged ``observed`` when a training
camera sees it (the mesh itself occluding) or a touch lies within a voxel of it.

The fusion is a dense grid (numpy, by slabs): Open3D's scalable TSDF would add
a C++ dependency that pulls a web framework with it, and it keeps only the
observed band, which leaves holes where no view looked. The default voxel is 1 %
of the object's radius (200^3 voxels: the grid spans the object's diameter): fine enough for an F-score at 1 %.

:func:`~.metrics.mesh_metrics` compares a mesh with the ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from tacsplat.errors import ConfigError, InvalidInputError, UsageError
from tacsplat.files import atomic_file, atomic_write
from tacsplat.geometry import invert_pose, look_at
from tacsplat.reconstruction.metrics import finite_or_none, ground_truth_surface, mesh_metrics
from tacsplat.reconstruction.ply import make_parent
from tacsplat.types import CameraIntrinsics

SLAB_VOXELS = 2_000_000  # voxels projected at once (memory: about 100 bytes each)


MIN_VOXEL = 0.005  # of the bounding radius: a grid of 400^3 cells, about 6 GB at its peak
FLOAT32_TOLERANCE = 1e-3  # voxels: mesh.ply's vertices are float64 where float32 would move one by more


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
        if not MIN_VOXEL <= self.voxel <= 0.2:  # (below, the grid's (2 / voxel)^3 cells need more than ~6 GB)
            raise InvalidInputError(
                f"voxel: must be in [{MIN_VOXEL}, 0.2] of the object's bounding radius (0.005: 400^3 cells, about "
                f"6 GB), got {self.voxel}"
            )
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
    cameras = []  # (none: :func:`extract_mesh` refuses it)
    for frame in sphere_cameras(centre, radius, config.views, config.image_size):
        direction = frame.T_world_cam[:3, 3] - centre
        cosine = seen @ (direction / np.linalg.norm(direction))
        if cosine.max() >= np.cos(np.radians(config.cone_deg)):
            cameras.append(frame)
    return cameras


class TSDFVolume:
    """A dense truncated signed distance field: positive outside, weighted sums per voxel (``sdf``, ``weight``,
    ``color``); a voxel nothing reached reads -1 (inside), unless :meth:`clear_blobs` made it +1 (``cleared``)."""

    def __init__(self, lo: np.ndarray, voxel: float, shape: tuple[int, int, int], truncation: float):
        self.lo, self.voxel, self.shape, self.truncation = np.asarray(lo, np.float64), float(voxel), shape, truncation
        self.sdf = np.zeros(shape, np.float32)
        self.weight = np.zeros(shape, np.float32)
        self.color = np.zeros(shape + (3,), np.float32)
        self.color_weight = np.zeros(shape, np.float32)
        self.cleared = np.zeros(shape, bool)  # unreached, yet outside (:meth:`clear_blobs`)

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
        """The signed distance [X, Y, Z] in truncations: the weighted mean; where nothing reached, -1 (inside), or +1
        where :meth:`clear_blobs` cleared the voxel."""
        unreached = np.where(self.cleared, 1.0, -1.0)
        return np.where(self.weight > 0, self.sdf / np.maximum(self.weight, 1e-12), unreached).astype(np.float32)

    def clear_blobs(self, centre: np.ndarray, radius: float) -> None:
        """Make outside every connected piece of the inside (26-connected voxels, :meth:`field` < 0) that nothing
        reached (no view, no touch) and whose voxel centres all lie beyond the sphere ``centre``, ``radius`` that holds
        the object: a corner of the grid that no fused view covers, or that lies only ever behind the object. The
        object's own unseen inside touches its sphere and stays; so does a floater some view saw."""
        from scipy import ndimage

        inside = self.field() < 0
        labels, count = ndimage.label(inside, structure=np.ones((3, 3, 3), bool))
        if count == 0:
            return
        axes = [((np.arange(n) + 0.5) * self.voxel + self.lo[k] - centre[k]) ** 2 for k, n in enumerate(self.shape)]
        near = axes[0][:, None, None] + axes[1][None, :, None] + axes[2][None, None, :] <= radius**2
        keep = np.zeros(count + 1, bool)
        keep[labels[inside & ((self.weight > 0) | near)]] = True
        self.cleared |= inside & ~keep[labels]

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
    cameras = fused_cameras(centre, radius, train_frames, config)
    if not cameras:  # (a value out of range for this run's cameras: a usage error, as MeshConfig.validate's are)
        raise UsageError(
            "--cone-deg",
            f"none of the {config.views} cameras around the object (--views) lies within {config.cone_deg:g} degrees "
            "of a training camera's direction: nothing would be fused; raise --cone-deg or --views",
        )
    background = torch.zeros(config.image_size, config.image_size, 3)
    for frame in cameras:
        view = render_frame(gaussians, frame, background, backend, with_depth=False, look=look)
        median = view.median_depth if view.median_depth is not None else render_median_depth(gaussians, frame, backend)
        volume.integrate_depth(median.astype(np.float64), view.rgb, frame.intrinsics.K, frame.T_world_cam)
    touch_points = np.zeros((0, 3))
    if config.touches and any(t.in_contact for t in scene.touches):
        touch_points, normals = scene.touch_points(), scene.touch_normals()
        known = np.isfinite(normals).all(axis=1)
        volume.integrate_points(touch_points[known], normals[known], config.touch_weight * config.views)
    if not config.object_only:  # (the largest piece alone leaves them out anyway, and its faces in the same order)
        volume.clear_blobs(centre, radius)
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


def mesh_ply(extracted: ExtractedMesh):
    """A binary PLY (plyfile's ``PlyData``: ``.write(file)``): vertices with normals, colours and ``observed`` (0/1),
    triangles. The vertices are float32, or float64 where float32 would move one by more than ``FLOAT32_TOLERANCE``
    voxels (a scene far from its origin: 4 mm steps at 50 km), so that the file holds the mesh its metrics measure.
    """
    from plyfile import PlyData, PlyElement

    mesh = extracted.mesh
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    rounding = np.abs(vertices.astype(np.float32) - vertices).max(initial=0.0)
    precision = "f4" if rounding <= FLOAT32_TOLERANCE * extracted.voxel else "f8"
    dtype = [(k, precision) for k in ("x", "y", "z")] + [(k, "f4") for k in ("nx", "ny", "nz")]
    dtype += [(k, "u1") for k in ("red", "green", "blue", "observed")]
    columns = [*mesh.vertices.T, *mesh.vertex_normals.T, *mesh.visual.vertex_colors[:, :3].T, extracted.observed]
    vertex = np.rec.fromarrays(columns, dtype=dtype)
    faces = np.empty(len(mesh.faces), dtype=[("vertex_indices", "i4", (3,))])
    faces["vertex_indices"] = mesh.faces
    return PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(faces, "face")])


def check_mesh_path(out: str | Path) -> None:
    """Refuse a mesh file that is not a ``.ply``: the mesh is written as PLY (its normals, colours and ``observed``
    flag have no place in most other formats), and PLY bytes under another suffix mislead every reader."""
    if Path(out).suffix.lower() != ".ply":
        raise ConfigError("--out", f"the mesh is written as PLY: name a .ply file, got {out}")


def written_by_export(path: Path) -> bool:
    """Whether ``path`` is a PLY that :func:`mesh_ply` wrote: its header declares the export's ``observed``."""
    try:
        with path.open("rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.startswith(b"ply") and b"property uchar observed\n" in head.partition(b"end_header")[0]


def check_mesh_out(run_dir: str | Path, out: str | Path, overwrite: bool = False) -> None:
    """Refuse (a ConfigError on ``--out``) a mesh file that the run or its scene owns, whatever ``overwrite`` says:
    one of the run's own files or renders (its meshes, MESH_FILES, aside), or anything inside its scene's folder
    (its ground truth: every later evaluation would score the reconstruction against itself). Refuse an existing
    file that ``export mesh`` did not write (its header has no ``observed``) unless ``overwrite``; a previous
    export is replaced."""
    from tacsplat.reconstruction.run_dir import RENDERS, RUN_FILES, read_checkpoint, recorded_scene, run_checkpoint

    run, target = Path(run_dir).resolve(), Path(out).resolve()
    record = recorded_scene(run)
    scene = Path(record["path"] if record else read_checkpoint(run_checkpoint(run))["scene_path"]).resolve()
    if target in {run / name for name in RUN_FILES} or target.is_relative_to(run / RENDERS):
        raise ConfigError("--out", f"{out} is one of the run's own files: name another .ply")
    if target.is_relative_to(scene) and target.parent != run:  # (a run kept inside its scene writes its own mesh)
        raise ConfigError("--out", f"{out} lies in the run's scene {scene}, whose files are not to be replaced")
    if target.exists() and not overwrite and not written_by_export(target):
        raise ConfigError(
            "--out", f"{out} exists and is not a mesh that export mesh wrote; pass --overwrite to replace it"
        )


def export_mesh(
    run_dir: str | Path,
    out: str | Path | None = None,
    config: MeshConfig | None = None,
    record: str | None = None,
    overwrite: bool = False,
) -> dict:
    """Extract a run's mesh (its last checkpoint) into ``out`` (default ``RUN/mesh.ply``; a ``.ply``, its folder
    created once the mesh is made); returns a summary: the file, vertex and face counts, the share of vertices
    observed, and the mesh metrics where the scene has a ground truth. The metrics go into ``RUN/metrics.json`` too,
    as ``mesh_*`` for ``RUN/mesh.ply``, ``mesh_untouched_*`` for ``RUN/mesh-untouched.ply`` (``MESH_FILES``), or
    under the prefix ``record``. The metrics are measured and recorded before the mesh file appears (it is
    renamed into place last): a mesh file on disk has its metrics recorded, so an interrupted export leaves no
    ``RUN/mesh.ply`` that looks done (:func:`export_meshes`). ``out`` is refused as :func:`check_mesh_out` says.
    An export that writes into the run (a mesh file inside it, or its metrics.json) holds the run's lock throughout,
    as ``evaluate`` does: a run being trained or evaluated is refused (a ConfigError on ``RUN``), so that a mesh of
    old Gaussians and its metrics never land in a run that moves on."""
    from contextlib import nullcontext

    from tacsplat.datasets.outputs import claim_output_dir

    run_dir = Path(run_dir)
    out = run_dir / "mesh.ply" if out is None else Path(out)
    check_mesh_path(out)
    check_mesh_out(run_dir, out, overwrite)
    into_run = record is not None or out.resolve().is_relative_to(run_dir.resolve())
    with claim_output_dir(run_dir, "RUN") if into_run else nullcontext():
        return _export_mesh(run_dir, out, config, record)


def _export_mesh(run_dir: Path, out: Path, config: MeshConfig | None, record: str | None) -> dict:
    """:func:`export_mesh`'s work, once ``out`` is checked (and the run locked where the export writes into it)."""
    import json

    from tacsplat.reconstruction.evaluation import seen_by_training_views
    from tacsplat.reconstruction.run_dir import MESH_FILES, load_run, render_backend, run_scene
    from tacsplat.reconstruction.views import scene_at, training_frames

    run = load_run(run_dir)
    scene = scene_at(run_scene(run), run.config.downscale)  # (refused if it has changed since the run)
    frames = training_frames(scene, run.config.train_views)
    extracted = extract_mesh(run.gaussians, scene, frames, render_backend(run.config, run_dir), run.look, config)
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
    run_files = {(run_dir / name).resolve(): prefix for prefix, name in MESH_FILES.items()}
    prefix = record or run_files.get(out.resolve())  # (RUN/mesh-untouched.ply by hand: mesh_untouched_*)
    recorded = truth is not None and prefix is not None and metrics_path.is_file()
    make_parent(out)  # (only now: a failed export creates no folder)
    with atomic_file(out) as f:  # the mesh goes to a temporary sibling, renamed over ``out`` when the block ends
        mesh_ply(extracted).write(f)
        if recorded:  # before that rename: a mesh file on disk has its metrics recorded
            metrics = json.loads(metrics_path.read_text())
            metrics.update({prefix + k[len("mesh") :]: v for k, v in summary.items() if k.startswith("mesh_")})
            atomic_write(metrics_path, json.dumps(metrics, indent=2).encode())
    return summary


def export_meshes(run_dir: str | Path) -> None:
    """A run's ``mesh.ply`` with its touches fused and ``mesh-untouched.ply`` without (``mesh_untouched_*`` in its
    metrics.json): what touching buys the mesh (``bench paper --mesh``)."""
    from tacsplat.reconstruction.run_dir import MESH_FILES

    run_dir = Path(run_dir)
    untouched = MESH_FILES["mesh_untouched"]
    export_mesh(run_dir, run_dir / untouched, MeshConfig(touches=False), record="mesh_untouched")
    export_mesh(run_dir)  # last: its file (renamed into place after its metrics) marks the run's meshes done
