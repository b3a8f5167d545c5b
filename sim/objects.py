"""The procedural glossy object library, user meshes, and their collision decomposition.

Six watertight objects in the spirit of Shiny Blender / Glossy Synthetic:
teapot, toaster, bell, helmet, torus and car. Each is built from revolved
profiles, rounded boxes (convex hulls of corner spheres) and exact mesh
booleans (manifold3d), then centred on its minimum bounding sphere and scaled
to the requested bounding-sphere radius.

Collision pieces (convex hulls) come from :mod:`tacsplat.sim.collision`.
Tactile depth and ground truth always use the exact mesh.
"""

from __future__ import annotations

import hashlib
import logging
import numbers
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from tacsplat.errors import ConfigError, InvalidInputError
from tacsplat.geometry import minimum_sphere
from tacsplat.sim import OBJECT_RADIUS_RANGE_M

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GlossyMaterial:
    """MuJoCo material of a glossy object (specular and shininess in [0, 1])."""

    rgba: tuple[float, float, float, float]
    specular: float = 0.9
    shininess: float = 0.9
    reflectance: float = 0.0


@dataclass
class SimObject:
    """An object mesh in its own frame (centred on its bounding sphere) with its material; a user's mesh also
    carries ``from_file``: ``(scale, translation [3])``, its file's points ``p`` are ``scale * p + translation`` in
    the object's frame (the twin's world)."""

    name: str
    mesh: trimesh.Trimesh
    material: GlossyMaterial
    from_file: tuple[float, np.ndarray] | None = None

    @property
    def bounding_radius(self) -> float:
        return bounding_sphere(self.mesh)[1]


_SPHERES: dict[bytes, tuple[np.ndarray, float, bool]] = {}  # vertices' digest -> (centre, radius, exact)


def bounding_sphere(mesh: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """Centre [3] and radius of the minimum sphere enclosing the mesh's vertices
    (:func:`~tacsplat.geometry.minimum_sphere`).

    Kept for the last few vertex arrays (by their SHA-1, not their bytes: an imported mesh can be tens of MB): a
    capture asks for the same object's sphere three times (its radius twice, its collision pieces once), 0.08 s
    each for the teapot."""
    centre, radius, _ = _sphere(mesh.vertices)
    return centre.copy(), radius


def _key(vertices) -> bytes:
    return hashlib.sha1(np.ascontiguousarray(vertices, dtype=np.float64).tobytes()).digest()


def _remember(key: bytes, sphere: tuple[np.ndarray, float, bool]) -> None:
    if len(_SPHERES) >= 8:
        _SPHERES.pop(next(iter(_SPHERES)))
    _SPHERES[key] = sphere


def _sphere(vertices) -> tuple[np.ndarray, float, bool]:
    """The cached :func:`~tacsplat.geometry.minimum_sphere` of ``vertices``, and whether it is exact (Welzl's: it
    moves and scales with the vertices)."""
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)  # [V, 3]
    if (key := _key(vertices)) not in _SPHERES:
        _remember(key, minimum_sphere(vertices))
    return _SPHERES[key]


def _rounded_box(extents, radius: float, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    """Box with edges rounded by ``radius`` (the convex hull of eight corner spheres)."""
    half = np.asarray(extents, dtype=np.float64) / 2 - radius
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    ball = trimesh.creation.icosphere(subdivisions=3, radius=radius).vertices
    pts = (corners[:, None, :] + ball[None]).reshape(-1, 3) + np.asarray(centre)
    return trimesh.convex.convex_hull(pts)


def _revolve(profile, sections: int = 96) -> trimesh.Trimesh:
    """Solid of revolution about z of a closed (radius, height) profile starting and ending on the axis."""
    mesh = trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=sections)
    if mesh.volume < 0:  # a clockwise profile gives inward normals
        mesh.invert()
    return mesh


