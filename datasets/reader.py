"""Reading and validating scene directories: the one definition of a valid scene.

:meth:`Scene.load` checks everything (index files, every image header, every
depth map, every pose, every number against what a capture can physically
hold, the index against the writer's journal, at least one train frame) and
raises one :class:`SceneFormatError` naming the file and field of the first
problem. :func:`check_scene` runs the same checks but collects every problem
and returns what could be read, for ``tacsplat inspect``. Every command that
reads a scene (reconstruct, evaluate, inspect, simulate-touches) goes through
them, so a scene one command refuses, every command refuses.
"""

from __future__ import annotations

import json
import shlex
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import NoReturn

import numpy as np
from PIL import Image

from tacsplat.errors import InvalidInputError, SceneFormatError
from tacsplat.geometry import opengl_to_opencv, tactile_depth_to_normals, tactile_depth_to_points
from tacsplat.types import CameraIntrinsics

from .records import (
    FORMAT_NAME,
    FORMAT_VERSION,
    GT_DEPTH_LIMIT,
    SOURCES,
    SPLITS,
    Frame,
    HandMotion,
    SceneMeta,
    SensorModel,
    Touch,
    camera_problem,
    depth_problem,
    intrinsics_equal,
    intrinsics_from_json,
    normal_map_problem,
    pose_problem,
    sparse_points_problem,
    touch_depth_limit,
)
from .writer import JOURNAL, journaled_state

_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_UNDISTORTED_MODELS = ("OPENCV", "PINHOLE")  # camera_model of a scene's images (with no distortion)
# nerfstudio keys a scene never holds: its poses are in the world frame, in metres, and what it does not import
# (depth maps, point clouds) it leaves out rather than keep unread
_FOREIGN_KEYS = ("applied_transform", "applied_scale", "ply_file_path")
_FOREIGN_FRAME_KEYS = ("depth_file_path",)
_SCENE_FILES = ("scene.json", "transforms.json", "touches.json", JOURNAL)  # one of them: a scene, maybe a broken one
_RUN_FILES = ("config.json", "checkpoint.pt", "splat.ply")  # what `tacsplat reconstruct` writes into its run folder


class _Dropped(Exception):
    """A record (or file) with a problem, reported already, is left out of the scene."""


class _Problems:
    """Raises the first problem (``collect=False``) or collects them all."""

    def __init__(self, collect: bool):
        self.collect = collect
        self.errors: list[SceneFormatError] = []

    def note(self, path: Path, field: str | None, message: str) -> None:
        """A problem after which reading goes on (when collecting)."""
        self.add(SceneFormatError(path, field, message))

    def report(self, path: Path, field: str | None, message: str) -> NoReturn:
        """A problem that leaves out what it is in: raised, or collected and then :class:`_Dropped` raised."""
        self.note(path, field, message)
        raise _Dropped

    def add(self, error: SceneFormatError) -> None:
        if not self.collect:
            raise error
        self.errors.append(error)

    @staticmethod
    def attempt(read, *args):
        """``read(*args)``, or None when what it reads was left out (:meth:`report`)."""
        try:
            return read(*args)
        except _Dropped:
            return None


STRICT = _Problems(collect=False)  # raises the first problem (and so holds none): for reading one file of a scene


def _first_line(exc: Exception) -> str:
    return (str(exc).splitlines() or [type(exc).__name__])[0]


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _check_fields(problems: _Problems, index: Path, prefix: str, raw: dict, **checks) -> list[str]:
    """Note each key of ``checks`` (key=(whether raw[key] is fine, what was expected)) whose value is not; returns
    those keys."""
    bad = [key for key, (fine, _) in checks.items() if not fine]
    for key in bad:
        problems.note(index, prefix + key, f"expected {checks[key][1]}, got {raw.get(key)!r}")
    return bad


def _read_json(path: Path, problems: _Problems, required: bool = True) -> dict:
    if not path.is_file():
        if required:
            problems.report(path, None, "missing (not a scene directory, or its creation never finished)")
        raise _Dropped
    try:
        data = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        problems.report(path, None, f"not valid JSON: {exc}")
    if not isinstance(data, dict):
        problems.report(path, None, f"expected a JSON object at the top level, got {type(data).__name__}")
    return data


def _relative_file(scene: Path, rel, index: Path, field: str, problems: _Problems) -> Path:
    """Resolve a path stored in an index file; it must stay inside the scene directory."""
    if not isinstance(rel, str) or not rel:
        problems.report(index, field, f"expected a relative file path, got {rel!r}")
    if Path(rel).is_absolute() or ".." in Path(rel).parts:
        problems.report(index, field, f"{rel!r} must be a path inside the scene directory")
    return scene / rel


def _pose(value, index: Path, field: str, problems: _Problems) -> np.ndarray:
    if problem := pose_problem(value):
        problems.report(index, field, problem)
    return np.asarray(value, dtype=np.float64)


