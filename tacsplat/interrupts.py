"""What ends a command early: Ctrl-C (which works in a process started with SIGINT ignored) and the other
ending signals, raised as :class:`SignalInterrupt` so that a command exits with 128 + the signal's number."""

from __future__ import annotations

import contextlib
import signal
import threading

# The signals that ask a process to end (a terminal's Ctrl-C, kill, a closed window, Ctrl-\\).
END_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT") if hasattr(signal, n))


# Set by the console script (tacsplat.cli.run), where a command's end is the process's: what ignores the ending
# signals for a command's last words then leaves them ignored until the exit (a second Ctrl-C there killed it).
COMMAND_IS_PROCESS = False


class SignalInterrupt(KeyboardInterrupt):
    """SIGINT, SIGTERM, SIGHUP or SIGQUIT asked the process to end (``signum``); a KeyboardInterrupt, so that
    whatever stops on Ctrl-C stops on it too. A command that ends on it exits with 128 + signum."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        super().__init__(signal.Signals(self.signum).name)


@contextlib.contextmanager
def signals_interrupt(signals=END_SIGNALS, *, once: bool = False):
    """While open (in the main thread; elsewhere nothing changes): each of ``signals`` raises SignalInterrupt, then
    the previous handlers come back. ``once``: for a block whose cleanup a second signal must not cut short, later
    ones are ignored until it ends, and a signal ignored on entry (``nohup``'s SIGHUP) stays ignored. Yields
    ``end()``, which starts ignoring them at once (a block unwinding on a signal another handler raised)."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    previous = {s: signal.getsignal(s) for s in signals}
    if once:
        previous = {s: handler for s, handler in previous.items() if handler is not signal.SIG_IGN}
    ended = []

    def end():
        """(``once``) The block is ending, on a signal this handler did not see (another handler installed over it
        raised one): from now on, ignore them, here and wherever this handler is put back."""
        ended.append(True)
        for s in previous:
            signal.signal(s, signal.SIG_IGN)

    def interrupt(signum, frame):
        if ended:
            return
        if once:
            end()
        raise SignalInterrupt(signum)

    for s in previous:
        signal.signal(s, interrupt)
    try:
        yield end
    finally:
        for s, handler in previous.items():  # (None: a handler installed outside Python)
            signal.signal(s, signal.SIG_DFL if handler is None else handler)


@contextlib.contextmanager
def signals_held(signals=END_SIGNALS):
    """While open (in the main thread; elsewhere nothing changes): a signal of ``signals`` whose handler is Python's
    (:func:`signals_interrupt`'s, Ctrl-C's) is held, then the previous handlers come back and the first one held is
    raised to them. For imports of native modules: an exception raised inside one comes out as another
    (pybind11's ``ImportError: initialization failed``, ctypes' ``ArgumentError``), or not at all (MuJoCo imports its
    renderer under ``except ImportError``, trimesh its parts under ``except BaseException``)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = {s: signal.getsignal(s) for s in signals}
    for s, handler in previous.items():
        # (not one ignored, nor the default or one installed outside Python: a process they end runs no code of its own)
        if callable(handler):
            signal.signal(s, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:  # all of them, whatever the block installed meanwhile (ray.init's core worker: SIGTERM's)
        for s, handler in previous.items():  # (None: a handler installed outside Python)
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        if held:
            signal.raise_signal(held[0])


@contextlib.contextmanager
def end_signals_ignored(signals=END_SIGNALS):
    """While open (in the main thread; elsewhere nothing changes): ``signals`` are ignored, then the previous
    handlers come back (in the console script's process, they stay ignored: :data:`COMMAND_IS_PROCESS`). For what a
    command does once a signal has ended it (its last words): a second Ctrl-C, typed because the first seemed slow,
    must not cut them short with a traceback."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in signals}
    try:
        yield
    finally:
        for s, handler in {} if COMMAND_IS_PROCESS else previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)


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
