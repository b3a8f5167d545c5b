"""`tacsplat reconstruct`, `tacsplat evaluate` and `tacsplat export mesh` (see tacsplat.cli); reconstruct parses its
own options (:mod:`.command`), the others' are :class:`Evaluate` and :class:`ExportMesh`."""

from __future__ import annotations

import json
import shlex
import signal
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro


@dataclass
class Evaluate:
    """evaluate a reconstruction run: PSNR, SSIM, Chamfer distance, renders

    Evaluates the run's last checkpoint on its scene and writes RUN/metrics.json and RUN/renders/ (and the baked
    RUN/splat.ply of an sh-lit run from before the bake, whose splat.ply holds its unlit colours)."""

    run: tyro.conf.Positional[Path]
    """run directory written by `tacsplat reconstruct`"""
    gt_mesh: Annotated[Path | None, tyro.conf.arg(metavar="PATH")] = None
    """ground-truth mesh or point cloud (for imported scenes without gt/)"""
    backend: Annotated[
        Literal["auto", "torch", "cpu", "gsplat"] | None,
        tyro.conf.arg(metavar="{auto,torch,cpu,gsplat}", help_behavior_hint="(default: the run's)"),
    ] = None
    """rasterization backend"""


@dataclass
class ExportMesh:
    """export a watertight mesh of a reconstruction run (PLY, metres, the scene's frame)

    Renders the run's median depth and colour from cameras around the object (those near the training cameras'
    directions), fuses them and the touches into a signed distance field and extracts its surface (marching cubes):
    vertex colours, outward normals, and an `observed` flag per vertex (a training camera sees it, or a touch lies
    on it). Prints the mesh metrics (F-score at 1/2/5 % of the radius, Chamfer distance, normal consistency,
    watertight) where the scene has a ground truth, and adds them to RUN/metrics.json. An export into the run is
    refused while the run trains or is evaluated."""

    run: tyro.conf.Positional[Path]
    """run directory written by `tacsplat reconstruct`"""
    out: Annotated[Path | None, tyro.conf.arg(metavar="PATH", help_behavior_hint="(default: RUN/mesh.ply)")] = None
    """mesh file, a .ply"""
    voxel: float = 0.01
    """voxel side, as a fraction of the object's radius"""
    views: int = 64
    """cameras on a sphere around the object (those within --cone-deg of a training camera are fused)"""
    cone_deg: float = 30.0
    """fuse the cameras within this angle of a training camera's direction"""
    touches: bool = True
    """fuse the touches' contact points"""
    seal: float = 0.1
    """fill the hollows that open to the outside only through gaps narrower than twice this (of the object's
    radius; 0: none)"""
    all_pieces: Annotated[bool, tyro.conf.arg(help_behavior_hint="(default: only the largest, the object)")] = False
    """keep every connected piece"""
    overwrite: bool = False
    """replace an existing --out that export mesh did not write (never the run's or its scene's own files)"""


def register(cli) -> None:
    """Add this package's commands to the tree."""
    command = "tactile-informed 3DGS: train on a scene directory and evaluate"
    cli.own("reconstruct", command, _reconstruct, "tacsplat.reconstruction.command.ReconstructCommand")

    cli.typed("evaluate", Evaluate, _evaluate)
    cli.typed("export mesh", ExportMesh, _export_mesh)


def _export_mesh(args: ExportMesh) -> int:
    from tacsplat.errors import ConfigError, InvalidInputError, UsageError
    from tacsplat.files import check_writable, refuse_unwritable
    from tacsplat.reconstruction.meshing import MeshConfig, check_mesh_out, check_mesh_path, export_mesh
    from tacsplat.reconstruction.run_dir import is_run_folder, run_checkpoint

    shared = ("voxel", "views", "cone_deg", "touches", "seal")  # the options named as MeshConfig's fields
    config = MeshConfig(**{k: getattr(args, k) for k in shared}, object_only=not args.all_pieces)
    try:
        config.validate()
    except InvalidInputError as exc:
        key, _, message = str(exc).partition(": ")
        raise UsageError("--" + key.replace("_", "-"), message) from None
    try:
        if args.out is not None:
            check_mesh_path(args.out)
        if not is_run_folder(args.run):
            run_checkpoint(args.run)  # refused before anything is created or written (a SceneFormatError)
        # (before the export: the run's splat.ply or its scene's ground truth is never replaced)
        check_mesh_out(args.run, args.run / "mesh.ply" if args.out is None else args.out, args.overwrite)
    except ConfigError as exc:
        raise UsageError(exc.key, str(exc).partition(": ")[2]) from None
    # a read-only or full folder: one error saying which, before the export (a missing --out folder is created
    # only once the mesh is made: a failed export leaves none)
    folder = args.run if args.out is None else args.out.parent
    if folder.is_dir():
        check_writable(folder)
    else:
        refuse_unwritable("--out", args.out)
    summary = export_mesh(args.run, args.out, config, overwrite=args.overwrite)
    print(json.dumps(summary, indent=2))
    return 0


def _reconstruct(args) -> int:
    from tacsplat.files import refuse_unwritable
    from tacsplat.interrupts import signals_interrupt
    from tacsplat.reconstruction.command import parse, resumed
    from tacsplat.reconstruction.trainer import TrainingInterrupted, reconstruct

    command = parse(args.rest)
    refuse_unwritable("--out", command.out)
    command.train.torch_device()
    again = shlex.join(["tacsplat", "reconstruct", str(command.scene), "--out", str(command.out), "--resume"])
    try:
        with signals_interrupt((signal.SIGTERM, signal.SIGHUP)):  # (training has its own: stop after the step)
            metrics = reconstruct(
                command.scene,
                command.out,
                command.train,
                resume=command.resume,
                overwrite=command.overwrite,
                resumed=lambda recorded: resumed(args.rest, recorded, command.out),
            )
    except TrainingInterrupted as stop:
        print(f"{stop}; continue with:\n  {again}", file=sys.stderr)
        return 128 + stop.signum
    except KeyboardInterrupt as stop:  # outside the training's steps (the evaluation after them, most likely)
        if not (Path(command.out) / "checkpoint.pt").is_file():
            raise  # (nothing to continue: the command's "interrupted")
        signum = getattr(stop, "signum", signal.SIGINT)
        print(f"interrupted ({signal.Signals(signum).name}); continue with:\n  {again}", file=sys.stderr)
        return 128 + signum
    shown = ("method", "cd", "psnr", "ssim", "train_seconds", "iterations", "num_gaussians", "num_touch_gaussians")
    print(json.dumps({k: metrics[k] for k in shown}, indent=2))
    return 0


def _evaluate(args: Evaluate) -> int:
    from tacsplat.datasets.outputs import claim_output_dir
    from tacsplat.files import check_writable
    from tacsplat.reconstruction.evaluation import evaluate_run
    from tacsplat.reconstruction.run_dir import is_run_folder, run_checkpoint

    if not is_run_folder(args.run):
        run_checkpoint(args.run)  # refused before anything is written into what is not a run
    check_writable(args.run)  # a read-only or full run folder: one error saying which, before the evaluation
    with claim_output_dir(args.run, "RUN"):
        metrics = evaluate_run(args.run, gt_path=args.gt_mesh, backend=args.backend)
    print(json.dumps({k: metrics.get(k) for k in ("method", "cd", "psnr", "ssim", "num_gaussians")}, indent=2))
    return 0
