"""The methods by name: TrainConfig's defaults are ``default``, the paper's rows switch every mechanism beyond the
paper off, a run's metrics name the method whose mechanisms it has (``custom`` for any other combination), and
old run configs read as what they trained."""

import dataclasses

import pytest

from tacsplat.errors import ConfigError
from tacsplat.reconstruction.config import TrainConfig, paper_departures, removed_losses, set_fields
from tacsplat.reconstruction.initialization import InitConfig
from tacsplat.reconstruction.methods import (
    DEFAULT_METHOD,
    METHODS,
    PAPER_METHODS,
    mechanisms,
    method_config,
    method_of,
)


def test_the_defaults_are_the_default_method_and_the_papers_rows_have_nothing_beyond_the_paper():
    assert method_config(DEFAULT_METHOD) == TrainConfig() and method_of(TrainConfig()) == "default"
    assert set(METHODS) == {"3dgs", "3dgs+s", "3dgs+t", "paper", "default"}
    table_3 = {"3dgs": (False, False), "3dgs+s": (False, True), "3dgs+t": (True, False), "paper": (True, True)}
    assert tuple(table_3) == PAPER_METHODS
    for name, (touch, smoothness) in table_3.items():
        on = mechanisms(method_config(name))
        assert (on.pop("touch"), on.pop("smoothness")) == (touch, smoothness) and not any(on.values()), name
        assert method_of(method_config(name)) == name
    assert all(mechanisms(TrainConfig()).values())  # the default has every mechanism on


def test_any_other_combination_is_custom_and_names_no_method():
    paper = method_config("paper")
    assert method_of(dataclasses.replace(paper, lambda_flatten=10.0)) == "custom"
    assert method_of(dataclasses.replace(TrainConfig(), use_touch=False)) == "custom"
    assert method_of(dataclasses.replace(paper, lambda_s=5.8, touch_top_k=20)) == "paper"  # other weights: same method
    assert method_of(dataclasses.replace(paper, use_touch=False)) == "3dgs+s"


def test_set_fields_sets_nested_fields_and_names_an_unknown_key():
    config = set_fields(TrainConfig(init=InitConfig(num_random_points=7)), {"lambda_s": 0.0, "init.use_sfm": False})
    assert (config.lambda_s, config.init.use_sfm, config.init.num_random_points) == (0.0, False, 7)
    assert set_fields(TrainConfig(), {"background": [1, 1, 1]}).background == (1, 1, 1)  # YAML lists: tuples
    for key in ("lambda_z", "init.nothing", "densify.max_gaussians.x"):
        with pytest.raises(ConfigError, match=f"rows.yaml: {key}: not a training setting"):
            set_fields(TrainConfig(), {key: 1}, "rows.yaml")


def test_a_run_config_written_before_the_lit_color_existed_reads_as_what_it_trained():
    """config.json of a run from before ``appearance`` and ``lambda_albedo_smoothness`` existed: unlit SH colour, no
    smooth albedo (the defaults of its day), not today's defaults."""
    old = TrainConfig().to_json()
    del old["appearance"], old["lambda_albedo_smoothness"]
    config = TrainConfig.from_json(old)
    assert (config.appearance, config.lambda_albedo_smoothness) == ("sh", 0.0)
    assert TrainConfig.from_json(TrainConfig().to_json()) == TrainConfig()  # a complete one reads as written
    sh_lit = TrainConfig().to_json()  # a default run from before the albedo smoothness had image weights
    del sh_lit["albedo_smoothness_beta"]
    assert TrainConfig.from_json(sh_lit) == TrainConfig(albedo_smoothness_beta=0.0)  # unweighted, as it trained
    paper = method_config("paper").to_json()  # from before the surface-normal losses
    for name in (
        "lambda_flatten",
        "lambda_depth_normal",
        "appearance",
        "lambda_albedo_smoothness",
        "albedo_smoothness_beta",
    ):
        del paper[name]
    assert method_of(TrainConfig.from_json(paper)) == "paper"
    before_view_colors = TrainConfig().to_json()  # a default run from before the initial colours from the views
    del before_view_colors["init"]["colors_from_views"]
    assert not TrainConfig.from_json(before_view_colors).init.colors_from_views  # random colours, as it trained
    british = TrainConfig(init=InitConfig(colors_from_views=False)).to_json()  # the field's name until 2026-11-28
    british["init"]["colours_from_views"] = british["init"].pop("colors_from_views")
    assert TrainConfig.from_json(british) == TrainConfig(init=InitConfig(colors_from_views=False))


