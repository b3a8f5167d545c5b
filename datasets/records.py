"""Typed records of a scene directory and their JSON (de)serialisation.

Records hold poses in the code's conventions (OpenCV camera-to-world, metres).
The OpenGL ``transform_matrix`` of nerfstudio's ``transforms.json`` is produced
and parsed only by :func:`frame_to_nerfstudio` / the reader, through
:func:`tacsplat.geometry.opencv_to_opengl` and its inverse.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from tacsplat.errors import InvalidInputError
from tacsplat.geometry import as_pose, intrinsics_matrix, opencv_to_opengl, rigidity_problem
from tacsplat.types import CameraIntrinsics

SPLITS = ("train", "test")
SOURCES = ("sim", "real", "import")
FORMAT_NAME = "tacsplat-scene"
FORMAT_VERSION = 1

# What a capture can physically hold; a number outside is a units or file error, refused where it enters.
MAX_DISTANCE_M = 1e5  # no position, depth or length in a scene is farther than 100 km
MAX_IMAGE_SIDE = 65536  # pixels per image or tactile map side
FIELD_OF_VIEW_DEG = (0.01, 170.0)  # of a pinhole camera, per axis
MAX_INDENTATION_GELS = 10.0  # an indentation deeper than 10 gel thicknesses is no touch
GT_DEPTH_LIMIT = (MAX_DISTANCE_M, "any scene")  # depth_problem's (deepest value, why) for ground-truth depth
# A scene's sparse points (an import's COLMAP points3D, in the world frame): the initialisation's SfM points
SPARSE_POINTS = "points3D.ply"


def is_finite_number(x) -> bool:
    """A JSON number (not a bool) that is finite as a float."""
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:  # an int too large for a float
        return False


def is_size(x) -> bool:
    """A positive integer pixel count up to MAX_IMAGE_SIDE."""
    return not isinstance(x, bool) and isinstance(x, (int, np.integer)) and 1 <= x <= MAX_IMAGE_SIDE


def as_size(x) -> int | None:
    """An image side as nerfstudio (``1080``) or instant-ngp (``1080.0``) writes it, as an int; None when it is
    no whole positive number up to MAX_IMAGE_SIDE."""
    if is_finite_number(x) and float(x).is_integer() and is_size(int(x)):
        return int(x)
    return None


def camera_problem(fx, fy, cx, cy, width, height) -> tuple[str, str] | None:
    """``(key, why)`` for intrinsics (nerfstudio keys) no pinhole camera has, or None."""
    for key, value in (("w", width), ("h", height)):
        if as_size(value) is None:
            return key, f"expected a positive integer up to {MAX_IMAGE_SIDE} (1080 or 1080.0), got {value!r}"
    lo, hi = FIELD_OF_VIEW_DEG
    for key, f, side in (("fl_x", fx, width), ("fl_y", fy, height)):
        if not is_finite_number(f) or f <= 0:
            return key, f"expected a finite positive number, got {f!r}"
        fov = math.degrees(2 * math.atan(side / (2 * f)))
        if not lo <= fov <= hi:
            return key, (
                f"{f:.6g} px gives a field of view of {fov:.3g} degrees over {side} px; a camera has "
                f"{lo:g} to {hi:g} (focal length {side / (2 * math.tan(math.radians(hi) / 2)):.3g} to "
                f"{side / (2 * math.tan(math.radians(lo) / 2)):.3g} px)"
            )
    for key, c, side in (("cx", cx, width), ("cy", cy, height)):
        if not is_finite_number(c) or not 0 <= c <= side:
            return key, f"the principal point must be inside the image, 0..{side} px, got {c!r}"
    return None


def pose_problem(T) -> str | None:
    """Why ``T`` is not a rigid transform within MAX_DISTANCE_M of the origin, or None."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return "expected a 4x4 matrix of numbers"
    if problem := rigidity_problem(T):
        return f"not a rigid transform: {problem}"
    if (distance := float(np.linalg.norm(T[:3, 3]))) > MAX_DISTANCE_M:
        return f"its origin is {distance:.3g} metres from the origin; no scene is larger than {MAX_DISTANCE_M:g} m (wrong units?)"
    return None


def check_pose(T, name: str) -> np.ndarray:
    """``T`` as float64 [4, 4] if :func:`pose_problem` finds nothing, else InvalidInputError naming ``name``."""
    if problem := pose_problem(T):
        raise InvalidInputError(f"{name}: {problem}")
    return np.asarray(T, dtype=np.float64)