def _entry_id(raw, index: Path, field: str, kind: str, seen: dict, problems: _Problems) -> int:
    """The id of entry ``field`` (``frames[3]``) of an index file's list: an object with a new non-negative id."""
    if not isinstance(raw, dict):
        problems.report(index, field, f"expected an object, got {type(raw).__name__}")
    rid = raw.get("id")
    if not _is_int(rid) or rid < 0:
        problems.report(index, f"{field}.id", f"expected a non-negative integer, got {rid!r}")
    if rid in seen:
        problems.report(index, f"{field}.id", f"duplicate {kind} id {rid} (also {seen[rid]})")
    seen[rid] = field
    return rid


def load_depth_npz(
    path: Path, shape: tuple[int, int] | None, problems: _Problems, field: str, limit: tuple[float, str]
) -> np.ndarray:
    """Load and check a float32 depth map saved by the writer (key ``depth``) of ``shape`` (None: any); ``limit`` is
    (deepest value in metres, why) as :func:`depth_problem` takes it."""
    if (depth := _npz_array(path, "depth", problems, field)) is None:
        problems.report(path, field, "no 'depth' array")
    if shape is not None and depth.shape != shape:
        problems.report(path, field, f"shape {depth.shape} does not match the expected {shape}")
    if problem := depth_problem(depth, *limit):
        problems.report(path, field, problem)
    return depth.astype(np.float32, copy=False)


def _npz_array(path: Path, key: str, problems: _Problems, field: str) -> np.ndarray | None:
    """Array ``key`` of an npz file the writer saved, None when it has none."""
    if not path.is_file():
        problems.report(path, None, "depth file missing")
    try:
        with np.load(path, allow_pickle=False) as npz:
            return npz[key] if key in npz.files else None
    except Exception as exc:  # zipfile, zlib and numpy raise a dozen types for damaged bytes
        problems.report(path, field, f"truncated or corrupt npz: {_first_line(exc)}")


def load_points_ply(path: Path, problems: _Problems, field: str) -> np.ndarray:
    """The vertices [N, 3] of a PLY point cloud written by the writer (``gt/points.ply``), checked finite."""
    import trimesh

    if not path.is_file():
        problems.report(path, None, "point cloud file missing")
    try:
        points = np.asarray(trimesh.load(str(path), file_type="ply").vertices, dtype=np.float64)
    except Exception as exc:  # trimesh raises many types for damaged files
        problems.report(path, field, f"unreadable PLY point cloud: {_first_line(exc)}")
    if points.ndim != 2 or points.shape[1:] != (3,) or not len(points):
        problems.report(path, field, f"expected a non-empty [N, 3] point cloud, got shape {points.shape}")
    if not np.isfinite(points).all():
        problems.report(path, field, "contains NaN or infinite coordinates")
    return points


def load_sparse_points(path: Path, problems: _Problems, field: str) -> tuple[np.ndarray, np.ndarray]:
    """The sparse points [N, 3] (float64, metres) and their colours [N, 3] (uint8 RGB) of the PLY file the writer
    wrote (``SceneWriter.set_sparse_points``), checked."""
    from plyfile import PlyData

    if not path.is_file():
        problems.report(path, None, "sparse points file missing")
    try:
        vertex = PlyData.read(str(path))["vertex"]
        points = np.stack([vertex[axis] for axis in "xyz"], axis=1).astype(np.float64)
        colors = np.stack([vertex[channel] for channel in ("red", "green", "blue")], axis=1)
    except Exception as exc:  # plyfile and numpy raise many types for damaged files
        problems.report(path, field, f"unreadable PLY of points (vertex x y z red green blue): {_first_line(exc)}")
    if problem := sparse_points_problem(points, colors):
        problems.report(path, field, problem)
    return points, colors


def load_mesh_ply(path: Path, problems: _Problems, field: str):
    """The ground-truth mesh (trimesh) of a PLY file (``gt/mesh.ply``), checked non-empty and finite."""
    import trimesh

    try:
        mesh = trimesh.load(str(path), file_type=path.suffix.lstrip(".") or "ply", force="mesh")  # [V, 3], [F, 3]
    except Exception as exc:  # trimesh raises many types for damaged files
        problems.report(path, field, f"unreadable mesh: {_first_line(exc)}")
    vertices, faces = mesh.vertices, mesh.faces
    if not len(vertices) or not len(faces):
        problems.report(path, field, f"expected a mesh with vertices and faces, got {len(vertices)} and {len(faces)}")
    if not np.isfinite(vertices).all():
        problems.report(path, field, "contains NaN or infinite coordinates")
    return mesh


