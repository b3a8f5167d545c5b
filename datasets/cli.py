"""`tacsplat` subcommands of tacsplat.datasets: ``import blender``, ``import nero``, ``import colmap``,
``import nerfstudio``, ``inspect``; their options are the dataclasses below (tacsplat.options)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from tacsplat.errors import ConfigError, UsageError

_FOLDER_NAME = "(default: the dataset folder's name)"  # the --object of import colmap and import nerfstudio


@dataclass
class ImportBlender:
    """import a Blender/NeRF-synthetic dataset (NeRF synthetic, Shiny Blender) into a scene directory

    Convert SRC (transforms_train.json, transforms_val.json, transforms_test.json and their RGBA images) into a
    scene directory: images composited onto the background colour, OpenGL poses converted to the scene format, the
    focal length from camera_angle_x unless fl_x fl_y cx cy w h (top level or per frame) give the camera, the
    train split from transforms_train.json and the test split from the file chosen by --test-split. Shiny
    Blender's disparity maps (r_N_disp.tiff) become the ground truth: the test views' depth and the train views'
    points, as the paper evaluates (the paper's code composites onto black: --background black)."""

    src: tyro.conf.Positional[Path]
    """dataset folder holding transforms_train.json"""
    out: Path
    """new scene directory (must not exist or be empty)"""
    background: str = "white"
    """colour the transparent background is composited onto: white, black or R,G,B (0-255 integers)"""
    test_split: Literal["test", "val"] = "test"
    """which file becomes the scene's test split: transforms_test.json or transforms_val.json"""
    scale: float = 1.0
    """metres per Blender unit (multiplies camera positions; NeRF-synthetic objects are ~2 units across)"""


@dataclass
class ImportNero:
    """import one object of NeRO's Glossy Synthetic dataset (N.png, N-camera.pkl, N-depth.png) into a scene

    Convert SRC (one object's folder, e.g. GlossySynthetic/bell) into a scene directory: the train and test views of
    NeRO's split file (configs/synthetic_split_128.pkl in NeRO's repository: 96 train, 32 test views), images
    composited onto the background colour outside the object's depth mask, the test views' depth and eval_pts.ply
    kept as the ground truth (the paper's code composites onto black: --background black)."""

    src: tyro.conf.Positional[Path]
    """the object's folder"""
    out: Path
    """new scene directory (must not exist or be empty)"""
    split: Annotated[
        Path | None, tyro.conf.arg(metavar="PATH", help_behavior_hint="(default: looked for in SRC and its parent)")
    ] = None
    """NeRO's synthetic_split_128.pkl"""
    background: str = "white"
    """colour outside the object's mask: white, black or R,G,B (0-255 integers)"""
    scale: float = 1.0
    """metres per dataset unit (multiplies camera positions, depths and points)"""


@dataclass
class ImportColmap:
    """import a COLMAP sparse model (text or binary) and its undistorted images into a scene directory

    Convert the COLMAP sparse model SRC (a folder with cameras/images/points3D .txt or .bin, such as sparse/0)
    into a scene directory. Cameras must be PINHOLE or SIMPLE_PINHOLE (or SIMPLE_RADIAL, RADIAL, OPENCV with zero
    distortion): run `colmap image_undistorter` first otherwise. Images of a downscaled folder (images_2 beside a
    full-size model) get their camera's intrinsics scaled to them. The model's 3D points become the scene's sparse
    points (points3D.ply), which `tacsplat reconstruct` starts from."""

    src: tyro.conf.Positional[Path]
    """COLMAP sparse model folder"""
    images: Path
    """folder the model's image names are relative to (or a downscaled copy of it, such as images_2)"""
    out: Path
    """new scene directory (must not exist or be empty)"""
    test_every: int = 8
    """every N-th image (in name order) goes to the test split; 0 puts all in train"""
    scale: float = 1.0
    """metres per COLMAP unit (COLMAP's scale is arbitrary)"""
    object: Annotated[str | None, tyro.conf.arg(metavar="STR", help_behavior_hint=_FOLDER_NAME)] = None
    """object name recorded in scene.json"""


@dataclass
class ImportNerfstudio:
    """import a nerfstudio or instant-ngp dataset (transforms.json and its images) into a scene directory

    Convert SRC (a folder holding transforms.json as ns-process-data or instant-ngp write it, or the file itself)
    into a scene directory: RGBA images composited onto the background colour, distorted images (OPENCV k1 k2 k3
    p1 p2) undistorted onto a pinhole camera, poses mapped back through applied_transform to the original world,
    masks (mask_path) kept, the splits from train_filenames/test_filenames (val_filenames when there is no test
    list) or every N-th frame. Depth maps and point clouds are not imported."""

    src: tyro.conf.Positional[Path]
    """dataset folder holding transforms.json, or the transforms.json file"""
    out: Path
    """new scene directory (must not exist or be empty)"""
    test_every: int = 8
    """without split lists in transforms.json: every N-th frame (in file-name order) goes to the test split; 0 puts
    all in train"""
    scale: float = 1.0
    """metres per dataset unit (multiplies camera positions)"""
    skip_missing: bool = False
    """leave out frames whose image file is missing (with a warning) instead of refusing"""
    object: Annotated[str | None, tyro.conf.arg(metavar="STR", help_behavior_hint=_FOLDER_NAME)] = None
    """object name recorded in scene.json"""
    background: str = "white"
    """colour transparent pixels (an alpha channel) are composited onto: white, black or R,G,B (0-255 integers)"""


@dataclass
class Inspect:
    """summarise a scene directory and list every problem in it

    Validate a scene directory and print frames per split, touches per grasp and finger, the sensor, the bounds
    and every problem found. Exits with 1 when there are problems."""

    dir: tyro.conf.Positional[Path]
    """scene directory"""
    json: bool = False
    """print one JSON object (frames {split: count}, touches, grasps, problems [...], ...)"""
    plot: Path | None = None
    """also save a 3D picture of the cameras, contact points and bounds (PNG, PDF or SVG)"""
    overwrite: bool = False
    """replace an existing --plot file (never one inside the scene)"""


def register(cli) -> None:
    """Add this package's commands to the tree."""
    for options in (ImportBlender, ImportNero, ImportColmap, ImportNerfstudio):
        cli.typed(f"import {options.__name__.removeprefix('Import').lower()}", options, _import)
    cli.typed("inspect", Inspect, _inspect)


# option -> the importer's parameter it gives
_PARAMETERS = {"background": "background_rgb", "images": "images_dir", "object": "object_name"}


def _import(o) -> int:
    """Run the importer of ``o``'s command (``import_<kind>`` of module ``<kind>``), then inspect the scene; an
    option value it refuses is a UsageError (exit 2) naming the option."""
    from . import blender, colmap, nerfstudio, nero  # (here, not above: reading a scene loads none of them)
    from .inspect import run_inspect

    kind = type(o).__name__.removeprefix("Import").lower()
    module = {"blender": blender, "nero": nero, "colmap": colmap, "nerfstudio": nerfstudio}[kind]
    importer = getattr(module, f"import_{kind}")
    options = {_PARAMETERS.get(key, key): value for key, value in vars(o).items()}
    if "background_rgb" in options:
        try:
            options["background_rgb"] = blender.parse_background(o.background)
        except ValueError as exc:
            raise UsageError("--background", str(exc)) from None
    try:
        importer(options.pop("src"), **options)
    except ConfigError as exc:
        if exc.key not in ("scale", "test_every"):
            raise
        raise UsageError("--" + exc.key.replace("_", "-"), str(exc).removeprefix(f"{exc.key}: ")) from None
    return run_inspect(o.out)


def _inspect(o: Inspect) -> int:
    from .inspect import run_inspect

    return run_inspect(o.dir, as_json=o.json, plot=o.plot, overwrite=o.overwrite)
