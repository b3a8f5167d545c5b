"""Import a Blender / NeRF-synthetic dataset (NeRF synthetic, Shiny Blender) into a scene directory.

The layout: ``transforms_train.json``, ``transforms_val.json`` and
``transforms_test.json`` beside the image folders, each with the horizontal
field of view ``camera_angle_x`` (radians; square pixels, centred principal
point) and ``frames`` whose ``file_path`` usually has no extension
(``./train/r_0`` means ``train/r_0.png``, see :func:`image_path`) and whose
``transform_matrix`` is an OpenGL camera-to-world pose. Explicit intrinsics
(``fl_x fl_y cx cy w h``, and ``camera_angle_y``: the BlenderNeRF add-on writes
them, and a lens shift moves ``cx cy``) win over ``camera_angle_x``, at the top
level or per frame, read as nerfstudio's ``transforms.json`` is
(:func:`read_intrinsics`); ``w`` and ``h`` must be the image's size, and lens
distortion is refused. Images are RGBA with a transparent background, composited
here onto a chosen colour (straight alpha). Other per-frame keys (``rotation``)
are ignored.

Shiny Blender (Ref-NeRF) ships a disparity map beside each image,
``r_N_disp.tiff``: 16 bits, whose first channel as OpenCV reads it (as the
paper's official code, ``helpers.py``, and Zip-NeRF's loader read it) divided
by 65535 is ``1 / (1 + z)``, ``z`` the depth along the optical axis (multinerf
and the official code back-project it as z-depth), 0 on the background. Where
they exist they become the scene's ground truth, the way the paper evaluates
(``data_making/refnerf_to_data.py``): each test view's depth is its ``gt/``
depth map (``cd``), and ``cd_paper``'s ground-truth cloud is the train views'
depth back-projected, 5000 random pixels of each view (a fixed seed here, none
there) within ``GT_MAX_DISTANCE`` of its camera. A test view's normal map,
``r_N_normal.png`` (world-frame ``rgb * 2 / 255 - 1``, as multinerf decodes
and compares it), is kept with its depth: the evaluation's normal error uses
it.
"""

from __future__ import annotations

import json
import reprlib
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

import cv2
import numpy as np

from tacsplat.errors import ConfigError, SceneFormatError
from tacsplat.geometry import focal_from_fov, intrinsics_matrix, opengl_to_opencv, rigidity_problem, unproject_depth
from tacsplat.progress import progress_bar
from tacsplat.types import CameraIntrinsics

from .records import as_size, camera_problem, is_finite_number
from .writer import new_import

BACKGROUNDS = {"white": (255, 255, 255), "black": (0, 0, 0)}
GT_POINTS_PER_VIEW = 5000  # cd_paper's ground truth: pixels back-projected per train view (the official code's)
GT_MAX_DISTANCE = 14.5  # dataset units: farther from the camera is background (the official code's filter)
LENS_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")  # nerfstudio's distortion, which this importer does not undistort


def parse_background(text: str) -> tuple[int, int, int]:
    """``white``, ``black`` or ``R,G,B`` with 0-255 integers."""
    if text in BACKGROUNDS:
        return BACKGROUNDS[text]
    parts = text.split(",")
    try:
        rgb = tuple(int(p) for p in parts)
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0 <= c <= 255 for c in rgb):
        raise ValueError(f"background must be white, black or R,G,B with integers 0-255, got {text!r}")
    return rgb


def check_options(scale: float, test_every: int = 0) -> None:
    """An importer's metres per dataset unit (finite, positive) and hold-out interval (an integer >= 0); a
    ConfigError naming the option otherwise."""
    if not (isinstance(scale, (int, float)) and np.isfinite(scale) and scale > 0):
        raise ConfigError("scale", f"must be a finite positive number of metres per unit, got {scale!r}")
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 0:
        raise ConfigError("test_every", f"must be an integer >= 0 (0: no test split), got {test_every!r}")


