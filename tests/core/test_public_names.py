"""The public names resolve from the package roots, and each root loads only what its names need when used."""

import subprocess
import sys


def _run(code: str) -> str:
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_importing_the_roots_loads_no_torch_and_no_hardware_sdk():
    loaded = _run(
        "import sys, tacsplat.reconstruction, tacsplat.drivers; "
        "print(sorted(m for m in ('torch', 'numba', 'dynamixel_sdk', 'mujoco') if m in sys.modules))"
    )
    assert loaded == "[]"


def test_every_public_name_resolves_to_its_definition():
    code = """
import tacsplat.drivers as drivers, tacsplat.reconstruction as reconstruction
from tacsplat.reconstruction import rasterization, reconstruct, TrainConfig
from tacsplat.drivers import DynamixelHand
from tacsplat.reconstruction.raster.rendering import rasterization as defined
assert rasterization is defined and TrainConfig().iterations > 0 and DynamixelHand.__module__.endswith("dynamixel_hand")
for package in (drivers, reconstruction):
    for name in package.__all__:
        assert getattr(getattr(package, name), "__name__", name) == name, name  # (METHODS is a dict)
    assert set(package.__all__) <= set(dir(package))
try:
    from tacsplat.reconstruction import no_such_name
except ImportError as exc:
    print(exc)
"""
    assert "cannot import name 'no_such_name'" in _run(code)
