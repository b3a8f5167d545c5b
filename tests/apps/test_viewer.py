"""`tacsplat view`: the served scene holds the splat, the frusta and the touches; the export opens without Python;
the controls change what is shown; renders of a browser viewpoint are tacsplat's own; bad paths are one error."""

from __future__ import annotations

import json
import os
import shutil
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from tacsplat.cli import main
from tacsplat.datasets import Scene
from tacsplat.reconstruction.gaussians import Gaussians, sh0_to_rgb
from tacsplat.reconstruction.ply import load_ply
from tacsplat.reconstruction.run_dir import read_checkpoint
from tacsplat.reconstruction.views import camera_tensors

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
sys.path.insert(0, str(Path(__file__).parents[1] / "reconstruction"))
from recon_synthetic import precisions  # noqa: E402
from viewer_client import exported_scene, served, served_scene, splat_count  # noqa: E402

pytest.importorskip("viser", reason="tacsplat view needs viser")

from tacsplat.apps import viewer  # noqa: E402
from tacsplat.apps.viewer_splat import camera_matrices, render_viewpoint, splat_buffers  # noqa: E402


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    """A 32 px simulated capture of the teapot: 2 train views, 1 test view, 1 grasp of 4 touches, a GT mesh."""
    scene = tmp_path_factory.mktemp("viewer") / "scene"
    args = [
        "sim-capture",
        "--resolution",
        "32",
        "--views",
        "2",
        "--test-views",
        "1",
        "--grasps",
        "1",
        "--out",
        str(scene),
        "--quiet",
    ]
    assert main(args) == 0
    return scene


@pytest.fixture(scope="module")
def small_run(small_scene, tmp_path_factory):
    """A 5-step reconstruction of :func:`small_scene` (touch and camera Gaussians, metrics.json)."""
    run = tmp_path_factory.mktemp("viewer") / "run"
    args = [
        "reconstruct",
        str(small_scene),
        "--out",
        str(run),
        "--iterations",
        "5",
        "--sh-degree",
        "0",
        "--backend",
        "cpu",
        "--init.no-use-sfm",
        "--quiet",
    ]
    assert main(args) == 0
    return run


@pytest.fixture
def server():
    import viser

    with viewer._viser_quiet():
        srv = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield srv
    with viewer._viser_quiet():
        srv.stop()


def _one_error_line(capsys, *words) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def _split_counts(run: Path) -> dict[str, int]:
    g = load_ply(run / "splat.ply")
    return {"/run/splat/camera": len(g) - g.num_touch, "/run/splat/touch": g.num_touch}


# --- the served page and scene (a subprocess, as a user runs it) -------------------------------------------------


def test_a_served_run_holds_its_splat_frusta_and_touches(small_run, small_scene):
    scene = Scene.load(small_scene)
    with served(small_run) as url:
        with urllib.request.urlopen(url, timeout=30) as response:
            page = response.read().decode()
        assert response.status == 200 and '<div id="root">' in page and "<title>Viser</title>" in page
        nodes = served_scene(url)
    from viser import _messages as m

    splats = {name: splat_count(n) for name, n in nodes.items() if n.message is m.GaussianSplatsMessage}
    assert splats == _split_counts(small_run) and all(v > 0 for v in splats.values())
    frusta = sorted(name for name, n in nodes.items() if n.message is m.CameraFrustumMessage)
    assert frusta == sorted(f"/run/scene/cameras/{f.split}/frame_{f.id:04d}" for f in scene.frames)
    assert all(len(nodes[name].props["_image_data"]) > 0 for name in frusta)  # each with its thumbnail
    touch_points = sum(
        n.buffers["points"].size // 3
        for name, n in nodes.items()
        if n.message is m.PointCloudMessage and name.startswith("/run/scene/touches/")
    )
    assert touch_points == len(scene.touch_points())
    gels = {f"/run/scene/touches/grasp_{t.grasp:02d}/{t.finger}_{t.id:04d}" for t in scene.touches}
    assert all(nodes[name].message is m.FrameMessage and nodes[f"{name}/gel"].message is m.BoxMessage for name in gels)
    assert nodes["/run/scene/gt_mesh"].message is m.MeshMessage and not nodes["/run/scene/gt_mesh"].visible
    assert nodes["/run/scene/bounding_sphere"].message is m.IcosphereMessage


