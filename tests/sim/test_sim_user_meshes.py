"""Meshes as users have them, for ``sim-capture --mesh``: scans with holes, meshes in millimetres or any unit,
multi-part OBJ files with materials and UV seams. Each works on the twin or fails with one clear message."""

import numpy as np
import pytest
import trimesh

from tacsplat.cli import main as tacsplat_main
from tacsplat.errors import ConfigError
from tacsplat.sim.objects import bounding_sphere, load_mesh_object

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(autouse=True)
def own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TACSPLAT_CACHE", str(tmp_path / "cache"))  # CoACD results of these meshes stay here


def twin_builds(path, radius=0.08) -> int:
    """Build the twin on the mesh (MuJoCo compiles the object and its collision hulls); the number of hulls."""
    from tacsplat.sim.twin import SimTwin, TwinConfig

    with SimTwin(TwinConfig(mesh_path=str(path), object_radius=radius, camera_width=32, camera_height=32)) as twin:
        return len(twin.hulls)


def test_scan_with_holes_is_closed(tmp_path):
    """Like the Stanford bunny: a closed surface scanned with openings where the scanner could not see."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=30.0)
    centres = ball.triangles_center
    open_faces = (centres[:, 2] > 27.0) | (centres[:, 0] > 28.0)  # a hole on top, one on the side
    scan = trimesh.Trimesh(ball.vertices, ball.faces[~open_faces])
    assert not scan.is_watertight and len(scan.outline().entities) == 2
    scan.export(tmp_path / "scan.ply")
    obj = load_mesh_object(tmp_path / "scan.ply", radius=0.08)
    assert obj.mesh.is_watertight and obj.mesh.is_winding_consistent and obj.mesh.volume > 0
    sphere_volume = 4 / 3 * np.pi * 0.08**3
    assert 0.85 * sphere_volume < obj.mesh.volume < sphere_volume
    assert obj.bounding_radius == pytest.approx(0.08, rel=1e-6)
    assert twin_builds(tmp_path / "scan.ply") <= 4  # a closed, nearly convex object: a few hulls, not dozens


def test_mesh_in_millimetres_is_scaled_to_the_object_radius(tmp_path, caplog):
    box = trimesh.creation.box([60.0, 40.0, 30.0])  # millimetres, as CAD exports them
    box.apply_translation([100.0, -20.0, 15.0])
    box.export(tmp_path / "part_mm.stl")
    with caplog.at_level("INFO", logger="tacsplat.sim.objects"):
        obj = load_mesh_object(tmp_path / "part_mm.stl", radius=0.05)
    centre, radius = bounding_sphere(obj.mesh)
    assert radius == pytest.approx(0.05, rel=1e-6) and np.linalg.norm(centre) < 1e-9
    scale = 0.05 / (np.sqrt(60.0**2 + 40.0**2 + 30.0**2) / 2)
    assert sorted(obj.mesh.extents) == pytest.approx(sorted(np.array([60.0, 40.0, 30.0]) * scale), rel=1e-6)
    assert "scaled by" in caplog.text and "part_mm.stl" in caplog.text  # the log says what happened to the units
    assert twin_builds(tmp_path / "part_mm.stl", radius=0.05) == 1


OBJ_CUBE_FACES = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


def obj_cube(origin, size, first_vertex, first_uv, name, material):
    """A cube as one OBJ object with its own material and a UV square per face (a seam along every edge)."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * size + origin
    lines = [f"o {name}", f"usemtl {material}"] + [f"v {x:g} {y:g} {z:g}" for x, y, z in corners]
    lines += [f"vt {u} {v}" for u, v in ((0, 0), (1, 0), (1, 1), (0, 1))]
    for quad in OBJ_CUBE_FACES:
        a, b, c, d = (first_vertex + i for i in quad)
        t = first_uv
        lines += [f"f {a}/{t} {b}/{t + 1} {c}/{t + 2}", f"f {a}/{t} {c}/{t + 2} {d}/{t + 3}"]
    return lines