def depth_problem(depth: np.ndarray, max_m: float, limit: str) -> str | None:
    """Why a depth map [h, w] (metres) is not one: not float, not finite, negative, or deeper than ``max_m``
    (``limit`` says why that is the limit)."""
    if not np.issubdtype(depth.dtype, np.floating):
        return f"expected float metres, got dtype {depth.dtype}"
    if not np.all(np.isfinite(depth)):
        return f"{int((~np.isfinite(depth)).sum())} non-finite values (NaN or inf)"
    if depth.size and depth.min() < 0:
        return f"negative depth values (min {float(depth.min()):.3g} m)"
    if depth.size and float(depth.max()) > max_m:
        return f"depth of {float(depth.max()):.3g} m is deeper than {limit} ({max_m:.3g} m)"
    return None


def normal_map_problem(normal: np.ndarray, shape: tuple[int, int]) -> str | None:
    """Why ``normal`` is not a map [*shape, 3] of unit vectors, or zeros where there is no surface."""
    if normal.shape != (*shape, 3):
        return f"expected shape {(*shape, 3)}, got {normal.shape}"
    if not np.issubdtype(normal.dtype, np.floating) or not np.all(np.isfinite(normal)):
        return "expected finite float values"
    length = np.linalg.norm(normal, axis=-1)
    if not np.all((np.abs(length - 1) < 1e-3) | (length == 0)):
        return "expected unit vectors, or zeros where there is no surface"
    return None


def sparse_points_problem(points: np.ndarray, colors: np.ndarray) -> str | None:
    """Why ``points`` [N, 3] and ``colors`` [N, 3] uint8 are not a scene's sparse points (``SPARSE_POINTS``)."""
    if points.ndim != 2 or points.shape[1:] != (3,) or not len(points):
        return f"expected a non-empty [N, 3] point cloud, got shape {points.shape}"
    if colors.shape != points.shape or colors.dtype != np.uint8:
        return f"expected uint8 colours {points.shape} (RGB per point), got {colors.dtype} {colors.shape}"
    if not np.isfinite(points).all():
        return f"{int((~np.isfinite(points).all(axis=1)).sum())} points are not finite (NaN or inf)"
    return None


def touch_depth_limit(sensor: "SensorModel") -> tuple[float, str]:
    """The deepest indentation a sensor can record, and why."""
    return MAX_INDENTATION_GELS * sensor.gel_thickness_m, f"{MAX_INDENTATION_GELS:g} x the gel thickness"


def intrinsics_equal(a: CameraIntrinsics, b: CameraIntrinsics) -> bool:
    return a.width == b.width and a.height == b.height and np.array_equal(a.K, b.K)


def _same(a, b) -> bool:
    """Equality of two values of a record's field: arrays by value, intrinsics by size and K."""
    if isinstance(a, CameraIntrinsics):
        return isinstance(b, CameraIntrinsics) and intrinsics_equal(a, b)
    return np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b


class _ByValue:
    """Equality of frozen dataclass records field by field (:func:`_same`); unhashable, as their arrays are. Their
    poses (``T_world_*`` fields) are checked and frozen."""

    def __post_init__(self):
        for f in fields(self):
            if f.name.startswith("T_world_"):
                pose = as_pose(getattr(self, f.name), f"{type(self).__name__.lower()} {self.id} {f.name}").copy()
                pose.setflags(write=False)
                object.__setattr__(self, f.name, pose)

    def __eq__(self, other) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(_same(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))

    __hash__ = None


@dataclass(frozen=True, eq=False)
class Frame(_ByValue):
    """One camera view: ``file_path`` relative to the scene directory, OpenCV camera-to-world pose, and
    optionally ``mask_path``, a mask of the pixels to use (nerfstudio's per-frame ``mask_path``)."""

    id: int
    file_path: str
    T_world_cam: np.ndarray  # [4, 4] float64, OpenCV camera-to-world
    split: str
    intrinsics: CameraIntrinsics
    mask_path: str | None = None  # greyscale PNG, 255 = use the pixel, 0 = ignore it


@dataclass(frozen=True, eq=False)
class Touch(_ByValue):
    """One tactile reading: depth map file (relative path) and the sensor pose in the world."""

    id: int
    grasp: int
    finger: str
    depth_file: str
    T_world_sensor: np.ndarray  # [4, 4] float64
    in_contact: bool
    hand_file: str | None = None  # the grasp's HandMotion (scenes of a hand capture; None: not recorded)


# HandMotion.phase: where the hand was, closing, opening; "slide" (its pads sliding along the surface in contact)
# only in scenes captured before the slide was removed (docs/experiments.md), kept at its index so that they decode
MOTION_PHASES = ("preshape", "close", "open", "slide")


