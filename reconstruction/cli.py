"""`tacsplat reconstruct` and `tacsplat evaluate` (see tacsplat.cli)."""

from __future__ import annotations

import json
import shlex
import sys
from pathlib import Path

# TrainConfig fields set by `reconstruct` options: errors name the option.
OPTION_OF_FIELD = {
    "iterations": "--iterations", "seed": "--seed", "sh_degree": "--sh-degree", "lambda_t": "--lambda-t",
    "lambda_s": "--lambda-s", "smoothness_depth": "--smoothness-depth", "train_views": "--train-views",
    "backend": "--backend",
}  # fmt: skip


def register(cli) -> None:
    """Add this package's commands to the tree."""
    p = cli.command(
        "reconstruct",
        help="tactile-informed 3DGS: train on a scene directory and evaluate",
        description="Optimise Gaussians on SCENE (paper variants: default = full; --no-touch = +S; "
        "--no-smoothness = +T; both = vanilla 3DGS) and write a run directory: splat.ply, checkpoint.pt, "
        "progress.csv, error_vs_time.png, metrics.json, renders/. Ctrl-C or SIGTERM stop after the current step "
        "with a checkpoint (exit 130 or 143) and print the command that resumes.",
    )
    p.add_argument("scene", help="scene directory")
    p.add_argument("--out", required=True,
                   help="run directory to write: new or empty, or an earlier run with --resume or --overwrite")
    p.add_argument("--iterations", type=int, default=None,
                   help="optimisation steps, >= 1 (unset: 2000, or the run's own with --resume)")
    p.add_argument("--seed", type=int, default=0, help="random seed, 0 to 2^32 - 1")
    p.add_argument("--sh-degree", type=int, default=3, choices=range(4), help="maximum SH degree")
    p.add_argument("--lambda-t", type=float, default=None,
                   help="weight of the transmittance loss L_T, >= 0 (unset: 0.5)")
    p.add_argument("--lambda-s", type=float, default=None,
                   help="weight of the edge-aware smoothness loss L_S, >= 0 (unset: 2.0)")
    p.add_argument("--smoothness-depth", default=None, choices=("expected", "accumulated"),
                   help="depth map of L_S: expected depth inside the silhouette (unset) or the paper's accumulated "
                   "depth (Eq. 5)")
    p.add_argument("--no-touch", action="store_true", help="no touch Gaussians and no L_T")
    p.add_argument("--no-smoothness", action="store_true", help="no L_S (and no depth render)")
    p.add_argument("--train-views", type=int, default=None, metavar="K",
                   help="use only the first K >= 1 training views")
    p.add_argument("--backend", default="auto", choices=("auto", "torch", "cpu", "gsplat"))
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the earlier run in --out (its files only; other files stay)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_reconstruct)

    e = cli.command("evaluate", help="evaluate a reconstruction run: PSNR, SSIM, Chamfer distance, renders")
    e.add_argument("run", help="run directory written by `tacsplat reconstruct`")
    e.add_argument("--gt-mesh", default=None, metavar="PATH",
                   help="ground-truth mesh or point cloud (for imported scenes without gt/)")
    e.add_argument("--backend", default=None, choices=("auto", "torch", "cpu", "gsplat"),
                   help="rasterization backend (default: the run's)")
    e.set_defaults(func=_evaluate)


def config_from_args(args):
    """The TrainConfig of `tacsplat reconstruct`'s options; a ConfigError naming the option out of range."""
    from tacsplat.reconstruction.config import TrainConfig

    config = TrainConfig(seed=args.seed, sh_degree=args.sh_degree, backend=args.backend,
                         train_views=args.train_views, use_touch=not args.no_touch)
    if args.iterations is not None:
        config.iterations = args.iterations
    if args.lambda_t is not None:
        config.lambda_t = args.lambda_t
    if args.lambda_s is not None:
        config.lambda_s = args.lambda_s
    if args.smoothness_depth is not None:
        config.smoothness_depth = args.smoothness_depth
    if args.no_smoothness:
        config.lambda_s = 0.0
    config.validate(OPTION_OF_FIELD)
    return config


def _reconstruct(args) -> int:
    from tacsplat.reconstruction.trainer import TrainingInterrupted, reconstruct

    try:
        metrics = reconstruct(args.scene, args.out, config_from_args(args), resume=args.resume,
                              show_progress=not args.quiet, iterations_override=args.iterations,
                              overwrite=args.overwrite)
    except TrainingInterrupted as stop:
        again = shlex.join(["tacsplat", "reconstruct", args.scene, "--out", args.out, "--resume"])
        print(f"{stop}; continue with:\n  {again}", file=sys.stderr)
        return 128 + stop.signum
    print(json.dumps({k: metrics[k] for k in ("variant", "cd", "psnr", "ssim", "train_seconds", "iterations",
                                              "num_gaussians", "num_touch_gaussians")}, indent=2))
    return 0


def _evaluate(args) -> int:
    from tacsplat.datasets.outputs import claim_output_dir
    from tacsplat.reconstruction.evaluation import evaluate_run
    from tacsplat.reconstruction.run_dir import is_run_folder, run_checkpoint

    if not is_run_folder(Path(args.run)):
        run_checkpoint(args.run)  # refused before anything is written into what is not a run
    with claim_output_dir(args.run, "RUN"):
        metrics = evaluate_run(args.run, gt_path=args.gt_mesh, backend=args.backend)
    print(json.dumps({k: metrics[k] for k in ("variant", "cd", "psnr", "ssim", "num_gaussians")}, indent=2))
    return 0