def _union(*meshes: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.boolean.union(list(meshes), engine="manifold")


def _rotated(mesh: trimesh.Trimesh, angle: float, axis, translate=(0, 0, 0)) -> trimesh.Trimesh:
    mesh = mesh.copy()
    mesh.apply_transform(trimesh.transformations.rotation_matrix(angle, axis))
    mesh.apply_translation(translate)
    return mesh


def _teapot() -> trimesh.Trimesh:
    t = np.linspace(0.0, np.pi, 40)
    body = [(0.0, 0.0)] + [(0.62 * np.sin(a) + 0.08 * np.sin(a) ** 2, 0.42 - 0.42 * np.cos(a)) for a in t[1:-1]]
    body += [(0.22, 0.84), (0.24, 0.87), (0.06, 0.92), (0.09, 0.98), (0.0, 1.0)]
    pot = _revolve(body)
    spout = trimesh.creation.cone(radius=0.14, height=0.75, sections=48)
    spout = _rotated(spout, np.deg2rad(55), [0, 1, 0], [0.45, 0.0, 0.3])
    handle = trimesh.creation.torus(major_radius=0.28, minor_radius=0.055, major_sections=48, minor_sections=16)
    handle = _rotated(handle, np.pi / 2, [1, 0, 0], [-0.62, 0.0, 0.45])
    return _union(pot, spout, handle)


def _toaster() -> trimesh.Trimesh:
    body = _rounded_box([1.0, 0.6, 0.7], 0.12, centre=(0, 0, 0.35))
    slots = [
        trimesh.creation.box([0.7, 0.08, 0.5], trimesh.transformations.translation_matrix([0, y, 0.65]))
        for y in (-0.12, 0.12)
    ]
    lever = _rounded_box([0.14, 0.1, 0.06], 0.02, centre=(0.55, 0.0, 0.45))
    return trimesh.boolean.difference([_union(body, lever), *slots], engine="manifold")


def _bell() -> trimesh.Trimesh:
    s = np.linspace(0.0, 1.0, 30)
    outer = [(0.25 + 0.42 * (1 - u) ** 2.2 + 0.05 * (1 - u), 0.1 + 0.85 * u) for u in s]  # lip up to crown
    lip = outer[0][0]
    # a solid bell: flared lip, shallow dome underneath
    profile = [(0.0, 0.2), (lip - 0.1, 0.08), (lip - 0.02, 0.03), (lip + 0.03, 0.06)] + outer + [(0.0, 0.95)]
    bell = _revolve(profile)
    loop = trimesh.creation.torus(major_radius=0.1, minor_radius=0.035, major_sections=32, minor_sections=12)
    loop = _rotated(loop, np.pi / 2, [1, 0, 0], [0, 0, 1.05])
    return _union(bell, loop)


def _helmet() -> trimesh.Trimesh:
    a = np.linspace(0.0, np.pi / 2, 40)
    # a solid helmet-like dome (slightly elongated front to back) with a rim and a visor
    profile = [(0.0, 0.0)] + [(1.05, 0.0), (1.05, 0.08)] + [(np.sin(t), 0.15 + np.cos(t)) for t in a[::-1]]
    shell = _revolve(profile)
    shell.apply_scale([1.12, 1.0, 1.0])
    visor = _rounded_box([0.45, 1.2, 0.08], 0.03, centre=(1.05, 0.0, 0.3))
    visor = _rotated(visor, np.deg2rad(-12), [0, 1, 0])
    return _union(shell, visor)


def _torus() -> trimesh.Trimesh:
    return trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=96, minor_sections=32)


def _car() -> trimesh.Trimesh:
    body = _rounded_box([2.0, 0.9, 0.45], 0.12, centre=(0, 0, 0.42))
    cabin = _rounded_box([1.05, 0.8, 0.5], 0.15, centre=(-0.15, 0, 0.75))
    wheel = trimesh.creation.cylinder(radius=0.22, height=0.18, sections=40)
    wheels = [_rotated(wheel, np.pi / 2, [1, 0, 0], [x, y, 0.22]) for x in (-0.62, 0.62) for y in (-0.42, 0.42)]
    return _union(body, cabin, *wheels)