@dataclass(frozen=True, eq=False)
class HandMotion:
    """What the hand did through one grasp (proprioception), sampled at the grasp controller's polls.

    The hand base stays at ``T_world_hand`` throughout (the logger measures it
    once, before the fingers move). ``link_poses`` places the hand model's solid
    boxes (palm, links, gels up to their undeformed surface) at each sample: the
    space they occupied was empty then.
    """

    grasp: int
    joint_names: tuple[str, ...]  # [J]
    t: np.ndarray  # [S] seconds on the rig's clock since the grasp started
    phase: np.ndarray  # [S] indices into MOTION_PHASES
    q: np.ndarray  # [S, J] measured joint positions, radians
    q_target: np.ndarray  # [S, J] commanded positions, radians
    effort: np.ndarray  # [S, J] in effort_unit
    effort_unit: str  # "A" (servo current) | "N m" (joint torque)
    T_world_hand: np.ndarray  # [4, 4]
    link_names: tuple[str, ...]  # [L]
    link_half_extents: np.ndarray  # [L, 3] metres
    link_poses: np.ndarray  # [S, L, 4, 4] world poses of the boxes
    # [N] when each of the grasp's N touches was read (seconds since the grasp started, in record order); None in
    # scenes written before it was recorded, whose grasps hold one touch per sensor
    touch_t: np.ndarray | None = None

    def __post_init__(self):
        if problem := hand_motion_problem(self):
            raise InvalidInputError(f"hand motion of grasp {self.grasp}: {problem}")

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {f.name: np.asarray(getattr(self, f.name)) for f in fields(self) if getattr(self, f.name) is not None}
        names = {k: np.array(getattr(self, k), dtype=str) for k in ("joint_names", "link_names")}
        return {**arrays, **names, "grasp": np.int64(self.grasp), "phase": arrays["phase"].astype(np.uint8)}

    @classmethod
    def from_arrays(cls, a) -> "HandMotion":
        floats = ("t", "q", "q_target", "effort", "T_world_hand", "link_half_extents", "link_poses")
        return cls(
            **{k: np.asarray(a[k], dtype=np.float64) for k in floats},
            grasp=int(a["grasp"]),
            joint_names=tuple(str(n) for n in a["joint_names"]),
            phase=np.asarray(a["phase"]),
            effort_unit=str(a["effort_unit"]),
            link_names=tuple(str(n) for n in a["link_names"]),
            touch_t=np.asarray(a["touch_t"], dtype=np.float64) if "touch_t" in a else None,
        )


def hand_motion_problem(m: HandMotion) -> str | None:
    """Why a HandMotion is not one (shapes that disagree, values that are not finite, a bad pose), or None."""
    S, J, L = len(np.atleast_1d(m.t)), len(m.joint_names), len(m.link_names)
    shapes = {"t": (S,), "phase": (S,), "q": (S, J), "q_target": (S, J), "effort": (S, J)}
    shapes.update(link_half_extents=(L, 3), link_poses=(S, L, 4, 4))
    phases = f"phase must hold whole numbers 0 to {len(MOTION_PHASES) - 1}, indices into {MOTION_PHASES}"
    for name, shape in shapes.items():
        value = np.asarray(getattr(m, name))
        if value.shape != shape:
            return f"{name} has shape {value.shape}, expected {shape}"
        if name == "phase" and value.dtype.kind not in "iuf":  # (the file holds uint8)
            return f"{phases}, got dtype {value.dtype}"
        if name != "effort" and not np.all(np.isfinite(value)):
            return f"{name} holds NaN or infinite values"
    if S == 0:
        return "no samples"
    if np.any(np.diff(m.t) < 0):
        return "t goes backwards"
    if m.touch_t is not None and (np.ndim(m.touch_t) != 1 or not np.all(np.isfinite(m.touch_t))):
        return "touch_t must be a finite vector of seconds"
    phase = np.asarray(m.phase)
    if bad := np.flatnonzero((phase < 0) | (phase >= len(MOTION_PHASES)) | (phase % 1 != 0)).tolist():
        return f"{phases}, got {phase[bad[0]].item()!r} at sample {bad[0]}"
    if np.any(np.asarray(m.link_half_extents) <= 0) or np.any(np.asarray(m.link_half_extents) > MAX_DISTANCE_M):
        return "link_half_extents must be positive lengths in metres"
    problem = pose_problem(m.T_world_hand)
    return f"T_world_hand: {problem}" if problem else None


@dataclass(frozen=True)
class SensorModel:
    """The tactile sensor, modelled as an orthographic depth camera behind its gel (DESIGN.md)."""

    name: str
    width_px: int
    height_px: int
    pixel_size_m: float
    gel_thickness_m: float

    def __post_init__(self):
        if problem := sensor_problem(self):
            raise InvalidInputError(f"SensorModel: {problem}")
        for name, kind in (("width_px", int), ("height_px", int), ("pixel_size_m", float), ("gel_thickness_m", float)):
            object.__setattr__(self, name, kind(getattr(self, name)))  # plain numbers, as the files hold them


