"""Import a nerfstudio or instant-ngp dataset (``transforms.json`` beside its images) into a scene directory.

It reads what ``ns-process-data`` and instant-ngp's ``colmap2nerf.py`` write, the way nerfstudio's own data
parser reads it:

* Intrinsics (:func:`~tacsplat.datasets.blender.read_intrinsics`) ``fl_x fl_y cx cy w h`` at the top level (shared; a top-level key wins, as in nerfstudio) or per
  frame. ``w`` and ``h`` may be whole floats (instant-ngp writes ``1080.0``). Without ``fl_x``, instant-ngp's
  ``camera_angle_x`` (and ``camera_angle_y``) give the focal lengths; ``cx`` and ``cy`` default to the centre,
  ``w`` and ``h`` to the image's size.
* ``camera_model``: a perspective model (``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL``,
  ``OPENCV``; none given means perspective) with ``k1 k2 k3 p1 p2``. Distorted images (and their masks) are
  undistorted with OpenCV onto a pinhole camera of the same size whose every pixel sees the scene
  (``cv2.getOptimalNewCameraMatrix`` with alpha 0): that camera is the frame's K, since the scene format holds
  undistorted images. Fisheye and spherical models, and ``k4`` (an r^8 term OpenCV's model lacks), are refused.
* ``transform_matrix``, OpenGL camera-to-world, goes through :func:`~tacsplat.datasets.blender.pose_from_opengl`.
  ns-process-data re-orients the COLMAP world (z up) and records that as ``applied_transform`` (and a scale as
  ``applied_scale``): the poses are mapped back to the original world, as nerfstudio's
  ``transform_poses_to_original_space`` does (translation / applied_scale, then the inverse of
  applied_transform), so a scene imported from ns-process-data shares the COLMAP model's frame. ``scale``
  (metres per dataset unit) then multiplies positions.
* Splits: ``train_filenames`` and ``test_filenames`` (``val_filenames`` when there is no test list) decide them;
  frames in no list are left out. Without lists, every ``test_every``-th frame in file-name order (nerfstudio's
  ``interval`` evaluation mode, the 3DGS hold-out) is a test view; 0 puts every frame in train.
* ``mask_path`` (a non-zero colour = use the pixel, an alpha channel ignored; on every frame or on none, as
  nerfstudio requires) becomes the scene's per-frame mask (``masks/``, ``mask_path`` in the scene's
  ``transforms.json``).
* A ``file_path`` without an image suffix names the image with one (``./train/r_0`` is ``train/r_0.png``), as
  instant-ngp resolves it (:func:`~tacsplat.datasets.blender.image_path`); ``mask_path`` is taken as written, as
  nerfstudio takes it.
* Frames whose image is missing are one error listing them, or with ``skip_missing`` are left out with a
  warning (and listed in scene.json).
* ``ply_file_path`` (ns-process-data's ``sparse_pc.ply``: the COLMAP model's points, relative to the
  transforms.json's folder as nerfstudio resolves it) becomes the scene's sparse points, where training's G_c
  start (as splatfacto's do): mapped into the scene's world exactly as the poses are (``applied_scale``, the
  inverse of ``applied_transform``, then ``scale``); colours from its ``red green blue`` (0-255), mid-grey for a
  PLY without them. A missing, unreadable or empty PLY is a warning naming it, and the scene has no sparse points
  (nerfstudio, too, goes on without them; training triangulates its own).
* ``depth_file_path`` is not imported (training reads no depth maps): a warning. It, and a ``ply_file_path``
  left out, are listed in ``extra.not_imported`` in scene.json.

Images are stored as RGB PNG. An alpha channel (straight alpha) is composited onto ``background_rgb`` (white by
default, as ``import blender``), before any undistortion, as nerfstudio's and instant-ngp's loaders composite RGBA
images onto a background: the colour under transparent pixels is no training data. Opaque images are stored as
they are; a frame's ``mask_path`` stays its mask.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import NoReturn

import cv2
import numpy as np
from PIL import Image

from tacsplat.errors import ConfigError, SceneFormatError
from tacsplat.geometry import intrinsics_matrix, rigidity_problem
from tacsplat.progress import progress_bar
from tacsplat.types import CameraIntrinsics

from .blender import (
    check_options,
    check_readable,
    composite,
    hold_out,
    image_path,
    over_background,
    pose_from_opengl,
    read_index,
    read_intrinsics,
    read_raw,
    read_rgba,
    transforms_value,
)
from .records import is_finite_number, pose_problem, sparse_points_problem
from .writer import new_import

log = logging.getLogger(__name__)

PERSPECTIVE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "PERSPECTIVE")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order of its radial-tangential coefficients
SPLIT_LISTS = ("train_filenames", "val_filenames", "test_filenames")
MAX_CORNER_SCALE = 2.0  # distortion at the image corner: distorted over undistorted radius (distortion_problem)
MAX_TANGENTIAL = 0.1  # tangential distortion: the largest shift of a point, over its radius (distortion_problem)
_PIXEL_CENTRE_SHIFT = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])  # ours (+0.5) -> OpenCV's (0)
MID_GREY = 128  # the colour of the points of a PLY without colours


@dataclass(frozen=True)
class Camera:
    """A frame's camera as the dataset gives it: pinhole K and OpenCV distortion (k1 k2 p1 p2 k3)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, float, float, float, float]


