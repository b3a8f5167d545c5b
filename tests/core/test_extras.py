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
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)


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