def test_multi_part_obj_with_materials_and_uv_seams_is_merged_by_position(tmp_path):
    lines = (
        ["mtllib parts.mtl"]
        + obj_cube([0, 0, 0], 40, 1, 1, "body", "red")
        + obj_cube([40, 10, 10], 20, 9, 5, "knob", "blue")
    )
    (tmp_path / "parts.obj").write_text("\n".join(lines) + "\n")
    (tmp_path / "parts.mtl").write_text(
        "newmtl red\nKd 0.8 0.1 0.1\nmap_Kd missing_texture.png\nnewmtl blue\nKd 0.1 0.1 0.8\n"
    )
    obj = load_mesh_object(tmp_path / "parts.obj", radius=0.08)
    assert len(obj.mesh.vertices) == 16  # 8 + 8 corners: the seams' copies merged by position
    assert obj.mesh.is_watertight and obj.mesh.volume > 0
    scale = 0.08 / bounding_sphere(trimesh.load(tmp_path / "parts.obj", force="mesh"))[1]
    assert obj.mesh.volume == pytest.approx((40**3 + 20**3) * scale**3, rel=1e-6)
    assert twin_builds(tmp_path / "parts.obj") >= 2  # two boxes: at least a hull each


def test_meshes_that_cannot_be_an_object_fail_with_one_clear_message(tmp_path):
    sheet = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    sheet.export(tmp_path / "sheet.obj")
    with pytest.raises(ConfigError, match=r"sheet\.obj.*(flat|no volume)"):
        load_mesh_object(tmp_path / "sheet.obj")
    (tmp_path / "points.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    )
    with pytest.raises(ConfigError, match=r"points\.ply.*no triangles"):
        load_mesh_object(tmp_path / "points.ply")
    (tmp_path / "empty.stl").write_bytes(b"")
    with pytest.raises(ConfigError, match=r"empty\.stl"):
        load_mesh_object(tmp_path / "empty.stl")
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 nan 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    with pytest.raises(ConfigError, match=r"nan\.obj.*(NaN|finite)"):
        load_mesh_object(tmp_path / "nan.obj")


def test_sim_capture_refuses_a_flat_mesh_in_one_line(tmp_path, capsys):
    sheet = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    sheet.export(tmp_path / "sheet.obj")
    code = tacsplat_main(
        [
            "sim-capture",
            "--mesh",
            str(tmp_path / "sheet.obj"),
            "--out",
            str(tmp_path / "scene"),
            "--views",
            "1",
            "--grasps",
            "1",
        ]
    )
    err = capsys.readouterr().err
    assert code == 1 and err.count("error:") == 1 and "sheet.obj" in err and "Traceback" not in err
    assert not (tmp_path / "scene" / "transforms.json").exists()


BROKEN_MESHES = {
    # three zero-area triangles (collinear vertices) spanning 3-D: no triangle is left once they are dropped
    "degenerate.obj": "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nv 0 2 0\nv 0 0 1\nv 0 0 2\nf 1 2 3\nf 1 4 5\nf 1 6 7\n",
    # a flat square and a zero-area triangle out of its plane: flat once that is dropped
    "flat_plus_degenerate.obj": "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 0 0 2\nf 1 2 3\nf 1 3 4\nf 1 5 6\n",
    # a tetrahedron with coordinates of 1e200: their squares and cross products overflow
    "huge_coords.obj": "v 0 0 0\nv 1e200 0 0\nv 0 1e200 0\nv 0 0 1e200\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
}


@pytest.mark.parametrize("name", sorted(BROKEN_MESHES))
def test_meshes_broken_once_cleaned_fail_with_one_error_naming_them(tmp_path, capsys, name):
    """The checks hold for the mesh as simulated, after its degenerate faces are dropped (they crashed in qhull)."""
    (tmp_path / name).write_text(BROKEN_MESHES[name])
    with pytest.raises(ConfigError, match=name.replace(".", r"\.")):
        load_mesh_object(tmp_path / name)
    code = tacsplat_main(
        ["sim-capture", "--mesh", str(tmp_path / name), "--out", str(tmp_path / "scene"), "--views", "1"]
    )
    err = capsys.readouterr().err
    assert code == 1 and err.count("error:") == 1 and name in err and "Traceback" not in err, err


def test_a_stray_speck_gets_no_collision_piece_of_its_own(tmp_path):
    """A scan's speck far from the object: CoACD gives it a hull of its own, too small for MuJoCo's inertia (it
    refused the model with a traceback); it is dropped, the object keeps its piece."""
    speck = trimesh.creation.icosphere(subdivisions=1, radius=1e-3)
    speck.apply_translation([100.0, 0.0, 0.0])
    trimesh.util.concatenate([trimesh.creation.box([1.0, 1.0, 1.0]), speck]).export(tmp_path / "speck.obj")
    assert twin_builds(tmp_path / "speck.obj") == 1


def test_a_mesh_mujoco_refuses_is_one_error_naming_it(tmp_path, monkeypatch):
    from tacsplat.sim import twin as twin_module

    speck = trimesh.creation.icosphere(subdivisions=1, radius=1e-6)  # a collision piece under MuJoCo's least volume
    monkeypatch.setattr(twin_module, "convex_decomposition", lambda mesh, config: [speck])
    trimesh.creation.box([1.0, 1.0, 1.0]).export(tmp_path / "box.obj")
    with pytest.raises(ConfigError, match=r"box\.obj: MuJoCo cannot simulate this mesh \(.*volume is too small"):
        twin_builds(tmp_path / "box.obj")


def bow_tie_sphere(inward: bool = False) -> trimesh.Trimesh:
    """An icosphere missing two triangles that share one vertex: a hole whose boundary passes that vertex twice."""
    ball = trimesh.creation.icosphere(subdivisions=3)
    faces = ball.faces
    other = next(
        i for i in np.flatnonzero((faces == faces[0, 0]).any(axis=1)) if len(set(faces[i]) & set(faces[0])) == 1
    )
    kept = np.delete(faces, [0, other], axis=0)
    return trimesh.Trimesh(ball.vertices, kept[:, ::-1] if inward else kept, process=False)


@pytest.mark.parametrize("inward", [False, True])
def test_holes_that_touch_at_a_vertex_are_closed(tmp_path, inward):
    """A bow-tie hole was left open: CoACD then remeshed the object into hulls standing 1.5 mm off it, more than
    the gel gives, and no grasp read a touch (an inward-wound one also kept its inward normals)."""
    mesh = bow_tie_sphere(inward)
    assert len(mesh.outline().entities) >= 1 and not mesh.is_watertight
    mesh.export(tmp_path / "bow_tie.obj")
    obj = load_mesh_object(tmp_path / "bow_tie.obj", radius=0.08)
    assert obj.mesh.is_watertight and obj.mesh.is_winding_consistent
    assert obj.mesh.volume == pytest.approx(trimesh.creation.icosphere(subdivisions=3).volume * 0.08**3, rel=0.01)


@pytest.mark.parametrize("inflation, warned", [(1.0, False), (1.03, True)])
def test_collision_hulls_standing_off_the_mesh_are_warned_about(tmp_path, monkeypatch, caplog, inflation, warned):
    """Hulls more than the gel's compliance off the surface (CoACD's remesh of a mesh it cannot use as it is) stop
    the fingers before their gel reaches the mesh: the capture would read no touch, so the log says so."""
    from tacsplat.sim import twin as twin_module

    def hulls(mesh, config):  # the mesh's own hull, grown by ``inflation`` about its centre (2.4 mm at 3 %)
        return [mesh.convex_hull.apply_scale(inflation)]

    monkeypatch.setattr(twin_module, "convex_decomposition", hulls)
    trimesh.creation.box([1.0, 1.0, 1.0]).export(tmp_path / "box.obj")
    with caplog.at_level("WARNING", logger="tacsplat.sim.twin"):
        twin_builds(tmp_path / "box.obj")
    assert ("box.obj" in caplog.text and "no touch" in caplog.text) == warned, caplog.text


@pytest.mark.parametrize("name", ["empty.glb", "empty.obj", "empty.ply"])
def test_an_empty_file_of_any_format_holds_no_triangles(tmp_path, name):
    (tmp_path / name).write_bytes(b"")  # trimesh fails on an empty .glb with an IndexError
    with pytest.raises(ConfigError, match=rf"{name.replace('.', '[.]')} holds no triangles") as error:
        load_mesh_object(tmp_path / name)
    assert "index" not in str(error.value) and "\n" not in str(error.value)


def test_a_user_mesh_says_where_its_files_points_went(tmp_path):
    box = trimesh.creation.box([60.0, 40.0, 30.0])
    box.apply_translation([100.0, -20.0, 15.0])
    box.export(tmp_path / "part_mm.stl")
    obj = load_mesh_object(tmp_path / "part_mm.stl", radius=0.05)
    scale, translation = obj.from_file
    assert scale == pytest.approx(0.05 / (np.sqrt(60.0**2 + 40.0**2 + 30.0**2) / 2), rel=1e-9)
    placed = scale * np.asarray(trimesh.load(tmp_path / "part_mm.stl").vertices) + translation
    assert np.abs(np.sort(placed, axis=0) - np.sort(obj.mesh.vertices, axis=0)).max() < 1e-12
