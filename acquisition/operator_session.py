"""The operator session of ``tacsplat capture``: terminal only, one key per action.

A live status line shows whether the board is seen and its reprojection error,
the hand's state and the counts so far against the plan. Keys: Enter takes a
view (train views first, then test views), ``g`` grasps, ``u`` undoes the last
record (a view, or a whole grasp), ``q`` stops. End of input is ``q``. On a
device fault (or a full disk, or any other error once the session runs) the rig
is closed first (the hand's context manager turns torque off), then the session
says what failed and the exact command that resumes (or, when the fault came
before a scene was written, that starts again). A resume
continues only the capture that was started: see
:mod:`~tacsplat.acquisition.capture_scene`.

Input is any text stream: a terminal (put in cbreak mode, so keys need no
Enter), a pipe or pseudo-terminal (read byte by byte, with the status
refreshed while waiting), or an in-memory stream of scripted keys.

SIGINT, SIGTERM, SIGHUP and SIGQUIT end a session as a device fault does: the
rig closes, the command that carries on is printed, and on a real rig the last
line says which servos confirmed torque off and which did not (cut the servo
power then); the exit code is 128 + the signal's number. A terminal that hangs
up (its window closed) ends the session as SIGHUP does, whether or not the
signal reaches this process: its keys end (a read gives nothing, or EIO) and
writing to it fails with EIO. The last words then go to standard error when
that is not the dead terminal (a log file), and nowhere otherwise.
"""

from __future__ import annotations

import contextlib
import errno
import io
import logging
import os
import select
import shlex
import signal
import sys
import termios
import tty
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, TextIO

from tacsplat.acquisition.capture_scene import open_scene
from tacsplat.acquisition.config import CapturePlan, RigConfig
from tacsplat.acquisition.devices import Rig, import_device_modules
from tacsplat.acquisition.logger import CaptureLogger, CaptureRejected
from tacsplat.datasets.writer import JOURNAL
from tacsplat.errors import CameraError, ConfigError, DeviceError, SimulationError, StorageError, TacsplatError
from tacsplat.interrupts import SignalInterrupt, end_signals_ignored, signals_interrupt

log = logging.getLogger(__name__)

KEYS_HELP = "[Enter] view  [g] grasp  [u] undo  [q] quit"
EXIT_FAULT = 3  # a device, the disk or the session failed; the scene is resumable


def _fileno(stream) -> int | None:
    try:
        return stream.fileno()
    except (AttributeError, io.UnsupportedOperation, ValueError):
        return None


def _hangup(exc: BaseException) -> BaseException:
    """What a failed terminal operation raises: SignalInterrupt(SIGHUP) for a terminal that hung up (EIO, from an
    OSError or a termios.error, which is not one: the end that a closed window's SIGHUP gives, whether or not the
    signal reaches this process), else ``exc`` itself."""
    code = exc.errno if isinstance(exc, OSError) else (exc.args[0] if exc.args else None)
    return SignalInterrupt(signal.SIGHUP) if code == errno.EIO else exc


@contextmanager
def _cbreak(stream) -> Iterator[None]:
    """Keys without Enter on a terminal (restored on exit, unless it hung up meanwhile: nothing to restore then).
    Keys typed before it (while the devices were opening) are discarded: they were not meant for the session."""
    fd = _fileno(stream)
    if fd is None or not os.isatty(fd):
        yield
        return
    try:
        saved = termios.tcgetattr(fd)
    except termios.error as exc:
        raise _hangup(exc) from None
    try:
        try:
            tty.setcbreak(fd)
        except termios.error as exc:
            raise _hangup(exc) from None
        yield
    finally:
        try:  # never in place of what ends the session (a SIGHUP's SignalInterrupt when the window was closed)
            termios.tcsetattr(fd, termios.TCSADRAIN, saved)
        except (termios.error, OSError) as exc:
            log.debug("terminal not restored: %s", exc)