@dataclass
class _SourceFrame:
    position: int  # index in the file's ``frames`` list, for error messages
    raw: dict
    name: Path  # file_path, normalised
    image: Path
    split: str | None = None

    @property
    def field(self) -> str:
        return f"frames[{self.position}]"


def _source_frames(index: Path, data: dict) -> list[_SourceFrame]:
    """The frames in file-name order (nerfstudio's), with their image paths."""
    frames, seen = [], {}
    for i, raw in enumerate(data["frames"]):
        if not isinstance(raw, dict) or not isinstance(raw.get("file_path"), str) or not raw["file_path"]:
            raise SceneFormatError(index, f"frames[{i}].file_path", "expected an object with a file_path string")
        if "mask_path" in raw and (not isinstance(raw["mask_path"], str) or not raw["mask_path"]):
            raise SceneFormatError(index, f"frames[{i}].mask_path", f"expected a path string, got {raw['mask_path']!r}")
        name = Path(raw["file_path"])
        if name in seen:
            raise SceneFormatError(
                index, f"frames[{i}].file_path", f"{raw['file_path']!r} again (also frames[{seen[name]}])"
            )
        seen[name] = i
        frames.append(_SourceFrame(i, raw, name, image_path(index.parent, raw["file_path"])))
    return sorted(frames, key=lambda f: f.name)


def _assign_splits(index: Path, data: dict, frames: list[_SourceFrame]) -> bool:
    """Splits from the file's lists; False when it has none. A frame in no list keeps split None."""
    lists = {key: data[key] for key in SPLIT_LISTS if key in data}
    known = {f.name for f in frames}
    for key, names in lists.items():
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise SceneFormatError(index, key, "expected a list of file paths")
        lists[key] = {Path(n) for n in names}
        if unknown := sorted(str(n) for n in lists[key] - known):
            raise SceneFormatError(
                index, key, f"{len(unknown)} file paths are no frame's file_path: {_listed(unknown)}"
            )
    if not lists:
        return False
    train = lists.get("train_filenames", set())
    test_key = "test_filenames" if "test_filenames" in lists else "val_filenames"
    test = lists.get(test_key, set())
    if shared := sorted(str(n) for n in train & test):
        raise SceneFormatError(
            index,
            test_key,
            f"{', '.join(shared[:5])} also in train_filenames: a frame is a train or a test view, not both",
        )
    for f in frames:
        f.split = "train" if f.name in train else "test" if f.name in test else None
    return True


def _listed(names: list[str], most: int = 5) -> str:
    return ", ".join(names[:most]) + (" ..." if len(names) > most else "")


def _image_size(frame: _SourceFrame) -> tuple[int, int]:
    """The (w, h) of the frame's image, from its header."""
    check_readable(frame.image, frame.field)
    try:
        with Image.open(frame.image) as img:
            return img.size
    except OSError as exc:
        raise SceneFormatError(frame.image, frame.field, f"unreadable image: {exc}") from exc


