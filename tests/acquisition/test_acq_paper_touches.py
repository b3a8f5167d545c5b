"""The paper's touches (--touch-model paper): the official code's sampling (50 surface samples around the furthest
hit of a random ray from the centroid), recorded as pad touches that lift back onto the sampled points; sim-capture
resumes them identically and refuses a resume with another touch model; simulate-touches writes them in an imported
scene's frame and units."""

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from tacsplat.acquisition.config import TouchPlan, example_rig, load_rig, parse_rig
from tacsplat.acquisition.operator_session import run_capture
from tacsplat.acquisition.paper_touches import COLLISION_TOLERANCE_PX, PaperTouches, encode_touch
from tacsplat.acquisition.sim_capture import sim_capture, sim_rig_config
from tacsplat.cli import main
from tacsplat.datasets import Scene, SceneMeta, SceneWriter, SensorModel
from tacsplat.errors import ConfigError
from tacsplat.geometry import look_at, tactile_depth_to_points
from tacsplat.sim.hand import FINGER_NAMES
from tacsplat.types import CameraIntrinsics

pytestmark = pytest.mark.timeout(180)

PLAN = dict(object="bell", views=1, test_views=0, grasps=5, resolution=32, seed=3)
CLI_PLAN = [
    "--object",
    "bell",
    "--views",
    "1",
    "--test-views",
    "0",
    "--grasps",
    "5",
    "--resolution",
    "32",
    "--seed",
    "3",
]
PAD = SensorModel("pad", 160, 128, 1.5e-4, 0.002)  # the twin's pad


def _lifted(scene: Scene, touch) -> np.ndarray:
    return tactile_depth_to_points(scene.load_touch_depth(touch), scene.sensor.pixel_size_m, touch.T_world_sensor)


def _match(samples: np.ndarray, lifted: np.ndarray) -> np.ndarray:
    """Each sample's distance to its nearest lifted point, after checking that there are as many of each."""
    assert len(lifted) == len(samples)
    return np.linalg.norm(samples[:, None] - lifted[None], axis=2).min(axis=1)


