"""The base install (no extra) alone: a fresh venv with torch and `pip install tacsplat`, which reconstructs a
small scene, and whose commands that need an extra name it. Slow: a real install (minutes)."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
EXTRA_MODULES = ("mujoco", "coacd", "manifold3d", "dynamixel_sdk", "serial", "viser", "ray", "gsplat")

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]


def _run(*argv, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=1500)
    assert not check or done.returncode == 0, done.stderr[-3000:]
    return done


def test_the_base_install_reconstructs_a_scene_and_names_the_extras_it_lacks(tmp_path):
    venv = tmp_path / "base"
    _run(sys.executable, "-m", "venv", venv)
    python, tacsplat = venv / "bin" / "python", venv / "bin" / "tacsplat"
    _run(python, "-m", "pip", "install", "--quiet", f"torch=={torch.__version__.split('+')[0]}")  # (pip's cache)
    source = tmp_path / "source"  # (pip builds in the tree it installs: a copy keeps build/ out of this one)
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".*", "build", "*.egg-info", "__pycache__", "*-output"))
    _run(python, "-m", "pip", "install", "--quiet", source)
    found = _run(python, "-c", f"import importlib.util as u; print([m for m in {EXTRA_MODULES!r} if u.find_spec(m)])")
    assert found.stdout.strip() == "[]"  # no extra came with it
    scene, run = tmp_path / "scene", tmp_path / "run"
    _run(
        sys.executable,
        "-m",
        "tacsplat",
        "sim-capture",
        "--resolution",
        "32",
        "--views",
        "2",
        "--test-views",
        "1",
        "--grasps",
        "1",
        "--out",
        scene,
        "--quiet",
    )  # (the full install's twin writes it)
    _run(
        tacsplat,
        "reconstruct",
        scene,
        "--out",
        run,
        "--iterations",
        "5",
        "--backend",
        "cpu",
        "--init.no-use-sfm",
        "--quiet",
    )
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["iterations"] == 5 and metrics["num_gaussians"] > 0 and (run / "splat.ply").is_file()
    missing = _run(tacsplat, "sim-capture", "--out", tmp_path / "twin", check=False)
    assert missing.returncode == 1 and missing.stderr.strip() == (
        "error: tacsplat sim-capture needs the sim extra (mujoco is not installed): pip install 'tacsplat[sim]'"
    )
