"""A closed user mesh goes to CoACD as it is: its hulls lie on its surface, within the gel's give."""

from __future__ import annotations

import trimesh

from tacsplat.sim.collision import (
    DecompositionConfig,
    _unit_mesh,
    convex_decomposition,
    decimated,
    decomposition_key,
    hull_offset,
    is_closed,
)
from tacsplat.sim.hand import HandGeometry


def _pinched_boxes() -> trimesh.Trimesh:
    """Two 2 cm cubes sharing one edge: closed and consistently wound, but that edge has four faces."""
    a = trimesh.creation.box(bounds=[[0, 0, 0], [0.02, 0.02, 0.02]])
    b = trimesh.creation.box(bounds=[[0.02, 0.02, 0], [0.04, 0.04, 0.02]])
    mesh = trimesh.util.concatenate([a, b])
    mesh.merge_vertices()
    return mesh


def test_a_closed_non_manifold_mesh_gets_hulls_on_its_surface(tmp_path, monkeypatch):
    monkeypatch.setenv("TACSPLAT_CACHE", str(tmp_path))
    mesh = _pinched_boxes()
    assert is_closed(mesh) and not mesh.is_watertight
    hulls = convex_decomposition(mesh)
    assert hull_offset(mesh, hulls) < 0.1 * HandGeometry().gel_compliance


def test_decimation_keeps_a_closed_mesh_closed_and_the_cache_keys_the_mode():
    torus = trimesh.creation.torus(0.03, 0.012, major_sections=64, minor_sections=32)
    small = decimated(torus, 800)
    assert is_closed(small) and len(small.faces) <= 800
    open_mesh = trimesh.Trimesh(torus.vertices, torus.faces[1:], process=False)
    assert not is_closed(open_mesh)
    unit = _unit_mesh(small)[0]
    assert decomposition_key(unit, DecompositionConfig(), "off") != decomposition_key(unit, DecompositionConfig())
