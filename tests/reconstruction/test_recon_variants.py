"""Which variant a config runs (the name metrics.json records): TrainConfig's defaults are the default variant,
the paper's rows switch every surface-normal loss off, and the normals variants need both of their losses on;
every variant's round trip is checked in tests/core/test_bench_report_writers.py."""

import dataclasses

import pytest

from tacsplat.errors import ConfigError
from tacsplat.reconstruction.config import TrainConfig, paper_departures
from tacsplat.reconstruction.initialization import InitConfig
from tacsplat.reconstruction.variants import DEFAULT_VARIANT, PAPER_VARIANTS, VARIANTS, get_variant, variant_of


def test_the_defaults_are_the_default_variant_and_the_papers_rows_have_no_normal_losses():
    assert variant_of(TrainConfig()) == DEFAULT_VARIANT == "full+n+tn+sl+as+vc"
    assert get_variant(DEFAULT_VARIANT).apply(TrainConfig()) == TrainConfig()  # the row is the defaults, exactly
    for name in PAPER_VARIANTS:
        config = get_variant(name).apply(TrainConfig())
        assert (config.lambda_flatten, config.lambda_depth_normal, config.lambda_touch_normal) == (0, 0, 0)
        assert (config.appearance, config.lambda_albedo_smoothness) == ("sh", 0)
    assert set(PAPER_VARIANTS) < set(VARIANTS)


def test_normals_need_both_losses():
    paper = get_variant("full").apply(TrainConfig())
    both = dataclasses.replace(paper, lambda_flatten=10.0, lambda_depth_normal=0.05)
    assert variant_of(both) == "full+n"
    sh_lit = dataclasses.replace(both, lambda_touch_normal=0.1, appearance="sh-lit", lambda_albedo_smoothness=0.1)
    assert variant_of(sh_lit) == "full+n+tn+sl+as"
    assert variant_of(dataclasses.replace(both, lambda_albedo_smoothness=0.1)) == "full+n"  # SH colour: no albedo
    only_flat = dataclasses.replace(paper, lambda_flatten=10.0)
    assert variant_of(only_flat) == "full+flat"  # not the paper's full method: named by what is on
    assert variant_of(dataclasses.replace(paper, lambda_depth_normal=0.05, lambda_touch_normal=0.1)) == "full+dn+tn"
    no_touch = dataclasses.replace(paper, use_touch=False, lambda_flatten=10.0, lambda_depth_normal=0.05,
                                   lambda_touch_normal=0.1)
    assert variant_of(no_touch) == "3dgs+s+n"  # tactile normals need touches: not named without them
    assert variant_of(dataclasses.replace(sh_lit, lambda_albedo_smoothness=0.0)) == "full+n+tn+sl"
    assert variant_of(get_variant("full").apply(TrainConfig(init=InitConfig(colours_from_views=True)))) == "full"
    assert variant_of(dataclasses.replace(sh_lit, init=InitConfig())) == "full+n+tn+sl+as+vc"


def test_a_variant_sets_its_init_fields_and_leaves_the_rest():
    config = TrainConfig(init=InitConfig(num_random_points=7))
    assert get_variant("full").apply(config) is config
    assert (config.init.colours_from_views, config.init.num_random_points, config.appearance) == (False, 7, "sh")


def test_a_run_config_written_before_the_lit_colour_existed_reads_as_what_it_trained():
    """config.json of a run from before ``appearance`` and ``lambda_albedo_smoothness`` existed: unlit SH colour, no
    smooth albedo (the defaults of its day), not today's defaults."""
    old = get_variant("full+n+tn").apply(TrainConfig()).to_json()
    del old["appearance"], old["lambda_albedo_smoothness"]
    config = TrainConfig.from_json(old)
    assert (config.appearance, config.lambda_albedo_smoothness, config.variant) == ("sh", 0.0, "full+n+tn")
    assert TrainConfig.from_json(TrainConfig().to_json()) == TrainConfig()  # a complete one reads as written
    sh_lit = TrainConfig().to_json()  # a default run from before the albedo smoothness had image weights
    del sh_lit["albedo_smoothness_beta"]
    assert TrainConfig.from_json(sh_lit) == TrainConfig(albedo_smoothness_beta=0.0)  # unweighted, as it trained
    paper = get_variant("full").apply(TrainConfig()).to_json()  # from before the surface-normal losses
    for name in ("lambda_flatten", "lambda_depth_normal", "lambda_touch_normal", "appearance",
                 "lambda_albedo_smoothness", "albedo_smoothness_beta"):
        del paper[name]
    assert TrainConfig.from_json(paper).variant == "full"
    before_view_colours = TrainConfig().to_json()  # a default run from before the initial colours from the views
    del before_view_colours["init"]["colours_from_views"]
    assert TrainConfig.from_json(before_view_colours).variant == "full+n+tn+sl+as"  # random colours, as it trained


def test_a_run_config_of_a_removed_mechanism_reads_when_it_was_off_and_is_refused_when_on():
    """config.json written before the reflective and lit appearances, plane depth and the touch-pixel normals were
    removed: their fields switched off read as today's config (the light's rate, once ``lr_env_map``, kept); a run
    that used one is refused naming the field and the file."""
    old = {**TrainConfig().to_json(), "depth_render": "centre", "plane_depth_start_iter": 700, "env_map_height": 16,
           "lambda_touch_normal_pixels": 0.0, "lr_reflective": 5e-3, "lr_env_map": 0.02}
    old.pop("lr_light")
    assert TrainConfig.from_json(old) == TrainConfig(lr_light=0.02)
    for field, value in (("depth_render", "plane"), ("lambda_touch_normal_pixels", 0.1), ("appearance", "lit"),
                         ("appearance", "reflective")):
        with pytest.raises(ConfigError, match=f"run/config.json: {field}: this run used .*reconstruct the scene again"):
            TrainConfig.from_json({**old, field: value}, "run/config.json")


def test_a_switched_off_mechanisms_settings_are_unused():
    assert TrainConfig().unused_fields() == set()  # the default uses every setting it has
    assert get_variant("full").apply(TrainConfig()).unused_fields() == {
        "depth_normal_start_iter", "albedo_smoothness_beta", "lambda_albedo_smoothness", "lit_start_iter"}
    assert "albedo_smoothness_beta" in TrainConfig(lambda_albedo_smoothness=0.0).unused_fields()


def test_colours_from_the_views_are_listed_among_the_departures_from_the_paper_only_when_on():
    assert [line for line in paper_departures(TrainConfig()) if "initial colours" in line]
    assert not [line for line in paper_departures(get_variant("full").apply(TrainConfig())) if "initial colours" in line]