@dataclass
class CaptureSession:
    """Maps keys to logger actions for one open rig and writer; ``run()`` returns when the operator stops."""

    rig: Rig
    logger: CaptureLogger
    plan: CapturePlan
    keys: TextIO
    out: TextIO
    planner: object = None  # positions the twin before a view or grasp (None on a real rig: the operator does)
    refresh_s: float = 0.5

    def __post_init__(self):
        self._live = bool(getattr(self.out, "isatty", lambda: False)())
        # a real hand's own check: a fault it found while waiting for a key (its heartbeat) ends the session at once
        self._check_hand = getattr(self.rig.hand, "check", lambda: None)

    # --- display ----------------------------------------------------------------------------------
    def board_status(self) -> str:
        if self.rig.kind == "sim":
            return "camera pose: ground truth"
        image, _ = self.rig.camera.read()
        try:
            est = self.rig.poses.measure(image)
        except CameraError:  # the board was not found in the frame (a read failure raised above)
            return "board: NOT SEEN"
        limit = self.rig.poses.board.max_reprojection_px
        flag = "" if est.reprojection_px <= limit else f" OVER {limit:g}"
        return (
            f"board: seen, {est.corners} corners, {est.reprojection_px:.2f} px{flag}, "
            f"camera +-{1e3 * est.position_std_m:.1f} mm"
        )

    def status(self) -> str:
        c, v, g = self.logger.counts(), self.plan.views, self.plan.grasps
        return (
            f"{self.board_status()} | hand: {self.logger.hand_state} | views: train {c.train}/{v.train} "
            f"test {c.test}/{v.test} | grasps {c.grasps}/{g.count} ({c.contacts}/{c.touches} touches in contact)"
            f" | {KEYS_HELP}"
        )

    def show_status(self) -> None:
        line = self.status()
        if self._live:  # one terminal row, redrawn in place (a wrapped line could not be cleared)
            try:
                width = os.get_terminal_size(self.out.fileno()).columns or 160  # 0: size never set
            except (OSError, ValueError, io.UnsupportedOperation):
                width = 160
            self._write("\r\x1b[K" + line[: max(width - 1, 20)])
        else:
            self._write(line + "\n")

    def say(self, message: str) -> None:
        self._write(("\r\x1b[K" if self._live else "") + message + "\n")

    def _write(self, text: str) -> None:
        """``text`` on the output, now; a terminal that hung up (EIO) ends the session as SIGHUP does."""
        try:
            self.out.write(text)
            self.out.flush()
        except OSError as exc:
            raise _hangup(exc) from None

    # --- input ------------------------------------------------------------------------------------
    def _keys(self) -> Iterator[str]:
        """The keys one by one, until the end of input, each once the hand's check passed (a fault its heartbeat
        found ends the session before a key queued meanwhile acts). A terminal has none in cbreak mode (Ctrl-D is a
        key): there a read that gives nothing, or fails with EIO, is a hangup, and ends the session as SIGHUP does."""
        fd = _fileno(self.keys)
        terminal = fd is not None and os.isatty(fd)
        while True:
            if fd is None:
                ch = self.keys.read(1)
            else:
                while not select.select([fd], [], [], self.refresh_s)[0]:
                    self._check_hand()
                    if self._live:
                        self.show_status()
                try:
                    ch = os.read(fd, 1).decode(errors="replace")
                except OSError as exc:
                    raise _hangup(exc) from None
                if ch == "" and terminal:
                    raise SignalInterrupt(signal.SIGHUP)
            self._check_hand()
            if ch == "":
                return
            yield ch

    # --- actions ----------------------------------------------------------------------------------
    def plan_complete(self) -> bool:
        c, v = self.logger.counts(), self.plan.views
        return c.train >= v.train and c.test >= v.test and c.grasps >= self.plan.grasps.count

    def view(self) -> None:
        c, v = self.logger.counts(), self.plan.views
        split = next((s for s in ("train", "test") if getattr(c, s) < getattr(v, s)), None)  # train views first
        if split is None:
            self.say(f"all {v.train} train and {v.test} test views of the plan are taken (u undoes one)")
            return
        index = getattr(c, split)
        if self.planner is not None:
            self.planner.before_view(split, index)
        try:
            outcome = self.logger.take_view(split)
        except CaptureRejected as exc:
            self.say(f"view NOT recorded: {exc}")
            return
        self.say(f"view {outcome.frame.id} recorded ({split} {index + 1}/{getattr(v, split)}){outcome.board_note}")

    def grasp(self) -> None:
        c = self.logger.counts()
        if c.grasps >= self.plan.grasps.count:
            self.say(f"all {self.plan.grasps.count} grasps of the plan are taken (u undoes one)")
            return
        self.say(f"grasp {self.logger.next_grasp_index()}: closing the hand")
        try:
            if self.planner is not None:
                outcome = self.planner.grasp(self.logger, self.logger.next_grasp_index())
                if outcome is None:
                    self.say("grasp NOT recorded: no approach touched the object")
                    return
            else:
                outcome = self.logger.take_grasp()
        except CaptureRejected as exc:
            self.say(f"grasp NOT recorded: {exc}")
            return
        missed = [t.finger for t in outcome.touches if not t.in_contact]
        self.say(
            f"grasp {outcome.index} recorded: {len(outcome.touches)} touches, contact on "
            f"{', '.join(outcome.fingers_in_contact) or 'none'}"
            + (f"; no contact on {', '.join(missed)} (recorded)" if missed else "")
            + ("" if outcome.settled else "; fingers had not settled")
        )

    def undo(self) -> None:
        try:
            self.say(f"undone: {self.logger.undo()}")
        except CaptureRejected as exc:
            self.say(str(exc))

    def run(self) -> bool:
        """Serve keys until ``q`` or the end of input; returns whether the plan is complete."""
        actions = {"\n": self.view, "\r": self.view, "g": self.grasp, "u": self.undo}
        with _cbreak(self.keys):  # first, so that keys typed once the status line shows are never flushed
            self.show_status()
            for key in self._keys():
                if key in ("q", "Q", "\x04"):  # q, or Ctrl-D (a literal character in cbreak mode)
                    break
                if key.lower() in actions:
                    actions[key.lower()]()
                    self.show_status()
                elif key.isprintable() and not key.isspace():  # (not an arrow key's escape sequence, not a space)
                    self.say(f"key {key!r} does nothing: {KEYS_HELP}")
                    self.show_status()
        return self.plan_complete()


