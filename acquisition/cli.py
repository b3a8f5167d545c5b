"""`tacsplat` subcommands of tacsplat.acquisition: capture (see tacsplat.cli)."""

from __future__ import annotations


def register(cli) -> None:
    """Add this package's commands to the tree."""
    p = cli.command(
        "capture",
        help="operator capture session on a rig (real, --mock, or the twin): views and grasps into a scene directory",
        description="Guides a person at the rig from the terminal. A status line shows the board (seen or not, "
        "reprojection error), the hand and the counts against the plan. Keys: Enter = take a view, g = grasp, "
        "u = undo the last record, q = stop. A device fault leaves the hand with torque off and prints the "
        "command that resumes. Example rigs: acquisition/rigs/{real,mock,sim}.yaml.",
    )
    p.add_argument("--rig", required=True, help="rig YAML file (devices, calibrations, board, capture plan)")
    p.add_argument("--out", required=True, help="scene directory to create (or continue with --resume)")
    p.add_argument("--resume", action="store_true", help="continue a capture that stopped or was killed")
    p.add_argument("--mock", action="store_true",
                   help="emulated devices instead of the real rig's (servo emulator on a pty, video-file tactile "
                   "sensors, a camera that sees a rendered board)")
    p.set_defaults(func=_capture)


def _capture(args) -> int:
    from tacsplat.acquisition.config import load_rig
    from tacsplat.acquisition.session import run_capture

    return run_capture(load_rig(args.rig, mock=args.mock), args.out, resume=args.resume)
