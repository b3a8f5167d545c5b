"""--out of sim-capture and capture: a file, a folder inside a file or an unwritable folder is one clear error
naming --out, before any device or the twin starts."""

import os
import sys
from pathlib import Path

import pytest

from tacsplat.cli import main  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from acq_helpers import write_mock_rig  # noqa: E402

pytestmark = pytest.mark.timeout(120)

SMALL = ["--resolution", "32", "--views", "1", "--test-views", "0", "--grasps", "0"]


def _command(name: str, tmp_path: Path) -> list[str]:
    if name == "sim-capture":
        return ["sim-capture", *SMALL]
    return ["capture", "--rig", write_mock_rig(tmp_path), "--mock"]


@pytest.fixture(params=["sim-capture", "capture"])
def command(request, tmp_path):
    return _command(request.param, tmp_path)


def test_out_that_is_a_file(command, tmp_path, capsys):
    out = tmp_path / "scene.txt"
    out.write_text("notes")
    assert main([*command, "--out", str(out)]) == 1
    assert f"error: --out: {out} is a file; choose a folder" in capsys.readouterr().err
    assert out.read_text() == "notes"


def test_out_inside_a_file(command, tmp_path, capsys):
    (tmp_path / "notes").write_text("notes")
    out = tmp_path / "notes" / "scene"
    assert main([*command, "--out", str(out)]) == 1
    assert f"error: --out: {out} is inside {tmp_path / 'notes'}, which is a file" in capsys.readouterr().err


def test_out_that_is_not_writable(command, tmp_path, capsys, monkeypatch):
    out = tmp_path / "locked"
    out.mkdir()
    access = os.access  # root may write anywhere: the folder reports itself unwritable, as a read-only mount does
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: False if Path(path) == out else access(path, mode, **kw))
    assert main([*command, "--out", str(out)]) == 1
    assert f"error: --out: {out} is not writable" in capsys.readouterr().err
    assert list(out.iterdir()) == []


def test_resume_of_out_that_is_a_file(command, tmp_path, capsys):
    out = tmp_path / "scene.txt"
    out.write_text("notes")
    assert main([*command, "--out", str(out), "--resume"]) == 1
    assert f"error: --out: {out} is a file; choose a folder" in capsys.readouterr().err


def test_out_that_holds_other_files(command, tmp_path, capsys):
    out = tmp_path / "photos"
    out.mkdir()
    (out / "IMG_0001.png").write_bytes(b"not ours")
    assert main([*command, "--out", str(out)]) == 1
    assert (
        f"error: --out: {out} holds other files and no scene; choose an empty or new folder" in capsys.readouterr().err
    )
    assert [p.name for p in out.iterdir()] == ["IMG_0001.png"]


def test_a_scene_another_capture_is_creating_between_the_checks_is_named_as_a_scene(tmp_path, monkeypatch):
    """Another capture renames its journal into place, then makes its folders, while this one checks --out: the
    folder must be reported as that scene (with --resume), never as 'other files' (a race two captures into one new
    folder ran into under load)."""
    from tacsplat.acquisition import capture_scene
    from tacsplat.datasets.writer import JOURNAL
    from tacsplat.errors import ConfigError

    out = tmp_path / "scene"
    out.mkdir()
    real_has_content = capture_scene.has_content

    def other_capture_creates(path):  # the other creation's steps happen between this check's two looks
        (out / JOURNAL).write_text("{}\n")
        (out / "images").mkdir()
        return real_has_content(path)

    monkeypatch.setattr(capture_scene, "has_content", other_capture_creates)
    with pytest.raises(ConfigError, match="already holds a scene: add --resume"):
        capture_scene.check_out(out, resume=False)


def test_a_scene_being_written_names_the_writer(tmp_path):
    from tacsplat.acquisition.capture_scene import check_out
    from tacsplat.datasets.writer import JOURNAL, _lock_journal
    from tacsplat.errors import ConfigError

    out = tmp_path / "scene"
    out.mkdir()
    holder = _lock_journal(out / JOURNAL, out)  # this process as the other writer
    (out / ".tacsplat.lock").write_text("4242\n")
    try:
        with pytest.raises(ConfigError, match=r"being written by another tacsplat process \(PID 4242\).*--resume"):
            check_out(out, resume=False)
    finally:
        holder.close()


def test_another_commands_write_probe_is_not_content(tmp_path, monkeypatch):
    """The probe file another command's --out check writes for a moment is not 'other files' to this one (two
    captures into one new folder at once: the loser was told the folder held other files)."""
    from tacsplat.datasets.writer import has_content
    from tacsplat.files import check_writable

    seen = []
    fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (seen.append(has_content(tmp_path)), fsync(fd))[1])
    check_writable(tmp_path)  # its probe is in the folder while it is synced
    assert seen == [False]