def run_capture(
    config: RigConfig,
    out: str | Path,
    resume: bool = False,
    keys: TextIO | None = None,
    output: TextIO | None = None,
    on_open=None,
) -> int:
    """``tacsplat capture``: open the rig and the scene, serve the operator, close everything safely.

    Returns 0 (plan complete), 1 (stopped before the plan was complete),
    ``EXIT_FAULT`` (a device failed, the disk filled or another error ended
    the session once it ran; the scene is resumable) or 128 + signum
    (SIGINT, SIGTERM, SIGHUP or SIGQUIT: 130, 143, 129, 131). On a real rig the
    last line printed says which servos confirmed torque off and which did not.
    ``on_open(rig, logger)`` is called once the devices are open (tests inject
    faults through it).
    """
    if config.plan.touches.model != "gel":
        raise ConfigError(
            "plan.touches.model",
            "an operator capture grasps with the hand: use 'gel' (the paper's "
            "touches need no operator: tacsplat sim-capture --touch-model paper)",
            config.source,
        )
    keys = sys.stdin if keys is None else keys
    output = sys.stdout if output is None else output
    out = Path(out)
    code, told = 1, "stopped before the plan was complete.\n"
    hands = []  # the real rig's hand, once made: its torque-off report is the last line
    running = False  # whether the session started (the rig and the scene open)
    try:
        with signals_interrupt(once=True) as ending:
            import_device_modules(config)  # (a signal meanwhile is raised once they are in, the hand not made)
            with open_scene(config, out, resume, on_hand=hands.append) as opened:
                running = True
                try:
                    if _serve(*opened, config, keys, output, on_open):
                        code, told = 0, f"plan complete: scene written to {out}\n"
                except BaseException:  # (the hand's own handler may have raised the signal: ours never saw it)
                    ending()  # the rig closes as the session unwinds: a second signal must not cut that short
                    raise
    except (DeviceError, SimulationError) as fault:
        code, told = EXIT_FAULT, _fault("DEVICE FAULT", fault, out, "Fix the device.")
    except StorageError as fault:  # a full or read-only disk, before or during the session (it says what to do)
        code, told = EXIT_FAULT, _fault("STORAGE FAULT", fault, out)
    except TacsplatError as fault:
        if not running:  # refused before the session (a rig file, --out, a scene to resume): the command's error
            _hand_if_made(config, output, hands)
            raise
        code, told = EXIT_FAULT, _fault("FAULT", fault, out)
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        code, told = 128 + signum, f"interrupted ({signal.Signals(signum).name}).\n"
    except Exception:  # a bug: its traceback follows, and the operator still learns what the hand confirmed
        _hand_if_made(config, output, hands)
        raise
    with end_signals_ignored() if code > 128 else contextlib.nullcontext():  # (a second Ctrl-C: not cut short)
        carry_on = _carry_on(config, out) if code else ""
        _last_words(output, f"\n{told}{carry_on}{'' if config.rig == 'sim' else _hand_line(hands)}")
    return code


