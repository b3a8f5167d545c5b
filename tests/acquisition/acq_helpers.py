"""Shared helpers of the acquisition tests: a mocked real rig file with a short plan, scripted keys, the operator's
side of a pseudo-terminal, a command signalled mid-run."""

import io
import os
import select
import signal
import subprocess
import sys
import threading
import time

import yaml

from tacsplat.acquisition.config import example_rig
from tacsplat.sim.hand import FINGER_NAMES, JOINT_NAMES


class NoHand:
    """A hand that only names its joints: what a CaptureLogger reads of it before a grasp."""

    joint_names = JOINT_NAMES


class Named:
    """A tactile sensor that only has a name: what a CaptureLogger reads of it before a grasp."""

    def __init__(self, name):
        self.name = name


def no_devices() -> tuple:
    """``(hand, sensors, camera, clock, poses)`` of a CaptureLogger that only checks a resumed scene."""
    return NoHand(), [Named(f) for f in FINGER_NAMES], None, None, None


def write_mock_rig(folder, **changes) -> str:
    """The shipped mock rig with a plan of 3 train views, 1 test view and 3 grasps (plus ``changes``, by
    top-level section: a mapping updates the section, anything else replaces it), written to ``folder/rig.yaml``."""
    data = yaml.safe_load(example_rig("mock").read_text())
    data["plan"] = {"views": {"train": 3, "test": 1}, "grasps": {"count": 3}}
    for section, values in changes.items():
        if isinstance(values, dict):
            data.setdefault(section, {}).update(values)
        else:
            data[section] = values
    path = folder / "rig.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def sigterm_when(args: list[str], prefix: str) -> tuple[int, str, str]:
    """``(exit code, stdout, stderr)`` of ``tacsplat ARGS`` (standard input closed) sent SIGTERM once it prints a
    line starting with ``prefix``."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tacsplat", *args],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        for line in proc.stdout:
            if line.startswith(prefix):
                break
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, stdout, stderr


class ScriptedKeys(io.TextIOBase):
    """Keys handed out one character at a time; ``hooks[i]`` runs just before key ``i`` is read (to inject a
    fault at a known point of the session). No fileno: the session reads it without waiting."""

    def __init__(self, keys: str, hooks: dict | None = None):
        self.keys = keys
        self.hooks = dict(hooks or {})
        self.pos = 0

    def readable(self) -> bool:
        return True

    def read(self, n: int = -1) -> str:
        if self.pos in self.hooks:
            self.hooks.pop(self.pos)()
        out = self.keys[self.pos : self.pos + 1]
        self.pos += len(out)
        return out


def capture_on_a_terminal(rig: str, out, stderr=None, **popen) -> tuple[subprocess.Popen, "Terminal"]:
    """``tacsplat capture --rig RIG --out OUT --mock`` in a child process whose standard input and output (and
    error, unless ``stderr`` is given) are a new pseudo-terminal; ``popen``: more of ``subprocess.Popen``'s
    arguments. Returns the process and the operator's side of the terminal."""
    import pty

    master, slave = pty.openpty()
    command = [sys.executable, "-m", "tacsplat", "capture", "--rig", rig, "--out", str(out), "--mock"]
    proc = subprocess.Popen(
        command, stdin=slave, stdout=slave, stderr=slave if stderr is None else stderr, close_fds=True, **popen
    )
    os.close(slave)
    return proc, Terminal(master)


class Terminal:
    """The operator's side of a pseudo-terminal: collects the output in a thread (the live status line has no
    newline); ``wait_for`` blocks until a text appears after the last ``type``; ``type`` sends keys; ``close``
    stops the thread, then closes the terminal."""

    def __init__(self, master_fd: int):
        self.fd = master_fd
        self.text = ""
        self._since = 0
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._run, daemon=True)
        self._reader.start()

    def _run(self):
        while not self._stop.is_set():
            if not select.select([self.fd], [], [], 0.05)[0]:
                continue
            try:
                chunk = os.read(self.fd, 4096)
            except OSError:  # EIO: the other side is gone
                chunk = b""
            if not chunk:
                return
            with self._cond:
                self.text += chunk.decode(errors="replace")
                self._cond.notify_all()

    def close(self) -> None:
        """Stop the reader before closing its descriptor: a reader left running would read from whatever file
        next takes the descriptor's number (a scene file the test opens), moving that file's offset."""
        self._stop.set()
        self._reader.join()
        os.close(self.fd)

    def type(self, keys: str) -> None:
        with self._cond:
            self._since = len(self.text)
        os.write(self.fd, keys.encode())

    def wait_for(self, text: str, timeout_s: float = 90.0) -> None:  # generous: a loaded 2-core machine
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while text not in self.text[self._since :]:
                remaining = deadline - time.monotonic()
                assert remaining > 0, f"no {text!r} in the output:\n{self.text}"
                self._cond.wait(remaining)

    def wait_closed(self, timeout_s: float = 20.0) -> None:
        """Until every process that writes to the terminal has closed it (all the output is in ``text``)."""
        self._reader.join(timeout_s)
        assert not self._reader.is_alive(), f"the terminal is still open after {timeout_s} s:\n{self.text}"

    def last_line(self) -> str:
        return self.text.replace("\r\n", "\n").rstrip("\n").rsplit("\n", 1)[-1]
