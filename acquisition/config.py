"""The rig YAML: which devices, their ports and calibration files, the mounting transforms, the board,
the grasp controller, and the capture plan, as dataclasses.

``rig: real`` describes the Dynamixel hand, the optical tactile sensors and the
wrist camera; ``rig: sim`` the MuJoCo twin. ``--mock`` (``load_rig(...,
mock=True)``) keeps a real rig's file and swaps in emulated devices (see
:mod:`tacsplat.acquisition.mock`). Every value is checked where it enters
(:func:`validate`, also for configs built in code): types, the physical and
logical range each field declares (:func:`bounded`), rigid 4x4 transforms and
the cross-field rules; each invalid value raises one
:class:`~tacsplat.errors.ConfigError` naming the file, the field path
(``tactile.sensors[2].T_fingertip_sensor``) and the allowed range. The
example files are in ``acquisition/rigs/`` (:func:`example_rig`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from tacsplat.errors import ConfigError
from tacsplat.geometry import rigidity_problem

FINGERS = ("index", "middle", "ring", "thumb")
RIGS_DIR = Path(__file__).parent / "rigs"
DYNAMIXEL_BAUDRATES = (9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000)  # X-series rates the SDK opens
DYNAMIXEL_MAX_ID = 252  # protocol 2.0: 253 is reserved, 254 is the broadcast id
MAX_OBJECT_RADIUS_M = 0.3  # a graspable object (DESIGN.md: about 0.05-0.15 m); the hand spans about 0.2 m


@dataclass(frozen=True)
class Bounds:
    """The values a number (or each number of a list) may take: ``lo <= x <= hi``, ``lo < x`` when ``lo_open``."""

    lo: float
    hi: float = math.inf
    lo_open: bool = False
    unit: str = ""

    def holds(self, x: float) -> bool:
        try:
            finite = math.isfinite(x)
        except OverflowError:  # an integer too large for a float
            return False
        return finite and (x > self.lo if self.lo_open else x >= self.lo) and x <= self.hi

    def __str__(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if math.isinf(self.hi):
            return f"{'>' if self.lo_open else '>='} {self.lo:g}{unit}"
        return f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}]{unit}"


def bounded(default, lo: float, hi: float = math.inf, unit: str = "", lo_open: bool = False):
    """A config field whose value (each value, for a list; unchecked when None) must lie within :class:`Bounds`."""
    return field(default=default, metadata={"bounds": Bounds(lo, hi, lo_open, unit)})


def positive(default, hi: float = math.inf, unit: str = ""):
    """A field that must be > 0 (and <= ``hi``)."""
    return bounded(default, 0, hi, unit, lo_open=True)


@dataclass(frozen=True)
class HandConfig:
    """The Dynamixel hand (``rig: real``)."""

    port: str = "/dev/ttyUSB0"  # the U2D2 adapter
    baudrate: int = 4_000_000  # one of DYNAMIXEL_BAUDRATES
    ids: tuple[int, ...] = bounded(tuple(range(16)), 0, DYNAMIXEL_MAX_ID)  # servo of each joint, twin's joint order
    calibration: str | None = None  # HandCalibration JSON (offsets, signs); None = identity


@dataclass(frozen=True)
class CameraConfig:
    """The wrist camera (``rig: real``)."""

    source: int | str = 0  # device index, file path or stream URL
    calibration: str = "wrist_camera.json"  # CameraCalibration JSON (intrinsics, distortion, board)
    T_hand_cam: tuple | None = None  # [4, 4] camera in the hand frame; None = the calibration file's hand-eye result
    fps: float | None = positive(None, 1000.0, "Hz")
    timeout_s: float = positive(2.0, 60.0, "s")  # no frame for this long is a CameraError


@dataclass(frozen=True)
class BoardConfig:
    """The ChArUco board that defines the world frame (defaults: CharucoBoardSpec's)."""

    squares_x: int = bounded(7, 2, 100)
    squares_y: int = bounded(5, 2, 100)
    square_length_m: float = positive(0.03, 1.0, "m")
    marker_length_m: float = positive(0.022, 1.0, "m")  # smaller than the square
    dictionary: str = "DICT_5X5_100"  # with at least one marker per white square
    legacy_pattern: bool = False
    max_reprojection_px: float = positive(1.0, 50.0, "px")  # a view or grasp whose board PnP is worse is rejected
    min_corners: int = bounded(6, 4, 10_000)  # PnP needs 4; at most the board's inner corners

    def spec(self):
        from tacsplat.drivers.wrist_camera import CharucoBoardSpec

        return CharucoBoardSpec(self.squares_x, self.squares_y, self.square_length_m, self.marker_length_m,
                                self.dictionary, self.legacy_pattern)


@dataclass(frozen=True)
class TactileSensorConfig:
    """One optical tactile fingertip (``rig: real``)."""

    finger: str  # index | middle | ring | thumb: whose fingertip frame it is mounted on
    source: int | str  # device index, file path or URL
    calibration: str  # TactileCalibration file (tacsplat calibrate tactile)
    T_fingertip_sensor: tuple | None = None  # [4, 4] mounting: sensor frame in the fingertip pad frame; None = identity


@dataclass(frozen=True)
class TactileConfig:
    sensor_name: str = "digit"  # the scene's sensor model name
    gel_thickness_m: float = positive(0.002, 0.02, "m")
    timeout_s: float = positive(2.0, 60.0, "s")
    sensors: tuple[TactileSensorConfig, ...] = ()


@dataclass(frozen=True)
class GraspControl:
    """How the logger closes the hand: a speed-limited ramp toward ``close_pose``, each finger stopping when it
    stalls, then a wait until the joints settle; then the read, then ``open_pose``."""

    close_pose: tuple[float, ...] = bounded((0.0, 1.2, 1.0, 1.0) * 3 + (1.2, 0.6, 0.6, 0.8), -math.pi, math.pi,
                                            "rad")  # [16] joint positions
    open_pose: tuple[float, ...] = bounded((0.0,) * 16, -math.pi, math.pi, "rad")  # [16] joint positions
    close_speed_rad_s: float = positive(1.5, 10.0, "rad/s")  # largest joint speed of the commanded ramp
    poll_s: float = positive(0.02, 1.0, "s")  # joint polling period (through the rig's clock)
    stall_error_rad: float = positive(0.15, math.pi, "rad")  # a finger lagging its ramp by this much has stalled
    settle_tol_rad: float = positive(0.004, math.pi, "rad")  # joints moving less than this per poll ...
    settle_polls: int = bounded(3, 1, 1000)  # ... for this many polls in a row have settled
    max_close_s: float = positive(5.0, 60.0, "s")  # give up waiting (the reading is still taken, with a warning)
    open_s: float = bounded(0.3, 0, 60.0, "s")  # wait after opening


@dataclass(frozen=True)
class ViewPlan:
    train: int = bounded(20, 1)  # a scene needs a view to train on
    test: int = bounded(5, 0)
    mode: str = "operator"  # operator (a person places the camera) | hemisphere (the twin places it)
    radius_m: float | None = positive(None, 10.0, "m")  # hemisphere radius; None = the twin's default for the object


@dataclass(frozen=True)
class GraspPlan:
    count: int = bounded(5, 0)
    mode: str = "operator"  # operator (a person places the hand) | random (the twin samples approaches)
    seed: int = bounded(0, 0)


@dataclass(frozen=True)
class CapturePlan:
    views: ViewPlan = field(default_factory=ViewPlan)
    grasps: GraspPlan = field(default_factory=GraspPlan)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class SimConfig:
    """The twin (``rig: sim``)."""

    object: str = "teapot"
    mesh: str | None = None
    object_radius: float = positive(0.08, MAX_OBJECT_RADIUS_M, "m")  # bounding-sphere radius
    resolution: int = bounded(200, 8, 4096, "px")
    seed: int = bounded(0, 0)


@dataclass(frozen=True)
class MockConfig:
    """The emulated devices of ``--mock`` (a real rig's file, no hardware)."""

    camera_width: int = bounded(320, 16, 4096, "px")
    camera_height: int = bounded(240, 16, 4096, "px")
    camera_focal_px: float = positive(280.0, 1e5, "px")
    camera_frames: int = bounded(24, 1, 1000)  # board renders in the looping video
    tactile_width: int = bounded(160, 8, 4096, "px")
    tactile_height: int = bounded(120, 8, 4096, "px")
    tactile_pixel_size_m: float = positive(1.6e-4, 1e-3, "m")
    servo_timeout_s: float = positive(0.1, 10.0, "s")


@dataclass(frozen=True)
class RigConfig:
    rig: str  # real | sim
    object: str = "object"  # the scene's object name
    hand: HandConfig = field(default_factory=HandConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    board: BoardConfig = field(default_factory=BoardConfig)
    tactile: TactileConfig = field(default_factory=TactileConfig)
    grasp: GraspControl = field(default_factory=GraspControl)
    plan: CapturePlan = field(default_factory=CapturePlan)
    sim: SimConfig = field(default_factory=SimConfig)
    mock_devices: MockConfig = field(default_factory=MockConfig)
    source: str | None = None  # the YAML file it came from
    mock: bool = False  # --mock: emulated devices instead of a real rig's

    @property
    def scene_object(self) -> str:
        """The scene's object name: ``object`` when the file gives one, else (``rig: sim``) the twin's object, the
        library name or the mesh file's stem."""
        if self.object != "object" or self.rig != "sim":
            return self.object
        return Path(self.sim.mesh).stem if self.sim.mesh else self.sim.object

    def path(self, relative: str) -> Path:
        """A file named in the YAML, relative to the YAML's folder."""
        p = Path(relative).expanduser()
        return p if p.is_absolute() or self.source is None else Path(self.source).parent / p


def example_rig(name: str) -> Path:
    """The shipped example rig file ``acquisition/rigs/<name>.yaml`` (real, sim, mock)."""
    return RIGS_DIR / f"{name}.yaml"


# --- parsing ------------------------------------------------------------------------------------

def _pose(value, key: str, source) -> tuple:
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(key, f"expected a 4x4 matrix of numbers, got {value!r}", source) from None
    problem = rigidity_problem(T)
    if problem:
        raise ConfigError(key, f"not a rigid transform: {problem} (expected [[R, t], [0, 0, 0, 1]], R a rotation: "
                          "orthonormal, determinant +1; all finite)", source)
    return tuple(map(tuple, T.tolist()))


def _build(cls, data: Any, prefix: str, source, nested: dict | None = None):
    """A dataclass from a YAML mapping; unknown keys and wrong types name their key."""
    nested = nested or {}
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(prefix, f"expected a mapping, got {type(data).__name__}", source)
    reserved = ("source", "mock") if cls is RigConfig else ()  # set by load_rig, not by the file
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name not in reserved}
    kwargs = {}
    for key, value in data.items():
        full = f"{prefix}.{key}" if prefix else str(key)
        if key not in fields:
            raise ConfigError(full, f"unknown key (expected one of {sorted(fields)})", source)
        if key in nested:
            kwargs[key] = nested[key](value, full)
            continue
        kwargs[key] = _coerce(value, fields[key].type, full, source)
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise ConfigError(prefix or "(top level)", str(exc), source) from None


def _coerce(value, annotation: str, key: str, source):
    """Check a scalar or sequence against a field's annotation (written as a string)."""
    ann = str(annotation)
    if value is None:
        if "None" in ann:
            return None
        raise ConfigError(key, "must not be empty", source)
    if ann.startswith("tuple[float"):
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            raise ConfigError(key, f"expected a list of numbers, got {value!r}", source)
        return tuple(float(v) for v in value)
    if ann.startswith("tuple[int"):
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            raise ConfigError(key, f"expected a list of integers, got {value!r}", source)
        return tuple(value)
    if ann.startswith("tuple"):  # 4x4 poses
        return _pose(value, key, source)
    if ann.startswith("int | str"):
        index = isinstance(value, int) and not isinstance(value, bool) and value >= 0
        if not (index or isinstance(value, str) and value.strip()):
            raise ConfigError(key, f"expected a device index (>= 0) or a path, got {value!r}", source)
        return value
    if ann.startswith("bool"):
        if not isinstance(value, bool):
            raise ConfigError(key, f"expected true or false, got {value!r}", source)
        return value
    if ann.startswith("int"):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, f"expected an integer, got {value!r}", source)
        return value
    if ann.startswith("float"):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise ConfigError(key, f"expected a finite number, got {value!r}", source)
        return float(value)
    if ann.startswith("str"):
        if not isinstance(value, str) or not value.strip():
            raise ConfigError(key, f"expected a non-empty string, got {value!r}", source)
        return value
    raise ConfigError(key, f"unsupported value {value!r}", source)  # pragma: no cover