def _camera(frame: _SourceFrame, data: dict, index: Path) -> Camera:
    def value(key: str, default=None):
        return transforms_value(key, data, frame.raw, frame.field, default)[0]

    def refuse(key: str, why: str) -> NoReturn:
        raise SceneFormatError(index, transforms_value(key, data, frame.raw, frame.field)[1], why)

    if (model := value("camera_model", "PERSPECTIVE")) not in PERSPECTIVE_MODELS:
        refuse(
            "camera_model",
            f"camera model {model!r} is not supported: only perspective models "
            f"({', '.join(PERSPECTIVE_MODELS)}); undistort the images to a pinhole camera first",
        )
    if value("is_fisheye", False):
        refuse("is_fisheye", "fisheye cameras are not supported; undistort the images first")
    fx, fy, cx, cy, w, h = read_intrinsics(data, frame.raw, frame.field, index, partial(_image_size, frame))
    if (k4 := value("k4", 0.0)) != 0:
        refuse(
            "k4",
            f"k4 = {k4!r}: a radial r^8 term, which OpenCV's perspective model lacks; only k1 k2 k3 p1 p2 are supported",
        )
    distortion = {key: value(key, 0.0) for key in DISTORTION_KEYS}
    if bad := next((key for key, v in distortion.items() if not is_finite_number(v)), None):
        refuse(bad, f"expected a finite number, got {distortion[bad]!r}")
    camera = Camera(fx, fy, cx, cy, w, h, tuple(map(float, distortion.values())))
    if problem := distortion_problem(camera):
        refuse(*problem)
    return camera


def distortion_problem(camera: Camera) -> tuple[str, str] | None:
    """``(key, why)`` when the distortion is no lens's over this image, or None.

    Every pixel must see exactly one ray, and the lens must stay a perspective one:

    1. The model ``(x, y) -> (x_d, y_d)`` is invertible over the image: radially, ``r (1 + k1 r^2 + k2 r^4 +
       k3 r^6)`` keeps growing until it reaches the farthest image corner, and the Jacobian determinant of the
       whole model (tangential terms included) stays positive on that disc. A model that folds back sends two
       rays to some pixels and none to others, and OpenCV's undistortion returns nonsense.
    2. At the corner, the distorted radius is within a factor MAX_CORNER_SCALE of the undistorted one. Real
       perspective lenses stay well inside (a wide-angle webcam's k1 -0.28, k2 0.09 gives 0.8 at a corner
       radius of 1); beyond it the undistorted camera's focal length is off by about that factor (k1 = 50 turned
       88 px into 1046 px): coefficients in the wrong units, or a fisheye lens, which this model cannot describe.
    3. The tangential (decentering) part moves no point by more than MAX_TANGENTIAL of its radius: it comes from
       lens elements a fraction of a millimetre off the axis; calibrations give |p1|, |p2| ~ 1e-3, a shift well
       under 1 % at the corner.
    """
    k1, k2, p1, p2, k3 = camera.distortion
    if not any(camera.distortion):
        return None
    x = (np.array([0.0, camera.width]) - camera.cx) / camera.fx
    y = (np.array([0.0, camera.height]) - camera.cy) / camera.fy
    corner = float(np.hypot(*np.meshgrid(x, y)).max())  # distorted (image) radius of the farthest corner
    coefficients = f"k1 {k1:g}, k2 {k2:g}, k3 {k3:g} (OpenCV's model, on normalised image coordinates)"
    r = np.linspace(0.0, MAX_CORNER_SCALE * corner, 2001)  # undistorted radii
    distorted = r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6)
    reached = np.flatnonzero(distorted >= corner)
    end = reached[0] if reached.size else len(r) - 1
    terms = {"k1": abs(k1) * r[end] ** 2, "k2": abs(k2) * r[end] ** 4, "k3": abs(k3) * r[end] ** 6}
    radial = max(terms, key=terms.get)  # the coefficient that dominates at the corner
    folds = np.flatnonzero(np.diff(distorted[: end + 1]) <= 0)
    if folds.size:
        return radial, (
            f"the distortion folds the image back: the distorted radius grows only up to "
            f"{distorted[folds[0]]:.3g}, short of the image corner at {corner:.3g}, so pixels near the "
            f"corners would see two rays or none; no lens does this: check {coefficients}"
        )
    scale = corner / r[end] if reached.size else 0.0
    if not 1 / MAX_CORNER_SCALE <= scale <= MAX_CORNER_SCALE:
        size = f"{scale:.3g}" if reached.size else f"less than {1 / MAX_CORNER_SCALE:g}"
        return radial, (
            f"the distortion scales the image corner by {size} (distorted over undistorted radius), "
            f"beyond a perspective lens's 1/{MAX_CORNER_SCALE:g} to {MAX_CORNER_SCALE:g}: check "
            f"{coefficients}; a fisheye lens needs undistorting first"
        )
    angle = np.linspace(0.0, 2 * np.pi, 181)
    xu, yu = r[1 : end + 1, None] * np.cos(angle), r[1 : end + 1, None] * np.sin(angle)
    rr = xu**2 + yu**2
    factor = 1 + k1 * rr + k2 * rr**2 + k3 * rr**3
    g = 2 * k1 + 4 * k2 * rr + 6 * k3 * rr**2  # d(factor)/dx = g x, d(factor)/dy = g y
    cross = g * xu * yu + 2 * p1 * xu + 2 * p2 * yu  # d(x_d)/dy = d(y_d)/dx
    det = (factor + g * xu**2 + 2 * p1 * yu + 6 * p2 * xu) * (factor + g * yu**2 + 6 * p1 * yu + 2 * p2 * xu) - cross**2
    shift = np.hypot(2 * p1 * xu * yu + p2 * (rr + 2 * xu**2), p1 * (rr + 2 * yu**2) + 2 * p2 * xu * yu)
    tangential = "p1" if abs(p1) >= abs(p2) else "p2"
    if (det <= 0).any():
        return tangential, (
            f"the tangential distortion p1 {p1:g}, p2 {p2:g} folds the image back within its "
            "corners (pixels there would see two rays or none); no lens does this"
        )
    if (shift > MAX_TANGENTIAL * np.sqrt(rr)).any():
        return tangential, (
            f"the tangential distortion p1 {p1:g}, p2 {p2:g} moves the image corners by "
            f"{(shift / np.sqrt(rr)).max():.0%} of their radius, beyond a lens's "
            f"{MAX_TANGENTIAL:.0%} (decentering is ~1e-3): check p1 and p2"
        )
    return None