@dataclass(frozen=True)
class SceneMeta:
    """Provenance of a scene. Units are always metres; the writer adds the tacsplat version."""

    source: str  # "sim" | "real" | "import"
    object: str
    capture_plan: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.source not in SOURCES:
            raise InvalidInputError(f"SceneMeta.source: expected one of {SOURCES}, got {self.source!r}")
        if not isinstance(self.object, str) or not self.object:
            raise InvalidInputError("SceneMeta.object: expected a non-empty string")
        for name in ("capture_plan", "extra"):
            if not isinstance(getattr(self, name), dict):
                raise InvalidInputError(f"SceneMeta.{name}: expected a dict")


def sensor_problem(sensor: SensorModel) -> str | None:
    """Why a sensor model is invalid, or None."""
    length, gel = sensor.pixel_size_m, sensor.gel_thickness_m
    for name, fine, expected in (
        ("name", isinstance(sensor.name, str) and sensor.name, "a non-empty string"),
        ("width_px", is_size(sensor.width_px), f"a positive integer up to {MAX_IMAGE_SIDE}"),
        ("height_px", is_size(sensor.height_px), f"a positive integer up to {MAX_IMAGE_SIDE}"),
        ("pixel_size_m", is_finite_number(length) and length > 0, "positive and finite"),
        ("gel_thickness_m", is_finite_number(gel) and gel > 0, "positive and finite"),
    ):
        if not fine:
            return f"{name} must be {expected}, got {getattr(sensor, name)!r}"
    if (extent := sensor.pixel_size_m * max(sensor.width_px, sensor.height_px)) > MAX_DISTANCE_M:
        return (
            f"pixel_size_m {sensor.pixel_size_m:.3g} makes the sensor {extent:.3g} m wide; no scene is larger than "
            f"{MAX_DISTANCE_M:g} m (wrong units?)"
        )
    if sensor.gel_thickness_m > MAX_DISTANCE_M:
        return f"gel_thickness_m {sensor.gel_thickness_m:.3g} is larger than any scene ({MAX_DISTANCE_M:g} m)"
    return None


# --- JSON forms ---------------------------------------------------------------------------------


def intrinsics_to_json(intr: CameraIntrinsics) -> dict:
    """nerfstudio intrinsics keys (``fl_x, fl_y, cx, cy, w, h``); skew is not representable, and neither is a
    camera :func:`camera_problem` refuses."""
    if intr.K[0, 1] != 0 or intr.K[1, 0] != 0 or not np.array_equal(intr.K[2], [0.0, 0.0, 1.0]):
        raise InvalidInputError(f"intrinsics: only zero-skew pinhole K is supported, got {intr.K.tolist()}")
    if problem := camera_problem(intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height):
        raise InvalidInputError(f"intrinsics.{problem[0]}: {problem[1]}")
    return {"fl_x": intr.fx, "fl_y": intr.fy, "cx": intr.cx, "cy": intr.cy, "w": int(intr.width), "h": int(intr.height)}


def intrinsics_from_json(d: dict) -> CameraIntrinsics:
    return CameraIntrinsics(intrinsics_matrix(d["fl_x"], d["fl_y"], d["cx"], d["cy"]), int(d["w"]), int(d["h"]))


def sensor_to_json(sensor: SensorModel | None) -> dict | None:
    return None if sensor is None else asdict(sensor)


def record_to_json(record, **values) -> dict:
    """A record's fields (``values`` replacing some) as JSON data, arrays as nested lists; an optional path that
    is None is left out (the writer's journal, ``touches.json``)."""
    out = {f.name: values.get(f.name, getattr(record, f.name)) for f in fields(record)}
    return {
        k: v.tolist() if isinstance(v, np.ndarray) else v
        for k, v in out.items()
        if v is not None or k not in ("mask_path", "hand_file")
    }


def frame_to_json(frame: Frame) -> dict:
    """The writer's journal form of a frame (OpenCV pose, full intrinsics, the mask if any)."""
    return record_to_json(frame, intrinsics=intrinsics_to_json(frame.intrinsics))


def frame_from_json(d: dict) -> Frame:
    return Frame(**{**d, "intrinsics": intrinsics_from_json(d["intrinsics"])})


def frame_to_nerfstudio(frame: Frame, with_intrinsics: bool) -> dict:
    """A ``transforms.json`` frame entry: OpenGL camera-to-world ``transform_matrix`` (and ``mask_path``)."""
    entry = {
        "id": frame.id,
        "file_path": frame.file_path,
        "transform_matrix": opencv_to_opengl(frame.T_world_cam).tolist(),
        "split": frame.split,
    }
    if frame.mask_path is not None:
        entry["mask_path"] = frame.mask_path
    if with_intrinsics:
        entry.update(intrinsics_to_json(frame.intrinsics))
    return entry


def touch_to_json(touch: Touch) -> dict:
    return record_to_json(touch, in_contact=bool(touch.in_contact))
