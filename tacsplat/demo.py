"""`tacsplat demo`: the README's main job (see `make demo`)."""

from __future__ import annotations


def register(cli) -> None:
    parser = cli.command("demo", help="the main job: simulated capture of a glossy object, reconstruction without and with touch, report")
    parser.add_argument("--out", default="demo-output", help="output folder")
    parser.set_defaults(func=run)


def run(args) -> int:
    from tacsplat.errors import TacsplatError

    raise TacsplatError("the demo needs the simulator and the trainer, which have not landed yet")