def undistortion(camera: Camera) -> tuple[CameraIntrinsics, tuple[np.ndarray, np.ndarray] | None]:
    """The pinhole camera of the undistorted images and OpenCV's remap tables to them (None: no distortion).

    The new camera keeps the image size and sees nothing outside the distorted image (alpha 0). OpenCV puts
    pixel centres at integers and the scene format at +0.5: K is shifted by half a pixel both ways.
    """
    K = intrinsics_matrix(camera.fx, camera.fy, camera.cx, camera.cy)
    size = (camera.width, camera.height)
    if not any(camera.distortion):
        return CameraIntrinsics(K, *size), None
    K_cv = _PIXEL_CENTRE_SHIFT @ K
    dist = np.array(camera.distortion)
    new_cv, _ = cv2.getOptimalNewCameraMatrix(K_cv, dist, size, alpha=0)
    maps = cv2.initUndistortRectifyMap(K_cv, dist, None, new_cv, size, cv2.CV_32FC1)
    new_K = np.linalg.solve(_PIXEL_CENTRE_SHIFT, new_cv)
    new_K[0, 1] = new_K[1, 0] = 0.0
    return CameraIntrinsics(new_K, *size), maps


def _applied_transform(data: dict, index: Path) -> tuple[np.ndarray | None, float]:
    """ns-process-data's ``applied_transform`` [4, 4] (None if absent) and ``applied_scale`` (1 if absent)."""
    applied = None
    if "applied_transform" in data:
        try:
            A = np.asarray(data["applied_transform"], dtype=np.float64)
        except (TypeError, ValueError, OverflowError):  # not numbers, ragged rows, an int too large for a float
            A = np.zeros(0)
        if A.shape not in ((3, 4), (4, 4)):
            raise SceneFormatError(index, "applied_transform", f"expected a 3x4 matrix of numbers, got {np.shape(A)}")
        applied = np.vstack([A[:3], [0.0, 0.0, 0.0, 1.0]])
        if problem := rigidity_problem(applied, atol=1e-6):
            raise SceneFormatError(index, "applied_transform", f"not a rigid transform: {problem}")
    scale = data.get("applied_scale", 1.0)
    if not is_finite_number(scale) or scale <= 0:
        raise SceneFormatError(index, "applied_scale", f"expected a finite positive number, got {scale!r}")
    return applied, float(scale)


def _read_mask(path: Path, camera: Camera, frame: _SourceFrame) -> np.ndarray:
    """A mask file as uint8 0/255 [H, W]: any non-zero colour channel means use the pixel. An alpha channel is no
    part of it (an editor saves an opaque one: it would keep every pixel)."""
    raw = read_raw(path, f"{frame.field}.mask_path", "mask", (camera.width, camera.height), "the image")
    keep = raw != 0 if raw.ndim == 2 else (raw[:, :, :3] != 0).any(axis=2)  # (OpenCV reads grey + alpha as BGRA)
    return np.where(keep, 255, 0).astype(np.uint8)