def _serve(rig, writer, config: RigConfig, keys, output, on_open) -> bool:
    """The session on an open rig and scene; whether the plan is complete."""
    logger = CaptureLogger(writer, rig.hand, rig.sensors, rig.camera, rig.clock, rig.poses, rig.control)
    if logger.dropped_partial_grasp:
        output.write(
            f"resumed: removed {logger.dropped_partial_grasp} touches of a grasp cut short; it will be redone whole\n"
        )
    planner = None
    if rig.kind == "sim":
        from tacsplat.acquisition.twin_planner import TwinPlanner

        planner = TwinPlanner(rig.twin, config.plan.grasps.seed, config.plan.views)
    if on_open is not None:
        on_open(rig, logger)
    return CaptureSession(rig, logger, config.plan, keys, output, planner).run()


def _last_words(output: TextIO, text: str) -> None:
    """``text`` on ``output``, or, when that fails (a terminal that hung up: EIO), on standard error if that is
    another stream (a log file); nowhere when both fail."""
    for stream in dict.fromkeys(s for s in (output, sys.stderr) if s is not None):
        try:
            stream.write(text)
            stream.flush()
            return
        except OSError as exc:
            log.debug("%s: %s", getattr(stream, "name", stream), exc)


def _hand_line(hands: list) -> str:
    """The last line of a real rig's capture: what the hand's closing confirmed, and only that."""
    report = hands[0].torque_off_report if hands else None
    if report is None:
        return "Hand: not connected; nothing was sent to its servos.\n"
    return f"Hand: {report}.\n"


def _hand_if_made(config: RigConfig, output: TextIO, hands: list) -> None:
    """The hand's line (:func:`_hand_line`) where a real rig's hand was made, for a capture that ends in an error."""
    if hands and config.rig != "sim":
        _last_words(output, "\n" + _hand_line(hands))


def _fault(what: str, fault: Exception, out: Path, fix: str = "") -> str:
    """The report of a fault: what failed, that the scene in ``out`` (if one was written) keeps its records, ``fix``."""
    held = f"The scene in {out} holds every record completed before the fault." if (out / JOURNAL).is_file() else ""
    after = " ".join(filter(None, (held, fix)))
    return f"{what}: {fault}\n" + (f"{after}\n" if after else "")


def _carry_on(config: RigConfig, out: Path) -> str:
    """How to carry on after a stop: the command that resumes the scene in ``out``, or that starts the capture again
    when it never wrote one."""
    started = (out / JOURNAL).is_file()  # the capture wrote a scene in ``out`` (to resume)
    how = "Resume with:" if started else "The capture did not start (no scene was written). Start it again with:"
    rig = shlex.quote(str(config.source or "RIG.yaml"))
    command = f"tacsplat capture --rig {rig} --out {shlex.quote(str(out))}"
    return f"{how}\n  {command}{' --resume' if started else ''}{' --mock' if config.mock else ''}\n"