_BUILDERS = {
    "teapot": (_teapot, GlossyMaterial((0.85, 0.85, 0.9, 1.0))),
    "toaster": (_toaster, GlossyMaterial((0.8, 0.1, 0.1, 1.0))),
    "bell": (_bell, GlossyMaterial((0.85, 0.65, 0.2, 1.0))),
    "helmet": (_helmet, GlossyMaterial((0.1, 0.25, 0.8, 1.0))),
    "torus": (_torus, GlossyMaterial((0.9, 0.75, 0.3, 1.0))),
    "car": (_car, GlossyMaterial((0.1, 0.6, 0.3, 1.0))),
}
OBJECT_NAMES = list(_BUILDERS)
DEFAULT_OBJECT_RADIUS = 0.08
TEXTURES = ("none", "checker")  # the object's surface: its one colour, or a checker of it and a contrasting grey
CHECKER_SQUARES = 6  # squares along each side of a face of the checker's cube map


def texture_problem(texture) -> str | None:
    """What is wrong with ``texture`` as one of :data:`TEXTURES` (None: nothing)."""
    return None if texture in TEXTURES else f"must be one of {', '.join(map(repr, TEXTURES))}, got {texture!r}"


def checker_texture(rgba: tuple[float, float, float, float]) -> np.ndarray:
    """A face of the "checker" texture, RGB uint8 [CHECKER_SQUARES * 32, CHECKER_SQUARES * 32, 3] (32 texels a
    square): the material's colour and a grey far from it (dark on a light object, light on a dark one),
    alternating."""
    square = np.arange(CHECKER_SQUARES * 32) // 32  # each texel's square along a side
    parity = np.add.outer(square, square) % 2
    color = 255.0 * np.asarray(rgba[:3], dtype=np.float64)
    grey = np.full(3, 40.0 if color.mean() > 127.5 else 235.0)
    return np.where(parity[..., None] == 1, color, grey).round().astype(np.uint8)


def object_radius_problem(radius) -> str | None:
    """What is wrong with ``radius`` as the bounding-sphere radius of an object of the twin (None: nothing): it
    must lie in :data:`OBJECT_RADIUS_RANGE_M`."""
    lo, hi = OBJECT_RADIUS_RANGE_M
    real = isinstance(radius, numbers.Real) and not isinstance(radius, bool)
    if real and lo <= radius <= hi:
        return None
    shown = f"{radius:g}" if real else repr(radius)
    return f"must be in [{lo:g}, {hi:g}] m (the sizes the twin's hand grasps), got {shown}"


def normalise_mesh(mesh: trimesh.Trimesh, radius: float, name: str) -> trimesh.Trimesh:
    """Centre a mesh on its bounding sphere and scale it to bounding-sphere ``radius`` metres (a ConfigError
    outside :data:`OBJECT_RADIUS_RANGE_M`).

    A mesh whose bounding radius is already within 0.1 % of ``radius`` keeps its scale (:func:`normalised_scale`).
    """
    return _normalised(mesh, radius, name)[0]


def normalised_scale(mesh_radius: float, radius: float) -> float:
    """The scale :func:`normalise_mesh` applies to a mesh of bounding radius ``mesh_radius`` to make it ``radius``:
    1 when the two are within 0.1 %."""
    return 1.0 if abs(mesh_radius / radius - 1.0) <= 1e-3 else radius / mesh_radius


def _normalised(mesh: trimesh.Trimesh, radius: float, name: str) -> tuple[trimesh.Trimesh, float, np.ndarray]:
    """:func:`normalise_mesh`'s mesh, its scale and the translation after it: ``p_out = scale * p + translation``."""
    if problem := object_radius_problem(radius):
        raise ConfigError("object_radius", problem)
    if len(mesh.faces) == 0 or not np.all(np.isfinite(mesh.vertices)):
        raise InvalidInputError(f"{name}: mesh is empty or has non-finite vertices")
    centre, r, exact = _sphere(mesh.vertices)
    if r <= 0:
        raise InvalidInputError(f"{name}: mesh has zero extent")
    out = mesh.copy()
    out.apply_translation(-centre)
    scale = normalised_scale(r, radius)
    if scale != 1.0:
        out.apply_scale(scale)
    if exact:  # Welzl's sphere moved and scaled is the new mesh's (trimesh's is recomputed, as captures had it)
        _remember(_key(out.vertices), (np.zeros(3), r * scale, True))
    return out, scale, -scale * centre