def test_a_run_config_of_a_removed_mechanism_reads_when_it_was_off_and_is_refused_when_on():
    """config.json written before the reflective and lit appearances, plane depth, the touch-pixel normals and the
    pads' free space were removed: their fields switched off read as today's config (the light's rate, once
    ``lr_env_map``, kept); a run that used one is refused naming the field and the file."""
    old = {
        **TrainConfig().to_json(),
        "depth_render": "centre",
        "plane_depth_start_iter": 700,
        "env_map_height": 16,
        "lambda_touch_normal_pixels": 0.0,
        "lambda_pad_free": 0.0,
        "pad_free_margin": 0.001,
        "lr_reflective": 5e-3,
        "lr_env_map": 0.02,
    }
    old.pop("lr_light")
    assert TrainConfig.from_json(old) == TrainConfig(lr_light=0.02)
    for field, value in (
        ("depth_render", "plane"),
        ("lambda_touch_normal_pixels", 0.1),
        ("lambda_pad_free", 2.0),
        ("appearance", "lit"),
        ("appearance", "reflective"),
    ):
        with pytest.raises(ConfigError, match=f"run/config.json: {field}: this run used .*reconstruct the scene again"):
            TrainConfig.from_json({**old, field: value}, "run/config.json")


def test_a_switched_off_mechanisms_settings_are_unused():
    assert TrainConfig().unused_fields() == {"coarse_until"}  # every setting but the unused schedule's
    assert TrainConfig(coarse_factors=(2,)).unused_fields() == set()
    assert method_config("paper").unused_fields() == {
        "depth_normal_start_iter",
        "albedo_smoothness_beta",
        "lambda_albedo_smoothness",
        "lit_start_iter",
        "coarse_until",
    }
    assert "albedo_smoothness_beta" in TrainConfig(lambda_albedo_smoothness=0.0).unused_fields()


def test_colors_from_the_views_are_listed_among_the_departures_from_the_paper_only_when_on():
    assert [line for line in paper_departures(TrainConfig()) if "initial colours" in line]
    assert not [line for line in paper_departures(method_config("paper")) if "initial colours" in line]


@pytest.mark.parametrize("weight", [0.1, 0.0])
def test_a_run_config_of_the_removed_tactile_normal_loss_reads_as_todays_and_resumes_only_without_it(weight):
    """config.json of a run from before the tactile-normal loss was removed (the default's weight was 0.1): the loss
    shaped the Gaussians but not how they render, so the config reads as today's (to evaluate, view or export the
    run); resuming a run that trained with it is refused naming the field, one with it off resumes."""
    old = {**TrainConfig().to_json(), "lambda_touch_normal": weight}
    assert TrainConfig.from_json(old, "run/config.json") == TrainConfig()
    assert removed_losses(old) == ({"lambda_touch_normal": weight} if weight else {})
    if weight:
        match = (
            "run/config.json: lambda_touch_normal: this run trained with the tactile-normal loss, removed "
            r"\(no gain on held-out meshes: docs/experiments.md\); reconstruct the scene again"
        )
        with pytest.raises(ConfigError, match=match):
            TrainConfig.from_json(old, "run/config.json", resuming=True)
    else:
        assert TrainConfig.from_json(old, "run/config.json", resuming=True) == TrainConfig()


def test_a_settings_file_for_more_steps_than_run_is_told_which_mechanisms_never_start(caplog):
    """paper_schedule.yaml's step numbers are for its 30000 steps: run for 1200, its smoothness (from step 20000)
    never starts, and the command says so rather than training another method without a word."""
    from tacsplat.reconstruction.command import parse
    from tacsplat.reconstruction.config import PAPER_SCHEDULE, read_settings

    config = set_fields(method_config("paper"), read_settings(PAPER_SCHEDULE))
    config.iterations = 1200
    assert config.never_started() == ["smoothness_start_iter 20000"]  # (densification starts at 500, in time)
    assert method_config("paper").never_started() == [] and TrainConfig().never_started() == []
    short = TrainConfig(iterations=500)  # the default's depth-normal consistency starts at 700, its light at 300
    assert short.never_started() == ["depth_normal_start_iter 700"]
    parse(["S", "--out", "R", "--method", "paper", "--config", str(PAPER_SCHEDULE), "--iterations", "1200"])
    assert f"{PAPER_SCHEDULE} sets smoothness_start_iter 20000: at or past --iterations 1200, never reached" in (
        caplog.text
    )
    caplog.clear()
    parse(["S", "--out", "R", "--iterations", "500"])  # the method's own start steps: as its fields document
    parse(["S", "--out", "R", "--method", "paper", "--config", str(PAPER_SCHEDULE)])
    assert "never reached" not in caplog.text


