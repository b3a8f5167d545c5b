"""The ``tacsplat`` console script.

Subcommands are registered per package: each module in ``COMMAND_MODULES``
defines ``register(cli: CommandTree)`` and adds its commands with
``cli.command("bench rasterizer", help=..., description=...)``, which returns
an ``argparse.ArgumentParser`` to add arguments to and to
``set_defaults(func=handler)`` on. A handler takes the parsed namespace and
returns an exit code (or None for 0). Command modules import heavy packages
(torch, mujoco, SDKs) inside their handlers, so ``tacsplat --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from tacsplat import __version__
from tacsplat.errors import TacsplatError

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
)

GROUP_HELP = {
    "import": "import a dataset (Blender/NeRF-synthetic, COLMAP, nerfstudio/instant-ngp) into a scene directory",
    "bench": "benchmarks: error and run time, medians and ratios against a reference",
    "calibrate": "calibrate real devices (wrist camera, tactile sensors)",
    "tactile": "optical tactile sensors: depth maps from images with a calibration",
}


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default only when it says something (not for required options, flags, or None)."""

    def _get_help_string(self, action):
        if action.required or action.default in (None, False, argparse.SUPPRESS) or "(default:" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


class CommandTree:
    """Builds nested argparse subcommands from space-separated paths."""

    def __init__(self, parser: argparse.ArgumentParser):
        self._root = parser
        self._subparsers = {"": parser.add_subparsers(dest="command", metavar="COMMAND")}
        self._parsers: dict[str, argparse.ArgumentParser] = {"": parser}

    def _group(self, path: str) -> argparse._SubParsersAction:
        if path not in self._subparsers:
            parent, _, name = path.rpartition(" ")
            parser = self._group(parent).add_parser(
                name, help=GROUP_HELP.get(path, ""), description=GROUP_HELP.get(path)
            )
            parser.set_defaults(func=lambda args, p=parser: (p.print_help(), 2)[1])
            self._parsers[path] = parser
            self._subparsers[path] = parser.add_subparsers(dest=f"{path}_command", metavar="COMMAND")
        return self._subparsers[path]

    def command(self, path: str, help: str, description: str | None = None) -> argparse.ArgumentParser:
        parent, _, name = path.strip().rpartition(" ")
        parser = self._group(parent).add_parser(
            name,
            help=help,
            description=description or help,
            formatter_class=_HelpFormatter,
        )
        self._parsers[path] = parser
        return parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tacsplat",
        description="Tactile-informed 3D Gaussian Splatting: capture (real rig or MuJoCo twin), "
        "scene datasets, reconstruction and evaluation.",
    )
    parser.add_argument("--version", action="version", version=f"tacsplat {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    tree = CommandTree(parser)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(tree)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        code = args.func(args)
    except TacsplatError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
