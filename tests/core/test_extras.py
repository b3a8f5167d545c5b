"""A command whose extra is not installed says which one to install, in one line, exit 1 (the extra's modules are
made unimportable in a subprocess, as in a base install)."""

import subprocess
import sys
from pathlib import Path

import pytest

RIGS = Path(__file__).parents[2] / "acquisition" / "rigs"


def _without(modules: tuple[str, ...], argv: list[str]) -> subprocess.CompletedProcess:
    code = (
        "import sys\n"
        f"for name in {modules!r}:\n"
        "    sys.modules[name] = None  # import of it fails as when it is not installed\n"
        "from tacsplat.cli import main\n"
        f"sys.exit(main({argv!r}))\n"
    )
    return subprocess.run(
        [sys.executable, "-c", code], stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=300
    )


@pytest.mark.parametrize(
    "modules, argv, extra, command",
    [
        (("mujoco",), ["sim-capture", "--out", "{tmp}/scene", "--quiet"], "sim", "tacsplat sim-capture"),
        (("viser",), ["view", "{tmp}"], "viewer", "tacsplat view"),
        (
            ("ray",),
            ["batch", "{tmp}/jobs.yaml", "--out", "{tmp}/batch", "--executor", "ray"],
            "cluster",
            "tacsplat batch",
        ),
        (
            ("dynamixel_sdk", "serial"),
            ["capture", "--rig", str(RIGS / "real.yaml"), "--out", "{tmp}/real"],
            "hardware",
            "tacsplat capture",
        ),
    ],
)
def test_a_missing_extra_is_named_in_one_line(tmp_path, modules, argv, extra, command):
    (tmp_path / "jobs.yaml").write_text("jobs:\n  - {kind: capture, out: s, object: teapot, resolution: 16}\n")
    done = _without(modules, [a.replace("{tmp}", str(tmp_path)) for a in argv])
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1, done.stderr
    assert lines[0] == (
        f"error: {command} needs the {extra} extra ({modules[0]} is not installed): pip install 'tacsplat[{extra}]'"
    )


def test_a_capture_on_the_twin_needs_no_hardware_extra(tmp_path):
    """`capture --rig sim.yaml` drives the twin: without dynamixel_sdk and pyserial it opens, serves the (empty)
    keys and stops before the plan is complete, naming no extra."""
    done = _without(
        ("dynamixel_sdk", "serial"), ["capture", "--rig", str(RIGS / "sim.yaml"), "--out", str(tmp_path / "s")]
    )
    assert done.returncode == 1 and "stopped before the plan was complete" in done.stdout, done.stdout + done.stderr
    assert "extra" not in done.stderr, done.stderr
