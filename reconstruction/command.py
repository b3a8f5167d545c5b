"""`tacsplat reconstruct`'s options: the fields of :class:`ReconstructCommand` and of its TrainConfig, parsed by
tyro (typed dataclasses, help from their docstrings and comments, as gsplat's and nerfstudio's trainers do), in one
order: the method's settings, then those of the ``--config`` file, then the options given."""

from __future__ import annotations

import argparse
import copy
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from tacsplat.errors import ConfigError, UsageError
from tacsplat.options import parse_options
from tacsplat.reconstruction.config import TrainConfig, changed_settings, flat_settings, read_settings, set_fields
from tacsplat.reconstruction.methods import DEFAULT_METHOD, METHODS, get_method, method_config, method_of

MethodName = Literal[tuple(METHODS)]  # the names of reconstruction.methods.METHODS
PROG = "tacsplat reconstruct"
log = logging.getLogger(__name__)


@dataclass
class ReconstructCommand:
    """Optimise Gaussians on SCENE and write a run directory: splat.ply, checkpoint.pt, progress.csv,
    error_vs_time.png, metrics.json, renders/. The settings come from --method, then from the --config file, then
    from the options given; -H says what each one does. Ctrl-C or SIGTERM stop after the current step with a
    checkpoint (exit 130 or 143) and print the command that resumes."""

    scene: Annotated[tyro.conf.Positional[Path], tyro.conf.arg(metavar="SCENE")]
    """the scene directory"""
    out: Path
    """run directory to write: new or empty, or an earlier run with --resume or --overwrite"""
    method: MethodName = DEFAULT_METHOD
    """3dgs, 3dgs+s, 3dgs+t: the paper's Table 3 rows; paper: its method; default: ours"""
    config: Path | None = None
    """YAML file of training settings (field: value; init: and densify: nested), applied after the method's, e.g.
    reconstruction/paper_schedule.yaml, the official code's 30k-step schedule"""
    resume: bool = False
    """continue the run in --out from its last checkpoint, with its own settings: an option given that differs is
    refused, except --iterations, which may raise the step count"""
    overwrite: bool = False
    """replace the earlier run in --out (its files only; other files stay)"""
    train: Annotated[TrainConfig, tyro.conf.arg(name="")] = field(default_factory=TrainConfig)


def parse(argv: list[str], recorded: TrainConfig | None = None) -> ReconstructCommand:
    """The command of ``argv``: its options on the settings of --method and of --config, or on ``recorded`` (a
    run's own settings, which --resume continues with); a UsageError naming the option of a bad value, a ConfigError
    naming the --config file and its key for a bad value the file gives (no option given in its place)."""
    given = _early_options(argv)
    if given.method is not None and given.method not in METHODS:
        raise UsageError("--method", f"unknown method {given.method!r}; choose one of {', '.join(METHODS)}")
    if recorded is None:
        base = method_config(given.method or DEFAULT_METHOD)
    else:
        base = set_fields(copy.deepcopy(recorded), get_method(given.method).overrides if given.method else {})
    from_file = {} if given.config is None else read_settings(given.config)
    try:
        set_fields(base, from_file, given.config)
    except UsageError as exc:  # (a value in place of the init: or densify: settings): the file's, like its keys
        raise ConfigError(exc.key, str(exc).removeprefix(f"{given.config}: {exc.key}: "), given.config) from None
    default = ReconstructCommand(
        scene=tyro.MISSING,
        out=tyro.MISSING,
        method=given.method or DEFAULT_METHOD,
        config=None if given.config is None else Path(given.config),
        train=base,
    )
    command = parse_options(ReconstructCommand, argv, PROG, default, compact=True)
    if problem := command.train.problem():  # (TrainConfig.validate's, naming the option, or the file and its key)
        key, option = problem[0], option_names(command.train).get(problem[0], problem[0])
        flags = {token.split("=", 1)[0] for token in argv}
        if key in from_file and not flags & {option, "--no-" + option.removeprefix("--")}:
            raise ConfigError(key, problem[1], given.config)  # the file's value: no option replaced it
        raise UsageError(option, problem[1])
    if late := [start for start in command.train.never_started() if start.split()[0] in from_file]:
        message = "%s sets %s: at or past --iterations %d, never reached (step numbers do not scale with --iterations)"
        log.warning(message, given.config, ", ".join(late), command.train.iterations)
    return command


def _early_options(argv: list[str]) -> argparse.Namespace:
    """``method`` and ``config`` as ``argv`` gives them (None: not given), read before the rest."""
    early = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    early.add_argument("--method")
    early.add_argument("--config")
    return early.parse_known_args(argv)[0]


def option_names(config: TrainConfig) -> dict[str, str]:
    """``{"densify.max_gaussians": "--densify.max-gaussians", ...}``: the option of each setting, as tyro names it."""
    return {key: "--" + key.replace("_", "-") for key in flat_settings(config.to_json())}


def _trained_on(out: Path, recorded: str, given: str) -> bool:
    """Whether a --device given on resume of a run that recorded ``auto`` names the kind of device its checkpoint
    trained on (what the checkpoint's own device check asks for)."""
    from tacsplat.reconstruction.run_dir import read_checkpoint, run_checkpoint

    return recorded == "auto" and given == read_checkpoint(run_checkpoint(out)).get("device", "cpu")


def resumed(argv: list[str], recorded: TrainConfig, out: Path) -> TrainConfig:
    """The config a --resume continues with: the run's own (``recorded``) with the options given, which may only
    raise --iterations; a UsageError on --resume naming each other option that differs, and a --method given that
    the run was not trained with (even one that sets nothing the run lacks: ``default`` sets nothing)."""
    given = parse(argv, recorded).train
    names = option_names(given)
    changes = [
        f"{names.get(path, path)} {before!r} in the run, {now!r} given"
        for path, before, now in changed_settings(recorded, given)
        if path != "iterations" and not (path == "device" and _trained_on(out, before, now))
    ]
    method, asked = method_of(recorded), _early_options(argv).method  # (as set up: whatever their step counts)
    if changes and method_of(given) != method:
        changes.insert(0, f"--method {method} in the run, {method_of(given)} given")
    elif asked is not None and method_of(parse(argv).train) != method:  # (this command line trains another)
        changes.insert(0, f"--method {method} in the run, {asked} given")
    if changes:  # options of this command line: a usage error, as --iterations below the step reached is
        raise UsageError(
            "--resume",
            f"{out} was trained with other settings than this command line gives "
            f"({'; '.join(changes)}): a resumed run keeps its own settings (only --iterations may "
            "raise its step count); leave those options out, or train into a new --out",
        )
    return given
