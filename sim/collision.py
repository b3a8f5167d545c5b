"""Convex collision pieces of an object mesh (MuJoCo collides a mesh as its convex hull).

Non-convex objects are split by CoACD (approximate convex decomposition) into
convex hulls. The decomposition runs on the mesh scaled to a unit bounding
sphere, keyed by a hash of that mesh and the settings, so one object at any
radius is decomposed once. Pieces are looked up, in order:

1. shipped with the package (``sim/decompositions/<key>.npz``): the six library
   objects, so a fresh install never runs CoACD for them;
2. the user cache (``$TACSPLAT_CACHE/coacd``, default ``~/.cache/tacsplat/coacd``);
3. computed by CoACD and written to the user cache (user meshes, ``--mesh``).

Regenerate the shipped files after changing a library object or the settings:
``python -m tacsplat.sim.collision`` (a test fails while they are stale).
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import trimesh

from tacsplat.errors import StorageError
from tacsplat.files import atomic_write
from tacsplat.sim.objects import bounding_sphere

log = logging.getLogger(__name__)

SHIPPED_DIR = Path(__file__).resolve().parent / "decompositions"
DECOMPOSITION_FACES = 20_000  # more faces are decimated before CoACD (the library objects have fewer)
# A piece with less volume than this fraction of the largest is dropped: a scan's stray speck gets a hull of its
# own, too small for MuJoCo's inertia (it refuses the model), and too small to grasp (the library's smallest piece
# is 1e-3 of its largest)
MIN_PIECE_FRACTION = 1e-6


@dataclass(frozen=True)
class DecompositionConfig:
    """CoACD settings, traded for speed. Measured on the library at radius 0.08 m: 2-4 s an
    object on one core, 5-24 hulls, hull volume 0.7-7.8 % above the mesh's, 99 % of the hull
    surface within 0.6-3.0 mm of the mesh (at most 3.8 mm, in concave creases)."""

    # the fields are coacd.run_coacd's keywords, passed as they are
    threshold: float = 0.05  # concavity tolerance relative to the bounding box (CoACD default)
    max_convex_hull: int = 24
    preprocess_resolution: int = 30
    resolution: int = 500  # surface samples for the concavity metric
    mcts_iterations: int = 30
    mcts_max_depth: int = 2
    seed: int = 0


def _unit_mesh(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, np.ndarray, float]:
    centre, radius = bounding_sphere(mesh)
    unit = trimesh.Trimesh((np.asarray(mesh.vertices) - centre) / radius, mesh.faces, process=False)
    return unit, centre, radius


def decomposition_key(unit: trimesh.Trimesh, config: DecompositionConfig, preprocess_mode: str = "auto") -> str:
    """Hash of a unit-sphere mesh (vertices rounded to 1e-6), the CoACD settings and its ``preprocess_mode`` (only
    when not "auto": the shipped files' keys, made with "auto", stand)."""
    key = hashlib.sha1()
    key.update(np.round(unit.vertices, 6).tobytes())
    key.update(np.ascontiguousarray(unit.faces, dtype=np.int64).tobytes())
    key.update(repr(config).encode())
    if preprocess_mode != "auto":
        key.update(f"preprocess_mode={preprocess_mode}".encode())
    return key.hexdigest()


def is_closed(mesh: trimesh.Trimesh) -> bool:
    """Whether ``mesh`` is closed and consistently wound: each edge is used as often one way as the other (no
    boundary, no flipped face). CoACD can take such a mesh as it is; a pinch where two sheets share an edge
    (four faces) is allowed: CoACD splits the mesh into hulls anyway."""
    edges = np.asarray(mesh.edges)  # [3F, 2], each face's edges in its winding order
    if not len(edges):
        return False
    _, index = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
    way = np.where(edges[:, 0] < edges[:, 1], 1, -1)  # +1 one way along an edge, -1 the other
    return not np.bincount(index.ravel(), weights=way).any()


def decimated(mesh: trimesh.Trimesh, faces: int) -> trimesh.Trimesh:
    """``mesh`` decimated to about ``faces`` faces (quadric error, fast-simplification), less the faces it collapsed
    onto each other (the same three vertices, both windings: an edge shared by four faces), so that a closed mesh
    stays closed (:func:`is_closed`)."""
    small = mesh.simplify_quadric_decimation(face_count=faces)
    _, index, counts = np.unique(np.sort(small.faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    return trimesh.Trimesh(small.vertices, small.faces[counts[index.ravel()] == 1], process=False)


def _read(path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    with np.load(path) as data:
        return [(data[f"v{i}"], data[f"f{i}"]) for i in range(int(data["n"]))]


def _write(path: Path, pieces) -> None:
    """Atomic write (temporary name + rename) of the pieces [(vertices [V, 3], faces [F, 3])]."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"n": np.array(len(pieces))}
    for i, (v, f) in enumerate(pieces):
        arrays[f"v{i}"], arrays[f"f{i}"] = np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int32)
    # a per-process temporary name: two processes may fill the same cache entry at once
    atomic_write(
        path, lambda f: np.savez_compressed(f, **arrays), temp=path.with_name(f"{path.stem}.{os.getpid()}.tmp")
    )


def _run_coacd(unit: trimesh.Trimesh, config: DecompositionConfig, preprocess_mode: str = "auto"):
    if unit.convex_hull.volume - unit.volume < 1e-3 * unit.volume:  # already convex
        hull = unit.convex_hull
        return [(np.asarray(hull.vertices), np.asarray(hull.faces))]
    import coacd

    log.info("convex decomposition of %d faces by CoACD (seconds to minutes) ...", len(unit.faces))
    coacd.set_log_level("error")
    return coacd.run_coacd(coacd.Mesh(unit.vertices, unit.faces), preprocess_mode=preprocess_mode, **asdict(config))


def convex_decomposition(
    mesh: trimesh.Trimesh, config: DecompositionConfig = DecompositionConfig()
) -> list[trimesh.Trimesh]:
    """Convex pieces of ``mesh`` (shipped, cached or computed by CoACD; see the module docstring). A mesh of more
    than :data:`DECOMPOSITION_FACES` faces (a reconstruction's, ``tacsplat export mesh``) is decimated first (quadric
    error, fast-simplification): CoACD's time grows with the faces (67 s for a 187k-face export, 12 s at 20k), and
    the pieces are hulls a few millimetres loose anyway. A closed mesh (:func:`is_closed`) goes to CoACD as it is
    (``preprocess_mode="off"``); CoACD remeshes any other coarsely, and its hulls then stand about a millimetre off
    the surface. The shipped files were made with "auto", which leaves the (closed) library objects as they are."""
    if len(mesh.faces) > DECOMPOSITION_FACES:
        mesh = decimated(mesh, DECOMPOSITION_FACES)
    unit, centre, radius = _unit_mesh(mesh)
    mode = "off" if is_closed(unit) else "auto"
    cache = Path(os.environ.get("TACSPLAT_CACHE") or Path.home() / ".cache" / "tacsplat") / "coacd"  # user meshes
    shipped = SHIPPED_DIR / f"{decomposition_key(unit, config)}.npz"
    cached = cache / f"{decomposition_key(unit, config, mode)}.npz"
    if stored := next((path for path in (shipped, cached) if path.is_file()), None):
        pieces = _read(stored)
    else:
        pieces = _run_coacd(unit, config, mode)
        try:
            _write(cached, pieces)
        except (OSError, StorageError) as exc:  # the cache only saves the next run CoACD's time
            log.warning("cannot cache the convex decomposition in %s (%s): the next run computes it again", cache, exc)
    return [trimesh.Trimesh(np.asarray(v) * radius + centre, f, process=False) for v, f in _without_specks(pieces)]


def _without_specks(pieces):
    """The pieces less those under :data:`MIN_PIECE_FRACTION` of the largest one's volume."""
    volumes = np.array([abs(trimesh.Trimesh(v, f, process=False).volume) for v, f in pieces])
    return [piece for piece, volume in zip(pieces, volumes) if volume >= MIN_PIECE_FRACTION * volumes.max()]


def hull_offset(mesh: trimesh.Trimesh, hulls: list[trimesh.Trimesh], samples: int = 2000) -> float:
    """How far the hulls stand off the mesh: the median distance from its surface of their vertices (at most
    ``samples`` of them, evenly picked). CoACD's hull vertices lie on the surface, unless it remeshed the object
    first (a mesh it cannot use as it is, not closed or not manifold): then they lie about half a voxel off it."""
    points = np.vstack([h.vertices for h in hulls])
    _, distance, _ = trimesh.proximity.closest_point(mesh, points[:: max(1, len(points) // samples)])
    return float(np.median(distance))


def write_shipped_decompositions(config: DecompositionConfig = DecompositionConfig()) -> list[Path]:
    """Decompose every library object with CoACD into ``SHIPPED_DIR``, removing stale files."""
    from tacsplat.sim.objects import OBJECT_NAMES, make_object

    written = []
    for name in OBJECT_NAMES:
        unit, _, _ = _unit_mesh(make_object(name).mesh)
        path = SHIPPED_DIR / f"{decomposition_key(unit, config)}.npz"
        _write(path, _run_coacd(unit, config))
        written.append(path)
        print(f"{name}: {path.name}")
    for stale in set(SHIPPED_DIR.glob("*.npz")) - set(written):
        stale.unlink()
    return written


if __name__ == "__main__":
    write_shipped_decompositions()