def parse_rig(data: Any, source: str | Path | None = None, mock: bool = False) -> RigConfig:
    """A :class:`RigConfig` from the YAML's data (``source`` names the file in errors)."""
    src = None if source is None else str(source)

    def sensors(value, key):
        if not isinstance(value, list):
            raise ConfigError(key, f"expected a list of sensors, got {type(value).__name__}", src)
        return tuple(_build(TactileSensorConfig, v, f"{key}[{i}]", src) for i, v in enumerate(value))

    nested = {
        "hand": lambda v, k: _build(HandConfig, v, k, src),
        "camera": lambda v, k: _build(CameraConfig, v, k, src),
        "board": lambda v, k: _build(BoardConfig, v, k, src),
        "tactile": lambda v, k: _build(TactileConfig, v, k, src, {"sensors": sensors}),
        "grasp": lambda v, k: _build(GraspControl, v, k, src),
        "plan": lambda v, k: _build(CapturePlan, v, k, src, {
            "views": lambda v2, k2: _build(ViewPlan, v2, k2, src),
            "grasps": lambda v2, k2: _build(GraspPlan, v2, k2, src),
        }),
        "sim": lambda v, k: _build(SimConfig, v, k, src),
        "mock_devices": lambda v, k: _build(MockConfig, v, k, src),
    }
    if not isinstance(data, dict) or "rig" not in data:
        raise ConfigError("rig", "missing: the file must say `rig: real` or `rig: sim`", src)
    config = _build(RigConfig, data, "", src, nested)
    config = dataclasses.replace(config, source=src, mock=bool(mock))
    validate(config)
    return config


