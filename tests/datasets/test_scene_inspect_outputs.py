"""`tacsplat inspect --plot` never replaces the scene's own files, nor an existing file without --overwrite; a
picture file without an image suffix is refused before anything is read."""

from __future__ import annotations

import pytest

from tacsplat.cli import main
from tacsplat.datasets.inspect import run_inspect
from tacsplat.errors import UsageError
from tests.reconstruction.recon_synthetic import one_error_line


def _one_error_line(capsys, *words) -> str:
    return one_error_line(capsys, *words, prefix="")


def test_a_plot_inside_the_scene_is_refused_and_the_image_kept(scene_dir, capsys):
    image = sorted((scene_dir / "images").iterdir())[0]
    before = image.read_bytes()
    assert main(["inspect", str(scene_dir), "--plot", str(image.with_suffix(".png"))]) == 2
    _one_error_line(capsys, "--plot", "scene")
    with pytest.raises(UsageError, match="--plot"):
        run_inspect(scene_dir, plot=image.with_suffix(".png"), overwrite=True)  # (--overwrite does not allow it)
    assert image.read_bytes() == before
    assert main(["inspect", str(scene_dir)]) == 0


def test_an_existing_plot_is_replaced_only_with_overwrite(scene_dir, tmp_path, capsys):
    picture = tmp_path / "mine.png"
    picture.write_bytes(b"a picture of mine")
    assert main(["inspect", str(scene_dir), "--plot", str(picture)]) == 2
    _one_error_line(capsys, "--plot", "exists", "--overwrite")
    assert picture.read_bytes() == b"a picture of mine"
    assert main(["inspect", str(scene_dir), "--plot", str(picture), "--overwrite"]) == 0
    assert picture.read_bytes().startswith(b"\x89PNG")


def test_a_plot_without_an_image_suffix_is_a_usage_error(scene_dir, tmp_path, capsys):
    assert main(["inspect", str(scene_dir), "--plot", str(tmp_path / "picture")]) == 2
    _one_error_line(capsys, "--plot", ".png")
    assert not (tmp_path / "picture").exists()


def test_a_plot_of_what_is_no_scene_is_refused_before_anything_is_printed(tmp_path, capsys):
    run = tmp_path / "run"  # a reconstruction run's folder, given for its scene
    run.mkdir()
    (run / "config.json").write_text("{}\n")
    picture = tmp_path / "scene.png"
    assert main(["inspect", str(run), "--plot", str(picture)]) == 1
    out, err = capsys.readouterr()
    assert out == "" and err.startswith(f"error: {run}: a reconstruction run, not a scene") and err.count("\n") == 1
    assert not picture.exists()


def test_a_plot_below_a_file_is_a_usage_error_and_new_folders_are_made(scene_dir, tmp_path, capsys):
    (tmp_path / "afile").write_text("mine")
    assert main(["inspect", str(scene_dir), "--plot", str(tmp_path / "afile" / "p.png")]) == 2
    _one_error_line(capsys, "--plot", "is not a folder")
    assert (tmp_path / "afile").read_text() == "mine"
    assert main(["inspect", str(scene_dir), "--plot", str(tmp_path / "new" / "sub" / "p.png")]) == 0
    assert (tmp_path / "new" / "sub" / "p.png").is_file()


def test_a_refused_inspect_leaves_no_new_folder_of_its_plot(tmp_path, capsys):
    """Before: the plot's folders new/sub were made by the folder check, then the command failed on its input."""
    (tmp_path / "empty").mkdir()
    assert main(["inspect", str(tmp_path / "empty"), "--plot", str(tmp_path / "new" / "sub" / "p.png")]) == 1
    _one_error_line(capsys, "not a scene")
    assert not (tmp_path / "new").exists()
