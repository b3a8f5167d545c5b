"""End to end: a synthetic sphere scene is reconstructed; unneeded paths are skipped; resume is exact; CLI."""

import csv
import json
import logging
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh

from tacsplat.cli import main as tacsplat_main
from tacsplat.datasets import Scene
from tacsplat.reconstruction import losses
from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.densification import DensifyStrategy
from tacsplat.reconstruction.gaussians import Gaussians, quats_to_rotmats
from tacsplat.reconstruction.initialization import InitConfig
from tacsplat.reconstruction.methods import method_of
from tacsplat.reconstruction.ply import load_ply
from tacsplat.reconstruction.trainer import Trainer, reconstruct

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import RADIUS, build_sphere_scene, sphere_gaussians  # noqa: E402

from tacsplat.reconstruction.raster import rendering as raster  # the module: tests spy on its calls


@pytest.fixture(scope="module")
def sphere_scene(tmp_path_factory):
    return build_sphere_scene(tmp_path_factory.mktemp("scenes") / "sphere", size=48)


@pytest.fixture(scope="module")
def bare_scene(tmp_path_factory):
    return build_sphere_scene(
        tmp_path_factory.mktemp("scenes") / "bare", size=24, train_views=3, test_views=1, touches=False
    )


def _config(iterations: int, **overrides) -> TrainConfig:
    base = dict(
        iterations=iterations,
        backend="cpu",
        sh_degree=0,
        eval_every_iters=100,
        eval_every_seconds=1e9,
        init=InitConfig(use_sfm=False, num_random_points=500),
        densify=DensifyStrategy(start_iter=100, refine_every=100, reset_every=10**6, stop_iter=iterations),
    )
    base.update(overrides)
    return TrainConfig(**base)


def test_touch_and_fallback_gaussians_start_with_the_colors_their_pixels_show(sphere_scene, tmp_path):
    """``init.colors_from_views``: the randomly coloured Gaussians (here all of them: no SfM) take the median colour
    of the training pixels they project to on the silhouettes; off, they keep random colours. Nothing else of the
    initialisation changes (the same random draws)."""
    from tacsplat.reconstruction.gaussians import sh0_to_rgb
    from tacsplat.reconstruction.initialization import foreground_mask, view_colors

    trainers = {}
    for on in (True, False):
        trainers[on] = Trainer(
            Scene.load(sphere_scene),
            tmp_path / str(on),
            _config(10, init=InitConfig(use_sfm=False, num_random_points=500, colors_from_views=on)),
        )
        trainers[on].initialize()
    seen, unseen = (trainers[on].gaussians for on in (True, False))
    assert torch.equal(seen.means, unseen.means) and seen.num_touch > 0
    t = trainers[True]
    expected = view_colors(
        seen.means.detach().double().numpy(),
        [im.numpy() for im in t.images],
        [f.intrinsics.K for f in t.train_frames],
        [f.T_world_cam for f in t.train_frames],
        [foreground_mask(m) for m in t.backdrop_pixels],
    )  # [N, 3]
    found = np.isfinite(expected).all(axis=1)
    assert found.mean() > 0.9
    rgb = sh0_to_rgb(seen.params["sh0"].detach()[:, 0]).numpy()
    np.testing.assert_allclose(rgb[found], expected[found], atol=0.02)  # float32 means: a pixel's neighbour at most
    random_rgb = sh0_to_rgb(unseen.params["sh0"].detach()[:, 0]).numpy()
    assert np.abs(random_rgb[found] - expected[found]).mean() > 0.1


