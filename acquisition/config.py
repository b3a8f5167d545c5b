"""The rig YAML: which devices, their ports and calibration files, the mounting transforms, the board,
the grasp controller, and the capture plan, as dataclasses.

``rig: real`` describes the Dynamixel hand, the optical tactile sensors and the
wrist camera; ``rig: sim`` the MuJoCo twin. ``--mock`` (``load_rig(...,
mock=True)``) keeps a real rig's file and swaps in emulated devices (see
:mod:`tacsplat.acquisition.mock`). Every invalid value raises one
:class:`~tacsplat.errors.ConfigError` naming the key and the file. The
example files are in ``acquisition/rigs/`` (:func:`example_rig`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from tacsplat.errors import ConfigError

FINGERS = ("index", "middle", "ring", "thumb")
RIGS_DIR = Path(__file__).parent / "rigs"


@dataclass(frozen=True)
class HandConfig:
    """The Dynamixel hand (``rig: real``)."""

    port: str = "/dev/ttyUSB0"  # the U2D2 adapter
    baudrate: int = 4_000_000
    ids: tuple[int, ...] = tuple(range(16))  # servo of each joint, in the twin's joint order
    calibration: str | None = None  # HandCalibration JSON (offsets, signs); None = identity


@dataclass(frozen=True)
class CameraConfig:
    """The wrist camera (``rig: real``)."""

    source: int | str = 0  # device index, file path or stream URL
    calibration: str = "wrist_camera.json"  # CameraCalibration JSON (intrinsics, distortion, board)
    T_hand_cam: tuple | None = None  # [4, 4] camera in the hand frame; None = the calibration file's hand-eye result
    fps: float | None = None
    timeout_s: float = 2.0  # no frame for this long is a CameraError


@dataclass(frozen=True)
class BoardConfig:
    """The ChArUco board that defines the world frame (defaults: CharucoBoardSpec's)."""

    squares_x: int = 7
    squares_y: int = 5
    square_length_m: float = 0.03
    marker_length_m: float = 0.022
    dictionary: str = "DICT_5X5_100"
    legacy_pattern: bool = False
    max_reprojection_px: float = 1.0  # a view or grasp whose board PnP is worse is rejected
    min_corners: int = 6

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
    gel_thickness_m: float = 0.002
    timeout_s: float = 2.0
    sensors: tuple[TactileSensorConfig, ...] = ()


@dataclass(frozen=True)
class GraspControl:
    """How the logger closes the hand: a speed-limited ramp toward ``close_pose``, each finger stopping when it
    stalls, then a wait until the joints settle; then the read, then ``open_pose``."""

    close_pose: tuple[float, ...] = (0.0, 1.2, 1.0, 1.0) * 3 + (1.2, 0.6, 0.6, 0.8)  # [16] radians
    open_pose: tuple[float, ...] = (0.0,) * 16  # [16] radians
    close_speed_rad_s: float = 1.5  # largest joint speed of the commanded ramp
    poll_s: float = 0.02  # joint polling period (through the rig's clock)
    stall_error_rad: float = 0.15  # a finger lagging its ramp by this much has stalled on the object
    settle_tol_rad: float = 0.004  # joints moving less than this per poll ...
    settle_polls: int = 3  # ... for this many polls in a row have settled
    max_close_s: float = 5.0  # give up waiting (the reading is still taken, with a warning)
    open_s: float = 0.3  # wait after opening


@dataclass(frozen=True)
class ViewPlan:
    train: int = 20
    test: int = 5
    mode: str = "operator"  # operator (a person places the camera) | hemisphere (the twin places it)
    radius_m: float | None = None  # hemisphere radius; None = the twin's default for the object


@dataclass(frozen=True)
class GraspPlan:
    count: int = 5
    mode: str = "operator"  # operator (a person places the hand) | random (the twin samples approaches)
    seed: int = 0


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
    object_radius: float = 0.08
    resolution: int = 200
    seed: int = 0


@dataclass(frozen=True)
class MockConfig:
    """The emulated devices of ``--mock`` (a real rig's file, no hardware)."""

    camera_width: int = 320
    camera_height: int = 240
    camera_focal_px: float = 280.0
    camera_frames: int = 24  # board renders in the looping video
    tactile_width: int = 160
    tactile_height: int = 120
    tactile_pixel_size_m: float = 1.6e-4
    servo_timeout_s: float = 0.1


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
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ConfigError(key, f"expected a finite 4x4 matrix, got shape {T.shape}", source)
    R = T[:3, :3]
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-5) and np.linalg.det(R) > 0 and np.allclose(T[3], [0, 0, 0, 1])):
        raise ConfigError(key, "not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)", source)
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
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise ConfigError(key, f"expected a device index or a path, got {value!r}", source)
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
        if not isinstance(value, str) or not value:
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