def load_hand_motion(path: Path, problems: _Problems, field: str) -> HandMotion:
    """Load and check a grasp's hand motion written by the writer (:meth:`HandMotion.to_arrays`'s keys)."""
    if not path.is_file():
        problems.report(path, None, "hand motion file missing")
    try:
        with np.load(path, allow_pickle=False) as npz:
            return HandMotion.from_arrays(npz)
    except InvalidInputError as exc:
        problems.report(path, field, str(exc))
    except Exception as exc:  # zipfile, zlib and numpy raise a dozen types for damaged bytes; KeyError for a key
        problems.report(path, field, f"truncated, corrupt or incomplete npz: {_first_line(exc)}")


def _check_image(
    path: Path, intr: CameraIntrinsics, index: Path, field: str, problems: _Problems, mode: str = "RGB"
) -> None:
    """Header and chunk checksums of an image file (no full decode): exists, intact, ``mode`` (RGB, or L for a
    mask), size w x h. A missing file is a problem that leaves the frame in (it is listed: counted, its file named)."""
    if not path.is_file():
        problems.note(index, field, f"{'image' if mode == 'RGB' else 'mask'} file {path.name} is missing")
        return
    try:
        with Image.open(path) as img:
            size, actual_mode = img.size, img.mode
            img.verify()
    except Exception as exc:  # PIL raises many types for damaged bytes (OSError, SyntaxError, struct.error, ...)
        problems.report(path, field, f"corrupt or truncated image: {_first_line(exc)}")
    if actual_mode != mode:
        what = "RGB image" if mode == "RGB" else "greyscale mask"
        problems.report(path, field, f"expected an 8-bit {what}, got PIL mode {actual_mode!r}")
    if size != (intr.width, intr.height):
        problems.report(
            path, field, f"image is {size[0]}x{size[1]} but the camera says w x h = {intr.width}x{intr.height}"
        )


def _intrinsics(frame: dict, top: dict, index: Path, field: str, problems: _Problems) -> CameraIntrinsics:
    values = {key: frame.get(key, top.get(key)) for key in _INTRINSIC_KEYS}
    for key, value in values.items():
        if value is None:
            problems.report(index, f"{field}.{key}", "missing (neither in the frame nor at the top level)")
    if problem := camera_problem(*values.values()):
        problems.report(index, f"{field}.{problem[0]}", problem[1])
    return intrinsics_from_json(values)  # (w and h whole numbers, as camera_problem found them)


