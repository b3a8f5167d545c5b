"""`tacsplat reconstruct` and `tacsplat evaluate` (see tacsplat.cli)."""

from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path

from tacsplat.errors import ConfigError, UsageError
from tacsplat.reconstruction.methods import DEFAULT_METHOD, METHODS

def register(cli) -> None:
    """Add this package's commands to the tree."""
    p = cli.command(
        "reconstruct", build=_add_config_options,
        help="tactile-informed 3DGS: train on a scene directory and evaluate",
        description="Optimise Gaussians on SCENE and write a run directory: splat.ply, checkpoint.pt, progress.csv, "
        "error_vs_time.png, metrics.json, renders/. --method picks a row of the paper's Table 3 or ours (default); every "
        "training setting has its own option below (defaults as in TrainConfig). Ctrl-C or SIGTERM stop after the current "
        "step with a checkpoint (exit 130 or 143) and print the command that resumes.",
    )
    p.add_argument("scene", help="scene directory")
    p.add_argument("--out", required=True,
                   help="run directory to write: new or empty, or an earlier run with --resume or --overwrite")
    p.add_argument("--method", default=None, choices=list(METHODS),
                   help="; ".join(f"{m.name}: {m.description}" for m in METHODS.values())
                   + f". Options given explicitly win over the method's settings (default: {DEFAULT_METHOD})")
    p.add_argument("--preset", default=None, choices=("default", "paper"),
                   help="starting settings: default (tuned for few views on a CPU) or paper (the official code's "
                   "30k-step schedule, every step-based number scaled to --iterations); the method and any option "
                   "given apply on top (default: default)")
    p.add_argument("--no-smoothness", action="store_true", help="no L_S and no depth render (same as --lambda-s 0)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last checkpoint, on the scene it was trained on, with its "
                   "own settings: an option given that differs from them is refused, except --iterations, which may "
                   "raise the step count (not below the step reached)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the earlier run in --out (its files only; other files stay)")
    p.set_defaults(func=_reconstruct)

    e = cli.command("evaluate", help="evaluate a reconstruction run: PSNR, SSIM, Chamfer distance, renders")
    e.add_argument("run", help="run directory written by `tacsplat reconstruct`")
    e.add_argument("--gt-mesh", default=None, metavar="PATH",
                   help="ground-truth mesh or point cloud (for imported scenes without gt/)")
    e.add_argument("--backend", default=None, choices=("auto", "torch", "cpu", "gsplat"),
                   help="rasterization backend (default: the run's)")
    e.set_defaults(func=_evaluate)


def _add_config_options(parser) -> None:
    """One option per TrainConfig field (made only when `reconstruct` is on the command line: it imports torch)."""
    from tacsplat.reconstruction.config import TrainConfig
    from tacsplat.reconstruction.options import add_config_options

    parser.set_defaults(config_options=add_config_options(parser, TrainConfig))


def config_from_args(args, iterations: int | None = None):
    """The TrainConfig of `tacsplat reconstruct`'s options: the preset (scaled to ``iterations``, by default
    --iterations), the method's fields, then every option given; a ConfigError naming the option out of range."""
    from tacsplat.reconstruction.config import preset_config
    from tacsplat.reconstruction.methods import get_method, set_fields
    from tacsplat.reconstruction.options import apply_options, option_names

    config = preset_config(args.preset or "default", iterations or getattr(args, "cfg__iterations", None))
    set_fields(config, get_method(args.method or DEFAULT_METHOD).overrides)
    apply_options(config, args, args.config_options)
    if args.no_smoothness:
        config.lambda_s = 0.0
    try:
        config.validate(option_names(args.config_options))
    except ConfigError as exc:
        raise UsageError(exc.key, str(exc).split(": ", 1)[1]) from None
    config.torch_device()
    return config


def refuse_changed_settings(args, recorded) -> None:
    """With --resume: an option given whose value differs from the one the run in --out recorded (``recorded``)
    is a ConfigError on --resume naming each such option and both values (--iterations aside: it may raise the
    step count). --method compares the fields it sets, --preset every setting."""
    from tacsplat.reconstruction.config import changed_settings
    from tacsplat.reconstruction.methods import method_of
    from tacsplat.reconstruction.options import option_names

    given = config_from_args(args, iterations=recorded.iterations)  # (a paper preset scaled as the run's was)
    names = option_names(args.config_options)
    fields = {".".join(o.path) for o in args.config_options if hasattr(args, o.dest)}
    if args.no_smoothness:
        fields.add("lambda_s")
        names["lambda_s"] = "--no-smoothness"
    if args.method is not None:
        fields |= set(METHODS[args.method].overrides)
    changes = [f"{names.get(path, path)} {before!r} in the run, {now!r} given"
               for path, before, now in changed_settings(recorded, given, None if args.preset else fields)
               if path != "iterations"]
    if args.method is not None and method_of(recorded) != method_of(given):
        changes.insert(0, f"--method {method_of(recorded)} in the run, {method_of(given)} given")
    if changes:
        raise ConfigError("--resume", f"{args.out} was trained with other settings than this command line gives "
                          f"({'; '.join(changes)}): a resumed run keeps its own settings (only --iterations may "
                          "raise its step count); leave those options out, or train into a new --out")


def _reconstruct(args) -> int:
    from tacsplat.reconstruction.trainer import TrainingInterrupted, reconstruct

    try:
        config = config_from_args(args)
        metrics = reconstruct(args.scene, args.out, config, resume=args.resume, show_progress=True,
                              iterations_override=config.iterations if hasattr(args, "cfg__iterations") else None,
                              overwrite=args.overwrite, check_resumed=lambda run: refuse_changed_settings(args, run))
    except TrainingInterrupted as stop:
        again = shlex.join(["tacsplat", "reconstruct", args.scene, "--out", args.out, "--resume"])
        print(f"{stop}; continue with:\n  {again}", file=sys.stderr)
        return 128 + stop.signum
    print(json.dumps({k: metrics[k] for k in ("method", "cd", "psnr", "ssim", "train_seconds", "iterations",
                                              "num_gaussians", "num_touch_gaussians")}, indent=2))
    return 0


def _evaluate(args) -> int:
    from tacsplat.datasets.outputs import claim_output_dir
    from tacsplat.files import check_writable
    from tacsplat.reconstruction.evaluation import evaluate_run
    from tacsplat.reconstruction.run_dir import is_run_folder, run_checkpoint

    if not is_run_folder(Path(args.run)):
        run_checkpoint(args.run)  # refused before anything is written into what is not a run
    check_writable(args.run)  # a read-only or full run folder: one error saying which, before the evaluation
    with claim_output_dir(args.run, "RUN"):
        metrics = evaluate_run(args.run, gt_path=args.gt_mesh, backend=args.backend)
    print(json.dumps({k: metrics.get(k) for k in ("method", "cd", "psnr", "ssim", "num_gaussians")}, indent=2))
    return 0