def validate(c: RigConfig) -> None:
    """Cross-field checks; each names its key."""
    src = c.source
    if c.rig not in ("real", "sim"):
        raise ConfigError("rig", f"must be 'real' or 'sim', got {c.rig!r}", src)
    v, g = c.plan.views, c.plan.grasps
    for key, value in (("plan.views.train", v.train), ("plan.views.test", v.test), ("plan.grasps.count", g.count)):
        if value < 0:
            raise ConfigError(key, f"must be non-negative, got {value}", src)
    if v.mode not in ("operator", "hemisphere"):
        raise ConfigError("plan.views.mode", f"must be 'operator' or 'hemisphere', got {v.mode!r}", src)
    if g.mode not in ("operator", "random"):
        raise ConfigError("plan.grasps.mode", f"must be 'operator' or 'random', got {g.mode!r}", src)
    if c.rig == "real" and (v.mode != "operator" or g.mode != "operator"):
        key = "plan.views.mode" if v.mode != "operator" else "plan.grasps.mode"
        raise ConfigError(key, "a real rig is positioned by the operator: use 'operator'", src)
    if v.radius_m is not None and not v.radius_m > 0:
        raise ConfigError("plan.views.radius_m", f"must be positive, got {v.radius_m}", src)
    gc = c.grasp
    for key in ("close_pose", "open_pose"):
        if len(getattr(gc, key)) != 16:
            raise ConfigError(f"grasp.{key}", f"expected 16 joint positions, got {len(getattr(gc, key))}", src)
    for key in ("close_speed_rad_s", "poll_s", "stall_error_rad", "settle_tol_rad", "max_close_s"):
        if not getattr(gc, key) > 0:
            raise ConfigError(f"grasp.{key}", f"must be positive, got {getattr(gc, key)}", src)
    if gc.settle_polls < 1:
        raise ConfigError("grasp.settle_polls", f"must be at least 1, got {gc.settle_polls}", src)
    if gc.open_s < 0:
        raise ConfigError("grasp.open_s", f"must be non-negative, got {gc.open_s}", src)
    b = c.board
    if not b.max_reprojection_px > 0:
        raise ConfigError("board.max_reprojection_px", f"must be positive, got {b.max_reprojection_px}", src)
    if not 0 < b.marker_length_m < b.square_length_m:
        raise ConfigError("board.marker_length_m", "must be positive and smaller than board.square_length_m", src)
    if b.squares_x < 2 or b.squares_y < 2:
        raise ConfigError("board.squares_x", "a board needs at least 2 x 2 squares", src)
    import cv2

    if not hasattr(cv2.aruco, b.dictionary):
        raise ConfigError("board.dictionary", f"unknown ArUco dictionary {b.dictionary!r}", src)
    if c.rig == "real":
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
        if not c.tactile.gel_thickness_m > 0:
            raise ConfigError("tactile.gel_thickness_m", "must be positive", src)
        if not c.camera.timeout_s > 0:
            raise ConfigError("camera.timeout_s", "must be positive", src)
        if not c.mock:  # the mock generates its own calibrations; a real rig's files must exist
            files = [("camera.calibration", c.camera.calibration)]
            files += [("hand.calibration", c.hand.calibration)] if c.hand.calibration else []
            files += [(f"tactile.sensors[{i}].calibration", s.calibration) for i, s in enumerate(c.tactile.sensors)]
            for key, name in files:
                if not c.path(name).is_file():
                    raise ConfigError(key, f"file not found: {c.path(name)}", src)
    else:
        s = c.sim
        if s.resolution < 8:
            raise ConfigError("sim.resolution", f"must be at least 8 pixels, got {s.resolution}", src)
        if not s.object_radius > 0:
            raise ConfigError("sim.object_radius", f"must be positive, got {s.object_radius}", src)
        if s.mesh is not None and not c.path(s.mesh).is_file():
            raise ConfigError("sim.mesh", f"file not found: {c.path(s.mesh)}", src)
        if s.mesh is None:
            from tacsplat.sim.objects import OBJECT_NAMES

            if s.object not in OBJECT_NAMES:
                raise ConfigError("sim.object", f"unknown library object {s.object!r} (one of {list(OBJECT_NAMES)})", src)
