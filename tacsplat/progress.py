"""Progress of long jobs: a tqdm bar on a terminal, plain periodic lines otherwise.

Every long job shows its progress through :func:`progress_bar`. On a terminal that
is a tqdm bar; when stderr is a file or a pipe (a log, CI, a batch job) the bar
would write carriage-return updates into it, so instead one plain line is
written at most every ``PLAIN_INTERVAL_S`` seconds and at the end. ``-q`` on the
command line (:func:`set_quiet`) silences both.
"""

from __future__ import annotations

import sys
import time

PLAIN_INTERVAL_S = 30.0
_quiet = False


def set_quiet(quiet: bool) -> None:
    """Silence every progress display of this process (the CLI's ``-q``)."""
    global _quiet
    _quiet = quiet


class _PlainLines:
    """tqdm's interface, written as a line every PLAIN_INTERVAL_S seconds (and at close)."""

    def __init__(self, iterable=None, total=None, desc="", unit="it", initial=0, **_):
        self.iterable, self.desc, self.unit = iterable, desc or "progress", unit
        self.total = len(iterable) if total is None and hasattr(iterable, "__len__") else total
        self.n = initial
        self.postfix = ""
        self._started = self._last = time.monotonic()
        self._shown = None  # (count, postfix) of the last line written

    def __iter__(self):
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def update(self, n: int = 1) -> None:
        self.n += n
        if time.monotonic() - self._last >= PLAIN_INTERVAL_S:
            self._write()

    def set_postfix(self, refresh: bool = True, **values) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def set_postfix_str(self, text: str, refresh: bool = True) -> None:
        self.postfix = text

    def write(self, text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    def _write(self) -> None:
        self._last = time.monotonic()
        done = f"{self.n}/{self.total}" if self.total else str(self.n)
        postfix = f" ({self.postfix})" if self.postfix else ""
        self.write(f"{self.desc}: {done} {self.unit} in {self._last - self._started:.0f} s{postfix}")
        self._shown = (self.n, self.postfix)

    def close(self) -> None:
        """The last line, unless the last update wrote this one already."""
        if self._last != -1.0:
            if self._shown != (self.n, self.postfix):
                self._write()
            self._last = -1.0


class _Silent(_PlainLines):
    """No display; messages given to ``write`` still print unless the process is quiet."""

    def _write(self) -> None:
        pass

    def write(self, text: str) -> None:
        if not _quiet:
            super().write(text)


def progress_bar(iterable=None, *, total=None, desc: str = "", unit: str = "it", enabled: bool = True, **kwargs):
    """A progress display around ``iterable`` (or of ``total`` steps, advanced with ``update``)."""
    if _quiet or not enabled:
        return _Silent(iterable, total=total, desc=desc, unit=unit, **kwargs)
    if sys.stderr.isatty():
        from tqdm import tqdm

        return tqdm(iterable, total=total, desc=desc, unit=unit, dynamic_ncols=True, **kwargs)
    return _PlainLines(iterable, total=total, desc=desc, unit=unit, **kwargs)
