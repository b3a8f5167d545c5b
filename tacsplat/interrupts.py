"""Ctrl-C that works in a process started with SIGINT ignored."""

from __future__ import annotations

import contextlib
import signal


@contextlib.contextmanager
def ctrl_c_interrupts():
    """SIGINT raises KeyboardInterrupt inside the block, then the previous handler comes back (main thread only).

    A process inherits an ignored SIGINT (a script's background job has one, and so does every process it
    starts, Ray's workers among them), and Python then leaves Ctrl-C ignored: `tacsplat view` would not stop, and
    ``ray.cancel``, which interrupts a running task as Ctrl-C does, would leave the task running."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)
