"""The variants table: each variant's overrides give back its own name (the name metrics.json records)."""

import dataclasses

import pytest

from tacsplat.errors import ConfigError
from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.variants import VARIANTS, get_variant, variant_of


@pytest.mark.parametrize("name", list(VARIANTS))
def test_overrides_round_trip(name):
    config = dataclasses.replace(TrainConfig(), **get_variant(name).overrides)
    assert variant_of(config) == name


def test_normals_need_both_losses():
    only_flat = dataclasses.replace(TrainConfig(), lambda_flatten=10.0)
    assert variant_of(only_flat) == "full"
    no_touch = dataclasses.replace(TrainConfig(), use_touch=False, lambda_flatten=10.0, lambda_depth_normal=0.05)
    assert variant_of(no_touch) == "3dgs+s"


def test_unknown_variant_names_the_option():
    with pytest.raises(ConfigError, match="--variant.*full\\+n"):
        get_variant("fancy", "--variant")
