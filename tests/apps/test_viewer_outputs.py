"""`tacsplat view --export` never replaces a file of what it shows (a scene's, a run's or its scene's), nor an
existing file without --overwrite, and writes only .html; each refused before anything is read."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from tacsplat.cli import main
from tests.reconstruction.recon_synthetic import one_error_line

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from viewer_test_splats import splat  # noqa: E402

pytest.importorskip("viser", reason="tacsplat view needs viser")


def _one_error_line(capsys, *words) -> str:
    return one_error_line(capsys, *words, prefix="")


@pytest.fixture
def scene(tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "transforms.json").write_text('{"the": "index"}')
    return scene


@pytest.mark.parametrize("overwrite", [[], ["--overwrite"]])
def test_an_export_into_the_scene_shown_is_refused(scene, capsys, overwrite):
    assert main(["view", str(scene), "--export", str(scene / "view.html"), *overwrite]) == 2
    _one_error_line(capsys, "--export", str(scene))
    assert sorted(p.name for p in scene.iterdir()) == ["transforms.json"]


def test_an_export_over_a_runs_file_or_its_scenes_is_refused(scene, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "splat.ply").write_bytes(b"splat")
    (run / "config.json").write_text(json.dumps({"scene": {"path": str(scene), "sha256": "0"}}))
    for page in (run / "view.html", scene / "view.html"):
        assert main(["view", str(run), "--export", str(page), "--overwrite"]) == 2
        _one_error_line(capsys, "--export")
    assert (run / "splat.ply").read_bytes() == b"splat" and not (scene / "view.html").exists()


def test_an_export_must_be_html_and_new_unless_overwrite(scene, tmp_path, capsys):
    assert main(["view", str(scene), "--export", str(tmp_path / "transforms.json")]) == 2
    _one_error_line(capsys, "--export", ".html")
    page = tmp_path / "page.html"
    page.write_text("mine")
    assert main(["view", str(scene), "--export", str(page)]) == 2
    _one_error_line(capsys, "--export", "exists", "--overwrite")
    assert page.read_text() == "mine"


@pytest.mark.parametrize("host", ["nosuchhost.invalid", "10.255.255.1"])
def test_a_host_this_machine_cannot_listen_on_is_a_usage_error_not_a_hang(scene, host, capsys):
    assert main(["view", str(scene), "--host", host, "--port", "0"]) == 2
    _one_error_line(capsys, "--host", host)


def test_a_port_in_use_is_no_error_and_an_ipv6_url_is_bracketed():
    import socket

    from tacsplat.apps import viewer

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        viewer.check_host("127.0.0.1", taken.getsockname()[1])  # (the server takes the next port)
    assert viewer.server_url("::1", 8895) == "http://[::1]:8895"
    assert viewer.server_url("127.0.0.1", 8895) == "http://127.0.0.1:8895"


def test_an_export_into_new_folders_makes_them(tmp_path, capsys):
    """Before: "error: --export: new/sub is not a folder" (exit 1), where `inspect --plot` made its folder."""
    import numpy as np

    from tacsplat.reconstruction.ply import save_ply

    save_ply(splat(np.full((8, 3), -5.0)), tmp_path / "run" / "splat.ply")
    page = tmp_path / "new" / "sub" / "view.html"
    assert main(["view", str(tmp_path / "run"), "--export", str(page)]) == 0
    assert page.read_text().startswith("<!doctype html>")


def test_a_refused_view_leaves_no_new_folder_of_its_export(tmp_path, capsys):
    """Before: the export's folders new/sub were made by the folder check, then PATH was refused."""
    (tmp_path / "empty").mkdir()
    assert main(["view", str(tmp_path / "empty"), "--export", str(tmp_path / "new" / "sub" / "view.html")]) == 1
    _one_error_line(capsys, "PATH")
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("below", ["", "sub"])
def test_an_export_below_a_file_is_a_usage_error(scene, tmp_path, capsys, below):
    (tmp_path / "afile").write_text("mine")
    assert main(["view", str(scene), "--export", str(tmp_path / "afile" / below / "view.html")]) == 2
    _one_error_line(capsys, "--export", f"{tmp_path / 'afile'} is not a folder")
    assert (tmp_path / "afile").read_text() == "mine"