def _select_frames(index: Path, data: dict, test_every: int, skip_missing: bool) -> tuple[list[_SourceFrame], dict]:
    """The frames to import, each with its split, and what was left out ({"left_out": [...], "skipped_missing":
    [...]}, file paths as written)."""
    frames = _source_frames(index, data)
    has_lists = _assign_splits(index, data, frames)
    if left_out := [f.raw["file_path"] for f in frames if has_lists and f.split is None]:
        log.warning(
            "%s: %d frames are in none of %s and are left out: %s",
            index,
            len(left_out),
            "/".join(SPLIT_LISTS),
            _listed(left_out),
        )
        frames = [f for f in frames if f.split is not None]
    missing = [f.raw["file_path"] for f in frames if not f.image.is_file()]
    if missing and not skip_missing:
        raise SceneFormatError(
            index,
            "frames",
            f"the images of {len(missing)} of {len(frames)} frames are missing: {_listed(missing, 10)} "
            "(--skip-missing imports the others)",
        )
    if missing and len(missing) == len(frames):
        raise SceneFormatError(
            index,
            "frames",
            f"the images of all {len(frames)} frames are missing: {_listed(missing, 10)}; nothing to import",
        )
    if missing:
        log.warning("%s: skipping %d frames whose image is missing: %s", index, len(missing), ", ".join(missing))
        frames = [f for f in frames if f.image.is_file()]
    if not has_lists:
        for f, split in zip(frames, hold_out(len(frames), test_every, index, "frames", "frames in file-name order")):
            f.split = split
    elif not any(f.split == "train" for f in frames):
        raise SceneFormatError(
            index,
            "train_filenames",
            f"no train frame to import: none of the {len(frames)} frames to import is in train_filenames",
        )
    first, *others = sorted(frames, key=lambda f: f.position)
    if odd := next((f for f in others if ("mask_path" in f.raw) != ("mask_path" in first.raw)), None):
        raise SceneFormatError(
            index,
            f"{odd.field}.mask_path",
            f"{'present' if 'mask_path' in odd.raw else 'missing'}"
            f", but {first.field} {'has' if 'mask_path' in first.raw else 'has no'} mask_path: "
            "masks go on every frame or none (nerfstudio refuses anything else)",
        )
    return frames, {
        "left_out": left_out,
        "skipped_missing": missing,
        "split": "lists" if has_lists else f"every {test_every}-th frame in file-name order is a test view",
    }


def _original_world_pose(
    frame: _SourceFrame, index: Path, applied: np.ndarray | None, applied_scale: float, scale: float
) -> np.ndarray:
    """The frame's OpenCV camera-to-world pose in the original world, in metres (nerfstudio's
    ``transform_poses_to_original_space``, then ``scale``); one that no scene holds (100 km away) is an error
    naming the field that put it there (``applied_scale``, ...), or a ConfigError on ``scale``."""
    field = f"{frame.field}.transform_matrix"
    pose = pose_from_opengl(frame.raw.get("transform_matrix"), index, field)
    if problem := pose_problem(pose):
        raise SceneFormatError(index, field, problem)
    pose[:3, 3] /= applied_scale
    if applied is not None:
        pose = np.linalg.solve(applied, pose)
    if problem := pose_problem(pose):
        culprit = "applied_scale" if applied_scale != 1 else "applied_transform"
        raise SceneFormatError(index, culprit, f"{frame.field}'s camera mapped back to the original world: {problem}")
    pose[:3, 3] *= scale
    if problem := pose_problem(pose):
        raise ConfigError("scale", f"{scale:g} metres per unit puts {frame.field} of {index} out of range: {problem}")
    return pose