def make_object(name: str, radius: float = DEFAULT_OBJECT_RADIUS) -> SimObject:
    """A library object (one of ``OBJECT_NAMES``) at bounding-sphere ``radius`` metres."""
    if name not in _BUILDERS:
        raise ConfigError("object", f"unknown object {name!r}; choose one of {', '.join(OBJECT_NAMES)} or pass --mesh")
    build, material = _BUILDERS[name]
    mesh = build()
    mesh.merge_vertices()
    if not mesh.is_watertight or mesh.volume <= 0:
        raise AssertionError(f"library object {name} is not a watertight solid")  # a bug here, not user input
    return SimObject(name, normalise_mesh(mesh, radius, name), material)


MAX_COORDINATE = 1e100  # a mesh file's coordinates, in its units: the squares of larger ones overflow float64


def read_mesh(path: str | Path) -> trimesh.Trimesh:
    """A user's mesh file as one closed triangle mesh, in the file's own units and frame.

    Every part (OBJ objects and groups, a scene's meshes) is concatenated; materials, UVs and normals are
    dropped and the vertices merged by position (within 1e-9 of the mesh's size), so UV and normal seams no
    longer split the surface; degenerate and repeated faces are dropped; holes (a scan's openings, like the
    Stanford bunny's) are closed by fans around each opening's centroid; faces are wound outwards. A file
    that cannot be an object is one ConfigError naming it: unreadable, no triangles, NaN, infinite or
    overflowing coordinates, zero size; no triangle or a flat surface (all in one plane) left once the degenerate
    faces are dropped.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError("mesh", f"file not found: {path}")
    if path.stat().st_size == 0:  # (trimesh fails on an empty .glb with an IndexError)
        raise ConfigError("mesh", f"{path} holds no triangles (a point cloud or an empty file?)")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ConfigError("mesh", f"cannot read {path}: {exc}") from exc
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ConfigError("mesh", f"{path} holds no triangles (a point cloud or an empty file?)")
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    if not_finite := int((~np.isfinite(vertices)).any(axis=1).sum()):
        raise ConfigError("mesh", f"{path}: {not_finite} vertices have NaN or infinite coordinates (not finite)")
    if (largest := float(np.abs(vertices).max())) > MAX_COORDINATE:
        raise ConfigError(
            "mesh",
            f"{path}: coordinates up to {largest:.3g}, more than {MAX_COORDINATE:g} (their squares overflow); "
            "rescale the file",
        )
    size = float(np.ptp(vertices, axis=0).max())
    if not size > 0:
        raise ConfigError("mesh", f"{path}: every vertex is at the same point (zero size)")
    mesh = trimesh.Trimesh(vertices, loaded.faces, process=False)  # geometry only
    mesh.merge_vertices(merge_tex=True, merge_norm=True, digits_vertex=max(0, int(9 - np.floor(np.log10(size)))))
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    # the checks below hold for what is simulated: the faces left once the degenerate ones are dropped
    if len(mesh.faces) == 0:
        raise ConfigError(
            "mesh",
            f"{path}: all its {len(loaded.faces)} triangles are degenerate (no area: collinear or repeated vertices)",
        )
    centred, size = mesh.vertices - mesh.vertices.mean(axis=0), float(np.ptp(mesh.vertices, axis=0).max())
    if np.linalg.svd(centred, compute_uv=False)[-1] <= 1e-9 * size * np.sqrt(len(mesh.vertices)):
        raise ConfigError(
            "mesh",
            f"{path} is flat (all its triangles of non-zero area lie in one plane): a surface with no volume, "
            "not an object that can be grasped",
        )
    if holes := _close_holes(mesh):
        log.info("%s: closed %d hole(s) (%d boundary edges)", path, len(holes), sum(holes))
    trimesh.repair.fix_winding(mesh)
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()
    return mesh


def _close_holes(mesh: trimesh.Trimesh) -> list[int]:
    """Close every boundary loop with a fan of triangles around its centroid (wound like its faces); the edge count
    of each loop closed. Where holes touch at a vertex (a bow-tie: the boundary passes it twice), an edge into the
    vertex goes on along the edge out of it across the same hole: the first one counter-clockwise from it about the
    vertex normal (faces run counter-clockwise about their normals: that way past the edge's own face is its hole)."""
    # the edges of one face only, directed as they run in it
    boundary = mesh.edges[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)]
    leaving: dict[int, list[int]] = {}  # vertex -> the boundary edges leaving it
    for i, a in enumerate(boundary[:, 0].tolist()):
        leaving.setdefault(a, []).append(i)

    def following(i: int) -> int | None:
        """The boundary edge after edge ``i`` along its hole (None: the boundary stops)."""
        p, v = boundary[i]
        out = leaving.get(int(v), [])
        if len(out) < 2:
            return out[0] if out else None
        normal, back = mesh.vertex_normals[v], mesh.vertices[p] - mesh.vertices[v]
        ahead = mesh.vertices[boundary[out, 1]] - mesh.vertices[v]  # [k, 3]
        back, ahead = back - (back @ normal) * normal, ahead - np.outer(ahead @ normal, normal)  # in the tangent plane
        angle = np.arctan2(np.cross(back, ahead) @ normal, ahead @ back) % (2 * np.pi)  # from back, counter-clockwise
        return out[int(np.argmin(angle))]

    new_vertices, new_faces, closed = [], [], []
    seen = np.zeros(len(boundary), dtype=bool)
    for first in range(len(boundary)):
        loop, i = [], first
        while i is not None and not seen[i]:
            seen[i] = True
            loop.append(int(boundary[i, 0]))
            i = following(i)
        if i != first or len(loop) < 3:
            continue
        centre = len(mesh.vertices) + len(new_vertices)
        new_vertices.append(mesh.vertices[loop].mean(axis=0))
        # a boundary edge a -> b runs along its face; the fan's triangle runs b -> a, towards the centre
        new_faces += [[loop[(k + 1) % len(loop)], loop[k], centre] for k in range(len(loop))]
        closed.append(len(loop))
    if closed:
        mesh.vertices, mesh.faces = np.vstack([mesh.vertices, new_vertices]), np.vstack([mesh.faces, new_faces])
    return closed


def load_mesh_object(path: str | Path, radius: float = DEFAULT_OBJECT_RADIUS) -> SimObject:
    """Any .obj/.ply/.stl/.glb mesh file (:func:`read_mesh`) as an object at bounding-sphere ``radius`` metres,
    whatever its units (millimetres, inches, ...), centred on its bounding sphere (``from_file`` maps the file's
    points into it)."""
    path = Path(path)
    mesh = read_mesh(path)
    if not mesh.is_watertight:
        _, uses = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
        log.warning(
            "%s is not watertight even with its holes closed (%d edges of one face, %d shared by more than two): "
            "tactile depth is cast on it as it is, but CoACD remeshes it before cutting it into collision pieces, "
            "which may then stand off its surface",
            path,
            int((uses == 1).sum()),
            int((uses > 2).sum()),
        )
    normalised, scale, translation = _normalised(mesh, radius, str(path))
    obj = SimObject(path.stem, normalised, GlossyMaterial((0.8, 0.8, 0.82, 1.0)), (scale, translation))
    r = obj.bounding_radius
    log.info("%s: bounding radius %.6g in the file's units, scaled by %.6g to %.6g m", path, r / scale, scale, r)
    return obj
