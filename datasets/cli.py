"""`tacsplat` subcommands of tacsplat.datasets: ``import blender``, ``import colmap``, ``import nerfstudio``,
``inspect``."""

from __future__ import annotations

import argparse

from tacsplat.errors import ConfigError, UsageError


def _background(text: str) -> tuple[int, int, int]:
    from .blender import parse_background

    try:
        return parse_background(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def register(cli) -> None:
    """Add this package's commands to the tree."""
    p = cli.command(
        "import blender",
        help="import a Blender/NeRF-synthetic dataset (NeRF synthetic, Shiny Blender) into a scene directory",
        description="Convert SRC (transforms_train.json, transforms_val.json, transforms_test.json and their RGBA "
        "images) into a scene directory: images composited onto the background colour, OpenGL poses converted to "
        "the scene format, the train split from transforms_train.json and the test split from the file chosen by "
        "--test-split.",
    )
    p.add_argument("src", metavar="SRC", help="dataset folder holding transforms_train.json")
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        default=argparse.SUPPRESS,
        help="new scene directory (must not exist or be empty)",
    )
    p.add_argument(
        "--background",
        type=_background,
        default="white",
        metavar="white|black|R,G,B",
        help="colour the transparent background is composited onto (R,G,B as 0-255 integers)",
    )
    p.add_argument(
        "--test-split",
        choices=("test", "val"),
        default="test",
        help="which file becomes the scene's test split: transforms_test.json or transforms_val.json",
    )
    p.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="metres per Blender unit (multiplies camera positions; NeRF-synthetic objects are ~2 units across)",
    )
    p.set_defaults(func=_import_blender)

    p = cli.command(
        "import colmap",
        help="import a COLMAP sparse model (text or binary) and its undistorted images into a scene directory",
        description="Convert the COLMAP sparse model SRC (a folder with cameras/images/points3D .txt or .bin, such "
        "as sparse/0) into a scene directory. Cameras must be PINHOLE or SIMPLE_PINHOLE (or SIMPLE_RADIAL, RADIAL, "
        "OPENCV with zero distortion): run `colmap image_undistorter` first otherwise.",
    )
    p.add_argument("src", metavar="SRC", help="COLMAP sparse model folder")
    p.add_argument(
        "--images",
        required=True,
        metavar="DIR",
        default=argparse.SUPPRESS,
        help="folder the model's image names are relative to",
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        default=argparse.SUPPRESS,
        help="new scene directory (must not exist or be empty)",
    )
    p.add_argument(
        "--test-every",
        type=int,
        default=8,
        metavar="N",
        help="every N-th image (in name order) goes to the test split; 0 puts all in train",
    )
    p.add_argument("--scale", type=float, default=1.0, help="metres per COLMAP unit (COLMAP's scale is arbitrary)")
    p.add_argument(
        "--object",
        default=argparse.SUPPRESS,
        help="object name recorded in scene.json (when omitted: the dataset folder's name)",
    )
    p.set_defaults(func=_import_colmap)

    p = cli.command(
        "import nerfstudio",
        help="import a nerfstudio or instant-ngp dataset (transforms.json and its images) into a scene directory",
        description="Convert SRC (a folder holding transforms.json as ns-process-data or instant-ngp write it, or the "
        "file itself) into a scene directory: distorted images (OPENCV k1 k2 k3 p1 p2) undistorted onto a pinhole "
        "camera, poses mapped back through applied_transform to the original world, masks (mask_path) kept, the "
        "splits from train_filenames/test_filenames (val_filenames when there is no test list) or every N-th frame. "
        "Depth maps and point clouds are not imported.",
    )
    p.add_argument("src", metavar="SRC", help="dataset folder holding transforms.json, or the transforms.json file")
    p.add_argument(
        "--out",
        required=True,
        metavar="DIR",
        default=argparse.SUPPRESS,
        help="new scene directory (must not exist or be empty)",
    )
    p.add_argument(
        "--test-every",
        type=int,
        default=8,
        metavar="N",
        help="without split lists in transforms.json: every N-th frame (in file-name order) goes to the "
        "test split; 0 puts all in train",
    )
    p.add_argument("--scale", type=float, default=1.0, help="metres per dataset unit (multiplies camera positions)")
    p.add_argument(
        "--skip-missing",
        action="store_true",
        help="leave out frames whose image file is missing (with a warning) instead of refusing",
    )
    p.add_argument(
        "--object",
        default=argparse.SUPPRESS,
        help="object name recorded in scene.json (when omitted: the dataset folder's name)",
    )
    p.set_defaults(func=_import_nerfstudio)

    p = cli.command(
        "inspect",
        help="summarise a scene directory and list every problem in it",
        description="Validate a scene directory and print frames per split, touches per grasp and finger, the "
        "sensor, the bounds and every problem found. Exits with 1 when there are problems.",
    )
    p.add_argument("dir", metavar="DIR", help="scene directory")
    p.add_argument(
        "--json",
        action="store_true",
        default=argparse.SUPPRESS,
        help="print one JSON object (frames {split: count}, touches, grasps, problems [...], ...)",
    )
    p.add_argument(
        "--plot",
        metavar="PNG",
        default=argparse.SUPPRESS,
        help="also save a 3D picture of the cameras, contact points and bounds",
    )
    p.set_defaults(func=_inspect)


_IMPORT_OPTIONS = {"scale": "--scale", "test_every": "--test-every"}  # the importers' keys of option values


def _importing(run, args) -> int:
    """Run an importer (``run()``), then inspect the scene; an option value it refuses is a UsageError (exit 2)
    naming the option."""
    from .inspect import run_inspect

    try:
        run()
    except ConfigError as exc:
        if exc.key not in _IMPORT_OPTIONS:
            raise
        raise UsageError(_IMPORT_OPTIONS[exc.key], str(exc).removeprefix(f"{exc.key}: ")) from None
    return run_inspect(args.out)


def _import_blender(args) -> int:
    from .blender import import_blender

    return _importing(
        lambda: import_blender(
            args.src, args.out, background_rgb=args.background, test_split=args.test_split, scale=args.scale
        ),
        args,
    )


def _import_colmap(args) -> int:
    from .colmap import import_colmap

    return _importing(
        lambda: import_colmap(
            args.src,
            args.images,
            args.out,
            test_every=args.test_every,
            scale=args.scale,
            object_name=getattr(args, "object", None),
        ),
        args,
    )


def _import_nerfstudio(args) -> int:
    from .nerfstudio import import_nerfstudio

    return _importing(
        lambda: import_nerfstudio(
            args.src,
            args.out,
            test_every=args.test_every,
            scale=args.scale,
            skip_missing=args.skip_missing,
            object_name=getattr(args, "object", None),
        ),
        args,
    )


def _inspect(args) -> int:
    from .inspect import picture_format, plot_formats, run_inspect

    plot = getattr(args, "plot", None)
    if plot is not None and picture_format(plot) not in plot_formats():
        raise UsageError(
            "--plot",
            f"cannot save a picture as .{picture_format(plot)}; use one of "
            f"{', '.join('.' + f for f in plot_formats())}",
        )
    return run_inspect(args.dir, as_json=getattr(args, "json", False), plot=plot)