def _sparse_points(
    index: Path, data: dict, applied: np.ndarray | None, applied_scale: float, scale: float
) -> tuple[np.ndarray, np.ndarray] | str:
    """``ply_file_path``'s points [N, 3] in the scene's world, in metres (each mapped as
    :func:`_original_world_pose` maps a camera's position), and their colours [N, 3] uint8; or why there are none
    (a missing, unreadable or empty PLY), naming the file."""
    from plyfile import PlyData

    rel = data["ply_file_path"]
    if not isinstance(rel, str) or not rel:
        raise SceneFormatError(index, "ply_file_path", f"expected a path string, got {rel!r}")
    path = index.parent / rel
    if not path.is_file():
        return f"{path}: no such file"
    try:
        vertex = PlyData.read(str(path))["vertex"]
        xyz = np.stack([np.asarray(vertex[axis], np.float64) for axis in "xyz"], axis=1)
        channels = ("red", "green", "blue")
        has_rgb = set(channels) <= set(vertex.data.dtype.names)
        rgb = np.stack([np.asarray(vertex[c], np.float64) for c in channels], axis=1) if has_rgb else None
    except Exception as exc:  # plyfile and numpy raise many types for damaged files
        why = (str(exc).splitlines() or [type(exc).__name__])[0]
        return f"{path}: unreadable PLY of points (vertex x y z, optionally red green blue): {why}"
    if not len(xyz):
        return f"{path}: holds no points"
    if rgb is not None and not np.isfinite(rgb).all():
        return f"{path}: colours that are not finite (NaN or inf)"
    xyz = np.c_[xyz / applied_scale, np.ones(len(xyz))].T  # [4, N], homogeneous
    xyz = scale * (xyz if applied is None else np.linalg.solve(applied, xyz))[:3].T
    colors = np.full(xyz.shape, MID_GREY, np.uint8) if rgb is None else np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    if problem := sparse_points_problem(xyz, colors):
        return f"{path}: {problem}"
    return xyz, colors


def import_nerfstudio(
    src,
    out,
    test_every: int = 8,
    scale: float = 1.0,
    skip_missing: bool = False,
    object_name: str | None = None,
    background_rgb=(255, 255, 255),
) -> Path:
    """Convert the nerfstudio / instant-ngp dataset ``src`` (its folder or its ``transforms.json``) into ``out``.

    See the module docstring for what is read and how; ``background_rgb`` (0-255) is what transparent pixels are
    composited onto. ``out`` is claimed as the ``--out`` of a writing command (``datasets.outputs``). Returns
    ``out``.
    """
    src, out = Path(src), Path(out)
    check_options(scale, test_every)
    index = src if src.suffix.lower() == ".json" else src / "transforms.json"
    data = read_index(
        index, "expected a nerfstudio or instant-ngp dataset: a folder holding transforms.json, or the file itself"
    )
    frames, selection = _select_frames(index, data, test_every, skip_missing)
    cameras = [_camera(f, data, index) for f in frames]
    applied, applied_scale = _applied_transform(data, index)
    poses = [_original_world_pose(f, index, applied, applied_scale, scale) for f in frames]

    not_imported = {}
    if depth_maps := sum("depth_file_path" in f.raw for f in frames):
        not_imported["depth_file_path"] = depth_maps
        log.warning("%s: not imported (training reads no depth maps): depth_file_path", index)
    sparse = None if "ply_file_path" not in data else _sparse_points(index, data, applied, applied_scale, scale)
    if isinstance(sparse, str):
        not_imported["ply_file_path"] = data["ply_file_path"]
        log.warning("%s: ply_file_path %s; not imported: training triangulates its own points", index, sparse)
    split = selection.pop("split")
    optional = {
        **selection,
        "not_imported": not_imported,
        "applied_scale": data.get("applied_scale"),
        "applied_transform": None if applied is None else applied[:3].tolist(),
    }
    tables = {camera: undistortion(camera) for camera in set(cameras)}
    with new_import(
        out,
        tables[cameras[0]][0],
        "nerfstudio",
        index,
        object_name or index.parent.resolve().name,
        scale=scale,
        background_rgb=list(background_rgb),
        nerfstudio_names=[f.raw["file_path"] for f in frames],
        split=split,
        **{key: value for key, value in optional.items() if value},
    ) as writer:
        for f, camera, pose in progress_bar(
            list(zip(frames, cameras, poses)), desc=f"import {index.parent.name}", unit="frame"
        ):
            intr, maps = tables[camera]
            rgba = read_rgba(f.image, f.field, (camera.width, camera.height), "the camera (w x h)")
            rgb = over_background(rgba, background_rgb).astype(np.float32)
            mask = None if "mask_path" not in f.raw else _read_mask(index.parent / f.raw["mask_path"], camera, f)
            if maps is not None:
                rgb = cv2.remap(rgb, *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                if mask is not None:
                    mask = cv2.remap(mask, *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
            writer.add_frame(
                composite(rgb, background_rgb),
                pose,
                split=f.split,
                intrinsics=intr,
                mask=None if mask is None else mask > 0,
            )
        if isinstance(sparse, tuple):
            writer.set_sparse_points(*sparse)
    return out