def test_reconstruction_of_the_synthetic_sphere_converges(sphere_scene, tmp_path):
    run = tmp_path / "run"
    # random points in the bounds (no visual hull): the optimisation itself must find the sphere
    init = InitConfig(use_sfm=False, num_random_points=500, use_silhouette_hull=False)
    metrics = reconstruct(sphere_scene, run, _config(400, init=init), show_progress=False)
    with (run / "progress.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["iteration"]) for r in rows] == [0, 100, 200, 300, 400]
    initial_cd = float(rows[0]["cd"])
    # Bound: the CD (in units of the 5 cm radius) of 48x48 views starts near 0.73 and is ~0.19 after 400 steps.
    assert metrics["cd"] < 0.25
    assert metrics["cd"] < 0.5 * initial_cd
    # the paper's CD (squared, summed, median depth against the whole mesh surface) falls too
    assert 0 < metrics["cd_paper"] < 0.5 * float(rows[0]["cd_paper"])
    assert metrics["psnr"] > 18.0
    assert metrics["iterations"] == 400 and not metrics["mechanisms"]["depth_normal"]  # from step 700: never reached
    assert metrics["method"] == "custom"  # the default's other mechanisms, as the run used them
    assert metrics["num_touch_gaussians"] > 0 and metrics["num_gaussians"] == len(load_ply(run / "splat.ply"))
    seconds = [float(r["seconds"]) for r in rows]
    assert seconds == sorted(seconds)
    # the last progress row (all test views: there are fewer than eval_max_views) is the final evaluation's
    assert len(Scene.load(sphere_scene).split("test")) <= TrainConfig().eval_max_views
    for key in ("psnr", "cd", "cd_paper"):
        assert float(rows[-1][key]) == pytest.approx(metrics[key], rel=1e-5)
    assert all(float(r["transmittance"]) > 0 for r in rows[1:])
    saved = json.loads((run / "metrics.json").read_text())
    for key in (
        "cd",
        "cd_paper",
        "psnr",
        "ssim",
        "train_seconds",
        "iterations",
        "num_gaussians",
        "num_touch_gaussians",
        "method",
        "settings",
    ):
        assert key in saved
    assert saved["cd_paper"] == pytest.approx(saved["cd_paper_accuracy"] + saved["cd_paper_completeness"])
    assert saved["cd_seen"] is None and saved["unseen_fraction"] is None  # no mesh to tell what cameras see
    assert abs(saved["psnr_splat"] - saved["psnr"]) < 1.0  # splat.ply's baked shading looks like the lit render
    assert (run / "error_vs_time.png").stat().st_size > 0
    assert len(list((run / "renders").glob("*.png"))) == len(Scene.load(sphere_scene).split("test"))


def _sphere_of_gaussians(scale: float):
    """The scene's textured sphere of flat Gaussians, its radius times ``scale``."""
    from tacsplat.reconstruction.gaussians import Gaussians

    means, quats, scales, opacities, colors = sphere_gaussians()
    params = {
        "means": means * scale,
        "quats": quats,
        "scales": (scales * scale).log(),
        "opacities": torch.logit(opacities),
        "sh0": ((colors - 0.5) / 0.28209479177387814)[:, None],
        "shN": torch.zeros(len(means), 0, 3),
    }
    return Gaussians(params, torch.zeros(len(means), dtype=torch.bool), sh_degree=0)


def test_depth_bias_is_positive_behind_the_truth_in_radii(sphere_scene):
    """A sphere 4 % smaller than the true one renders behind it: the median signed depth error rises by 0.04 radii
    at the view's centre and a little more towards its rim; 4 % larger lowers it as much. (The flat Gaussians of
    the true size already sit in front of the analytic sphere away from the centre: they stand off it.)"""
    from tacsplat.reconstruction.evaluation import evaluate_views, load_ground_truth

    scene = Scene.load(sphere_scene)
    test = scene.split("test")
    truth = load_ground_truth(scene, test)
    bias = {
        s: evaluate_views(_sphere_of_gaussians(s), scene, test, None, "cpu", truth)["depth_bias"]
        for s in (0.96, 1.0, 1.04)
    }
    assert 0.035 < bias[0.96] - bias[1.0] < 0.07
    assert 0.035 < bias[1.0] - bias[1.04] < 0.07
    assert np.isnan(evaluate_views(_sphere_of_gaussians(1.0), scene, test, None, "cpu", None)["depth_bias"])


def test_a_test_view_whose_object_crosses_the_border_is_scored_over_its_fitted_backdrop(tmp_path, caplog):
    """The true sphere in close test views (across the top edge) in front of a gradient: rendered over each view's
    fitted backdrop it matches the images (over black it would score about 8 dB). A cluttered test image is
    rendered over black, and the final evaluation's warning names it; a progress row's does not warn."""
    from tacsplat.reconstruction.evaluation import evaluate_views

    path = build_sphere_scene(
        tmp_path / "sphere", size=32, train_views=2, test_views=2, touches=False, backdrop=True, centre_row=0.15
    )
    scene = Scene.load(path)
    test = scene.split("test")
    assert all((scene.gt_depth(f)[0] > 0).any() for f in test)  # (the sphere crosses the top edge)
    with caplog.at_level("WARNING"):
        assert evaluate_views(_sphere_of_gaussians(1.0), scene, test, None, "cpu", None)["psnr"] > 30.0
    assert not caplog.records

    cluttered = test[1].file_path
    image = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    cv2.imwrite(str(path / cluttered), image)
    with caplog.at_level("WARNING"):
        evaluate_views(_sphere_of_gaussians(1.0), Scene.load(path), test, None, "cpu", None, progress=True)
        assert not caplog.records
        evaluate_views(_sphere_of_gaussians(1.0), Scene.load(path), test, None, "cpu", None)
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and "test images whose border is not a smooth backdrop" in warnings[0]
    assert str(path / cluttered) in warnings[0] and str(path / test[0].file_path) not in warnings[0]


class _Spy:
    """Records calls of a function and still calls it."""

    def __init__(self, fn):
        self.fn, self.calls = fn, []

    def __call__(self, *args, **kwargs):
        self.calls.append((kwargs, torch.is_grad_enabled()))
        return self.fn(*args, **kwargs)


def _spy_paths(monkeypatch):
    spies = {
        "render": _Spy(raster.rasterization),
        "transmittance": _Spy(losses.transmittance_loss),
        "smoothness": _Spy(losses.edge_aware_smoothness),
        "neighbours": _Spy(losses.TouchNeighbours._build),
    }
    monkeypatch.setattr(raster, "rasterization", spies["render"])
    monkeypatch.setattr(losses, "transmittance_loss", spies["transmittance"])
    monkeypatch.setattr(losses, "edge_aware_smoothness", spies["smoothness"])
    monkeypatch.setattr(losses.TouchNeighbours, "_build", lambda self, *a: spies["neighbours"](self, *a))
    return spies


def _training_render_modes(spy: _Spy) -> set:
    return {kwargs["render_mode"] for kwargs, grad in spy.calls if grad}


def test_scene_without_touches_and_zero_smoothness_skips_those_paths(bare_scene, tmp_path, monkeypatch):
    spies = _spy_paths(monkeypatch)
    trainer = Trainer(Scene.load(bare_scene), tmp_path / "run", _config(3, lambda_s=0.0))
    gaussians = trainer.run(show_progress=False)
    assert gaussians.num_touch == 0 and trainer.neighbours is None
    assert spies["transmittance"].calls == [] and spies["neighbours"].calls == []
    assert spies["smoothness"].calls == []
    assert _training_render_modes(spies["render"]) == {"RGB"}  # no depth rendered for training


def test_touch_scene_runs_the_touch_and_smoothness_paths(sphere_scene, tmp_path, monkeypatch):
    spies = _spy_paths(monkeypatch)
    trainer = Trainer(Scene.load(sphere_scene), tmp_path / "run", _config(3))
    trainer.run(show_progress=False)
    assert len(spies["transmittance"].calls) == 3 and len(spies["neighbours"].calls) == 1
    assert len(spies["smoothness"].calls) == 3
    assert _training_render_modes(spies["render"]) == {"RGB+D"}


def test_the_settings_of_a_switched_off_mechanism_change_nothing(sphere_scene, tmp_path):
    """TrainConfig.unused_fields is what bench paper ignores when it compares a run's settings with today's: changing
    them leaves the trained Gaussians identical (here the consistency's start step, with the consistency off, and the
    albedo smoothness's weights, with the smoothness off)."""

    def trained(name: str, **changes) -> dict:
        config = _config(4, lambda_depth_normal=0.0, lambda_albedo_smoothness=0.0, **changes)
        trainer = Trainer(Scene.load(sphere_scene), tmp_path / name, config)
        trainer.run(show_progress=False)
        return {"unused": config.unused_fields(), **trainer.gaussians.params}

    base = trained("base", depth_normal_start_iter=0, albedo_smoothness_beta=10.0)
    other = trained("other", depth_normal_start_iter=700, albedo_smoothness_beta=0.0)
    assert {"depth_normal_start_iter", "albedo_smoothness_beta"} <= base.pop("unused") == other.pop("unused")
    assert base.keys() == other.keys() and all(torch.equal(base[k], other[k]) for k in base)


def test_smoothness_waits_for_its_start_step_and_the_proximity_mask_can_be_off(sphere_scene, tmp_path, monkeypatch):
    spies = _spy_paths(monkeypatch)
    trainer = Trainer(
        Scene.load(sphere_scene), tmp_path / "run", _config(5, smoothness_start_iter=3, use_proximity_mask=False)
    )
    trainer.run(show_progress=False)
    assert len(spies["smoothness"].calls) == 2  # steps 3 and 4
    assert all(kwargs.get("proximity") is None for kwargs, _ in spies["smoothness"].calls)
    modes = [kwargs["render_mode"] for kwargs, grad in spies["render"].calls if grad]
    assert modes == ["RGB", "RGB", "RGB", "RGB+D", "RGB+D"]


def test_resume_continues_exactly_where_an_uninterrupted_run_would_be(sphere_scene, tmp_path, monkeypatch):
    config = _config(
        10,
        checkpoint_every=4,
        touch_rebuild_every=3,
        densify=DensifyStrategy(start_iter=2, refine_every=3, reset_every=5, stop_iter=100),
    )
    scene = Scene.load(sphere_scene)
    straight = Trainer(scene, tmp_path / "straight", config).run(show_progress=False)

    real_step = Trainer.train_step

    def killed_after_step_5(self):  # the process dies during step 6, after the checkpoint of step 4
        if self.step == 5:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(Trainer, "train_step", killed_after_step_5)
    with pytest.raises(KeyboardInterrupt):
        Trainer(scene, tmp_path / "resumed", config).run(show_progress=False)
    monkeypatch.setattr(Trainer, "train_step", real_step)
    resumed_trainer = Trainer(scene, tmp_path / "resumed", config)
    resumed = resumed_trainer.run(resume=True, show_progress=False)
    assert len(resumed) == len(straight)
    # Equal up to float summation order, compared through what a Gaussian is (mean, covariance, opacity,
    # colour): the rotation of a near-isotropic Gaussian has a ~1e-12 gradient whose sign follows the
    # summation order of torch's CPU reductions, and Adam (eps 1e-15) turns it into a full-size step.
    for name in ("means", "scales", "opacities", "sh0"):
        torch.testing.assert_close(resumed.params[name], straight.params[name], rtol=0, atol=1e-6)
    torch.testing.assert_close(_covariances(resumed), _covariances(straight), rtol=1e-4, atol=1e-12)
    assert torch.equal(resumed.from_touch, straight.from_touch)
    with (tmp_path / "resumed" / "progress.csv").open() as fh:
        assert [int(r["iteration"]) for r in csv.DictReader(fh)] == [0, 10]


def test_the_lit_appearance_learns_its_light_and_a_saved_run_evaluates_the_same(
    sphere_scene, tmp_path, monkeypatch, caplog
):
    """The sh-lit appearance shades from its start step on (the light gets gradients only then), the smooth albedo
    reaches the loss, and `evaluate` re-renders a finished run from its checkpoint, light included, to the same
    numbers; it replaces splat.ply only where it holds the unbaked Gaussians (a run from before the bake)."""
    from tacsplat.reconstruction.baking import bake_appearance
    from tacsplat.reconstruction.evaluation import evaluate_run
    from tacsplat.reconstruction.ply import save_ply
    from tacsplat.reconstruction.run_dir import load_run
    from tacsplat.reconstruction.shading import DiffuseLight

    smoothness = _Spy(losses.albedo_smoothness_loss)
    monkeypatch.setattr(losses, "albedo_smoothness_loss", smoothness)
    config = _config(30, appearance="sh-lit", lit_start_iter=20, lambda_albedo_smoothness=0.1, checkpoint_every=10)
    run = tmp_path / "run"
    trainer = Trainer(Scene.load(sphere_scene), run, config)
    trainer.initialize()
    for _ in range(20):
        trainer.train_step()
    start = DiffuseLight()
    assert torch.equal(trainer.light.coefficients.detach(), start.coefficients)  # not yet used: not yet moved
    assert len(smoothness.calls) == 20  # from the first step
    trainer.train_step()
    assert not torch.equal(trainer.light.coefficients.detach(), start.coefficients)
    metrics = reconstruct(sphere_scene, run, config, show_progress=False, overwrite=True)
    assert metrics["mechanisms"]["sh_lit"] and metrics["method"] == "custom"  # (no depth-normal before step 700)
    assert (run / "light.png").is_file()
    with (run / "progress.csv").open() as fh:  # the albedo smoothness has its own column
        assert float(list(csv.DictReader(fh))[-1]["albedo_smoothness"]) > 0
    again = evaluate_run(run)
    for key in ("psnr", "cd", "normal_error_deg", "psnr_splat"):
        assert again[key] == pytest.approx(metrics[key], rel=1e-6)
    # splat.ply holds the shading baked into plain SH (what a 3DGS viewer can show), not the unlit SH
    splat, final = load_ply(run / "splat.ply"), load_run(run)
    baked = bake_appearance(final.gaussians, final.look)
    assert splat.sh_degree == 3 and len(splat) == len(final.gaussians)
    torch.testing.assert_close(splat.sh_coefficients(), baked.sh_coefficients())
    # a splat.ply a user edited since (cut to 10 Gaussians in another program) stays as it is
    kept = slice(0, 10)
    cut = Gaussians({k: v[kept] for k, v in baked.params.items()}, baked.from_touch[kept], baked.sh_degree)
    save_ply(cut, run / "splat.ply")
    with caplog.at_level(logging.INFO, logger="tacsplat.reconstruction.evaluation"):
        evaluate_run(run)
    assert len(load_ply(run / "splat.ply")) == 10 and "before the bake" not in caplog.text
    # a run from before the bake (its splat.ply unlit) gets the baked one from evaluate, with one line saying so
    save_ply(final.gaussians, run / "splat.ply")
    with caplog.at_level(logging.INFO, logger="tacsplat.reconstruction.evaluation"):
        evaluate_run(run)
    torch.testing.assert_close(load_ply(run / "splat.ply").sh_coefficients(), baked.sh_coefficients())
    assert caplog.text.count("before the bake") == 1


def _covariances(g) -> torch.Tensor:
    R = quats_to_rotmats(g.quats.detach().double())
    return R @ torch.diag_embed(g.scales.detach().double() ** 2) @ R.transpose(-1, -2)


def test_cli_reconstruct_and_evaluate_with_a_mesh_as_ground_truth(sphere_scene, tmp_path, capsys):
    run = tmp_path / "run"
    code = tacsplat_main(
        [
            "reconstruct",
            str(sphere_scene),
            "--out",
            str(run),
            "--iterations",
            "5",
            "--sh-degree",
            "0",
            "--lambda-s",
            "0",
            "--backend",
            "cpu",
            "--quiet",
            "--train-views",
            "4",
        ]
    )
    assert code == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["method"] == "custom" and metrics["settings"]["train_views"] == 4  # the default, no L_S
    off = dict.fromkeys(("smoothness", "depth_normal", "sh_lit"), False)  # no L_S; the others start at 700 and 300
    assert metrics["mechanisms"] == {**dict.fromkeys(metrics["mechanisms"], True), **off}
    assert metrics["iterations"] == 5 and np.isfinite(metrics["cd"])
    mesh_path = tmp_path / "sphere.ply"
    trimesh.creation.icosphere(subdivisions=4, radius=RADIUS).export(mesh_path)
    capsys.readouterr()
    assert tacsplat_main(["evaluate", str(run), "--gt-mesh", str(mesh_path)]) == 0
    printed = json.loads(capsys.readouterr().out)
    again = json.loads((run / "metrics.json").read_text())
    assert again["gt_source"].startswith("mesh") and again["gt_radius"] == pytest.approx(RADIUS, rel=1e-3)
    assert printed["cd"] == pytest.approx(again["cd"])
    assert again["cd"] == pytest.approx(metrics["cd"], rel=0.2)  # mesh and analytic depth give the same surface
    # with a mesh, cd is also split where the run's training cameras (the 4 of --train-views) see the surface and
    # where none does; with the first of them alone, more is unseen
    assert 0 <= again["unseen_fraction"] < 0.5 and again["cd_seen"] > 0
    from tacsplat.reconstruction.run_dir import run_checkpoint

    checkpoint = torch.load(run_checkpoint(run), weights_only=False)
    checkpoint["config"]["train_views"] = 1
    torch.save(checkpoint, run_checkpoint(run))
    assert tacsplat_main(["evaluate", str(run), "--gt-mesh", str(mesh_path)]) == 0
    one_view = json.loads((run / "metrics.json").read_text())
    assert again["unseen_fraction"] < one_view["unseen_fraction"] < 1 and one_view["cd_unseen"] > 0
    cloud_path = tmp_path / "sphere_points.ply"
    trimesh.PointCloud(trimesh.creation.icosphere(subdivisions=5, radius=RADIUS).vertices).export(cloud_path)
    assert tacsplat_main(["evaluate", str(run), "--gt-mesh", str(cloud_path)]) == 0
    from_cloud = json.loads((run / "metrics.json").read_text())
    assert from_cloud["gt_source"].startswith("points") and np.isfinite(from_cloud["cd"])
    # a NaN point: one error naming the file and the point, exit 1 (it was a traceback from the radius's SVD)
    points = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS).vertices
    points[5] = np.nan
    trimesh.PointCloud(points).export(cloud_path)
    capsys.readouterr()
    assert tacsplat_main(["evaluate", str(run), "--gt-mesh", str(cloud_path)]) == 1
    assert capsys.readouterr().err == f"error: {cloud_path} [vertex 5]: coordinates [nan, nan, nan] are not finite\n"
    # a ground truth of zero extent (every vertex at one point): one error naming the file, and no numpy warning
    # before it (it divided by its radius of 0)
    trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False).export(mesh_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert tacsplat_main(["evaluate", str(run), "--gt-mesh", str(mesh_path)]) == 1
    assert not [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    one_point = "no extent: all its 3 vertices lie at [0.0, 0.0, 0.0], not on a surface"
    assert capsys.readouterr().err == f"error: {mesh_path}: {one_point}\n"


def _parse(*options, config=None):
    from tacsplat.reconstruction.command import parse

    return parse(["SCENE", "--out", "RUN", *options, *(["--config", str(config)] if config else [])]).train


def test_cli_options_reach_the_train_config_after_the_method_and_the_config_file(tmp_path):
    from tacsplat.errors import ConfigError, UsageError
    from tacsplat.reconstruction.config import PAPER_SCHEDULE

    config = _parse(
        "--seed",
        "3",
        "--sh-degree",
        "1",
        "--backend",
        "cpu",
        "--iterations",
        "7",
        "--lambda-s",
        "0.5",
        "--smoothness-depth",
        "accumulated",
        "--no-use-touch",
        "--densify.max-gaussians",
        "500",
        "--init.no-use-sfm",
        "--train-views",
        "None",
    )
    assert (config.seed, config.sh_degree, config.backend, config.iterations, config.lambda_s) == (3, 1, "cpu", 7, 0.5)
    assert (config.smoothness_depth, config.use_touch, config.densify.max_gaussians) == ("accumulated", False, 500)
    assert config.init.use_sfm is False and config.train_views is None and method_of(config) == "custom"
    assert _parse() == TrainConfig()  # no option given: exactly TrainConfig's defaults
    assert method_of(_parse("--method", "3dgs")) == "3dgs"
    assert method_of(_parse("--method", "3dgs", "--lambda-s", "1")) == "3dgs+s"  # the options after the method
    paper = _parse("--method", "paper", config=PAPER_SCHEDULE)  # the official schedule, as the YAML file cites it
    assert (paper.iterations, paper.smoothness_start_iter, paper.densify.stop_iter) == (30000, 20000, 15000)
    assert paper.touch_top_k == 20 and paper.use_proximity_mask is False and method_of(paper) == "paper"
    settings = tmp_path / "mine.yaml"
    settings.write_text("lambda_s: 1.5\ndensify:\n  max_gaussians: 900\n")
    mine = _parse("--method", "paper", "--lambda-s", "2.5", config=settings)  # method, then file, then options
    assert (mine.lambda_s, mine.densify.max_gaussians, method_of(mine)) == (2.5, 900, "paper")
    for options, words in (
        (["--iterations", "-5"], "--iterations: must be an integer >= 1, got -5"),
        (["--densify.max-gaussians", "-1"], "--densify.max-gaussians: must be an integer >= 0, got -1"),
        (["--iterations", "x"], "--iterations: invalid literal"),
        (["--method", "fancy"], "--method: unknown method 'fancy'"),
        (["--lambda-z", "1"], "--lambda-z: not an option of tacsplat reconstruct"),
    ):
        with pytest.raises(UsageError, match=words):
            _parse(*options)
    settings.write_text("lambda_z: 1\n")
    with pytest.raises(ConfigError, match=f"{settings}: lambda_z: not a training setting"):
        _parse(config=settings)
    with pytest.raises(ConfigError, match="smoothness_depth"):
        TrainConfig(smoothness_depth="median").validate()
    with pytest.raises(ConfigError, match="appearance"):
        TrainConfig(appearance="reflective").validate()


def test_reconstruct_help_fits_in_150_lines_and_every_setting_has_an_option(capsys):
    import dataclasses

    with pytest.raises(SystemExit) as stop:
        tacsplat_main(["reconstruct", "--help"])
    text = capsys.readouterr().out
    assert stop.value.code == 0 and len(text.splitlines()) <= 150
    for f in dataclasses.fields(TrainConfig):
        nested = getattr(TrainConfig(), f.name)
        names = (
            [f"{f.name}.{g.name}" for g in dataclasses.fields(nested)] if dataclasses.is_dataclass(nested) else [f.name]
        )
        for name in names:
            flag = f"--{name.replace('_', '-')}"
            assert f"{flag} " in text or f"{flag}, " in text, f"TrainConfig.{name} has no option"