def hold_out(count: int, test_every: int, path: Path, field: str, what: str) -> list[str]:
    """The splits of ``count`` views in order: every ``test_every``-th one, the first included, is a test view
    (the 3DGS / LLFF hold-out; 0: none); a SceneFormatError naming ``path`` and ``field`` when no train view is
    left."""
    splits = ["test" if test_every and i % test_every == 0 else "train" for i in range(count)]
    if "train" not in splits:
        raise SceneFormatError(
            path,
            field,
            f"no train frame to import: the test split takes every {test_every}-th of the {count} {what}, the first "
            "included; --test-every 0 (test_every=0) keeps them all for training",
        )
    return splits


def check_readable(path: Path, field: str | None = None, what: str = "image") -> None:
    """A SceneFormatError naming the file (and ``field``, the record that lists it) unless it exists in a format
    OpenCV reads here; OpenEXR is not one (this OpenCV is built without it), and the error says how to convert."""
    try:
        exists = path.is_file()
    except OSError as exc:  # (a name too long for the file system)
        raise SceneFormatError(path, field, f"not a readable {what}: {exc.strerror}") from None
    if not exists:
        raise SceneFormatError(path, field, f"missing {what} (no such file)")
    if not cv2.haveImageReader(str(path)):
        raise SceneFormatError(
            path,
            field,
            (
                "OpenEXR images are not supported (OpenCV here is built without OpenEXR): convert them to PNG, 8 or 16 "
                "bits, sRGB (Blender writes linear EXR: e.g. oiiotool r_0.exr --colorconvert linear sRGB -d uint16 -o "
                "r_0.png, or render with File Format PNG) and point file_path at them"
                if path.suffix.lower() == ".exr"
                else "not a format OpenCV reads: convert it to PNG"
            ),
        )


def read_raw(
    path: Path, field: str | None = None, what: str = "image", size: tuple[int, int] | None = None, of: str = ""
) -> np.ndarray:
    """An image file as OpenCV reads it (BGR(A) or grey, any depth); errors as :func:`check_readable`'s, and one
    unless the image is ``size`` (w, h) pixels, the size ``of`` (its camera, the first image) has."""
    check_readable(path, field, what)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SceneFormatError(path, field, f"unreadable {what} (damaged or truncated?)")
    if size is not None and raw.shape[1::-1] != tuple(size):
        raise SceneFormatError(path, field, f"{what} is {raw.shape[1]}x{raw.shape[0]}, but {of} is {size[0]}x{size[1]}")
    return raw


def read_rgba(
    path: Path, field: str | None = None, size: tuple[int, int] | None = None, of: str = "", what: str = "image"
) -> np.ndarray:
    """An image file as float RGB(A) in [0, 1], [H, W, 3 or 4] (8- or 16-bit, grey or colour); errors as
    :func:`read_raw`'s."""
    raw = read_raw(path, field, what, size, of)
    scale = float(np.iinfo(raw.dtype).max) if np.issubdtype(raw.dtype, np.integer) else 1.0
    img = (raw.astype(np.float64) / scale).reshape(*raw.shape[:2], -1)  # grey (+ alpha), or BGR (+ alpha)
    color = np.repeat(img[:, :, :1], 3, axis=2) if img.shape[2] < 3 else img[:, :, 2::-1]
    return np.concatenate([color, img[:, :, 1:2] if img.shape[2] == 2 else img[:, :, 3:4]], axis=2)


def over_background(rgba: np.ndarray, background_rgb) -> np.ndarray:
    """Straight-alpha ``rgb * a + background * (1 - a)`` as float RGB [H, W, 3] in [0, 1] (RGB without alpha as it
    is; an alpha of 1 leaves it exactly as it is too)."""
    rgb = rgba[:, :, :3]
    if rgba.shape[2] == 4:
        a = rgba[:, :, 3:4]
        rgb = rgb * a + (np.asarray(background_rgb, dtype=np.float64) / 255.0) * (1.0 - a)
    return rgb


def composite(rgba: np.ndarray, background_rgb) -> np.ndarray:
    """:func:`over_background` as uint8 RGB [H, W, 3]."""
    return np.clip(np.rint(over_background(rgba, background_rgb) * 255.0), 0, 255).astype(np.uint8)


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")  # what a file_path without one may name, tried in this order


