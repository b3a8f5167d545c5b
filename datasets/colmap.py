"""Import a COLMAP sparse model (text or binary) into a scene directory.

COLMAP stores world-to-camera poses with OpenCV camera axes (x right, y down,
z forward) and puts the centre of the top-left pixel at (0.5, 0.5), the same
conventions as tacsplat, so poses are only inverted and intrinsics copied
(scaled to the images of a downscaled folder such as Mip-NeRF 360's
``images_2``). The model's 3D points and their colours become the scene's
sparse points (``points3D.ply``), in its world frame: COLMAP's, scaled by
``scale`` as the poses' translations are.
Undistortion is out of scope: cameras must be pinhole (``PINHOLE``,
``SIMPLE_PINHOLE``) or a distortion model whose distortion parameters are all
zero (``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``); run ``colmap
image_undistorter`` first otherwise. The test split holds every
``test_every``-th image in name order (the 3DGS/LLFF hold-out convention).

The model is read here, not by ``pycolmap.Reconstruction``: pycolmap indexes
what the files reference before checking it (a camera id that cameras.txt
lacks is ``IndexError: Rig with ID 7 does not exist``, a track naming a
missing 2D point ``vector::_M_range_check``) and reads a repeated image NAME as
two images. Every record is checked first, and an error names the file and
its line (text) or entry (binary). Both layouts are read: cameras, images and
points3D alone (COLMAP before 3.12: each image holds its pose), or with rigs
and frames (COLMAP 3.12 on: the pose of an image is its frame's
``rig_from_world`` then its camera's ``sensor_from_rig``). pycolmap supplies
the camera models (parameter counts and meanings).
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from scipy.spatial.transform import Rotation

from tacsplat.errors import SceneFormatError
from tacsplat.geometry import intrinsics_matrix, invert_pose, make_pose
from tacsplat.progress import progress_bar
from tacsplat.types import CameraIntrinsics

from .blender import check_options, composite, hold_out, read_rgba
from .records import camera_problem
from .writer import new_import

log = logging.getLogger(__name__)

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
ZERO_DISTORTION_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")
MODEL_FILES = ("cameras", "images", "points3D")
RIG_FILES = ("rigs", "frames")
# |q| of a stored rotation: COLMAP writes 17 digits, so |q| - 1 is ~1e-16; other tools write 6-8 digits
# (up to ~1e-6, normalised silently). Up to 1e-2 (a quaternion written with 2-3 digits) it is normalised with a
# warning; beyond that the four numbers are no rotation (a typo, a column shifted).
QUATERNION_ROUNDING = 1e-6
QUATERNION_TOLERANCE = 1e-2


class _Record(SimpleNamespace):
    """One camera, image, 3D point, rig or frame of the model, with where it was read (``path``; ``where``: "line
    12" of a text file, "entry 3" of a binary one), and its fields:

    - camera: camera_id, model, width, height, params;
    - image: image_id, pose (cam_from_world as images.txt holds it), camera_id, name, point3D_ids (-1: none);
    - point: point3D_id, xyz, rgb [R, G, B], track [(image_id, point2D_idx)];
    - rig: rig_id, sensors {(type, id): sensor_from_rig _Pose, or None (unknown); the reference sensor first};
    - frame: frame_id, rig_id, pose (rig_from_world), data_ids [(sensor type, sensor id, data id)].
    """

    def error(self, message: str) -> SceneFormatError:
        return SceneFormatError(self.path, self.where, message)


@dataclass
class _Pose:
    """A stored Rigid3d: quaternion (w, x, y, z) and translation."""

    q: np.ndarray
    t: np.ndarray

    def matrix(self) -> np.ndarray:
        w, x, y, z = self.q
        return make_pose(Rotation.from_quat([x, y, z, w]).as_matrix(), self.t)  # scipy normalises q


@dataclass
class _Model:
    cameras: list
    images: list
    points: list
    rigs: list | None  # None: a model without rigs and frames
    frames: list | None
    suffix: str = ".txt"  # or ".bin"

    def file(self, name: str) -> str:
        return name + self.suffix

    def lacks(self, record: _Record, what: str, name: str) -> SceneFormatError:
        """The error of ``record`` whose ``what`` ("image 3 names camera 7") is not in file ``name``."""
        return record.error(f"{what}, which {self.file(name)} does not hold")


def _layout(model: str):
    """A ``pycolmap.Camera`` of COLMAP camera model ``model`` (its parameter count and meanings); None for a name
    COLMAP does not know."""
    import pycolmap

    if model not in pycolmap.CameraModelId.__members__ or model == "INVALID":
        return None
    return pycolmap.Camera.create_from_model_name(0, model, 1.0, 1, 1)


# --- reading: one reader per record kind, over the lines of a text file or the entries of a binary one ------------

_SENSOR_TYPES = {-1: "INVALID", 0: "CAMERA", 1: "IMU"}  # COLMAP's SensorType, as text files spell it
# The values an integer field holds: its binary type's (ids and counts of 64 bits up to int64's largest, as they
# are held here: no model comes near)
_INT_LIMITS = {"B": (0, 2**8 - 1), "i": (-(2**31), 2**31 - 1), "I": (0, 2**32 - 1), "Q": (0, 2**63 - 1)}


def _in_limits(src, value: int, what: str, fmt: str) -> int:
    """``value`` if the field ``what`` of binary type ``fmt`` holds it (:data:`_INT_LIMITS`); else ``src``'s
    error naming the file and line or entry."""
    lo, hi = _INT_LIMITS[fmt]
    if not lo <= value <= hi:
        raise src.error(f"{what} must be an integer from {lo} to {hi}, got {value}")
    return value


class _Source:
    """What the text and the binary reader share."""

    def pose(self, what: str) -> _Pose:
        values = [self.float(f"{what} {name}") for name in ("QW", "QX", "QY", "QZ", "TX", "TY", "TZ")]
        return _Pose(np.array(values[:4]), np.array(values[4:]))


class _Text(_Source):
    """A text model file read record by record (one line each, comments and blank lines skipped; an image's
    POINTS2D on the line after it) and field by field; errors name the file and line."""

    suffix = ".txt"

    def __init__(self, path: Path):
        try:
            self.lines = enumerate(path.read_text().splitlines(), start=1)
        except (OSError, UnicodeDecodeError) as exc:
            raise SceneFormatError(path, None, f"not a readable COLMAP text file: {exc}") from exc
        self.path = path

    def records(self):
        for self.number, text in self.lines:
            if text.strip() and not text.lstrip().startswith("#"):
                self.items, self.at = text.split(), 0
                yield _Record(path=self.path, where=f"line {self.number}")
                self.done()

    def error(self, message: str) -> SceneFormatError:
        return SceneFormatError(self.path, f"line {self.number}", message)

    def word(self, what: str) -> str:
        if self.at >= len(self.items):
            raise self.error(f"{what} is missing (the line ends after {self.at} fields)")
        self.at += 1
        return self.items[self.at - 1]

    name = model = sensor_type = word

    def int(self, what: str, fmt: str) -> int:
        return _in_limits(self, self._number(what, int, "an integer"), what, fmt)

    def float(self, what: str) -> float:
        return self._number(what, float, "a number")

    def _number(self, what: str, kind: type, name: str):
        text = self.word(what)
        try:
            return kind(text)
        except ValueError:
            raise self.error(f"{what} must be {name}, got {text!r}") from None

    def params(self, count: int, what: str) -> np.ndarray:
        """The rest of the line: ``count`` PARAMS of ``what`` (a camera of its model)."""
        params = np.array([self.float(f"PARAMS[{i}]") for i in range(len(self.items) - self.at)])
        if params.size != count:
            raise self.error(f"{what} has {count} parameters, got {params.size}")
        return params

    def points2d(self, what: str) -> list[np.ndarray]:
        """X, Y, POINT3D_ID of the next line (maybe blank)."""
        self.done()
        self.number, text = next(self.lines, (self.number + 1, ""))
        self.items, self.at = text.split(), 0
        return self._groups(("X", "Y", "POINT3D_ID"), what)

    def track(self, what: str) -> np.ndarray:
        return np.column_stack(self._groups(("IMAGE_ID", "POINT2D_IDX"), what))

    def _groups(self, names: tuple[str, ...], what: str) -> list[np.ndarray]:
        """The rest of the line as (names...) groups: one array per name, float for X and Y, else integer."""
        fields = self.items[self.at :]
        if len(fields) % len(names):
            raise self.error(f"{what} must be ({', '.join(names)}) groups, got {len(fields)} fields")
        self.at = len(self.items)
        columns = []
        for k, name in enumerate(names):
            column, number = fields[k :: len(names)], name in ("X", "Y")
            try:
                columns.append(np.array(column, np.float64 if number else np.int64))
            except (ValueError, OverflowError):
                for i, text in enumerate(column):
                    try:
                        float(text) if number else np.int64(int(text))
                    except (ValueError, OverflowError):
                        break
                raise self.error(
                    f"{what}[{i}] {name} must be {'a number' if number else 'an integer'}, got {text!r}"
                ) from None
        return columns

    def done(self) -> None:
        if left := len(self.items) - self.at:
            raise self.error(f"{left} fields too many: {' '.join(self.items[self.at : self.at + 3])} ...")


class _Binary(_Source):
    """A binary model file (little-endian) read entry by entry and field by field, as COLMAP lays it out; errors
    name the file and entry."""

    suffix = ".bin"

    def __init__(self, path: Path):
        try:
            self.data = path.read_bytes()
        except OSError as exc:
            raise SceneFormatError(path, None, f"not a readable COLMAP binary file: {exc}") from exc
        self.path, self.at, self.entry = path, 0, None

    def records(self):
        """A record for each of the entries the file's count announces; then checks nothing is left over."""
        for self.entry in range(1, self.int("the number of entries", "Q") + 1):
            yield _Record(path=self.path, where=f"entry {self.entry}")
        if self.at != len(self.data):
            raise SceneFormatError(
                self.path,
                None,
                f"{len(self.data) - self.at} bytes after the last of the {self.entry or 0} entries the file announces",
            )

    def error(self, message: str) -> SceneFormatError:
        return SceneFormatError(self.path, self.entry and f"entry {self.entry}", message)

    def _skip(self, size: int, what: str) -> int:
        """Where the next ``size`` bytes (``what``) start; moves past them."""
        if self.at + size > len(self.data):
            raise self.error(f"the file ends inside {what} (truncated?)")
        self.at += size
        return self.at - size

    def array(self, dtype, count: int, what: str) -> np.ndarray:
        dtype = np.dtype(dtype)
        return np.frombuffer(self.data, dtype, count, self._skip(dtype.itemsize * count, what))

    def _take(self, fmt: str, what: str):
        """One little-endian ``struct`` value (a number per field: np.frombuffer per number is 8x slower)."""
        return struct.unpack_from("<" + fmt, self.data, self._skip(struct.calcsize(fmt), what))[0]

    def int(self, what: str, fmt: str) -> int:
        return _in_limits(self, self._take(fmt, what), what, fmt)

    def float(self, what: str) -> float:
        return self._take("d", what)

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise self.error(f"the file ends inside {what} (truncated?)")
        name, self.at = self.data[self.at : end].decode("utf-8", "replace"), end + 1
        return name

    def model(self, what: str) -> str:
        import pycolmap

        model_id = self.int(what, "i")
        return next((n for n, v in pycolmap.CameraModelId.__members__.items() if int(v) == model_id), f"id {model_id}")

    def sensor_type(self, what: str) -> str:
        kind = self.int(what, "i")
        return _SENSOR_TYPES.get(kind, str(kind))

    def params(self, count: int, what: str) -> np.ndarray:
        return self.array("<f8", count, f"the PARAMS of {what}").copy()

    def points2d(self, what: str) -> list[np.ndarray]:
        points = self.array([("x", "<f8"), ("y", "<f8"), ("id", "<i8")], self.int(what, "Q"), what)
        return [points["x"], points["y"], points["id"].astype(np.int64)]  # COLMAP's invalid id, 2^64 - 1, reads as -1

    def track(self, what: str) -> np.ndarray:
        return self.array("<u4", 2 * self.int(what, "Q"), what).astype(np.int64).reshape(-1, 2)

    def done(self) -> None:
        pass


def _camera(src, camera: _Record) -> _Record:
    camera.camera_id, camera.model = src.int("CAMERA_ID", "I"), src.model("MODEL")
    camera.width, camera.height = src.int("WIDTH", "Q"), src.int("HEIGHT", "Q")
    if (layout := _layout(camera.model)) is None:
        raise camera.error(f"camera {camera.camera_id}: unknown camera model {camera.model}")
    camera.params = src.params(int(layout.params.size), f"camera {camera.camera_id}: a {camera.model} camera")
    return camera


def _image(src, image: _Record) -> _Record:
    image.image_id = src.int("IMAGE_ID", "I")
    what = f"image {image.image_id}"
    image.pose, image.camera_id = src.pose(f"{what}'s cam_from_world"), src.int("CAMERA_ID", "I")
    image.name = src.name(f"the NAME of {what}")
    x, y, image.point3D_ids = src.points2d(f"POINTS2D of {what}")
    if (k := _first_bad(~np.isfinite(x) | ~np.isfinite(y))) is not None:
        raise src.error(f"POINTS2D[{k}] of {what} is not finite: ({x[k]}, {y[k]})")
    return image


def _point(src, point: _Record) -> _Record:
    point.point3D_id = src.int("POINT3D_ID", "Q")
    point.xyz = np.array([src.float(name) for name in ("X", "Y", "Z")])
    point.rgb = [src.int(name, "B") for name in ("R", "G", "B")]
    src.float("ERROR")
    point.track = src.track(f"TRACK of point {point.point3D_id}")
    return point


def _rig(src, rig: _Record) -> _Record:
    rig.rig_id, rig.sensors = src.int("RIG_ID", "I"), {}
    for k in range(src.int("NUM_SENSORS", "I")):
        what = f"sensor {k} of rig {rig.rig_id}"
        sensor = (src.sensor_type(f"{what}: SENSOR_TYPE"), src.int(f"{what}: SENSOR_ID", "I"))
        if k == 0:  # the reference sensor: the rig's frame
            rig.sensors[sensor] = _Pose(np.array([1.0, 0, 0, 0]), np.zeros(3))
        else:
            rig.sensors[sensor] = src.pose(f"{what}: sensor_from_rig") if src.int(f"{what}: HAS_POSE", "B") else None
    return rig


def _frame(src, frame: _Record) -> _Record:
    frame.frame_id, frame.rig_id = src.int("FRAME_ID", "I"), src.int("RIG_ID", "I")
    frame.pose = src.pose(f"frame {frame.frame_id}'s rig_from_world")
    frame.data_ids = [
        (
            src.sensor_type(f"data {k} SENSOR_TYPE"),
            src.int(f"data {k} SENSOR_ID", "I"),
            src.int(f"data {k} DATA_ID", "Q"),
        )
        for k in range(src.int("NUM_DATA_IDS", "I"))
    ]
    return frame


_READERS = {"cameras": _camera, "images": _image, "points3D": _point, "rigs": _rig, "frames": _frame}


# --- checks ----------------------------------------------------------------------------------------------------


def _read_model(model_dir: Path) -> _Model:
    """The model in ``model_dir``, binary when its three .bin files are there (as COLMAP decides), else text."""
    for source in (_Binary, _Text):
        if all((model_dir / f"{name}{source.suffix}").is_file() for name in MODEL_FILES):
            present = {name: (model_dir / f"{name}{source.suffix}").is_file() for name in RIG_FILES}
            if any(present.values()) and not all(present.values()):
                missing = next(name for name, there in present.items() if not there)
                raise SceneFormatError(
                    model_dir / f"{missing}{source.suffix}",
                    None,
                    "missing: a model holds rigs and frames together (COLMAP 3.12 on) or neither",
                )
            lists = {}
            for name in MODEL_FILES + RIG_FILES * all(present.values()):
                src = source(model_dir / f"{name}{source.suffix}")
                lists[name] = [_READERS[name](src, record) for record in src.records()]
            return _Model(*(lists.get(name) for name in MODEL_FILES + RIG_FILES), source.suffix)
    raise SceneFormatError(
        model_dir,
        None,
        "not a readable COLMAP sparse model: expected cameras, images and points3D as .bin or .txt files"
        + _models_below(model_dir),
    )


def _is_model(folder: Path) -> bool:
    """Whether ``folder`` holds the three files of a model, binary or text."""
    return any(all((folder / f"{name}{suffix}").is_file() for name in MODEL_FILES) for suffix in (".bin", ".txt"))


def _models_below(folder: Path) -> str:
    """The hint for a ``folder`` one level above its models (``sparse`` rather than ``sparse/0``): "; pass ..."
    naming the subfolders that hold one, or "" when none does."""
    try:
        models = sorted((sub for sub in folder.iterdir() if sub.is_dir() and _is_model(sub)), key=_folder_order)
    except OSError:  # (not a folder, or not readable: the error says it is no model)
        return ""
    if not models:
        return ""
    return f"; its subfolder {models[0]} holds one: pass it" + (
        f" (or {', '.join(str(m) for m in models[1:])})" if len(models) > 1 else ""
    )


def _folder_order(folder: Path) -> tuple:
    """Model folders in COLMAP's order: 0, 1, ..., 10 (numbers by value), then other names."""
    return (0, int(folder.name), "") if folder.name.isdigit() else (1, 0, folder.name)


def _by_id(records: list, key: str, what: str) -> dict:
    """``{id: record}``; a SceneFormatError on the second record of an id."""
    seen = {}
    for record in records:
        value = getattr(record, key)
        if value in seen:
            raise record.error(f"{what} {value} again (also {seen[value].where})")
        seen[value] = record
    return seen


def _check_pose(record: _Record, pose: _Pose, what: str) -> None:
    """Finite, with a unit quaternion (normalised here: silently when off by rounding, with a warning up to
    QUATERNION_TOLERANCE); a SceneFormatError otherwise."""
    if not (np.isfinite(pose.q).all() and np.isfinite(pose.t).all()):
        raise record.error(f"{what} is not finite: QW QX QY QZ {pose.q.tolist()}, TX TY TZ {pose.t.tolist()}")
    norm = float(np.linalg.norm(pose.q))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise record.error(
            f"{what}: the quaternion QW QX QY QZ {pose.q.tolist()} has length {norm:.6g}, not 1: it is no rotation"
        )
    if abs(norm - 1.0) > QUATERNION_ROUNDING:
        log.warning("%s [%s]: %s: the quaternion has length %.6g, normalised", record.path, record.where, what, norm)
    pose.q = pose.q / norm


def _joined(arrays: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The arrays concatenated along axis 0, and for each row the index of the array it came from."""
    if not arrays:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    return np.concatenate(arrays), np.repeat(np.arange(len(arrays)), [len(a) for a in arrays])


def _first_bad(bad: np.ndarray) -> int | None:
    hits = np.flatnonzero(bad)
    return int(hits[0]) if hits.size else None


def _check_model(model: _Model) -> dict[int, np.ndarray]:
    """Every reference and number of the model checked; the cam_from_world [4, 4] of each posed image by id."""
    cameras = _by_id(model.cameras, "camera_id", "camera")
    images = _by_id(model.images, "image_id", "image")
    names = {}
    for image in model.images:
        if image.camera_id not in cameras:
            raise model.lacks(image, f"image {image.image_id} names camera {image.camera_id}", "cameras")
        _check_pose(image, image.pose, f"image {image.image_id}'s pose")
        other = names.setdefault(image.name, image)
        if other is not image:
            raise image.error(
                f"NAME {image.name} again: image {image.image_id} here and image {other.image_id} on "
                f"{other.where} would be two frames with one picture"
            )
    points = _by_id(model.points, "point3D_id", "point")
    refs, owner = _joined([image.point3D_ids for image in model.images])
    if (k := _first_bad((refs != -1) & ~np.isin(refs, np.array(list(points), np.int64)))) is not None:
        image, line = model.images[owner[k]], " (on the next line)" if model.suffix == ".txt" else ""
        i = k - np.searchsorted(owner, owner[k])
        raise model.lacks(image, f"POINTS2D[{i}] of image {image.image_id}{line} names 3D point {refs[k]}", "points3D")
    if (k := _first_bad(~np.isfinite([point.xyz for point in model.points]).reshape(-1, 3).all(axis=1))) is not None:
        point = model.points[k]
        raise point.error(f"point {point.point3D_id}: X Y Z {point.xyz.tolist()} is not finite")
    track, owner = _joined([point.track for point in model.points])
    image_ids = np.array(sorted(images), np.int64)
    at = np.clip(np.searchsorted(image_ids, track[:, 0]), 0, max(len(image_ids) - 1, 0))
    known = image_ids[at] == track[:, 0] if len(image_ids) else np.zeros(len(track), bool)
    counts = np.array([images[i].point3D_ids.size for i in image_ids], np.int64)
    if (k := _first_bad(~known)) is not None:
        point = model.points[owner[k]]
        raise model.lacks(point, f"the track of point {point.point3D_id} names image {track[k, 0]}", "images")
    if (k := _first_bad(known & (track[:, 1] >= counts[at]))) is not None:
        point, (iid, idx) = model.points[owner[k]], track[k]
        raise point.error(
            f"the track of point {point.point3D_id} names POINT2D_IDX {idx} of image {iid}, "
            f"which has {counts[at[k]]} 2D points ({images[iid].where} of {model.file('images')})"
        )
    if model.rigs is None:
        return {image.image_id: image.pose.matrix() for image in model.images}
    return _rig_poses(model, cameras, images)


def _rig_poses(model: _Model, cameras: dict, images: dict) -> dict[int, np.ndarray]:
    """cam_from_world of each image in a model with rigs and frames: sensor_from_rig after rig_from_world.
    An image whose camera has no pose in its rig is left out (COLMAP's unposed image)."""
    rigs = _by_id(model.rigs, "rig_id", "rig")
    for rig in model.rigs:
        for (kind, sensor_id), pose in rig.sensors.items():
            if kind == "CAMERA" and sensor_id not in cameras:
                raise model.lacks(rig, f"rig {rig.rig_id} holds camera {sensor_id}", "cameras")
            if pose is not None:
                _check_pose(rig, pose, f"rig {rig.rig_id}'s sensor_from_rig of {kind} {sensor_id}")
    frame_of = {}
    for frame in _by_id(model.frames, "frame_id", "frame").values():
        if (rig := rigs.get(frame.rig_id)) is None:
            raise model.lacks(frame, f"frame {frame.frame_id} names rig {frame.rig_id}", "rigs")
        _check_pose(frame, frame.pose, f"frame {frame.frame_id}'s rig_from_world")
        for kind, sensor_id, data_id in frame.data_ids:
            if (kind, sensor_id) not in rig.sensors:
                raise frame.error(
                    f"frame {frame.frame_id} holds data of {kind} {sensor_id}, which is not in its rig {rig.rig_id}"
                )
            if kind != "CAMERA":
                continue
            if (image := images.get(data_id)) is None:
                raise model.lacks(frame, f"frame {frame.frame_id} holds image {data_id}", "images")
            if image.camera_id != sensor_id:
                raise frame.error(
                    f"frame {frame.frame_id} holds image {data_id} as camera {sensor_id}, but the "
                    f"image names camera {image.camera_id} ({image.where} of {model.file('images')})"
                )
            if data_id in frame_of:
                raise frame.error(
                    f"image {data_id} is in frame {frame.frame_id} and in frame "
                    f"{frame_of[data_id].frame_id} ({frame_of[data_id].where})"
                )
            frame_of[data_id] = frame
    poses = {}
    for image in model.images:
        if (frame := frame_of.get(image.image_id)) is None:
            raise image.error(f"image {image.image_id} is in no frame of {model.file('frames')}")
        if (sensor_from_rig := rigs[frame.rig_id].sensors[("CAMERA", image.camera_id)]) is not None:
            poses[image.image_id] = sensor_from_rig.matrix() @ frame.pose.matrix()
    return poses


PARAMETER_NAMES = {
    "w": "WIDTH",
    "h": "HEIGHT",
    "fl_x": "the focal length (x)",
    "fl_y": "the focal length (y)",
    "cx": "the principal point (x)",
    "cy": "the principal point (y)",
}


def camera_intrinsics(camera: _Record) -> CameraIntrinsics:
    """Intrinsics of a model's camera, or a SceneFormatError naming its file, line or entry, id and model."""
    what = f"camera {camera.camera_id}"
    if camera.model not in PINHOLE_MODELS + ZERO_DISTORTION_MODELS:
        raise camera.error(
            f"{what}: camera model {camera.model} is not supported: undistort the images first "
            "(colmap image_undistorter) to get a PINHOLE model"
        )
    layout = _layout(camera.model)

    if not np.isfinite(camera.params).all():
        raise camera.error(f"{what}: PARAMS {camera.params.tolist()} are not all finite")
    distortion = camera.params[list(layout.extra_params_idxs())]
    if np.any(distortion != 0):
        raise camera.error(
            f"{what}: camera model {camera.model} has non-zero distortion {distortion.tolist()}: "
            "undistort the images first (colmap image_undistorter)"
        )
    focal = camera.params[list(layout.focal_length_idxs())].tolist()
    fx, fy = focal[0], focal[-1]  # (one focal length, or x and y)
    cx, cy = camera.params[list(layout.principal_point_idxs())].tolist()
    if problem := camera_problem(fx, fy, cx, cy, camera.width, camera.height):
        raise camera.error(f"{what}: {PARAMETER_NAMES[problem[0]]}: {problem[1]}")
    return CameraIntrinsics(intrinsics_matrix(fx, fy, cx, cy), int(camera.width), int(camera.height))


def _image_size(path: Path) -> tuple[int, int] | None:
    """(w, h) of an image file from its header, None when it cannot be read (reading it names the problem)."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            return image.size
    except Exception:  # PIL raises many types for damaged or unknown files
        return None


def _fit_to_images(model_dir: Path, images_dir: Path, images: list, intrinsics: dict) -> dict:
    """``intrinsics`` (by camera id), each scaled to its camera's images where they are all one size that is the
    camera's divided by one whole factor (w and h within 1 px of it rounded: Mip-NeRF 360's ``images_2`` beside a
    full-size model), as nerfstudio scales them: fx, cx by the images' w / the camera's, fy, cy by h / its h. Any
    other size stays the camera's (and reading the image names the mismatch)."""
    fitted = dict(intrinsics)
    for cid, intr in intrinsics.items():
        sizes = {_image_size(images_dir / img.name) for img in images if img.camera_id == cid}
        if len(sizes) != 1 or None in sizes or sizes == {(intr.width, intr.height)}:
            continue
        ((w, h),) = sizes
        factor = round(intr.width / w)
        if factor < 2 or abs(w - round(intr.width / factor)) > 1 or abs(h - round(intr.height / factor)) > 1:
            continue
        sx, sy = w / intr.width, h / intr.height
        fitted[cid] = CameraIntrinsics(np.diag([sx, sy, 1.0]) @ intr.K, w, h)
        log.info(
            "%s: camera %d is %dx%d and its images in %s are %dx%d, 1/%d of it: its fx, cx are scaled by %.6g and "
            "fy, cy by %.6g",
            model_dir,
            cid,
            intr.width,
            intr.height,
            images_dir,
            w,
            h,
            factor,
            sx,
            sy,
        )
    return fitted


def _dataset_name(model_dir: Path) -> str:
    """``garden`` for ``.../garden/sparse/0``: the first folder up that is not ``sparse`` or a model number."""
    for part in (model_dir.resolve(), *model_dir.resolve().parents):
        if part.name and part.name != "sparse" and not part.name.isdigit():
            return part.name
    return "colmap"


def import_colmap(
    model_dir, images_dir, out, test_every: int = 8, scale: float = 1.0, object_name: str | None = None
) -> Path:
    """Convert the COLMAP model in ``model_dir`` (e.g. ``sparse/0``) with images in ``images_dir`` into ``out``.

    ``scale`` multiplies translations (COLMAP's scale is arbitrary; the scene
    claims metres). ``test_every = 0`` puts every image in the train split.
    Images that are a camera's size divided by a whole factor (a downscaled
    folder) get its intrinsics scaled to them (:func:`_fit_to_images`). The
    model's 3D points, scaled alike, become the scene's sparse points
    (``SceneWriter.set_sparse_points``), which the initialisation starts from.
    ``out`` is claimed as the ``--out`` of a writing command (``datasets.outputs``). Returns ``out``.
    """
    model_dir, images_dir, out = Path(model_dir), Path(images_dir), Path(out)
    check_options(scale, test_every)
    model = _read_model(model_dir)
    poses = _check_model(model)
    if unposed := len(model.images) - len(poses):
        log.warning(
            "%s: %d images have no pose (their camera's pose in the rig is unknown) and are left out",
            model_dir,
            unposed,
        )
    images = sorted((img for img in model.images if img.image_id in poses), key=lambda img: img.name)
    if not images:
        raise SceneFormatError(model_dir, "images", "the model has no registered images")
    cameras = {camera.camera_id: camera for camera in model.cameras}
    intrinsics = {cid: camera_intrinsics(cameras[cid]) for cid in sorted({img.camera_id for img in images})}
    if missing := [img for img in images if not (images_dir / img.name).is_file()]:
        more = f" (and {len(missing) - 1} more images)" if len(missing) > 1 else ""
        raise missing[0].error(
            f"image {missing[0].image_id}: {images_dir / missing[0].name} does not exist{more}; "
            "--images must be the folder the NAMEs are relative to"
        )
    intrinsics = _fit_to_images(model_dir, images_dir, images, intrinsics)
    splits = hold_out(len(images), test_every, model_dir, "images", "images")
    with new_import(
        out,
        intrinsics[images[0].camera_id],
        "colmap",
        model_dir,
        object_name or _dataset_name(model_dir),
        images_path=str(images_dir.resolve()),
        scale=scale,
        test_every=test_every,
        num_points3D=len(model.points),
        colmap_names=[img.name for img in images],
    ) as writer:
        for img, split in progress_bar(list(zip(images, splits)), desc=f"import {model_dir}", unit="frame"):
            intr = intrinsics[img.camera_id]
            size, camera = (intr.width, intr.height), f"camera {img.camera_id}"
            rgba = read_rgba(images_dir / img.name, f"image {img.image_id}", size, camera)
            T_world_cam = invert_pose(poses[img.image_id])
            T_world_cam[:3, 3] *= scale
            # an alpha channel, if any, is dropped
            writer.add_frame(composite(rgba[:, :, :3], (0, 0, 0)), T_world_cam, split=split, intrinsics=intr)
        if model.points:  # in the scene's world: COLMAP's, its translations scaled as the poses' are
            xyz = scale * np.array([point.xyz for point in model.points])
            writer.set_sparse_points(xyz, np.array([point.rgb for point in model.points], np.uint8))
    return out
