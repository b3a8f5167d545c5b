"""Import a Blender / NeRF-synthetic dataset (NeRF synthetic, Shiny Blender) into a scene directory.

The layout: ``transforms_train.json``, ``transforms_val.json`` and
``transforms_test.json`` beside the image folders, each with the horizontal
field of view ``camera_angle_x`` (radians; square pixels, centred principal
point) and ``frames`` whose ``file_path`` usually has no extension
(``./train/r_0`` means ``train/r_0.png``) and whose ``transform_matrix`` is an
OpenGL camera-to-world pose. Images are RGBA with a transparent background,
composited here onto a chosen colour (straight alpha). Other per-frame keys
(``rotation``, Shiny Blender's depth and normal maps) are ignored.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from tacsplat.errors import ConfigError, SceneFormatError
from tacsplat.geometry import focal_from_fov, intrinsics_matrix, opengl_to_opencv, rigidity_problem
from tacsplat.progress import progress_bar
from tacsplat.types import CameraIntrinsics

from .outputs import claim_output_dir
from .records import SceneMeta
from .writer import SceneWriter, check_new_scene_dir, removed_on_failure

BACKGROUNDS = {"white": (255, 255, 255), "black": (0, 0, 0)}


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


def check_scale(scale: float) -> None:
    """An importer's metres per dataset unit: a ConfigError naming ``scale`` unless finite and positive."""
    if not (isinstance(scale, (int, float)) and np.isfinite(scale) and scale > 0):
        raise ConfigError("scale", f"must be a finite positive number of metres per unit, got {scale!r}")


def check_readable(path: Path, field: str | None = None, what: str = "image") -> None:
    """A SceneFormatError naming the file (and ``field``, the record that lists it) unless it exists in a format
    OpenCV reads here; OpenEXR is not one (this OpenCV is built without it), and the error says how to convert."""
    if not path.is_file():
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


def read_raw(path: Path, field: str | None = None, what: str = "image") -> np.ndarray:
    """An image file as OpenCV reads it (BGR(A) or grey, any depth); errors as :func:`check_readable`'s."""
    check_readable(path, field, what)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SceneFormatError(path, field, f"unreadable {what} (damaged or truncated?)")
    return raw


def read_rgba(path: Path, field: str | None = None) -> np.ndarray:
    """An image file as float RGB(A) in [0, 1], [H, W, 3 or 4] (8- or 16-bit, grey or colour); errors name the
    file and ``field`` (:func:`check_readable`)."""
    raw = read_raw(path, field)
    scale = float(np.iinfo(raw.dtype).max) if np.issubdtype(raw.dtype, np.integer) else 1.0
    img = raw.astype(np.float64) / scale
    if img.ndim == 2:
        img = img[:, :, None]
    channels = img.shape[2]
    if channels == 1:
        return np.repeat(img, 3, axis=2)
    if channels == 2:  # grey + alpha
        return np.concatenate([np.repeat(img[:, :, :1], 3, axis=2), img[:, :, 1:]], axis=2)
    if channels == 3:
        return img[:, :, ::-1]
    return np.concatenate([img[:, :, 2::-1], img[:, :, 3:4]], axis=2)


def composite(rgba: np.ndarray, background_rgb) -> np.ndarray:
    """Straight-alpha ``rgb * a + background * (1 - a)`` as uint8 RGB [H, W, 3]."""
    rgb = rgba[:, :, :3]
    if rgba.shape[2] == 4:
        a = rgba[:, :, 3:4]
        rgb = rgb * a + (np.asarray(background_rgb, dtype=np.float64) / 255.0) * (1.0 - a)
    return np.clip(np.rint(rgb * 255.0), 0, 255).astype(np.uint8)


def _image_path(src: Path, file_path: str) -> Path:
    p = src / file_path
    return p if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".exr") else p.with_name(p.name + ".png")


def _read_split(src: Path, name: str) -> tuple[Path, float, list[dict]]:
    index = src / f"transforms_{name}.json"
    if not index.is_file():
        raise SceneFormatError(index, None, "missing (expected a Blender/NeRF-synthetic dataset folder)")
    try:
        data = json.loads(index.read_text())
    except ValueError as exc:
        raise SceneFormatError(index, None, f"not valid JSON: {exc}") from exc
    angle = data.get("camera_angle_x") if isinstance(data, dict) else None
    if isinstance(angle, bool) or not isinstance(angle, (int, float)) or not 0 < angle < np.pi:
        raise SceneFormatError(index, "camera_angle_x", f"expected a field of view in (0, pi) radians, got {angle!r}")
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise SceneFormatError(index, "frames", "expected a non-empty list")
    return index, float(angle), frames


