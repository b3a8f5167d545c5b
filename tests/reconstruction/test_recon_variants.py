"""The normals variant is recognised only with both of its losses on (the name metrics.json records);
every variant's round trip is checked in tests/core/test_bench_report_writers.py."""

import dataclasses

from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.variants import variant_of


def test_normals_need_both_losses():
    both = dataclasses.replace(TrainConfig(), lambda_flatten=10.0, lambda_depth_normal=0.05)
    assert variant_of(both) == "full+n"
    only_flat = dataclasses.replace(TrainConfig(), lambda_flatten=10.0)
    assert variant_of(only_flat) == "full"
    no_touch = dataclasses.replace(TrainConfig(), use_touch=False, lambda_flatten=10.0, lambda_depth_normal=0.05)
    assert variant_of(no_touch) == "3dgs+s"
