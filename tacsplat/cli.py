"""The ``tacsplat`` console script.

Subcommands are registered per package: each module in ``COMMAND_MODULES``
defines ``register(cli: CommandTree)`` and adds its commands with
``cli.typed("bench rasterizer", Options, run)``: ``Options`` is a dataclass
whose fields are the command's options (parsed by tyro, help from the fields'
docstrings: :mod:`tacsplat.options`; its docstring's first paragraph is the
command's line in ``tacsplat --help``) and ``run(options)`` returns an exit
code (or None for 0). A module imports what is expensive (torch,
numba, MuJoCo) inside ``run``, so that ``tacsplat --help`` imports none.

Exit codes: 0 success, 1 a runtime error (one ``error:`` line), 2 a usage
error (one line naming the option: a bad or missing value, or one out of its
range: :class:`UsageError`), 130 Ctrl-C (0 for ``tacsplat view``, its normal
stop; 128 + the signal where a command stops cleanly on SIGTERM or SIGHUP: 143,
129), 141 when the reader of stdout went away (``| head``).
``-v``, ``-q`` and ``--log-level`` are accepted before or after the
subcommand.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import os
import signal
import sys

from tacsplat import __version__, interrupts
from tacsplat.errors import TacsplatError, UsageError
from tacsplat.interrupts import END_SIGNALS

COMMAND_MODULES = (
    "tacsplat.datasets.cli",
    "tacsplat.reconstruction.cli",
    "tacsplat.drivers.cli",
    "tacsplat.acquisition.cli",
    "tacsplat.apps.demo",
    "tacsplat.apps.paper_bench",
    "tacsplat.apps.touch_bench",
    "tacsplat.apps.bench_rasterizer",
    "tacsplat.apps.bench_sim",
    "tacsplat.apps.bench_gpu",
    "tacsplat.apps.bench_scaling",
    "tacsplat.apps.bench_step",
    "tacsplat.apps.bench_compare",
    "tacsplat.apps.batch",
    "tacsplat.apps.viewer",
)

# The modules of the optional extras (pyproject.toml), by the extra that installs them.
EXTRAS = {
    "mujoco": "sim",
    "coacd": "sim",
    "manifold3d": "sim",
    "dynamixel_sdk": "hardware",
    "serial": "hardware",
    "viser": "viewer",
    "ray": "cluster",
    "gsplat": "cuda",
}

GROUP_HELP = {
    "import": "import a dataset (Blender/NeRF-synthetic, Shiny Blender, Glossy Synthetic, COLMAP, nerfstudio/instant-ngp) "
    "into a scene directory",
    "export": "export a reconstruction: a watertight mesh",
    "bench": "benchmarks: error and run time, medians and ratios against a reference",
    "calibrate": "calibrate the rig: the hand's joints, the wrist camera, the tactile sensors",
    "rig": "the rig as a whole: check it before a capture",
    "tactile": "optical tactile sensors: depth maps from images with a calibration",
}


def _common_options() -> argparse.ArgumentParser:
    """-v, -q and --log-level, accepted by the root and by every subcommand (defaults SUPPRESS, so a
    subcommand's absent option never overwrites one given before it)."""
    common = argparse.ArgumentParser(add_help=False, argument_default=argparse.SUPPRESS)
    group = common.add_argument_group("logging")
    group.add_argument("-v", "--verbose", action="store_true", help="tacsplat's debug logging (other libraries: INFO)")
    group.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only; no progress display")
    levels = ("DEBUG", "INFO", "WARNING", "ERROR")
    group.add_argument("--log-level", type=str.upper, choices=levels, help="logging level (default INFO; DEBUG: as -v)")
    return common


class CommandTree:
    """Builds nested argparse subcommands from space-separated paths."""

    def __init__(self, parser: argparse.ArgumentParser, common: argparse.ArgumentParser, complete: bool = False):
        self._common = common
        self._complete = complete  # each command's parser has its options (for shtab), not only the logging ones
        self._subparsers = {"": parser.add_subparsers(dest="command", metavar="COMMAND")}
        self._parsers: dict[str, argparse.ArgumentParser] = {"": parser}
        self.own_options: set[str] = set()  # the commands that parse their own options
        self._value_options = [s for a in common._actions if a.nargs != 0 for s in a.option_strings]  # --log-level

    def _group(self, path: str) -> argparse._SubParsersAction:
        if path not in self._subparsers:
            parent, _, name = path.rpartition(" ")
            parser = self._group(parent).add_parser(
                name, help=GROUP_HELP.get(path, ""), description=GROUP_HELP.get(path), parents=[self._common]
            )
            parser.set_defaults(func=lambda args, p=parser: (p.print_help(), 2)[1])
            self._parsers[path] = parser
            self._subparsers[path] = parser.add_subparsers(dest=f"{path}_command", metavar="COMMAND")
        return self._subparsers[path]

    def typed(self, path: str, options: type, run, help: str | None = None) -> None:
        """A command whose options are the dataclass ``options`` (parsed by tyro: :mod:`tacsplat.options`; its
        docstring is the description, and its first paragraph the command list's line unless ``help`` is given):
        ``run(values)`` runs it, once its fields ``out`` and ``json`` (what it writes) are known to be writable."""

        def func(args) -> int:
            from tacsplat.files import refuse_unwritable
            from tacsplat.options import parse_options

            values = parse_options(options, args.rest, f"tacsplat {path}")
            for option in ("out", "json"):
                refuse_unwritable(f"--{option}", getattr(values, option, None))
            return run(values)

        self.own(path, help or " ".join(options.__doc__.split("\n\n")[0].split()), func, options)

    def own(self, path: str, help: str, func, options: type | str | None = None) -> None:
        """A command that parses what follows it itself: ``func(args)`` reads it as ``args.rest`` (-v, -q and
        --log-level aside). ``options``: the dataclass it parses, or its dotted name (its module imported only for
        a completion script, which lists its options)."""
        parents = [self._common]
        if self._complete and options is not None:
            from tacsplat.options import options_parser

            if isinstance(options, str):
                module, _, name = options.rpartition(".")
                options = getattr(importlib.import_module(module), name)
            parents.append(options_parser(options))
        parent, _, name = path.strip().rpartition(" ")
        parser = self._group(parent).add_parser(name, help=help, description=help, parents=parents, add_help=False)
        parser.set_defaults(func=func)
        self._parsers[path] = parser
        self.own_options.add(path)

    def _chosen(self, argv: list[str]) -> tuple[str, int]:
        """``(path, index after its last word in argv)``: the words of argv that extend a command's path, up to the
        first that does not (what follows is the command's own: a value that names a command is a value), with
        options, their values and empty words (which name no command) skipped."""
        path, end, value = "", 0, False
        for i, token in enumerate(argv):
            if value:  # the value of the option before it (--log-level DEBUG)
                value = False
            elif token.startswith("-"):
                value = self._takes_value(token)
            elif token.strip():
                if f"{path} {token}".strip() not in self._parsers:
                    break
                path, end = f"{path} {token}".strip(), i + 1
        return path, end

    def _takes_value(self, token: str) -> bool:
        """Whether ``token`` is a logging option (or an abbreviation argparse takes) followed by its value."""
        return len(token) > 2 and "=" not in token and any(o.startswith(token) for o in self._value_options)

    def prog(self, argv: list[str]) -> str:
        """The usage name of the command named in ``argv`` (for usage lines)."""
        return self._parsers[self._chosen(argv)[0]].prog

    def split_own_options(self, argv: list[str]) -> tuple[list[str], list[str]]:
        """``(argv, [])``, or for a command that parses its own options ``(what argparse parses, the rest)``: the
        command line up to the command, with the logging options found after it."""
        path, end = self._chosen(argv)
        if path not in self.own_options:
            return argv, []
        logging_parser = argparse.ArgumentParser(add_help=False, allow_abbrev=False, parents=[self._common])
        logging_options, rest = logging_parser.parse_known_args(argv[end:])
        given = [f"--{k.replace('_', '-')}" + ("" if v is True else f"={v}") for k, v in vars(logging_options).items()]
        return argv[:end] + given, rest


def build_parser(complete: bool = False) -> argparse.ArgumentParser:
    """The parser of the command tree (``complete``: with --print-completion)."""
    common = _common_options()
    parser = argparse.ArgumentParser(
        prog="tacsplat",
        description="Tactile-informed 3D Gaussian Splatting: capture (real rig or MuJoCo twin), "
        "scene datasets, reconstruction and evaluation.",
        parents=[common],
    )
    parser.add_argument("--version", action="version", version=f"tacsplat {__version__}")
    tree = CommandTree(parser, common, complete)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(tree)
    parser.tree = tree
    if complete:
        import shtab

        shtab.add_argument_to(parser, ["--print-completion"], help="print a shell completion script (bash, zsh, tcsh)")
    return parser


def _configure_logging(args: argparse.Namespace) -> None:
    from tacsplat.progress import set_quiet

    quiet = getattr(args, "quiet", False)
    level = getattr(args, "log_level", None) or (
        "DEBUG" if getattr(args, "verbose", False) else "WARNING" if quiet else "INFO"
    )
    logging.basicConfig(level=getattr(logging, level), format="%(levelname)s %(name)s: %(message)s", force=True)
    for handler in logging.getLogger().handlers:  # (a batch's workers log through these handlers too)
        handler.addFilter(_own_debug)
    # at INFO, PyOpenGL (under MuJoCo's renderer) says an optional speed-up is missing, and matplotlib that it built
    # its font cache (a new home's first plot): noise between tacsplat's own lines
    for noisy in ("OpenGL", "matplotlib.font_manager"):
        logging.getLogger(noisy).setLevel(max(logging.WARNING, getattr(logging, level)))
    set_quiet(quiet)


def _own_debug(record: logging.LogRecord) -> bool:
    """Whether a record is shown: at DEBUG only tacsplat's own (other libraries' DEBUG lines, PIL's PNG chunks or
    matplotlib's font search, would bury them), at INFO and above every one."""
    return record.levelno > logging.DEBUG or record.name.partition(".")[0] == "tacsplat"


def main(argv: list[str] | None = None) -> int:
    """Run the command of ``argv`` (default ``sys.argv[1:]``); its exit code (see the module docstring)."""
    try:
        try:
            return _main(argv)
        finally:  # output still buffered for a reader that went away fails here, not at the interpreter's exit
            sys.stdout.flush()
    except BrokenPipeError:
        # The reader of stdout went away (`tacsplat ... | head`): what is left goes to devnull (the recipe of
        # Python's signal docs), and the code is 128 + SIGPIPE, what a shell reports for a program a closed pipe
        # ended (cat, grep), rather than 1, which says the command itself failed.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


def _main(argv: list[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(complete="--print-completion" in argv)
    head, rest = parser.tree.split_own_options(argv)
    args = parser.parse_args(head)
    args.rest = rest
    _configure_logging(args)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        code = args.func(args)
    except UsageError as exc:
        prog = parser.tree.prog(argv)
        print(f"{prog}: error: {exc} (see {prog} --help)", file=sys.stderr)
        return 2
    except TacsplatError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        from tacsplat.files import is_storage_failure, storage_error

        if not is_storage_failure(exc):
            raise
        # a write no command turned into a StorageError itself: still one line naming the file
        print(f"error: {storage_error(exc, exc.filename or 'a file')}", file=sys.stderr)
        return 1
    except ModuleNotFoundError as exc:
        extra = EXTRAS.get((exc.name or "").partition(".")[0])
        if extra is None:
            raise
        print(
            f"error: {parser.tree.prog(argv)} needs the {extra} extra ({exc.name} is not installed): "
            f"pip install 'tacsplat[{extra}]'",
            file=sys.stderr,
        )
        return 1
    except KeyboardInterrupt as exc:  # Ctrl-C: 130; a SignalInterrupt: 128 + its signal (SIGTERM: 143)
        print("interrupted", file=sys.stderr)
        return 128 + getattr(exc, "signum", signal.SIGINT)
    return int(code or 0)


def run() -> None:
    """The program (console script and ``python -m tacsplat``): :func:`main`, then exit with its code.

    First one collection (the command's garbage, cycles included, is finalized as it would have been), then
    ``gc.freeze()``: the interpreter's teardown leaves what is still alive, mostly the imported libraries' objects,
    out of its repeated collections (atexit handlers still run). With torch, matplotlib and trimesh loaded that is
    0.3-0.5 s less of every command's wall time (an import of the three and a plain exit: 2.38-2.46 s; with the
    freeze 1.99-2.10 s; the collection adds 0.03-0.1 s). Not in :func:`main`, which tests call in a process that
    goes on."""
    interrupts.COMMAND_IS_PROCESS = True
    code = main()
    if code - 128 in END_SIGNALS:  # the command ended on a signal: a second one does not cut the exit short
        for s in END_SIGNALS:
            signal.signal(s, signal.SIG_IGN)
    gc.collect()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    run()