def load_rig(path: str | Path, mock: bool = False) -> RigConfig:
    """Read and validate a rig YAML file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError("rig", f"cannot read the rig file: {exc.strerror}", path) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError("rig", f"not valid YAML: {exc}", path) from None
    return parse_rig(data, path, mock)


def _check_bounds(config, prefix: str, source) -> None:
    """Every bounded field of a config and of the configs inside it; the first value out of its range is a
    ConfigError naming its field path (``tactile.sensors[2].timeout_s``, ``hand.ids[15]``) and the range."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            _check_bounds(value, f"{key}.", source)
        elif isinstance(value, tuple) and value and all(dataclasses.is_dataclass(v) for v in value):
            for i, item in enumerate(value):
                _check_bounds(item, f"{key}[{i}].", source)
        elif "bounds" in f.metadata and value is not None:
            bounds = f.metadata["bounds"]
            items = enumerate(value) if isinstance(value, tuple) else [(None, value)]
            for i, x in items:
                if not bounds.holds(x):
                    shown = x if isinstance(x, int) else f"{x:g}"
                    raise ConfigError(key if i is None else f"{key}[{i}]", f"must be {bounds}, got {shown}", source)


def validate(c: RigConfig) -> None:
    """Every value against its physical and logical range (field bounds first, then cross-field checks); each
    failure is one ConfigError naming its key."""
    src = c.source
    if c.rig not in ("real", "sim"):
        raise ConfigError("rig", f"must be 'real' or 'sim', got {c.rig!r}", src)
    _check_bounds(c, "", src)
    v, g = c.plan.views, c.plan.grasps
    if v.mode not in ("operator", "hemisphere"):
        raise ConfigError("plan.views.mode", f"must be 'operator' or 'hemisphere', got {v.mode!r}", src)
    if g.mode not in ("operator", "random"):
        raise ConfigError("plan.grasps.mode", f"must be 'operator' or 'random', got {g.mode!r}", src)
    if c.rig == "real" and (v.mode != "operator" or g.mode != "operator"):
        key = "plan.views.mode" if v.mode != "operator" else "plan.grasps.mode"
        raise ConfigError(key, "a real rig is positioned by the operator: use 'operator'", src)
    gc = c.grasp
    for key in ("close_pose", "open_pose"):
        if len(getattr(gc, key)) != 16:
            raise ConfigError(f"grasp.{key}", f"expected 16 joint positions, got {len(getattr(gc, key))}", src)
    if not gc.settle_tol_rad < gc.stall_error_rad:
        raise ConfigError("grasp.settle_tol_rad", f"must be smaller than grasp.stall_error_rad ({gc.stall_error_rad:g}),"
                          f" got {gc.settle_tol_rad:g}", src)
    if not gc.max_close_s > gc.poll_s:
        raise ConfigError("grasp.max_close_s", f"must be longer than grasp.poll_s ({gc.poll_s:g}), got {gc.max_close_s:g}",
                          src)
    _validate_board(c.board, src)
    if c.rig == "real":
        _validate_real(c, src)
    else:
        _validate_sim(c, src)