@dataclass
class Scene:
    """A validated scene directory (DESIGN.md). Poses are OpenCV camera-to-world, metres."""

    path: Path
    frames: list[Frame]
    touches: list[Touch]
    sensor: SensorModel | None
    meta: SceneMeta
    tacsplat_version: str = ""
    gt_depth_files: dict[int, str] = field(default_factory=dict)
    gt_mesh_file: str | None = None
    gt_points_file: str | None = None
    annotations: dict = field(default_factory=dict)  # scene.json's: what the capture recorded beside its records
    sparse_points_file: str | None = None  # an import's SfM points (records.SPARSE_POINTS), None without them

    @classmethod
    def load(cls, path, check_files: bool = True) -> "Scene":
        """Read and validate a scene; raises one :class:`SceneFormatError` naming the file and field at fault.

        ``check_files=False`` skips opening images and depth maps (index files only).
        """
        return _read_scene(Path(path), STRICT, check_files)

    # --- views --------------------------------------------------------------------------------

    def split(self, name: str) -> list[Frame]:
        """The frames of one split (``"train"`` or ``"test"``)."""
        if name not in SPLITS:
            raise InvalidInputError(f"split: expected one of {SPLITS}, got {name!r}")
        return [f for f in self.frames if f.split == name]

    @property
    def intrinsics(self) -> CameraIntrinsics | None:
        """The camera shared by every frame, or None when frames differ (or there are none)."""
        if not self.frames:
            return None
        first = self.frames[0].intrinsics
        return first if all(intrinsics_equal(f.intrinsics, first) for f in self.frames) else None

    @property
    def num_grasps(self) -> int:
        return len({t.grasp for t in self.touches})

    @property
    def gt_mesh_path(self) -> Path | None:
        """Ground-truth mesh (evaluation only), or None."""
        return None if self.gt_mesh_file is None else self.path / self.gt_mesh_file

    @property
    def gt_points_path(self) -> Path | None:
        """Ground-truth point cloud on the object's surface (evaluation only; a dataset without a mesh), or None."""
        return None if self.gt_points_file is None else self.path / self.gt_points_file

    def gt_points(self) -> np.ndarray | None:
        """The ground-truth point cloud [N, 3] in metres (:attr:`gt_points_path`), or None."""
        return None if self.gt_points_path is None else load_points_ply(self.gt_points_path, STRICT, "gt.points")

    @property
    def sparse_points_path(self) -> Path | None:
        """The scene's sparse points (an import's SfM points, in the world frame), or None."""
        return None if self.sparse_points_file is None else self.path / self.sparse_points_file

    def sparse_points(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The sparse points [N, 3] float64 metres and their colours [N, 3] uint8 RGB (:attr:`sparse_points_path`),
        or None in a scene without them."""
        if self.sparse_points_path is None:
            return None
        return load_sparse_points(self.sparse_points_path, STRICT, "sparse_points")

    # --- data ---------------------------------------------------------------------------------

    def load_image(self, frame: Frame) -> np.ndarray:
        """The frame's image as float32 RGB in [0, 1], [H, W, 3]."""
        return self._picture(frame, frame.file_path, "image", color=True).astype(np.float32) / 255.0

    def load_mask(self, frame: Frame) -> np.ndarray | None:
        """The frame's mask as bool [H, W] (True = use the pixel), or None when the scene has no masks."""
        if frame.mask_path is None:
            return None
        return self._picture(frame, frame.mask_path, "mask", color=False) > 0

    def _picture(self, frame: Frame, rel: str, what: str, color: bool) -> np.ndarray:
        """The frame's picture at ``rel``: RGB uint8 [H, W, 3] (``color``) or greyscale [H, W]."""
        import cv2  # here, where a picture is read: importing the package loads no OpenCV

        path, (w, h) = self.path / rel, (frame.intrinsics.width, frame.intrinsics.height)
        picture = cv2.imread(str(path), cv2.IMREAD_COLOR if color else cv2.IMREAD_GRAYSCALE)
        if picture is None or picture.shape[:2] != (h, w):
            got = "missing or unreadable" if picture is None else f"{picture.shape[1]}x{picture.shape[0]}"
            raise SceneFormatError(path, f"frame {frame.id}", f"{what} is {got}, expected {w}x{h}")
        return cv2.cvtColor(picture, cv2.COLOR_BGR2RGB) if color else picture

    def load_touch_depth(self, touch: Touch) -> np.ndarray:
        """The touch's indentation map, float32 metres [h, w] (0 = no contact)."""
        if self.sensor is None:
            raise SceneFormatError(self.path / "touches.json", "sensor", "touches need a sensor model")
        shape = (self.sensor.height_px, self.sensor.width_px)
        return load_depth_npz(
            self.path / touch.depth_file, shape, STRICT, f"touch {touch.id}", touch_depth_limit(self.sensor)
        )

    def load_hand_motion(self, touch: Touch) -> HandMotion | None:
        """The hand's motion through the touch's grasp, or None when the scene did not record it."""
        if touch.hand_file is None:
            return None
        return load_hand_motion(self.path / touch.hand_file, STRICT, f"touch {touch.id} hand_file")

    def hand_motions(self) -> list[HandMotion]:
        """Every recorded grasp's hand motion, in grasp order (empty for a scene that recorded none)."""
        by_file = {t.hand_file: t for t in self.touches if t.hand_file is not None}  # a touch of each grasp
        return sorted((self.load_hand_motion(t) for t in by_file.values()), key=lambda m: m.grasp)

    def touch_points(self, threshold_m: float = 1e-5) -> np.ndarray:
        """Every touch's contact points in the world, [M, 3] float64 (see ``tactile_depth_to_points``)."""
        return self._in_contact(tactile_depth_to_points, threshold_m)

    def touch_normals(self, threshold_m: float = 1e-5) -> np.ndarray:
        """The touched surface's outward normals [M, 3] at :meth:`touch_points` (same order; NaN where a contact
        pixel's slope is not known, see ``tactile_depth_to_normals``)."""
        return self._in_contact(tactile_depth_to_normals, threshold_m)

    def _in_contact(self, per_touch, threshold_m: float) -> np.ndarray:
        # (no points without the sensor's pixel size: touches of a sensor at fault, as check_scene reads them)
        rows = [
            per_touch(self.load_touch_depth(t), self.sensor.pixel_size_m, t.T_world_sensor, threshold_m)
            for t in self.touches
            if t.in_contact and self.sensor is not None
        ]
        return np.concatenate(rows, axis=0) if rows else np.zeros((0, 3))

    def gt_depth(self, frame: Frame) -> np.ndarray | None:
        """Ground-truth z-depth [H, W] float32 metres of a frame (evaluation only), or None."""
        if (rel := self.gt_depth_files.get(frame.id)) is None:
            return None
        return load_depth_npz(self.path / rel, _shape(frame), STRICT, f"gt depth of frame {frame.id}", GT_DEPTH_LIMIT)

    def gt_normal(self, frame: Frame) -> np.ndarray | None:
        """Ground-truth unit world-frame normals [H, W, 3] float32 of a frame (0 where no surface; evaluation
        only), or None where the scene has none (its depth's ``normal`` array)."""
        if (rel := self.gt_depth_files.get(frame.id)) is None:
            return None
        normal = _npz_array(self.path / rel, "normal", STRICT, "normal")
        if normal is not None and (problem := normal_map_problem(normal, _shape(frame))):
            raise SceneFormatError(self.path / rel, "normal", problem)
        return normal

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box (lo [3], hi [3]) where the object must be, from cameras and touches only.

        The cameras of an object capture look at it: the box is centred on the
        point nearest to every optical axis (least squares) and its half-size is
        the smallest half-width of the field of view at that point over all
        cameras, i.e. the region every camera sees. When the axes do not meet in
        front of the cameras (fewer than two views, a forward-facing capture),
        the box of the camera centres is used. The box is grown to hold every
        contact point. Never reads gt/.
        """
        boxes = [_camera_region(self.frames)] if self.frames else []
        if len(points := self.touch_points()):
            boxes.append((points.min(axis=0), points.max(axis=0)))
        if not boxes:
            raise SceneFormatError(self.path, None, "no frames and no contact points: the scene has no bounds")
        return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)


def _shape(frame: Frame) -> tuple[int, int]:
    """(height, width) of the frame's image."""
    return frame.intrinsics.height, frame.intrinsics.width


def _camera_region(frames: list[Frame]) -> tuple[np.ndarray, np.ndarray]:
    centres = np.array([f.T_world_cam[:3, 3] for f in frames])
    axes = np.array([f.T_world_cam[:3, 2] for f in frames])
    if len(frames) >= 2:
        projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # [N, 3, 3]
        A = projectors.sum(axis=0)
        b = np.einsum("nij,nj->i", projectors, centres)
        if np.linalg.cond(A) < 1e6:
            p = np.linalg.solve(A, b)
            along = np.einsum("ni,ni->n", p - centres, axes)
            if (along > 0).all():
                half = min(
                    d * min(0.5 * f.intrinsics.width / f.intrinsics.fx, 0.5 * f.intrinsics.height / f.intrinsics.fy)
                    for d, f in zip(along, frames)
                )
                return p - half, p + half
    return centres.min(axis=0), centres.max(axis=0)


def check_scene(path, check_files: bool = True) -> tuple[Scene | None, list[SceneFormatError]]:
    """Validate a scene collecting every problem; returns the readable part (None if nothing is) and the problems."""
    problems = _Problems(collect=True)
    return problems.attempt(_read_scene, Path(path), problems, check_files), problems.errors


def _is_foreign_dataset(path: Path) -> bool:
    """A transforms.json with frames but neither scene.json nor a journal: a dataset another tool wrote (a scene
    whose creation was cut short has no frames yet)."""
    if (path / "scene.json").exists() or (path / JOURNAL).exists() or not (path / "transforms.json").is_file():
        return False
    try:
        data = json.loads((path / "transforms.json").read_text())
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return isinstance(data, dict) and isinstance(data.get("frames"), list) and len(data["frames"]) > 0


def not_a_scene(path: Path) -> str | None:
    """Why ``path`` is no scene directory at all (missing, a file, another tool's dataset, a reconstruction run, a
    folder without a scene's files), or None; a scene refused here has nothing of it read."""
    if not path.is_dir():
        return "a file, not a scene directory" if path.exists() else "scene directory does not exist"
    if _is_foreign_dataset(path):
        return (
            "a nerfstudio or instant-ngp dataset (transforms.json with frames, no scene.json), "
            f"not a tacsplat scene: import it first with `tacsplat import nerfstudio {path} --out SCENE`"
        )
    if any((path / name).exists() for name in _SCENE_FILES):
        return None
    if any((path / name).is_file() for name in _RUN_FILES):
        run = shlex.quote(str(path))
        return f"a reconstruction run, not a scene: look at it with `tacsplat view {run}` or `tacsplat evaluate {run}`"
    return f"not a scene directory: it holds none of {', '.join(_SCENE_FILES)}"


def _read_scene(path: Path, problems: _Problems, check_files: bool) -> Scene:
    if why := not_a_scene(path):
        problems.report(path, None, why)
    read = problems.attempt(_read_scene_json, path, problems)
    meta, version, gt, annotations, sparse = read or (None, "", {}, {}, None)
    frames, declared_ids = problems.attempt(_read_frames, path, problems, check_files) or ([], set())
    sensor, touches = _read_touches(path, problems, check_files)
    if meta is None:
        raise _Dropped
    scene = Scene(path, frames, touches, sensor, meta, tacsplat_version=version, annotations=annotations)
    _read_gt(scene, gt, declared_ids, problems, check_files)
    _read_sparse_points(scene, sparse, problems, check_files)
    _check_complete(scene, problems)
    return scene


def _check_complete(scene: Scene, problems: _Problems) -> None:
    """The index holds every record the writer's journal holds, a job (an import) that wrote it finished, and the
    scene has a train frame."""
    journal = scene.path / JOURNAL
    if journal.is_file():
        try:
            journaled = journaled_state(scene.path)
        except SceneFormatError as exc:
            problems.add(exc)
        else:  # (with other problems the index holds fewer valid records anyway)
            frames, touches = journaled.num_frames, journaled.num_touches
            gt = (journaled.gt_mesh, journaled.gt_points, journaled.gt_depth_files)
            resume = "a writer stopped between the two; SceneWriter.resume (or resuming the capture) rewrites the index"
            if journaled.job is not None and not journaled.finished:  # (its index is behind, and stays so)
                problems.note(
                    journal,
                    None,
                    f"the {journaled.job} writing this scene never finished ({frames} frames and {touches} touches "
                    f"written): remove {scene.path} and {journaled.job} again",
                )
            elif (frames, touches) != (len(scene.frames), len(scene.touches)) and not problems.errors:
                problems.note(
                    journal,
                    None,
                    f"records {frames} frames and {touches} touches but the index files "
                    f"hold {len(scene.frames)} and {len(scene.touches)}: {resume}",
                )
            elif journaled.annotations != scene.annotations and not problems.errors:
                problems.note(journal, "annotations", f"records other annotations than scene.json holds: {resume}")
            elif gt != (scene.gt_mesh_file, scene.gt_points_file, scene.gt_depth_files) and not problems.errors:
                problems.note(journal, "gt", f"records other ground truth than scene.json holds: {resume}")
            elif journaled.sparse_points != scene.sparse_points_file and not problems.errors:
                problems.note(journal, "sparse_points", f"records other sparse points than scene.json holds: {resume}")
    if not problems.errors:
        _check_twin_ground_truth(scene, problems)
    index = scene.path / "transforms.json"
    if not scene.frames:
        problems.note(index, "frames", "the scene has no frames")
    elif not scene.split("train"):
        problems.note(index, "frames", "the scene has no train frames")


def _check_twin_ground_truth(scene: Scene, problems: _Problems) -> None:
    """A capture on the twin (``extra.simulator`` in scene.json) has the ground truth it writes: the object's mesh
    and the depth of every test view."""
    if scene.meta.source != "sim" or "simulator" not in scene.meta.extra:
        return
    index = scene.path / "scene.json"
    if scene.gt_mesh_file is None:
        problems.note(
            index,
            "gt.mesh",
            "a capture on the twin without its ground-truth mesh (its write failed, "
            "or the capture stopped before it): resume the capture (--resume) to write it",
        )
    if missing := [f.id for f in scene.split("test") if f.id not in scene.gt_depth_files]:
        problems.note(
            index,
            "gt.depth",
            f"a capture on the twin without the ground-truth depth of its test frame(s) {', '.join(map(str, missing))}",
        )


def _read_scene_json(path: Path, problems: _Problems) -> tuple[SceneMeta, str, dict, dict, object]:
    """Provenance, tacsplat version, ground truth, annotations and the sparse points' file as scene.json holds it
    (none in a scene older than them)."""
    index = path / "scene.json"
    data = _read_json(index, problems)
    version, name = data.get("format_version", FORMAT_VERSION), data.get("object")
    bad = _check_fields(
        problems,
        index,
        "",
        data,
        format=(data.get("format", FORMAT_NAME) == FORMAT_NAME, repr(FORMAT_NAME)),
        format_version=(
            _is_int(version) and version == FORMAT_VERSION,
            f"{FORMAT_VERSION} (the version this tacsplat reads)",
        ),
        units=(data.get("units") == "m", "'m' (all tacsplat scenes are in metres)"),
        source=(data.get("source") in SOURCES, f"one of {SOURCES}"),
        object=(isinstance(name, str) and name, "the object's name"),
        capture_plan=(isinstance(data.get("capture_plan", {}), dict), "an object"),
        extra=(isinstance(data.get("extra", {}), dict), "an object"),
        gt=(isinstance(data.get("gt") or {}, dict), "an object"),
        annotations=(isinstance(data.get("annotations", {}), dict), "an object {key: value}"),
    )
    if {"source", "object", "capture_plan", "extra"}.intersection(bad):
        raise _Dropped
    meta = SceneMeta(**{key: data[key] for key in ("source", "object", "capture_plan", "extra") if key in data})
    gt, annotations = ({} if key in bad else data.get(key) or {} for key in ("gt", "annotations"))
    return meta, str(data.get("tacsplat_version", "")), gt, annotations, data.get("sparse_points")


def _read_frames(path: Path, problems: _Problems, check_files: bool) -> tuple[list[Frame], set[int]]:
    """The valid frames, and every frame id declared (also by frames dropped for a problem)."""
    index = path / "transforms.json"
    data = _read_json(index, problems)
    _check_undistorted(data, index, "", problems.note, problems)
    for key in _FOREIGN_KEYS:
        if key in data:
            problems.note(
                index,
                key,
                "not part of a tacsplat scene (poses are in the world frame, in metres); "
                "import nerfstudio data with `tacsplat import nerfstudio`",
            )
    raw_frames = data.get("frames")
    if not isinstance(raw_frames, list):
        problems.report(index, "frames", f"expected a list, got {type(raw_frames).__name__}")
    seen = {"id": {}, "file_path": {}}  # -> the field of the frame that has it
    frames = [
        problems.attempt(_read_frame, path, data, f"frames[{i}]", raw, seen, problems, check_files)
        for i, raw in enumerate(raw_frames)
    ]
    frames = [f for f in frames if f is not None]
    masked = sum(f.mask_path is not None for f in frames)
    if 0 < masked < len(frames):
        problems.note(
            index,
            "frames",
            f"{masked} of {len(frames)} frames have a mask_path: a scene has masks on "
            "every frame or on none (nerfstudio refuses anything else)",
        )
    return frames, set(seen["id"])


def _read_frame(path: Path, data: dict, field: str, raw, seen: dict, problems: _Problems, check_files: bool) -> Frame:
    index = path / "transforms.json"
    fid = _entry_id(raw, index, field, "frame", seen["id"], problems)
    split, file_path, mask = raw.get("split"), raw.get("file_path"), raw.get("mask_path")
    if split not in SPLITS:
        problems.report(index, f"{field}.split", f"unknown split {split!r} (expected one of {SPLITS})")
    image_path = _relative_file(path, file_path, index, f"{field}.file_path", problems)
    if file_path in seen["file_path"]:
        problems.report(
            index, f"{field}.file_path", f"duplicate file_path {file_path!r} (also {seen['file_path'][file_path]})"
        )
    seen["file_path"][file_path] = field
    for key in _FOREIGN_FRAME_KEYS:
        if key in raw:
            problems.report(
                index,
                f"{field}.{key}",
                "not part of a tacsplat scene; import nerfstudio data with `tacsplat import nerfstudio`",
            )
    _check_undistorted(raw, index, f"{field}.", problems.report, problems)  # nerfstudio reads a frame's own camera
    mask_path = None if mask is None else _relative_file(path, mask, index, f"{field}.mask_path", problems)
    T_gl = problems.attempt(_pose, raw.get("transform_matrix"), index, f"{field}.transform_matrix", problems)
    intr = _intrinsics(raw, data, index, field, problems)
    if T_gl is None:
        raise _Dropped
    if check_files:
        _check_image(image_path, intr, index, f"{field}.file_path", problems)
        if mask_path is not None:
            _check_image(mask_path, intr, index, f"{field}.mask_path", problems, "L")
    return Frame(fid, file_path, opengl_to_opencv(T_gl), split, intr, mask)


def _check_undistorted(raw: dict, index: Path, prefix: str, distorted, problems: _Problems) -> None:
    """The camera_model and distortion keys of transforms.json (``prefix`` "") or of a frame (``prefix``
    "frames[3]."): those of undistorted images. A wrong model is reported, distortion goes to ``distorted``
    (``problems.note`` or ``problems.report``)."""
    if raw.get("camera_model", "OPENCV") not in _UNDISTORTED_MODELS:
        got = raw["camera_model"]
        problems.report(index, f"{prefix}camera_model", f"expected OPENCV or PINHOLE (undistorted images), got {got!r}")
    for key in _DISTORTION_KEYS:
        if raw.get(key, 0.0) != 0.0:
            distorted(index, prefix + key, f"images must be undistorted, but {key} = {raw[key]!r}")


def _read_sensor(raw, index: Path, problems: _Problems) -> SensorModel:
    if not isinstance(raw, dict):
        problems.report(index, "sensor", f"expected an object or null, got {type(raw).__name__}")
    keys = [f.name for f in fields(SensorModel)]
    if missing := [k for k in keys if k not in raw]:
        problems.report(index, "sensor", f"missing keys {missing}")
    try:
        return SensorModel(**{k: raw[k] for k in keys})
    except InvalidInputError as exc:
        problems.report(index, "sensor", str(exc))


def _read_touches(path: Path, problems: _Problems, check_files: bool) -> tuple[SensorModel | None, list[Touch]]:
    index = path / "touches.json"
    if (data := problems.attempt(_read_json, index, problems, False)) is None:
        return None, []
    sensor = None if data.get("sensor") is None else problems.attempt(_read_sensor, data["sensor"], index, problems)
    raw_touches = data.get("touches", [])
    if not isinstance(raw_touches, list):
        problems.note(index, "touches", f"expected a list, got {type(raw_touches).__name__}")
        return sensor, []
    if raw_touches and data.get("sensor") is None:
        problems.note(index, "sensor", f"{len(raw_touches)} touches but no sensor model")
    # (without a valid sensor each touch is still read and checked: all but its depth map's size and deepest value)
    seen, motions = {}, {}  # id -> field; hand file -> its HandMotion (each checked once)
    touches = [
        problems.attempt(_read_touch, path, f"touches[{i}]", raw, sensor, seen, motions, problems, check_files)
        for i, raw in enumerate(raw_touches)
    ]
    return sensor, [t for t in touches if t is not None]


def _read_touch(
    path: Path,
    field: str,
    raw,
    sensor: SensorModel | None,
    seen: dict,
    motions: dict,
    problems: _Problems,
    check_files: bool,
) -> Touch:
    index = path / "touches.json"
    tid = _entry_id(raw, index, field, "touch", seen, problems)
    grasp, finger, in_contact, hand_file = (raw.get(key) for key in ("grasp", "finger", "in_contact", "hand_file"))
    if _check_fields(
        problems,
        index,
        f"{field}.",
        raw,
        grasp=(_is_int(grasp) and grasp >= 0, "a non-negative integer"),
        finger=(isinstance(finger, str) and finger, "a finger name"),
        in_contact=(isinstance(in_contact, bool), "true or false"),
    ):
        raise _Dropped
    depth_path = problems.attempt(_relative_file, path, raw.get("depth_file"), index, f"{field}.depth_file", problems)
    T = _pose(raw.get("T_world_sensor"), index, f"{field}.T_world_sensor", problems)
    if depth_path is None:
        raise _Dropped
    if hand_file is not None:
        hand_path = _relative_file(path, hand_file, index, f"{field}.hand_file", problems)
        if check_files and hand_path not in motions:
            motions[hand_path] = problems.attempt(load_hand_motion, hand_path, problems, f"{field}.hand_file")
        if check_files and motions[hand_path] is None:
            raise _Dropped
    if check_files:
        shape = None if sensor is None else (sensor.height_px, sensor.width_px)
        limit = (np.inf, "") if sensor is None else touch_depth_limit(sensor)
        depth = load_depth_npz(depth_path, shape, problems, f"touch {tid} depth", limit)
        if bool((depth > 0).any()) != in_contact:
            problems.report(
                index,
                f"{field}.in_contact",
                f"says {in_contact} but the depth map {'has' if (depth > 0).any() else 'has no'} contact",
            )
    return Touch(tid, grasp, finger, raw["depth_file"], T, in_contact, hand_file)


def _read_sparse_points(scene: Scene, rel, problems: _Problems, check_files: bool) -> None:
    """scene.json's ``sparse_points`` (None: a scene without them), its file checked with ``check_files``."""
    if rel is None:
        return
    index = scene.path / "scene.json"
    path = problems.attempt(_relative_file, scene.path, rel, index, "sparse_points", problems)
    if path is not None and (
        not check_files or problems.attempt(load_sparse_points, path, problems, "sparse_points") is not None
    ):
        scene.sparse_points_file = rel


def _read_gt(scene: Scene, gt: dict, declared_ids: set[int], problems: _Problems, check_files: bool) -> None:
    index = scene.path / "scene.json"
    mesh, points, depth_files = gt.get("mesh"), gt.get("points"), gt.get("depth", {})
    if mesh is not None and (path := problems.attempt(_relative_file, scene.path, mesh, index, "gt.mesh", problems)):
        if check_files and not path.is_file():
            problems.note(index, "gt.mesh", f"ground-truth mesh {mesh!r} is missing")
        elif not check_files or problems.attempt(load_mesh_ply, path, problems, "gt.mesh") is not None:
            scene.gt_mesh_file = mesh
    if points is not None and (
        path := problems.attempt(_relative_file, scene.path, points, index, "gt.points", problems)
    ):
        if not check_files or problems.attempt(load_points_ply, path, problems, "gt.points") is not None:
            scene.gt_points_file = points
    if not isinstance(depth_files, dict):
        problems.note(index, "gt.depth", f"expected an object {{frame id: file}}, got {type(depth_files).__name__}")
        return
    frames = {f.id: f for f in scene.frames}
    for key, rel in depth_files.items():
        field = f"gt.depth[{key}]"
        fid = int(key) if isinstance(key, str) and key.isascii() and key.isdigit() else None  # ("²".isdigit())
        if fid not in frames:
            if fid not in declared_ids:  # (a declared frame with a problem has been reported already)
                problems.note(index, field, f"no frame with id {key!r}")
            continue
        path = problems.attempt(_relative_file, scene.path, rel, index, field, problems)
        shape, what = _shape(frames[fid]), f"gt depth of frame {fid}"
        if path is not None and (
            not check_files or problems.attempt(load_depth_npz, path, shape, problems, what, GT_DEPTH_LIMIT) is not None
        ):
            scene.gt_depth_files[fid] = rel
