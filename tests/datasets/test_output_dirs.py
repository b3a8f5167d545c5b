"""Output folders: one clear error for a file, a file parent, an unwritable folder, or a folder in use."""

import os

import pytest

from tacsplat.datasets.outputs import LOCK_NAME, claim_output_dir, ensure_output_dir, other_writer, record_writer
from tacsplat.errors import ConfigError


def test_a_new_nested_folder_is_created(tmp_path):
    assert ensure_output_dir(tmp_path / "a" / "b").is_dir()


def test_a_file_or_a_file_parent_is_refused_naming_the_option(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(ConfigError, match="--out: .*f is a file"):
        ensure_output_dir(tmp_path / "f")
    with pytest.raises(ConfigError, match="--run: .* is inside .*f, which is a file"):
        ensure_output_dir(tmp_path / "f" / "run", "--run")


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write into read-only folders")
def test_an_unwritable_folder_is_refused(tmp_path):
    locked = tmp_path / "ro"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(ConfigError, match="--out"):
            ensure_output_dir(locked / "run")
    finally:
        locked.chmod(0o700)


def test_an_unwritable_folder_is_refused_even_for_root(tmp_path, monkeypatch):
    monkeypatch.setattr(os, "access", lambda *a: False)
    with pytest.raises(ConfigError, match="is not writable"):
        ensure_output_dir(tmp_path / "run")


def test_a_second_claim_on_a_locked_folder_is_refused_until_released(tmp_path):
    first = claim_output_dir(tmp_path / "run")
    with pytest.raises(ConfigError, match="another tacsplat process"):
        claim_output_dir(tmp_path / "run")
    first.release()
    with claim_output_dir(tmp_path / "run"):
        pass


def test_a_refused_claim_names_the_process_holding_the_folder(tmp_path):
    with claim_output_dir(tmp_path / "run"):
        with pytest.raises(ConfigError, match=rf"another tacsplat process \(PID {os.getpid()}\)"):
            claim_output_dir(tmp_path / "run")


def test_a_claim_refused_before_the_holder_recorded_its_pid_still_names_it(tmp_path):
    # the holder takes the lock, then records its PID: a second claim in between waits for the PID
    import fcntl
    import threading

    folder = tmp_path / "run"
    folder.mkdir()
    with (folder / LOCK_NAME).open("a") as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        recorder = threading.Timer(0.2, record_writer, [folder])
        recorder.start()
        try:
            with pytest.raises(ConfigError, match=rf"another tacsplat process \(PID {os.getpid()}\)"):
                claim_output_dir(folder)
        finally:
            recorder.join()
    assert other_writer(tmp_path, wait_s=0.05) == "another tacsplat process"  # no lock file: no PID, soon


def test_a_folder_on_a_read_only_mount_is_refused_saying_so(tmpfs):
    mount = tmpfs("64k")
    mount.read_only()
    with pytest.raises(ConfigError, match=f"--out: {mount.path}: the file system is read-only"):
        ensure_output_dir(mount.path)