@pytest.mark.filterwarnings("ignore:.*but the default value")  # tyro's, on the file's value refused
def test_a_config_files_bad_value_names_the_file_and_key_and_an_options_names_the_option(tmp_path):
    """A value the --config file gives is the file's error (exit 1, like its unknown keys), never an option's the
    user did not type; a value an option gives keeps naming the option (a usage error); an option replaces the
    file's bad value."""
    from tacsplat.errors import UsageError
    from tacsplat.reconstruction.command import parse

    settings = tmp_path / "mine.yaml"
    for text, words in (
        ("lambda_s: -1", "lambda_s: must be a finite number >= 0, got -1"),
        ("densify:\n  max_gaussians: -5", "densify.max_gaussians: must be an integer >= 0, got -5"),
        ("lambda_s: .nan", "lambda_s: must be a finite number >= 0, got nan"),
        ("iterations: true", "iterations: must be an integer >= 1, got True"),  # (a bool is no number)
        ("use_touch: 'no'", "use_touch: must be true or false"),
        ("init: 5", "init: must be a mapping of init.x settings"),
    ):
        settings.write_text(text + "\n")
        with pytest.raises(ConfigError) as refused:
            parse(["S", "--out", "R", "--config", str(settings)])
        assert type(refused.value) is ConfigError and str(refused.value) == f"{settings}: {words}" + (
            str(refused.value).removeprefix(f"{settings}: {words}")
        )
        assert "--" not in str(refused.value), str(refused.value)
    settings.write_text("lambda_s: -1\n")
    assert parse(["S", "--out", "R", "--config", str(settings), "--lambda-s", "2"]).train.lambda_s == 2.0
    settings.write_text("lambda_s: 1.5\n")
    with pytest.raises(UsageError, match="^--lambda-s: must be a finite number >= 0, got -1"):
        parse(["S", "--out", "R", "--config", str(settings), "--lambda-s", "-1"])


@pytest.mark.filterwarnings("ignore:.*but the default value")  # tyro's, on the file's value refused
def test_a_config_files_numbers_in_exponent_form_are_numbers(tmp_path):
    """PyYAML reads 1e-3 (no dot) as a string: a number field takes the number it spells; an int field a whole
    one (1e3 is 1000), a float field an int; a string that is no finite number is still refused."""
    from tacsplat.reconstruction.command import parse

    settings = tmp_path / "mine.yaml"
    settings.write_text("lambda_s: 1e-3\niterations: 1e3\nlambda_t: 2\ninit:\n  touch_voxel_size: 5E-4\n")
    config = parse(["S", "--out", "R", "--config", str(settings)]).train
    assert (config.lambda_s, config.iterations, config.lambda_t, config.init.touch_voxel_size) == (1e-3, 1000, 2, 5e-4)
    assert type(config.iterations) is int and type(config.lambda_s) is float
    for text, words in (("seed: 1.5e0", "seed: must be an integer"), ("lambda_s: 1e999", "lambda_s: must be a finite")):
        settings.write_text(text + "\n")
        with pytest.raises(ConfigError, match=f"{settings}: {words}"):
            parse(["S", "--out", "R", "--config", str(settings)])


def test_a_config_file_of_only_comments_sets_nothing_and_a_list_is_refused(tmp_path):
    from tacsplat.reconstruction.command import parse

    settings = tmp_path / "mine.yaml"
    settings.write_text("# nothing changed yet\n")
    assert parse(["S", "--out", "R", "--config", str(settings)]).train == parse(["S", "--out", "R"]).train
    settings.write_text("- lambda_s: 1\n")
    with pytest.raises(ConfigError, match=f"{settings}: settings: expected a mapping of training settings, got list"):
        parse(["S", "--out", "R", "--config", str(settings)])


def test_a_run_without_touch_points_records_touch_off_and_its_method_as_trained(tmp_path, capsys):
    """3dgs+t (or paper) on a scene with no touches trains without touch: the trainer says so once, and
    metrics.json records the mechanisms used (touch off) and the method they make (3dgs+t: 3dgs), from the trainer
    and from `evaluate` alike; the same method on a scene with touches records touch."""
    import json
    import sys
    from pathlib import Path

    from tacsplat.cli import main
    from tacsplat.reconstruction.evaluation import evaluate_run

    sys.path.insert(0, str(Path(__file__).parent))
    from recon_synthetic import build_sphere_scene

    scenes = {
        t: build_sphere_scene(tmp_path / f"scene-{t}", size=24, train_views=3, test_views=1, touches=t)
        for t in (False, True)
    }
    fast = ["--iterations", "2", "--sh-degree", "0", "--backend", "cpu", "--init.no-use-sfm", "--quiet"]
    for touches, method, recorded in (
        (False, "3dgs+t", "3dgs"),
        (False, "paper", "3dgs+s"),
        (True, "3dgs+t", "3dgs+t"),
    ):
        run = tmp_path / f"run-{touches}-{method}"
        capsys.readouterr()
        assert main(["reconstruct", str(scenes[touches]), "--out", str(run), "--method", method, *fast]) == 0
        warned = [line for line in capsys.readouterr().err.splitlines() if "no touches" in line]
        expected = (
            f"the scene {scenes[touches]} has no touches (no contact points): touch is off for this run, "
            f"recorded as method {recorded}"
        )
        assert warned == ([] if touches else [f"WARNING tacsplat.reconstruction.trainer: {expected}"]), warned
        metrics = json.loads((run / "metrics.json").read_text())
        assert (metrics["method"], metrics["mechanisms"]["touch"]) == (recorded, touches), method
        assert (metrics["settings"]["use_touch"], metrics["settings"]["lambda_t"] > 0) == (True, True)  # as given
        again = evaluate_run(run)
        assert (again["method"], again["mechanisms"]["touch"]) == (recorded, touches), method
    assert mechanisms(method_config("3dgs+t"), touched=False) == mechanisms(method_config("3dgs"))
    assert method_of(TrainConfig(), touched=False) == "custom"
