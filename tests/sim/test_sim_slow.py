"""Longer simulator runs (marked slow: `make bench-quick` runs the quick one)."""



import json  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import trimesh  # noqa: E402

from tacsplat.apps.bench_sim import run_bench  # noqa: E402
from tacsplat.sim.grasps import DEFAULT_PENETRATION_BOUND_M, generate_grasps  # noqa: E402
from tacsplat.sim.objects import OBJECT_NAMES  # noqa: E402
from tacsplat.sim.twin import SimTwin, TwinConfig  # noqa: E402


@pytest.mark.slow
def test_bench_sim_quick(tmp_path):
    report = run_bench(tmp_path, quick=True)
    data = json.loads((tmp_path / "sim.json").read_text())
    assert (tmp_path / "sim.png").stat().st_size > 0 and "Penetration" in report
    plane = [r for r in data["tactile"] if r["surface"] == "plane"]
    assert all(r["max_depth_error_um"] < 0.01 for r in plane)
    sphere = [r for r in data["tactile"] if r["surface"] == "sphere"]
    assert all(r["max_depth_error_um"] < 1.0 for r in sphere)
    assert all(r["max_penetration_mm"] < 1.0 for r in data["physics"])


@pytest.mark.slow
@pytest.mark.parametrize("name", OBJECT_NAMES)
def test_many_grasps_touch_the_surface(name):
    with SimTwin(TwinConfig(object=name)) as twin:
        grasps = generate_grasps(twin, 8, seed=11)
        assert len(grasps) == 8
        points = np.concatenate([r.contact_points() for g in grasps for r in g.readings.values() if r.in_contact])
        _, distance, _ = trimesh.proximity.closest_point(twin.object_mesh, points)
        assert distance.mean() < 3e-4 and distance.max() < 1e-3
        assert max(g.max_penetration_m for g in grasps) < DEFAULT_PENETRATION_BOUND_M