def _validate_board(b: BoardConfig, src) -> None:
    if not b.marker_length_m < b.square_length_m:
        raise ConfigError("board.marker_length_m", f"must be smaller than board.square_length_m ({b.square_length_m:g})"
                          f", got {b.marker_length_m:g}", src)
    inner = (b.squares_x - 1) * (b.squares_y - 1)
    if b.min_corners > inner:
        raise ConfigError("board.min_corners", f"a {b.squares_x} x {b.squares_y} board has {inner} inner corners; "
                          f"must be in [4, {inner}], got {b.min_corners}", src)
    import cv2

    if not hasattr(cv2.aruco, b.dictionary):
        raise ConfigError("board.dictionary", f"unknown ArUco dictionary {b.dictionary!r}", src)
    markers = len(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, b.dictionary)).bytesList)
    needed = b.squares_x * b.squares_y // 2
    if needed > markers:
        raise ConfigError("board.dictionary", f"{b.dictionary} has {markers} markers; a {b.squares_x} x {b.squares_y} "
                          f"board needs {needed} (choose a larger dictionary or fewer squares)", src)


def _validate_real(c: RigConfig, src) -> None:
    if c.hand.baudrate not in DYNAMIXEL_BAUDRATES:
        raise ConfigError("hand.baudrate", f"must be one of the Dynamixel rates {DYNAMIXEL_BAUDRATES}, "
                          f"got {c.hand.baudrate}", src)
    if len(c.hand.ids) != 16 or len(set(c.hand.ids)) != 16:
        raise ConfigError("hand.ids", f"expected 16 distinct servo ids, got {list(c.hand.ids)}", src)
    if not c.tactile.sensors:
        raise ConfigError("tactile.sensors", "a real rig needs at least one tactile sensor", src)
    seen = set()
    for i, s in enumerate(c.tactile.sensors):
        if s.finger not in FINGERS:
            raise ConfigError(f"tactile.sensors[{i}].finger", f"must be one of {FINGERS}, got {s.finger!r}", src)
        if s.finger in seen:
            raise ConfigError(f"tactile.sensors[{i}].finger", f"{s.finger!r} has two sensors", src)
        seen.add(s.finger)
    if not c.mock:  # the mock generates its own calibrations; a real rig's files must exist
        files = [("camera.calibration", c.camera.calibration)]
        files += [("hand.calibration", c.hand.calibration)] if c.hand.calibration else []
        files += [(f"tactile.sensors[{i}].calibration", s.calibration) for i, s in enumerate(c.tactile.sensors)]
        for key, name in files:
            if not c.path(name).is_file():
                raise ConfigError(key, f"file not found: {c.path(name)}", src)


def _validate_sim(c: RigConfig, src) -> None:
    s = c.sim
    if s.mesh is not None and not c.path(s.mesh).is_file():
        raise ConfigError("sim.mesh", f"file not found: {c.path(s.mesh)}", src)
    if s.mesh is None:
        from tacsplat.sim.objects import OBJECT_NAMES

        if s.object not in OBJECT_NAMES:
            raise ConfigError("sim.object", f"unknown library object {s.object!r} (one of {list(OBJECT_NAMES)})", src)
    radius = c.plan.views.radius_m
    if radius is not None and not radius > s.object_radius:
        raise ConfigError("plan.views.radius_m", f"the camera must stay outside the object: must be larger than "
                          f"sim.object_radius ({s.object_radius:g}), got {radius:g}", src)
