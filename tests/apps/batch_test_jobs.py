"""Jobs for the executor tests: each writes ``folder/done`` and logs every attempt in ``folder/attempts``; a
``behaviour`` makes it fail the ways a real job can (raise, hit a bad input, kill its worker, hang, save what it
did when interrupted)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from tacsplat.errors import ConfigError

WAIT_S = 60.0  # bound of every wait of these jobs
SAVE_S = 0.5  # how long a "block-once" job takes to save when interrupted (a second signal then cuts it short)


@dataclass(frozen=True)
class FileJob:
    name: str
    folder: Path
    behaviour: str = "ok"  # ok | raise-while-broken | config-error | die-once | block | block-once
    wait_for: Path | None = None  # finish (die-once: die) only once this file exists
    needs: tuple[str, ...] = ()
    cpus: float = 1.0

    def gpus(self, cluster_has_gpus: bool) -> float:
        return 0

    def complete(self) -> bool:
        return (self.folder / "done").is_file()

    def attempts(self) -> list[int]:
        """The process id of each attempt so far."""
        log = self.folder / "attempts"
        return [int(line) for line in log.read_text().split()] if log.is_file() else []

    def __call__(self) -> dict:
        self.folder.mkdir(parents=True, exist_ok=True)
        with (self.folder / "attempts").open("a") as fh:
            fh.write(f"{os.getpid()}\n")
        if self.behaviour == "die-once" and len(self.attempts()) == 1:
            if self.wait_for is not None:
                wait_until(self.wait_for.exists)
            os._exit(1)  # the worker dies mid-task
        if self.behaviour == "raise-while-broken" and (self.folder / "broken").exists():
            raise RuntimeError(f"{self.folder / 'broken'} is there")
        if self.behaviour == "config-error":
            raise ConfigError("threshold", "must be > 0, got -1")
        if self.behaviour == "block":
            try:  # ("started" inside: a signal its reader sends may come before the next line runs)
                (self.folder / "started").touch()
                wait_until((self.folder / "release").exists)
            except KeyboardInterrupt:
                (self.folder / "interrupted").touch()
                raise
        if self.behaviour == "block-once" and len(self.attempts()) == 1:  # as a training: interrupted, it saves
            try:  # what it did (in "saved"), which a second signal cuts short
                (self.folder / "started").touch()  # (inside: the signal may come before the next line runs)
                wait_until((self.folder / "release").exists)
            except KeyboardInterrupt as exc:
                (self.folder / "interrupted").write_text(type(exc).__name__)
                time.sleep(SAVE_S)
                (self.folder / "saved").touch()
                raise
        if self.wait_for is not None:
            wait_until(self.wait_for.exists)
        (self.folder / "done").write_text("ok")
        return {"attempts": len(self.attempts())}


@dataclass(frozen=True)
class ImportingJob(FileJob):
    """A FileJob whose ``warm_up`` imports ``batch_test_warm``."""

    def warm_up(self) -> None:
        import batch_test_warm  # noqa: F401


@dataclass(frozen=True)
class SlowWarmJob(FileJob):
    """A FileJob whose ``warm_up`` lasts until ``wait_for`` appears, then records its process id in
    ``FOLDER/../warmed``: a warm-up still running when the jobs before it have finished, for as long as the test
    needs (a fixed delay is too short on a loaded machine)."""

    def warm_up(self) -> None:
        wait_until(self.wait_for.exists)
        (self.folder.parent / "warmed").write_text(str(os.getpid()))


@dataclass(frozen=True)
class DyingWarmJob(FileJob):
    """A FileJob whose ``warm_up`` kills its worker once ``wait_for`` appears (an import that crashes)."""

    def warm_up(self) -> None:
        wait_until(self.wait_for.exists)
        os._exit(1)


def wait_until(condition, timeout_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"waited {timeout_s} s")
        time.sleep(0.05)