def _files(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _records(path: Path) -> list:
    scene = Scene.load(path)
    return [(scene.load_touch_depth(t).tobytes(), t.grasp, t.finger, t.T_world_sensor.tobytes()) for t in scene.touches]


@pytest.fixture(scope="module")
def paper_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper") / "scene"
    sim_capture(sim_rig_config(**PLAN, touch_model="paper"), out, progress=False)
    return out


# --- the encoding -------------------------------------------------------------------------------


def test_a_touch_lifts_back_onto_its_points_the_deeper_of_two_keeps_a_shared_pixel(caplog):
    """A cap of a 3 cm sphere (tilted), with points stacked 1 mm under four of its points; then one off the pad."""
    R, pole = 0.03, np.array([0.3, -0.2, 0.93]) / np.linalg.norm([0.3, -0.2, 0.93])
    T = look_at(np.zeros(3), pole)
    grid = np.stack(np.meshgrid(*[(np.arange(6) - 2.5) * 0.00173] * 2), axis=-1).reshape(-1, 2)  # no pixel edge
    points = np.c_[grid, np.sqrt(R**2 - (grid**2).sum(axis=1))] @ T[:3, :3].T + [0.1, 0.2, 0.3]  # the cap at pole
    inner = np.flatnonzero(np.abs(grid).max(axis=1) < 0.001)  # the four around the middle: the cap stays symmetric
    stacked = points[inner] - 0.001 * pole  # each under one: its pixel, 1 mm shallower
    depth, T_world_sensor = encode_touch(np.vstack([points, stacked]), pole, PAD)
    assert np.allclose(T_world_sensor[:3, 2], -pole, atol=1e-9)  # the pad faces the cap, z into the object
    lifted = tactile_depth_to_points(depth, PAD.pixel_size_m, T_world_sensor)
    distance = _match(np.vstack([points, stacked]), lifted)
    assert distance[:36].max() <= PAD.pixel_size_m / np.sqrt(2) + 1e-9  # each alone on its pixel, or the deeper
    assert np.all(PAD.pixel_size_m / np.sqrt(2) < distance[36:])  # the shallower moved ...
    assert np.all(distance[36:] <= COLLISION_TOLERANCE_PX * PAD.pixel_size_m)  # ... to a neighbouring pixel
    assert depth[depth > 0].min() == pytest.approx(0.05 * PAD.gel_thickness_m, rel=1e-5)  # pressed just enough

    far = points[0] + 0.02 * T[:3, 0]  # 2 cm along the surface: off the 24 x 19.2 mm pad
    with caplog.at_level(logging.WARNING):
        depth, T_world_sensor = encode_touch(np.vstack([points, far]), pole, PAD)
    assert "1 of a touch's 37 points lie outside the pad" in caplog.text
    assert _match(points, tactile_depth_to_points(depth, PAD.pixel_size_m, T_world_sensor)).max() <= 2e-4


def test_rays_are_cast_as_the_official_code_casts_them():
    """theta ~ U(0, pi): |cos theta| > 0.9 for 29 % of rays (10 % if area-uniform); the furthest hit is kept, and a
    ray that misses (a torus seen from its hole) is cast again; touch t is the same on every call."""
    sphere = PaperTouches(trimesh.creation.icosphere(subdivisions=2), seed=7, plan=TouchPlan("paper", 2000, 50))
    directions = np.array([sphere.ray(t)[1] for t in range(300)])
    assert 0.2 < np.mean(np.abs(directions[:, 2]) > 0.9) < 0.38
    mesh = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3)
    torus = PaperTouches(mesh, seed=7, plan=TouchPlan("paper", 2000, 50))
    rays = [torus.ray(t) for t in range(100)]
    hits, directions = np.array([r[0] for r in rays]), np.array([r[1] for r in rays])
    assert np.allclose(np.cross(hits - mesh.centroid, directions), 0.0, atol=1e-9)  # on the ray
    assert not mesh.ray.intersects_any(hits + 1e-6 * directions, directions).any()  # the furthest hit
    assert np.abs(directions[:, 2]).max() <= 0.3  # from the hole, a ray meets the tube only at elevation sin <= 0.3 / 1
    again = torus.ray(11)
    assert np.array_equal(again[0], hits[11]) and np.array_equal(again[1], directions[11])
    points, _ = torus.touch(11)
    assert len(points) == 50 and np.linalg.norm(points - hits[11], axis=1).max() < 0.4


# --- sim-capture --touch-model paper --------------------------------------------------------------


