"""DESIGN.md: hardware SDKs only in drivers/, MuJoCo only in sim/."""

import subprocess
import sys

HEAVY = ["mujoco", "dynamixel_sdk", "serial"]


def test_reconstruction_and_datasets_load_no_hardware_or_simulator():
    code = (
        "import sys, tacsplat.reconstruction, tacsplat.datasets, tacsplat.drivers, tacsplat.cli\n"
        "import pkgutil, importlib\n"
        "for pkg in (tacsplat.reconstruction, tacsplat.datasets):\n"
        "    for m in pkgutil.iter_modules(pkg.__path__):\n"
        "        importlib.import_module(pkg.__name__ + '.' + m.name)\n"
        f"print([m for m in {HEAVY!r} if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_sim_and_drivers_never_import_reconstruction():
    code = (
        "import sys, pkgutil, importlib, tacsplat.sim, tacsplat.drivers\n"
        "for pkg in (tacsplat.sim, tacsplat.drivers):\n"
        "    for m in pkgutil.iter_modules(pkg.__path__):\n"
        "        importlib.import_module(pkg.__name__ + '.' + m.name)\n"
        "print(sorted(m for m in sys.modules if m.startswith('tacsplat.reconstruction')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_importing_datasets_loads_no_opencv_pycolmap_or_torch():
    # OpenCV (which also prepends to LD_LIBRARY_PATH) is imported where an image is read or written
    code = "import sys, tacsplat.datasets; print(sorted(m for m in ('cv2', 'pycolmap', 'torch') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