def image_path(folder: Path, file_path: str) -> Path:
    """The image a NeRF-style ``file_path`` relative to ``folder`` names: the file as written when it exists or ends
    in an image suffix, else the first that exists of it with one of IMAGE_SUFFIXES appended (NeRF synthetic's
    ``./train/r_0`` is ``train/r_0.png``; instant-ngp resolves it so), else the ``.png`` one."""
    p = folder / file_path
    if p.suffix.lower() in IMAGE_SUFFIXES or p.is_file():
        return p
    found = (p.with_name(p.name + suffix) for suffix in IMAGE_SUFFIXES)
    return next((c for c in found if c.is_file()), p.with_name(p.name + ".png"))


def disparity_path(image_path: Path) -> Path:
    """Shiny Blender's disparity map of an image: ``r_0.png`` -> ``r_0_disp.tiff``."""
    return image_path.with_name(image_path.stem + "_disp.tiff")


def read_disparity_depth(path: Path, shape: tuple[int, int], field: str | None = None) -> np.ndarray:
    """The z-depth [H, W] (dataset units, float64; 0 on the background) of a Shiny Blender disparity TIFF (module
    docstring); a SceneFormatError naming the file unless it is a 16-bit map of ``shape``."""
    raw = read_raw(path, field, "disparity map", shape[::-1], "its image")
    if raw.dtype != np.uint16:
        raise SceneFormatError(path, field, f"expected a 16-bit disparity map, got {raw.dtype}")
    disparity = (raw if raw.ndim == 2 else raw[:, :, 0]).astype(np.float64) / 65535.0
    with np.errstate(divide="ignore"):
        return np.where(disparity > 0, 1.0 / disparity - 1.0, 0.0)


def read_normal_map(path: Path, depth: np.ndarray, field: str | None = None) -> np.ndarray:
    """Shiny Blender's world-frame unit normals [H, W, 3] float32 of ``r_N_normal.png`` (module docstring), 0 where
    ``depth`` has no surface."""
    normal = read_rgba(path, field, depth.shape[::-1], "its depth", "normal map")[:, :, :3] * 2.0 - 1.0
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    keep = (depth > 0)[..., None] & (length > 0.5)  # (a quantised unit vector is within 1 % of unit length)
    return np.where(keep, normal / np.maximum(length, 1e-12), 0.0).astype(np.float32)


