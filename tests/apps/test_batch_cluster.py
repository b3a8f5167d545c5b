"""`tacsplat batch --executor ray --ray-address` on a separate local cluster of 2 CPUs (`ray start --head` on a
free port, started here and stopped at the end): the tiny batch (a capture, two reconstructions at 32 px, 10
steps) gives the local executor's results.csv value for value."""

from __future__ import annotations

import csv
import math
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from tacsplat.cli import main

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders

from batch_test_jobs import wait_until  # noqa: E402

RAY = Path(sys.executable).parent / "ray"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture(scope="module")
def ray_env() -> dict:
    """The environment of the cluster and of its driver: token authentication with a token made here (as on a
    real cluster), every address on the loopback interface (Ray's switch for single-machine clusters)."""
    return {
        **os.environ,
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN": secrets.token_hex(16),
        "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
    }


@pytest.fixture(scope="module")
def cluster(ray_env):
    """``host:port`` of a head node with 2 CPUs, in its own session and temp dir (only its processes are stopped)."""
    port = free_port()
    temp = Path(tempfile.mkdtemp(prefix="ray-", dir="/tmp"))  # short: Ray's socket paths live under it
    log = temp / "head.log"
    with log.open("w") as fh:
        head = subprocess.Popen(
            [
                str(RAY),
                "start",
                "--head",
                f"--port={port}",
                "--node-ip-address=127.0.0.1",
                "--num-cpus=2",
                "--include-dashboard=false",
                f"--object-store-memory={80 * 1024**2}",
                f"--temp-dir={temp}",
                "--disable-usage-stats",
                "--block",
            ],
            stdout=fh,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env=ray_env,
        )
    try:
        wait_until(lambda: head.poll() is not None or "Ray runtime started" in log.read_text(), timeout_s=120)
        assert head.poll() is None and port_open(port), log.read_text()
        yield f"127.0.0.1:{port}"
    finally:
        head.send_signal(signal.SIGTERM)  # `ray start --block` stops the processes it started
        try:
            head.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pass
        try:
            os.killpg(head.pid, signal.SIGKILL)  # whatever of its session is left
        except ProcessLookupError:
            pass
        shutil.rmtree(temp, ignore_errors=True)
    assert not port_open(port)


TINY_BATCH = """\
jobs:
  - {kind: capture, out: scenes/teapot, object: teapot, resolution: 32, test_views: 1, grasps: 1}
  - {kind: reconstruct, out: runs/teapot-3dgs, scene: scenes/teapot, method: 3dgs, iterations: 10}
  - {kind: reconstruct, out: runs/teapot-paper, scene: scenes/teapot, method: paper, iterations: 10}
"""


def read_rows(path: Path) -> list[dict]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def test_tiny_batch_on_a_cluster_through_ray_address_equals_local(tmp_path, cluster, ray_env):
    jobs = tmp_path / "jobs.yaml"
    jobs.write_text(TINY_BATCH)
    assert main(["batch", str(jobs), "--out", str(tmp_path / "local")]) == 0  # first: fills numba's cache

    out = tmp_path / "ray"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "tacsplat",
            "batch",
            str(jobs),
            "--out",
            str(out),
            "--executor",
            "ray",
            "--ray-address",
            cluster,
        ],
        capture_output=True,
        text=True,
        env=ray_env,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"connecting to the Ray cluster at {cluster}" in done.stderr
    assert "Started a local Ray instance" not in done.stderr
    rows, expected = read_rows(out / "results.csv"), read_rows(tmp_path / "local" / "results.csv")
    assert [r["job"] for r in rows] == [
        "reconstruct runs/teapot-3dgs",
        "reconstruct runs/teapot-paper",
    ]
    assert all(math.isfinite(float(r["cd"])) and float(r["psnr"]) > 10 for r in rows)
    assert [r["method"] for r in rows] == ["3dgs", "paper"] and {r["iterations"] for r in rows} == {"10"}
    timing = "train_seconds"
    assert [{k: v for k, v in r.items() if k != timing} for r in rows] == [
        {k: v for k, v in r.items() if k != timing} for r in expected
    ]
    assert all(float(r[timing]) > 0 for r in rows)
    assert not (out / "failures.csv").exists()