def pose_from_opengl(raw, index: Path, field: str) -> np.ndarray:
    """The OpenGL camera-to-world ``transform_matrix`` of a NeRF-style ``transforms.json`` as the OpenCV
    camera-to-world pose of the scene format, re-orthonormalised when off by float rounding only; a
    SceneFormatError naming ``index`` and ``field`` otherwise."""
    try:
        T = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        T = np.zeros(0)
    if T.shape != (4, 4):
        raise SceneFormatError(index, field, f"expected a 4x4 matrix, got {np.shape(raw)}")
    problem = rigidity_problem(T, atol=1e-4)
    if problem:
        raise SceneFormatError(index, field, f"not a rigid transform: {problem}")
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T = T.copy()
    T[:3, :3] = U @ Vt
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return opengl_to_opencv(T)


def import_blender(src, out, background_rgb=(255, 255, 255), test_split: str = "test", scale: float = 1.0) -> Path:
    """Convert a Blender/NeRF-synthetic dataset in ``src`` into a scene directory ``out``.

    ``transforms_train.json`` becomes the train split and
    ``transforms_{test_split}.json`` (``"test"`` or ``"val"``) the test split.
    ``scale`` (metres per Blender unit) multiplies the camera positions, e.g. to
    give a NeRF-synthetic object (about 2 units across) a graspable size.
    ``out`` is claimed as the ``--out`` of a writing command (``datasets.outputs``). Returns ``out``.
    """
    src, out = Path(src), Path(out)
    if test_split not in ("test", "val"):
        raise ConfigError("test_split", f"must be 'test' or 'val', got {test_split!r}")
    check_scale(scale)
    splits = [("train", *_read_split(src, "train")), ("test", *_read_split(src, test_split))]

    # The image size comes from the first image; every split shares it.
    first_index, _, first_frames = splits[0][1:]
    first_image = _image_path(src, str(first_frames[0].get("file_path", "")))
    height, width = read_rgba(first_image, f"{first_index.name} frames[0]").shape[:2]

    def intrinsics_for(angle: float) -> CameraIntrinsics:
        f = focal_from_fov(angle, width)
        return CameraIntrinsics(intrinsics_matrix(f, f, width / 2.0, height / 2.0), width, height)

    meta = SceneMeta(
        source="import",
        object=src.resolve().name,
        extra={
            "importer": "blender",
            "source_path": str(src.resolve()),
            "background_rgb": list(background_rgb),
            "test_split_file": f"transforms_{test_split}.json",
            "scale": scale,
        },
    )
    total = sum(len(frames) for *_, frames in splits)
    check_new_scene_dir(out)  # before the claim, which would put its lock file among someone's files
    with (
        claim_output_dir(out),
        removed_on_failure(out),
        SceneWriter.create(out, intrinsics_for(splits[0][2]), meta) as writer,
        progress_bar(total=total, desc=f"import {src.name}", unit="frame") as progress,
    ):
        for split, index, angle, frames in splits:
            intr = intrinsics_for(angle)
            for i, raw in enumerate(frames):
                field = f"frames[{i}]"
                if not isinstance(raw, dict) or not isinstance(raw.get("file_path"), str):
                    raise SceneFormatError(index, f"{field}.file_path", "expected an object with a file_path string")
                image_path = _image_path(src, raw["file_path"])
                rgba = read_rgba(image_path, f"{index.name} {field}")
                if rgba.shape[:2] != (height, width):
                    raise SceneFormatError(
                        image_path,
                        f"{index.name} {field}",
                        f"image is {rgba.shape[1]}x{rgba.shape[0]}, but {first_image.name} is {width}x{height}",
                    )
                pose = pose_from_opengl(raw.get("transform_matrix"), index, f"{field}.transform_matrix")
                pose[:3, 3] *= scale
                writer.add_frame(composite(rgba, background_rgb), pose, split=split, intrinsics=intr)
                progress.update()
    return out