def read_index(index: Path, missing: str) -> dict:
    """A dataset's JSON index file (an object with a non-empty ``frames`` list); a SceneFormatError naming it
    otherwise, ``missing`` saying what was expected where it does not exist."""
    if not index.is_file():
        raise SceneFormatError(index, None, f"missing ({missing})")
    try:
        data = json.loads(index.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise SceneFormatError(index, None, f"not valid JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise SceneFormatError(index, None, f"expected a JSON object, got {type(data).__name__}")
    if not isinstance(data.get("frames"), list) or not data["frames"]:
        raise SceneFormatError(index, "frames", "expected a non-empty list")
    return data


def _read_split(src: Path, name: str) -> tuple[Path, dict]:
    index = src / f"transforms_{name}.json"
    data = read_index(index, "expected a Blender/NeRF-synthetic dataset folder")
    angle = data.get("camera_angle_x")
    if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not 0 < angle < np.pi:
        raise SceneFormatError(index, "camera_angle_x", f"expected a field of view in (0, pi) radians, got {angle!r}")
    return index, data


def transforms_value(key: str, data: dict, raw: dict, field: str, default=None) -> tuple:
    """``key``'s value for frame ``raw`` (named ``field``, ``frames[3]``) of a NeRF-style transforms file whose top
    level is ``data``: the top level's (it wins, as in nerfstudio), else the frame's, else ``default``; (value, the
    field it is in)."""
    if key in data:
        return data[key], key
    return raw.get(key, default), f"{field}.{key}"


def read_intrinsics(
    data: dict, raw: dict, field: str, index: Path, image_size: Callable[[], tuple[int, int]]
) -> tuple[float, float, float, float, int, int]:
    """Frame ``raw``'s pinhole ``(fx, fy, cx, cy, w, h)`` in the NeRF-style transforms file ``index``, each where
    :func:`transforms_value` finds it: ``fl_x`` and ``fl_y``, else the fields of view ``camera_angle_x`` and
    ``camera_angle_y`` (radians), fy defaulting to fx; ``cx`` and ``cy``, the centre by default; ``w`` and ``h``
    (whole floats too, as instant-ngp writes them), ``image_size()`` by default. A SceneFormatError naming the
    field for a camera the scene format cannot hold."""

    def value(key: str, default=None):
        return transforms_value(key, data, raw, field, default)[0]

    def refuse(key: str, why: str) -> NoReturn:
        raise SceneFormatError(index, transforms_value(key, data, raw, field)[1], why)

    size = {key: value(key) for key in ("w", "h")}
    if None in size.values():  # the image's size
        default = image_size()
        size = {key: default[axis] if size[key] is None else size[key] for axis, key in enumerate(size)}
    for key, side in size.items():
        if as_size(side) is None:
            refuse(key, f"expected a whole number of pixels (1080 or 1080.0), got {side!r}")
    w, h = as_size(size["w"]), as_size(size["h"])
    focal = {}
    for key, angle_key, side in (("fl_x", "camera_angle_x", w), ("fl_y", "camera_angle_y", h)):
        focal[key], angle = value(key), value(angle_key)
        if focal[key] is None and angle is not None:
            if not is_finite_number(angle) or not 0 < angle < np.pi:
                refuse(angle_key, f"expected a field of view in (0, pi) radians, got {angle!r}")
            focal[key] = focal_from_fov(float(angle), side)
    fx, fy = focal["fl_x"], focal["fl_x"] if focal["fl_y"] is None else focal["fl_y"]
    cx, cy = value("cx", w / 2), value("cy", h / 2)
    if problem := camera_problem(fx, fy, cx, cy, w, h):
        refuse(*problem)
    return float(fx), float(fy), float(cx), float(cy), w, h


def _camera(index: Path, data: dict, i: int, default_size: tuple[int, int]) -> CameraIntrinsics:
    """Frame ``i``'s camera (:func:`read_intrinsics`, ``default_size`` without w and h); a SceneFormatError naming
    the field of a non-zero distortion coefficient."""
    raw, field = data["frames"][i], f"frames[{i}]"
    fx, fy, cx, cy, w, h = read_intrinsics(data, raw, field, index, lambda: default_size)
    for key in LENS_KEYS:
        k, where = transforms_value(key, data, raw, field, 0)
        if k != 0:
            raise SceneFormatError(
                index,
                where,
                f"{key} = {k!r}: lens distortion, which import blender does not undistort; undistort the images first "
                "(or import the file with tacsplat import nerfstudio, which does)",
            )
    return CameraIntrinsics(intrinsics_matrix(fx, fy, cx, cy), w, h)


def frame_file_path(index: Path, frames: list, i: int) -> str:
    """``frames[i]``'s ``file_path`` in the index file ``index``; a SceneFormatError naming them unless the frame is
    an object with a ``file_path`` string."""
    raw = frames[i]
    if not isinstance(raw, dict) or not isinstance(raw.get("file_path"), str):
        raise SceneFormatError(index, f"frames[{i}].file_path", "expected an object with a file_path string")
    return raw["file_path"]


def pose_from_opengl(raw, index: Path, field: str) -> np.ndarray:
    """The OpenGL camera-to-world ``transform_matrix`` of a NeRF-style ``transforms.json`` as the OpenCV
    camera-to-world pose of the scene format, re-orthonormalised when off by float rounding only; a
    SceneFormatError naming ``index`` and ``field`` otherwise."""
    try:
        T = np.array(raw, dtype=np.float64)  # (a copy: it is changed below)
    except (TypeError, ValueError, OverflowError):  # not numbers, ragged rows, an int too large for a float
        T = None
    if T is None or T.shape != (4, 4):
        got = f"shape {T.shape}" if T is not None and T.ndim else reprlib.repr(raw)
        raise SceneFormatError(index, field, f"expected a 4x4 matrix of numbers, got {got}")
    if problem := rigidity_problem(T, atol=1e-4):
        raise SceneFormatError(index, field, f"not a rigid transform: {problem}")
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ Vt
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return opengl_to_opencv(T)


def import_blender(src, out, background_rgb=(255, 255, 255), test_split: str = "test", scale: float = 1.0) -> Path:
    """Convert a Blender/NeRF-synthetic dataset in ``src`` into a scene directory ``out``.

    ``transforms_train.json`` becomes the train split and
    ``transforms_{test_split}.json`` (``"test"`` or ``"val"``) the test split.
    ``scale`` (metres per Blender unit) multiplies the camera positions, e.g. to
    give a NeRF-synthetic object (about 2 units across) a graspable size.
    Shiny Blender's disparity maps, where present, become the ground truth (module docstring).
    ``out`` is claimed as the ``--out`` of a writing command (``datasets.outputs``). Returns ``out``.
    """
    src, out = Path(src), Path(out)
    if test_split not in ("test", "val"):
        raise ConfigError("test_split", f"must be 'test' or 'val', got {test_split!r}")
    check_options(scale)
    splits = [("train", *_read_split(src, "train")), ("test", *_read_split(src, test_split))]

    # A camera without w and h has the first image's size; every image must have its camera's.
    first_image = image_path(src, frame_file_path(splits[0][1], splits[0][2]["frames"], 0))
    first_size = read_rgba(first_image, f"{splits[0][1].name} frames[0]").shape[1::-1]

    first_test = image_path(src, frame_file_path(splits[1][1], splits[1][2]["frames"], 0))
    with_depth = disparity_path(first_test).is_file()  # Shiny Blender: every view has its disparity map
    ground_truth = "disparity maps (*_disp.tiff): test views' depth, train views' points"
    rng = np.random.default_rng(0)  # the ground-truth points' pixels
    gt_points = []
    total = sum(len(data["frames"]) for *_, data in splits)
    with (
        new_import(
            out,
            _camera(*splits[0][1:], 0, first_size),
            "blender",
            src,
            None,
            background_rgb=list(background_rgb),
            test_split_file=f"transforms_{test_split}.json",
            scale=scale,
            **({"ground_truth": ground_truth} if with_depth else {}),
        ) as writer,
        progress_bar(total=total, desc=f"import {src.name}", unit="frame") as progress,
    ):
        for split, index, data in splits:
            frames = data["frames"]
            for i, raw in enumerate(frames):
                field = f"frames[{i}]"
                path = image_path(src, frame_file_path(index, frames, i))
                intr = _camera(index, data, i, first_size)
                sized = any(key in data or key in raw for key in ("w", "h"))  # else the first image's size
                size_of = f"its camera (w x h in {index.name})" if sized else first_image.name
                rgba = read_rgba(path, f"{index.name} {field}", (intr.width, intr.height), size_of)
                pose = pose_from_opengl(raw.get("transform_matrix"), index, f"{field}.transform_matrix")
                pose[:3, 3] *= scale
                gt_depth = gt_normal = None
                if with_depth:
                    depth = scale * read_disparity_depth(disparity_path(path), (intr.height, intr.width), field)
                    if split == "train":
                        gt_points.append(_sample_points(depth, intr.K, pose, GT_MAX_DISTANCE * scale, rng))
                    else:
                        gt_depth = depth.astype(np.float32)
                        normal_path = path.with_name(path.stem + "_normal.png")
                        gt_normal = read_normal_map(normal_path, depth, field) if normal_path.is_file() else None
                writer.add_frame(composite(rgba, background_rgb), pose, split, gt_depth, intr, gt_normal=gt_normal)
                progress.update()
        if gt_points and sum(map(len, gt_points)):
            writer.set_gt_points(np.concatenate(gt_points))
    return out


def _sample_points(depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, max_distance: float, rng) -> np.ndarray:
    """World points [<= GT_POINTS_PER_VIEW, 3] of random pixels of a depth map with surface (depth > 0) closer than
    ``max_distance`` to the camera."""
    points = unproject_depth(depth, K, T_world_cam)  # [M, 3]
    points = points[np.linalg.norm(points - T_world_cam[:3, 3], axis=1) < max_distance]
    if len(points) > GT_POINTS_PER_VIEW:
        points = points[rng.choice(len(points), GT_POINTS_PER_VIEW, replace=False)]
    return points
