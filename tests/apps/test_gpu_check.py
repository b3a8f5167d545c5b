"""`make gpu-check`'s CPU side: without CUDA it says so in one line and exits 0; with `--device cpu` the whole
device path runs here (this tree linked into a site folder, `tacsplat bench gpu` from there, the parity runs
written by `--prepare`), so that only CUDA itself is left for the device."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tacsplat.apps.bench_gpu import gpu_table, parity_verdict, source_hash
from tacsplat.cli import main

ROOT = Path(__file__).resolve().parents[2]
TINY = ["--resolution", "32", "--views", "3", "--test-views", "1", "--grasps", "1"]

pytestmark = pytest.mark.timeout(600)


def _make(*variables: str) -> subprocess.CompletedProcess:
    return subprocess.run(["make", "-s", "-C", str(ROOT), "gpu-check", *variables], capture_output=True, text=True)


def test_without_cuda_the_check_says_so_in_one_line_and_exits_0(tmp_path):
    done = _make(f"GPU_PYTHON={sys.executable}", f"GPU_OUT={tmp_path / 'out'}")
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        f"gpu-check: skipped: {sys.executable} here has no CUDA device (or no torch); nothing was measured"
    ]
    assert not (tmp_path / "out").exists()


def test_the_device_path_runs_on_the_cpu_and_writes_two_files(tmp_path, capsys):
    parity = tmp_path / "parity"
    prepare = ["bench", "gpu", "--prepare", str(parity), "--parity-steps", "3", "--parity-seeds", "0"]
    assert main([*prepare, "--parity-resolution", "32", "--grasps", "1"]) == 0
    cpu = json.loads((parity / "cpu.json").read_text())
    assert cpu["source"] == source_hash() and [r["seed"] for r in cpu["runs"]] == [0]

    args = " ".join(["--device cpu --steps 3 --methods 3dgs", *TINY])
    site, out = tmp_path / "site", tmp_path / "out"
    done = _make(
        f"GPU_PYTHON={sys.executable}",
        f"GPU_PARITY={parity}",
        f"GPU_OUT={out}",
        f"GPU_SITE={site}",
        f"GPU_WHEEL_DIR={tmp_path / 'no-wheels'}",  # (the device's wheels are for its Python)
        f"GPU_ARGS={args}",
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert sorted(p.name for p in out.iterdir()) == ["gpu.json", "gpu.md"]  # the device returns 8 files at most
    report = json.loads((out / "gpu.json").read_text())
    assert Path(report["scene"]["path"]).is_relative_to(f"{site}-work")  # the capture and runs stay out of --out
    (run,) = report["runs"]
    assert run["method"] == "3dgs" and run["steps"] == 3 and run["projected_30k_minutes"] > 0
    (device_run,) = report["parity"]["device_runs"]
    assert device_run["cd"] == cpu["runs"][0]["cd"]  # the same code on the same CPU: the same run
    table = (out / "gpu.md").read_text()
    assert "| 3dgs | 3 |" in table and "| cd |" in table and "| yes |" in table and "| NO |" not in table


def test_parity_is_the_device_mean_within_the_cpu_range_and_a_bad_folder_is_named(tmp_path, capsys):
    assert parity_verdict([1.0, 2.0, 3.0], [2.5, 3.5]) == (2.0, 2.0, 3.0, True)
    assert parity_verdict([1.0, 2.0], [2.5])[3] is False
    assert main(["bench", "gpu", "--device", "cpu", "--parity", str(tmp_path), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert "--parity" in err and "cpu.json" in err and "bench gpu --prepare" in err


def test_a_failed_run_is_a_row_of_the_table_and_the_others_stay():
    device = {"name": "GPU", "torch": "2.11", "cuda": "13.0", "gsplat": "1.5.3"}
    scene = {"train_views": 100, "test_views": 24, "touches": 20, "resolution": "800x800"}
    row = {
        "method": "paper",
        "steps": 1000,
        "seconds_per_1k_steps": 30.0,
        "projected_30k_minutes": 15.0,
        "peak_gpu_memory_gib": 3.5,
        "num_gaussians": 90000,
        "cd": 0.03,
        "psnr": 27.0,
    }
    cpu = {"method": "default", "steps": 1500, "seeds": [0, 1], "source": "x", "runs": [{"cd": 0.1, "psnr": 25.0}] * 2}
    parity = {
        "cpu": cpu,
        "device_runs": [
            {"method": "default", "seed": 0, "error": "RuntimeError: out of memory"},
            {"method": "default", "seed": 1, "cd": 0.1, "psnr": 25.0},
        ],
    }
    report = {
        "device": device,
        "scene": scene,
        "capture_seconds": 40.0,
        "source": "x",
        "wall_seconds": 250.0,
        "parity": parity,
        "runs": [{"method": "default", "seed": 0, "error": "RuntimeError: CUDA error"}, row],
    }
    table = gpu_table(report)
    assert (
        "| default | failed: RuntimeError: CUDA error |" in table and "| paper | 1000 | 30.0 | 15.0 | 3.50 |" in table
    )
    assert "| cd | 0.1000 | 0.0000 | 0.1000 | yes |" in table
    assert table.rstrip().endswith("Parity run of seed 0 failed: RuntimeError: out of memory")