def test_paper_touches_lie_on_the_surface_fifty_around_each_hit_spread_over_the_object(paper_scene):
    scene = Scene.load(paper_scene)
    assert scene.meta.capture_plan["touches"] == {"model": "paper", "surface_points": 20000, "points_per_touch": 50}
    assert [(t.grasp, t.finger) for t in scene.touches] == [(t // 4, FINGER_NAMES[t % 4]) for t in range(20)]
    mesh = trimesh.load(scene.gt_mesh_path, force="mesh")
    radius = mesh.bounding_sphere.primitive.radius
    tolerance = COLLISION_TOLERANCE_PX * scene.sensor.pixel_size_m
    sampled = PaperTouches(mesh, seed=3)
    centres = []
    for touch in scene.touches:
        lifted = _lifted(scene, touch)
        samples, _ = sampled.touch(touch.id)
        distance = _match(samples, lifted)
        assert distance.max() <= tolerance and np.mean(distance <= scene.sensor.pixel_size_m / np.sqrt(2)) >= 0.9
        _, to_surface, _ = trimesh.proximity.closest_point(mesh, lifted)
        assert to_surface.max() <= tolerance
        centre = lifted.mean(axis=0)
        assert np.linalg.norm(lifted - centre, axis=1).max() < 0.15 * radius  # one cluster
        centres.append(centre)
    directions = np.array(centres) - mesh.centroid
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    assert np.linalg.norm(directions.mean(axis=0)) < 0.5  # not all on one side
    assert len({tuple(np.sign(d).astype(int)) for d in directions}) >= 5  # octants around the centroid


def test_a_paper_capture_cut_short_resumes_with_the_same_touches(paper_scene, tmp_path):
    out = tmp_path / "scene"
    shutil.copytree(paper_scene, out)
    with SceneWriter.resume(out) as writer:  # a kill in grasp 3's touches
        for _ in range(6):
            writer.remove_last()
    sim_capture(sim_rig_config(**PLAN, touch_model="paper"), out, resume=True, progress=False)
    assert _records(out) == _records(paper_scene)


def test_a_resume_with_another_touch_model_is_refused_naming_the_option(paper_scene, tmp_path, capsys):
    out = tmp_path / "scene"
    shutil.copytree(paper_scene, out)
    before = _files(out)
    assert main(["sim-capture", *CLI_PLAN, "--out", str(out), "--resume"]) == 1
    err = capsys.readouterr().err
    assert f"error: --touch-model: {out} was captured with 'paper', this run asks for 'gel'" in err, err
    assert (
        main(
            [
                "sim-capture",
                *CLI_PLAN,
                "--touch-model",
                "paper",
                "--surface-points",
                "10000",
                "--out",
                str(out),
                "--resume",
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert f"error: --surface-points: {out} was captured with 20000, this run asks for 10000" in err, err
    assert _files(out) == before


def test_a_gel_scene_of_older_code_is_not_resumed_with_paper_touches(tmp_path, capsys):
    out = tmp_path / "scene"
    gel = ["--object", "bell", "--views", "1", "--test-views", "0", "--grasps", "0", "--resolution", "32"]
    assert main(["sim-capture", *gel, "--out", str(out)]) == 0
    assert Scene.load(out).meta.capture_plan["touches"] == {"model": "gel"}
    journal = out / "journal.jsonl"  # older code recorded no touch model
    lines = journal.read_text().splitlines(keepends=True)
    header = json.loads(lines[0])
    del header["meta"]["capture_plan"]["touches"]
    journal.write_text(json.dumps(header) + "\n" + "".join(lines[1:]))
    assert main(["sim-capture", *gel, "--touch-model", "paper", "--out", str(out), "--resume"]) == 1
    err = capsys.readouterr().err
    assert f"error: --touch-model: {out} was captured with 'gel', this run asks for 'paper'" in err, err
    assert main(["sim-capture", *gel, "--out", str(out), "--resume"]) == 0


def test_paper_touches_need_the_twin_and_no_operator(tmp_path):
    data = yaml.safe_load(example_rig("mock").read_text())
    data["plan"] = {**data.get("plan", {}), "touches": {"model": "paper"}}
    with pytest.raises(ConfigError, match="use 'gel' on a real rig") as err:
        parse_rig(data, "real.yaml", mock=True)
    assert err.value.key == "plan.touches.model"
    sim = yaml.safe_load(example_rig("sim").read_text())
    with pytest.raises(ConfigError) as err:
        parse_rig({**sim, "plan": {**sim["plan"], "touches": {"model": "finger"}}}, "sim.yaml")
    assert err.value.key == "plan.touches.model" and "'gel', 'paper'" in str(err.value)
    with pytest.raises(ConfigError) as err:
        parse_rig({**sim, "plan": {**sim["plan"], "touches": {"model": "paper", "surface_points": 40}}}, "sim.yaml")
    assert err.value.key == "plan.touches.surface_points" and "at least the 50 points of a touch" in str(err.value)
    rig = tmp_path / "sim.yaml"
    rig.write_text(yaml.safe_dump({**sim, "plan": {**sim["plan"], "touches": {"model": "paper"}}}))
    with pytest.raises(ConfigError, match="sim-capture --touch-model paper") as err:
        run_capture(load_rig(rig), tmp_path / "scene")
    assert err.value.key == "plan.touches.model" and not (tmp_path / "scene").exists()


# --- simulate-touches --touch-model paper -----------------------------------------------------------


def test_paper_touches_of_an_imported_unit_scale_scene_come_out_in_its_frame_and_units(tmp_path, capsys):
    offset = np.array([0.5, -0.2, 0.1])
    mesh = trimesh.creation.capsule(height=1.0, radius=0.5, count=[48, 48])  # convex: no decomposition to wait for
    mesh.apply_scale(1.0 / mesh.bounding_sphere.primitive.radius)
    mesh.apply_translation(offset)
    mesh_path = tmp_path / "object.ply"
    mesh.export(mesh_path)
    imported = tmp_path / "imported"
    K = np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    with SceneWriter.create(imported, CameraIntrinsics(K, 32, 32), SceneMeta(source="import", object="capsule")) as w:
        w.add_frame(np.full((32, 32, 3), 128, np.uint8), look_at(offset + [0, -3.0, 1.0], offset), "train")
    out = tmp_path / "touched"
    assert (
        main(
            [
                "simulate-touches",
                "--mesh",
                str(mesh_path),
                str(imported),
                "--grasps",
                "2",
                "--out",
                str(out),
                "--seed",
                "1",
                "--touch-model",
                "paper",
            ]
        )
        == 0
    )
    assert f"touches written to {out}" in capsys.readouterr().out
    scene = Scene.load(out)
    assert scene.meta.capture_plan["simulated_touches"] == {
        "mesh": str(mesh_path),
        "grasps": 2,
        "seed": 1,
        "touches": {"model": "paper", "surface_points": 20000, "points_per_touch": 50},
    }
    scale = 1.0 / 0.08  # scene units per twin metre
    assert scene.sensor.pixel_size_m == pytest.approx(1.5e-4 * scale)
    assert [(t.grasp, t.finger) for t in scene.touches] == [(t // 4, FINGER_NAMES[t % 4]) for t in range(8)]
    tolerance = COLLISION_TOLERANCE_PX * scene.sensor.pixel_size_m
    for touch in scene.touches:
        lifted = _lifted(scene, touch)
        assert len(lifted) == 50
        _, to_surface, _ = trimesh.proximity.closest_point(mesh, lifted)
        assert to_surface.max() <= tolerance
        assert np.linalg.norm(lifted - lifted.mean(axis=0), axis=1).max() < 0.15  # one cluster, radius 1
    # a scene with this sensor model is extended in place, numbering grasps on
    assert (
        main(
            [
                "simulate-touches",
                "--mesh",
                str(mesh_path),
                str(out),
                "--grasps",
                "1",
                "--seed",
                "1",
                "--touch-model",
                "paper",
            ]
        )
        == 0
    )
    extended = Scene.load(out)
    assert [t.grasp for t in extended.touches[8:]] == [2] * 4


def test_paper_touches_on_an_imported_scene_with_ground_truth_points_only(tmp_path, capsys):
    """Glossy Synthetic ships points, not a mesh: the paper's touches are made on them, and lie on them; the
    hand's gel touches need a mesh, and the error says so."""
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1] / "datasets"))
    from paper_datasets import RADIUS, make_glossy_synthetic

    from tacsplat.datasets.nero import import_nero

    imported = import_nero(make_glossy_synthetic(tmp_path / "src"), tmp_path / "imported", scale=0.5)
    out = tmp_path / "touched"
    command = ["simulate-touches", str(imported), "--grasps", "2", "--out", str(out), "--seed", "4"]
    assert main([*command, "--touch-model", "paper"]) == 0
    scene = Scene.load(out)
    assert scene.meta.capture_plan["simulated_touches"]["mesh"] == "gt/points.ply"
    assert len(scene.touches) == 8 and scene.gt_points().shape == (3000, 3)
    samples = Scene.load(imported).gt_points()
    tolerance = COLLISION_TOLERANCE_PX * scene.sensor.pixel_size_m
    for touch in scene.touches:
        lifted = _lifted(scene, touch)
        assert len(lifted) == round(50 * 3000 / 20000)  # the paper's share of the surface: 50 of 20000 samples
        assert np.linalg.norm(samples[:, None] - lifted[None], axis=2).min(axis=0).max() <= tolerance
        assert np.linalg.norm(lifted - lifted.mean(axis=0), axis=1).max() < 0.3 * 0.5 * RADIUS  # one cluster
    capsys.readouterr()
    assert main([*command[:-4], "--out", str(tmp_path / "gel"), "--seed", "4"]) == 2  # (a usage error: pass --mesh)
    err = capsys.readouterr().err
    assert "--mesh" in err and "gt/points.ply" in err and "--touch-model paper" in err
