"""Collision pieces: the library's are shipped and current; user meshes are decomposed once and cached."""

import numpy as np
import trimesh

from tacsplat.sim import collision
from tacsplat.sim.collision import SHIPPED_DIR, DecompositionConfig, convex_decomposition, decomposition_key
from tacsplat.sim.objects import OBJECT_NAMES, make_object


def test_every_library_object_has_its_current_decomposition_shipped():
    """Stale shipped files (a library object or the CoACD settings changed) would make every fresh
    install run CoACD: regenerate with ``python -m tacsplat.sim.collision``."""
    expected = set()
    for name in OBJECT_NAMES:
        unit, _, _ = collision._unit_mesh(make_object(name).mesh)
        key = decomposition_key(unit, DecompositionConfig())
        assert (SHIPPED_DIR / f"{key}.npz").is_file(), f"{name}: no shipped decomposition {key}.npz"
        expected.add(f"{key}.npz")
    assert {p.name for p in SHIPPED_DIR.glob("*.npz")} == expected


def test_library_objects_never_run_coacd_and_pieces_scale_with_the_object(monkeypatch, tmp_path):
    monkeypatch.setenv("TACSPLAT_CACHE", str(tmp_path))
    monkeypatch.setattr(collision, "_run_coacd", lambda *a: (_ for _ in ()).throw(AssertionError("CoACD ran")))
    small, large = make_object("teapot", 0.05), make_object("teapot", 0.1)
    pieces_small, pieces_large = convex_decomposition(small.mesh), convex_decomposition(large.mesh)
    assert len(pieces_small) == len(pieces_large) > 1
    np.testing.assert_allclose(pieces_large[0].vertices, 2 * pieces_small[0].vertices, rtol=1e-9, atol=1e-12)
    assert not any(tmp_path.rglob("*.npz"))  # nothing written to the user cache


def test_a_user_mesh_is_decomposed_once_then_read_from_the_user_cache(monkeypatch, tmp_path):
    monkeypatch.setenv("TACSPLAT_CACHE", str(tmp_path))
    # an L-shaped solid: not convex, so CoACD runs
    mesh = trimesh.boolean.union(
        [
            trimesh.creation.box([2, 1, 1], trimesh.transformations.translation_matrix([0.5, 0, 0])),
            trimesh.creation.box([1, 2, 1], trimesh.transformations.translation_matrix([0, 0.5, 0])),
        ],
        engine="manifold",
    )
    calls = []
    real = collision._run_coacd
    monkeypatch.setattr(collision, "_run_coacd", lambda *a: calls.append(1) or real(*a))
    first = convex_decomposition(mesh)
    second = convex_decomposition(mesh)
    assert calls == [1] and len(first) == len(second) >= 2
    assert len(list((tmp_path / "coacd").glob("*.npz"))) == 1
    hull_volume = sum(p.volume for p in first)
    assert mesh.volume * 0.98 < hull_volume < mesh.volume * 1.2


def test_a_cache_that_cannot_be_written_is_warned_about_and_the_pieces_still_used(monkeypatch, tmp_path, tmpfs, caplog):
    """The cache only saves CoACD's time: a TACSPLAT_CACHE that is a file, or on a read-only file system, costs the
    next run that time, not this run its capture."""
    mesh = trimesh.creation.box([1, 1, 1])
    monkeypatch.setattr(collision, "_run_coacd", lambda unit, *settings: [(unit.vertices, unit.faces)] * 2)  # 2 pieces
    (tmp_path / "a_file").write_text("x")
    read_only = tmpfs("1m")
    read_only.read_only()
    for cache in (tmp_path / "a_file", read_only.path):
        monkeypatch.setenv("TACSPLAT_CACHE", str(cache))
        caplog.clear()
        with caplog.at_level("WARNING", logger="tacsplat.sim.collision"):
            pieces = convex_decomposition(mesh)
        assert len(pieces) == 2 and np.allclose(pieces[0].vertices, mesh.vertices)
        assert "cannot cache" in caplog.text and str(cache) in caplog.text
