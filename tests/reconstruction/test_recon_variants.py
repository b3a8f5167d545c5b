"""Which variant a config runs (the name metrics.json records): TrainConfig's defaults are the default variant,
the paper's rows switch every surface-normal loss off, and the normals variants need both of their losses on;
every variant's round trip is checked in tests/core/test_bench_report_writers.py."""

import dataclasses

from tacsplat.reconstruction.config import TrainConfig, paper_departures
from tacsplat.reconstruction.variants import DEFAULT_VARIANT, PAPER_VARIANTS, VARIANTS, get_variant, variant_of


def test_the_defaults_are_the_default_variant_and_the_papers_rows_have_no_normal_losses():
    assert variant_of(TrainConfig()) == DEFAULT_VARIANT == "full+n+tn+sl+as"
    assert TrainConfig(**get_variant(DEFAULT_VARIANT).overrides) == TrainConfig()  # the row is the defaults, exactly
    for name in PAPER_VARIANTS:
        config = TrainConfig(**get_variant(name).overrides)
        assert (config.lambda_flatten, config.lambda_depth_normal, config.lambda_touch_normal) == (0, 0, 0)
        assert (config.appearance, config.lambda_albedo_smoothness) == ("sh", 0)
    assert set(PAPER_VARIANTS) < set(VARIANTS)


def test_normals_need_both_losses():
    paper = TrainConfig(**get_variant("full").overrides)
    both = dataclasses.replace(paper, lambda_flatten=10.0, lambda_depth_normal=0.05)
    assert variant_of(both) == "full+n"
    assert variant_of(dataclasses.replace(both, lambda_touch_normal=0.1, appearance="reflective")) == "full+n+tn+r"
    lit = dataclasses.replace(both, lambda_touch_normal=0.1, appearance="lit")
    assert variant_of(lit) == "full+n+tn+l"
    assert variant_of(dataclasses.replace(lit, lambda_albedo_smoothness=0.1)) == "full+n+tn+l+as"
    sh_lit = dataclasses.replace(both, lambda_touch_normal=0.1, appearance="sh-lit", lambda_albedo_smoothness=0.1)
    assert variant_of(sh_lit) == "full+n+tn+sl+as"
    assert variant_of(dataclasses.replace(both, lambda_albedo_smoothness=0.1)) == "full+n"  # SH colour: no albedo
    only_flat = dataclasses.replace(paper, lambda_flatten=10.0)
    assert variant_of(only_flat) == "full+flat"  # not the paper's full method: named by what is on
    assert variant_of(dataclasses.replace(paper, lambda_depth_normal=0.05, lambda_touch_normal=0.1)) == "full+dn+tn"
    no_touch = dataclasses.replace(paper, use_touch=False, lambda_flatten=10.0, lambda_depth_normal=0.05,
                                   lambda_touch_normal=0.1)
    assert variant_of(no_touch) == "3dgs+s+n"  # tactile normals need touches: not named without them
    pixels = dataclasses.replace(both, lambda_touch_normal=0.1, lambda_touch_normal_pixels=0.1)
    assert variant_of(pixels) == "full+n+tn+tnp"
    assert variant_of(dataclasses.replace(pixels, lambda_depth_normal=0.0)) == "full+flat+tn"  # no rendered normals


def test_a_run_config_written_before_the_lit_colour_existed_reads_as_what_it_trained():
    """config.json of a run from before ``appearance`` and ``lambda_albedo_smoothness`` existed: unlit SH colour, no
    smooth albedo (the defaults of its day), not today's defaults."""
    old = TrainConfig(**get_variant("full+n+tn").overrides).to_json()
    del old["appearance"], old["lambda_albedo_smoothness"]
    config = TrainConfig.from_json(old)
    assert (config.appearance, config.lambda_albedo_smoothness, config.variant) == ("sh", 0.0, "full+n+tn")
    assert TrainConfig.from_json(TrainConfig().to_json()) == TrainConfig()  # a complete one reads as written
    sh_lit = TrainConfig().to_json()  # a default run from before the albedo smoothness had image weights
    del sh_lit["albedo_smoothness_beta"]
    assert TrainConfig.from_json(sh_lit) == TrainConfig(albedo_smoothness_beta=0.0)  # unweighted, as it trained
    paper = TrainConfig(**get_variant("full").overrides).to_json()  # from before the surface-normal losses
    for name in ("lambda_flatten", "lambda_depth_normal", "lambda_touch_normal", "appearance",
                 "lambda_albedo_smoothness", "albedo_smoothness_beta"):
        del paper[name]
    assert TrainConfig.from_json(paper).variant == "full"


def test_a_switched_off_mechanisms_settings_are_unused():
    # sh-lit: no environment map; centre depth: no plane depth to start
    assert TrainConfig().unused_fields() == {"env_map_height", "plane_depth_start_iter"}
    assert TrainConfig(**get_variant("full").overrides).unused_fields() == {
        "depth_normal_start_iter", "albedo_smoothness_beta", "lambda_albedo_smoothness", "lit_start_iter",
        "env_map_height", "plane_depth_start_iter"}
    assert TrainConfig(appearance="reflective").unused_fields() == {"lit_start_iter", "plane_depth_start_iter"}
    plane = TrainConfig(**get_variant("full+n+tn+sl+as+pd").overrides)
    assert plane.unused_fields() == {"env_map_height"} and plane.variant == "full+n+tn+sl+as+pd"
    assert "albedo_smoothness_beta" in TrainConfig(lambda_albedo_smoothness=0.0).unused_fields()


def test_plane_depth_is_listed_among_the_departures_from_the_paper_only_when_on():
    plane = TrainConfig(**get_variant("full+n+tn+sl+as+pd").overrides)
    assert [line for line in paper_departures(plane) if "blended plane" in line]
    assert not [line for line in paper_departures(TrainConfig()) if "blended plane" in line]