def test_export_writes_one_page_holding_the_scene(small_run, tmp_path, capsys):
    page = tmp_path / "view.html"
    assert main(["view", str(small_run), "--export", str(page)]) == 0
    assert f"wrote {page}" in capsys.readouterr().out
    html = page.read_text()
    assert html.startswith("<!doctype html>") and "<script" in html and 'src="http' not in html  # no fetches
    nodes = exported_scene(html)
    from viser import _messages as m

    assert {name: splat_count(n) for name, n in nodes.items() if n.message is m.GaussianSplatsMessage} == _split_counts(
        small_run
    )
    assert any(n.message is m.CameraFrustumMessage for n in nodes.values())


# --- one clear error ---------------------------------------------------------------------------------------------


def test_a_path_of_no_known_kind_is_one_error(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("not a scene")
    assert main(["view", str(tmp_path)]) == 1
    _one_error_line(capsys, str(tmp_path), "scene directory", "run directory", "report folder")
    assert main(["view", str(tmp_path / "missing")]) == 1
    _one_error_line(capsys, "missing", "does not exist")
    assert main(["view", str(tmp_path / "notes.txt")]) == 1
    _one_error_line(capsys, "notes.txt", "neither")


@pytest.mark.parametrize("damage", ["truncated", "not a ply"])
def test_a_run_with_a_corrupt_splat_is_one_error(small_run, tmp_path, capsys, damage):
    run = tmp_path / "run"
    shutil.copytree(small_run, run)
    ply = run / "splat.ply"
    ply.write_bytes(ply.read_bytes()[: ply.stat().st_size // 2] if damage == "truncated" else b"\x00garbage\n" * 10)
    assert main(["view", str(run)]) == 1
    _one_error_line(capsys, str(ply), "cannot read a 3DGS PLY")


def test_a_run_whose_gaussians_hold_nan_is_one_error_naming_the_file(small_run, tmp_path, capsys):
    from plyfile import PlyData, PlyElement

    run = Path(shutil.copytree(small_run, tmp_path / "run"))
    ply, checkpoint = run / "splat.ply", run / "checkpoint.pt"
    vertex = PlyData.read(str(ply))["vertex"].data.copy()
    vertex["x"][3] = np.nan
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(ply))
    assert main(["view", str(run), "--export", str(tmp_path / "view.html")]) == 1
    _one_error_line(capsys, str(ply), "means", "NaN")
    ply.unlink()  # a run without its splat.ply: its checkpoint is shown
    state = torch.load(checkpoint, weights_only=False)
    state["gaussians"]["params"]["means"][3, 0] = float("nan")
    torch.save(state, checkpoint)
    assert main(["view", str(run), "--export", str(tmp_path / "view.html")]) == 1
    _one_error_line(capsys, str(checkpoint), "means", "NaN")


def test_an_export_to_a_full_or_read_only_disk_is_one_error(small_run, tmpfs, monkeypatch, capsys):
    mount = tmpfs("1m")  # the page is several MB
    page = mount.path / "view.html"
    assert main(["view", str(small_run), "--export", str(page)]) == 1
    _one_error_line(capsys, str(page), "the disk is full")
    assert list(mount.path.iterdir()) == []  # no temporary file left

    def no_view(*args):
        raise AssertionError("the view was built for a folder that cannot take it")

    monkeypatch.setattr(viewer, "build_view", no_view)
    mount.read_only()
    assert main(["view", str(small_run), "--export", str(page)]) == 1
    _one_error_line(capsys, str(mount.path), "the file system is read-only")


def test_a_report_without_finished_runs_is_one_error(tmp_path, capsys):
    (tmp_path / "runs" / "teapot" / "minimal" / "paper-s0").mkdir(parents=True)
    assert main(["view", str(tmp_path)]) == 1
    _one_error_line(capsys, "no finished run")


# --- the controls ------------------------------------------------------------------------------------------------


def test_touch_and_camera_gaussians_are_shown_apart(small_run, server):
    view = viewer.build_view(server, viewer.load_content(small_run))
    slot = view.slots[0]
    assert set(slot.nodes) == {"camera", "touch"} and all(n.visible for n in slot.nodes.values())
    view.controls["Gaussians"].value = "touch only (G_t)"
    assert slot.nodes["touch"].visible and not slot.nodes["camera"].visible
    shown = slot.shown_gaussians()
    assert len(shown) == slot.gaussians.num_touch and bool(shown.from_touch.all())
    view.controls["Gaussians"].value = "camera only (G_c)"
    assert slot.nodes["camera"].visible and not slot.nodes["touch"].visible
    assert not bool(slot.shown_gaussians().from_touch.any())
    view.controls["ground-truth mesh"].value = True
    assert all(n.visible for n in view.scene_nodes.groups["mesh"])


def test_the_checkpoint_slider_shows_each_kept_checkpoint(small_run, tmp_path, server):
    run = tmp_path / "run"
    shutil.copytree(small_run, run)
    ckpt = read_checkpoint(run / "checkpoint.pt")
    early = Gaussians.from_state_dict(ckpt["gaussians"])
    keep = torch.arange(len(early)) < 100
    ckpt["gaussians"] = Gaussians(
        {k: v.detach()[keep] for k, v in early.params.items()}, early.from_touch[keep], early.sh_degree
    ).state_dict()
    ckpt["step"] = 2
    torch.save(ckpt, run / "checkpoint_000002.pt")
    stamp = (run / "checkpoint.pt").stat().st_mtime
    os.utime(run / "checkpoint_000002.pt", (stamp - 60, stamp - 60))  # kept before the last one
    view = viewer.build_view(server, viewer.load_content(run))
    slider, slot = view.controls["checkpoint"], view.slots[0]
    assert slider.max == 1 and slider.value == 1 and len(slot.gaussians) == len(load_ply(run / "splat.ply"))
    slider.value = 0
    assert len(slot.gaussians) == 100 and "step 2" in view.controls["checkpoint shown"].content
    slider.value = 1
    assert len(slot.gaussians) == len(early)


def _report(small_run: Path, small_scene: Path, root: Path) -> Path:
    """A report folder of three copies of ``small_run`` (its scene under scenes/, recorded with another prefix,
    as a report moved elsewhere has it), the 3dgs run's metrics changed to tell it apart."""
    report = root / "report"
    shutil.copytree(small_scene, report / "scenes" / "teapot" / "minimal-s0")
    for method in ("3dgs+t", "3dgs", "paper"):
        run = report / "runs" / "teapot" / "minimal" / f"{method}-s0"
        shutil.copytree(small_run, run)
        metrics = json.loads((run / "metrics.json").read_text())
        metrics.update(method=method, scene="/elsewhere/report/scenes/teapot/minimal-s0")
        (run / "metrics.json").write_text(json.dumps(metrics))
    return report


def test_a_report_shows_3dgs_and_the_paper_method_side_by_side(small_run, small_scene, tmp_path, server):
    content = viewer.load_content(_report(small_run, small_scene, tmp_path))
    assert content.kind == "report" and [r.label for r in content.pair] == [
        "teapot/minimal/3dgs-s0",
        "teapot/minimal/paper-s0",
    ]
    assert content.pair[0].scene is not None  # found inside the report
    view = viewer.build_view(server, content)
    left, right = view.slots
    centre = viewer.object_sphere(content.pair[0])[0]
    assert np.allclose(left.offset + centre, -right.offset - centre) and left.offset[0] < right.offset[0]
    metrics = view.controls["metrics"]
    assert "3dgs-s0" in view.controls["left run"].value and "| method | 3dgs | paper |" in metrics.content
    view.controls["left run"].value = "teapot/minimal/3dgs+t-s0"
    assert left.run.label == "teapot/minimal/3dgs+t-s0" and "| method | 3dgs+t | paper |" in metrics.content
    view.controls["right run"].value = "(none)"
    assert right.run is None and not right.nodes


# --- the browser's splat and tacsplat's render of its viewpoint --------------------------------------------------


def test_splat_buffers_are_the_gaussians_in_their_own_unit():
    """Covariances are the inverse of the rasterizer's precisions; 0.1 mm Gaussians survive viser's float16."""
    rng = np.random.default_rng(0)
    n = 50
    gaussians = Gaussians(
        {
            "means": torch.tensor(rng.normal(0, 0.05, (n, 3)), dtype=torch.float32),
            "quats": torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
            "scales": torch.tensor(np.log(rng.uniform(5e-5, 2e-4, (n, 3))), dtype=torch.float32),
            "opacities": torch.tensor(rng.normal(size=n), dtype=torch.float32),
            "sh0": torch.tensor(rng.normal(size=(n, 1, 3)), dtype=torch.float32),
            "shN": torch.zeros(n, 0, 3),
        },
        torch.zeros(n, dtype=torch.bool),
        0,
    )
    b = splat_buffers(gaussians)
    expected = torch.linalg.inv(precisions(gaussians.quats.detach().double(), gaussians.scales.detach().double()))
    assert np.allclose(b.covariances * b.unit**2, expected.numpy(), rtol=1e-4, atol=1e-16)
    assert np.allclose(b.centers * b.unit, gaussians.means.detach().numpy(), atol=1e-7)
    assert np.allclose(b.rgbs, sh0_to_rgb(gaussians.params["sh0"].detach())[:, 0].clamp(0, 1).numpy())
    assert np.allclose(b.opacities[:, 0], gaussians.opacities.detach().numpy())
    sent = b.covariances.astype(np.float16).astype(np.float64)  # what viser sends
    diagonal = np.diagonal(b.covariances, axis1=1, axis2=2)
    assert np.allclose(np.diagonal(sent, axis1=1, axis2=2), diagonal, rtol=2e-3)


def test_a_browser_camera_renders_as_the_scene_camera_it_stands_in(small_run, small_scene):
    """The viewpoint's render equals the rasterizer's render of the scene frame with the same pose and field of
    view, wherever the viewer placed the splat."""
    import viser.transforms as vtf

    from tacsplat.reconstruction.raster import rasterization

    frame = Scene.load(small_scene).frames[0]
    intr = frame.intrinsics
    assert np.isclose(intr.fx, intr.fy) and np.isclose(intr.cx, intr.width / 2) and np.isclose(intr.cy, intr.height / 2)
    fov_y = 2 * np.arctan2(0.5 * intr.height, intr.fy)
    wxyz = vtf.SO3.from_matrix(frame.T_world_cam[:3, :3]).wxyz
    T_world_cam, K = camera_matrices(wxyz, frame.T_world_cam[:3, 3], fov_y, intr.width, intr.height)
    assert np.allclose(T_world_cam, frame.T_world_cam, atol=1e-9) and np.allclose(K, intr.K)

    g = load_ply(small_run / "splat.ply")
    viewmat, Ks = camera_tensors([frame])
    expected, _, _ = rasterization(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.sh_coefficients(),
        viewmat,
        Ks,
        intr.width,
        intr.height,
        sh_degree=g.sh_degree,
        render_mode="RGB+ED",
        backgrounds=torch.ones(1, 3),
    )
    rgb, depth, _ = render_viewpoint(g, T_world_cam, K, intr.width, intr.height)
    assert np.allclose(rgb, expected[0, ..., :3].detach().clamp(0, 1).numpy(), atol=1e-5)
    assert np.allclose(depth, expected[0, ..., 3].detach().numpy(), atol=1e-5)

    placed = viewer.SplatSlot(None, "/left")
    placed.gaussians, placed.offset = g, np.array([-0.3, 0.1, 0.0])  # where a report puts its left run
    rows = viewer.render_rows([placed], wxyz, frame.T_world_cam[:3, 3] + placed.offset, fov_y, intr.width, intr.height)
    assert rows.shape == (intr.height, 2 * intr.width, 3)
    assert np.abs(rows[:, : intr.width].astype(int) - (rgb * 255).round()).max() <= 1


def test_the_first_viewpoint_looks_past_the_scene_cameras():
    """Without cameras: from the front (-y), above; with a camera there: from the azimuth farthest from all."""
    centre = np.array([0.1, 0.2, 0.3])
    position, look_at = viewer.initial_viewpoint(centre, 0.08)
    assert np.allclose(look_at, centre) and np.isclose(np.linalg.norm(position - centre), viewer.CAMERA_DISTANCE * 0.08)
    assert np.allclose((position - centre) / np.linalg.norm(position - centre), np.array([0, -1, 0.5]) / np.sqrt(1.25))
    cameras = centre + 0.3 * np.array([[0.0, -1.0, 0.5], [1.0, 0.0, 0.5], [0.0, 1.0, 0.5]])  # front, right, back
    position, _ = viewer.initial_viewpoint(centre, 0.08, cameras)
    assert np.allclose((position - centre)[:2] / np.linalg.norm((position - centre)[:2]), [-1.0, 0.0])  # left


def test_a_runs_exported_mesh_is_shown_behind_a_checkbox(small_run, tmp_path, server):
    import shutil

    import trimesh

    run = tmp_path / "run"
    shutil.copytree(small_run, run)
    trimesh.creation.icosphere(subdivisions=2, radius=0.05).export(run / "mesh.ply")
    view = viewer.build_view(server, viewer.load_content(run))
    assert "exported mesh" in view.controls and not view.controls["exported mesh"].value
    assert view.mesh_node is not None and not view.mesh_node.visible
    view.controls["exported mesh"].value = True
    assert view.mesh_node.visible
