"""Calibration files and pictures written onto a full or read-only disk: one StorageError naming the file, no
temporary file left, and the file written before kept (a real tmpfs; the tests run as root)."""

import os

import numpy as np
import pytest

from tacsplat.drivers.calibration import HandCalibration
from tacsplat.drivers.cli import _write_image
from tacsplat.drivers.wrist_camera import CameraCalibration, CharucoBoardSpec
from tacsplat.errors import StorageError
from tacsplat.sim.hand import HandKinematics


def _fill(folder) -> None:
    """Use up every byte of the file system that holds ``folder``."""
    fd = os.open(folder / "filler", os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    try:
        while os.write(fd, b"\0" * 4096):
            pass
    except OSError:
        pass  # no space left
    finally:
        os.close(fd)


def _camera() -> CameraCalibration:
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    return CameraCalibration(K, np.zeros(5), 320, 240, 0.1, CharucoBoardSpec())


WRITERS = {
    "hand.json": lambda path: HandCalibration.identity(HandKinematics().joint_names).save(path),
    "camera.json": lambda path: _camera().save(path),
    "picture.png": lambda path: _write_image(path, np.full((240, 320, 3), 90, np.uint8)),
}


@pytest.mark.parametrize("name", WRITERS)
def test_a_full_disk_keeps_the_old_file_and_leaves_no_temporary(tmpfs, name):
    mount = tmpfs("256k")
    path = mount.path / name
    WRITERS[name](path)
    before = path.read_bytes()
    _fill(mount.path)
    with pytest.raises(StorageError, match="disk is full") as caught:
        WRITERS[name](path)
    assert caught.value.path == path
    assert path.read_bytes() == before
    assert sorted(p.name for p in mount.path.iterdir()) == sorted(["filler", name])


@pytest.mark.parametrize("name", WRITERS)
def test_a_read_only_disk_is_named(tmpfs, name):
    mount = tmpfs("256k")
    mount.read_only()
    with pytest.raises(StorageError, match="read-only") as caught:
        WRITERS[name](mount.path / name)
    assert caught.value.path == mount.path / name
    mount.writable()
    assert list(mount.path.iterdir()) == []
