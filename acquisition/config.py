"""The rig YAML: which devices, their ports and calibration files, the mounting transforms, the board,
the grasp controller, and the capture plan, as dataclasses.

``rig: real`` describes the Dynamixel hand, the optical tactile sensors and the
wrist camera; ``rig: sim`` the MuJoCo twin. ``--mock`` (``load_rig(...,
mock=True)``) keeps a real rig's file and swaps in emulated devices (see
:mod:`tacsplat.acquisition.mock`). A file is read into the dataclasses by
pydantic (strict types: no string for a number, no number for a string, no
unknown key); then :func:`validate` (also for configs built in code) checks the
physical and logical range each field declares (:func:`bounded`), the board and
the cross-field rules. Each invalid value raises one
:class:`~tacsplat.errors.ConfigError` naming the file, the field path
(``tactile.sensors[2].T_fingertip_sensor``) and the allowed range. The example
files are in ``acquisition/rigs/`` (:func:`example_rig`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Annotated, Any, get_args, get_origin, get_type_hints

import numpy as np
import yaml
from pydantic import ConfigDict, PlainValidator, StringConstraints, TypeAdapter, ValidationError, with_config

from tacsplat.drivers.wrist_camera import CharucoBoardSpec
from tacsplat.errors import ConfigError
from tacsplat.geometry import rigidity_problem
from tacsplat.sim import OBJECT_RADIUS_RANGE_M
from tacsplat.sim.hand import FINGER_NAMES, JOINT_NAMES

RIGS_DIR = Path(__file__).parent / "rigs"
DYNAMIXEL_BAUDRATES = (9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000)  # X-series rates the SDK opens
DYNAMIXEL_MAX_ID = 252  # protocol 2.0: 253 is reserved, 254 is the broadcast id


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


# --- the types of the YAML's values beyond numbers, booleans and lists --------------------------------


def _pose(value) -> tuple:
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"expected a 4x4 matrix of numbers, got {value!r}") from None
    problem = rigidity_problem(T)
    if problem:
        raise ValueError(
            f"not a rigid transform: {problem} (expected [[R, t], [0, 0, 0, 1]], R a rotation: "
            "orthonormal, determinant +1; all finite)"
        )
    return tuple(map(tuple, T.tolist()))


def _device_source(value) -> int | str:
    index = isinstance(value, int) and not isinstance(value, bool) and value >= 0
    if not (index or isinstance(value, str) and value.strip()):
        raise ValueError(f"expected a device index (>= 0) or a path, got {value!r}")
    return value


def _when(value) -> datetime:
    try:
        return datetime.fromisoformat(str(value))
    except ValueError:
        raise ValueError(f"expected a date (2025-03-14) or a date and time (2025-03-14 15:30), got {value!r}") from None


Text = Annotated[str, StringConstraints(pattern=r"\S")]  # a non-empty string
When = Annotated[datetime, PlainValidator(_when)]  # a YAML date or date and time (naive: local time)
Pose = Annotated[tuple, PlainValidator(_pose)]  # a rigid 4x4 transform, as a tuple of rows
DeviceSource = Annotated[int | str, PlainValidator(_device_source)]  # a device index, file path or URL
YAML_SECTION = ConfigDict(extra="forbid", allow_inf_nan=False)  # every section: no unknown key, finite numbers


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class HandConfig:
    """The Dynamixel hand (``rig: real``)."""

    port: Text = "/dev/ttyUSB0"  # the U2D2 adapter
    baudrate: int = 4_000_000  # one of DYNAMIXEL_BAUDRATES
    ids: tuple[int, ...] = bounded(tuple(range(16)), 0, DYNAMIXEL_MAX_ID)  # servo of each joint, twin's joint order
    calibration: Text | None = None  # HandCalibration JSON (offsets, signs); None = identity


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class CameraConfig:
    """The wrist camera (``rig: real``)."""

    source: DeviceSource = 0
    calibration: Text = "wrist_camera.json"  # CameraCalibration JSON (intrinsics, distortion, board)
    T_hand_cam: Pose | None = None  # [4, 4] camera in the hand frame; None = hand_eye's, else the calibration file's
    hand_eye: Text | None = None  # hand-eye file (tacsplat calibrate hand-eye): T_hand_cam
    fps: float | None = positive(None, 1000.0, "Hz")
    timeout_s: float = positive(2.0, 60.0, "s")  # no frame for this long is a CameraError


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class BoardConfig(CharucoBoardSpec):
    """The ChArUco board that defines the world frame (the printed board's fields and defaults are
    :class:`~tacsplat.drivers.wrist_camera.CharucoBoardSpec`'s), and how well a view must see it."""

    max_reprojection_px: float = positive(1.0, 50.0, "px")  # a view or grasp whose board PnP is worse is rejected
    min_corners: int = bounded(6, 4, 10_000)  # PnP needs 4; at most the board's inner corners

    def spec(self) -> CharucoBoardSpec:
        """The printed board alone."""
        return CharucoBoardSpec(**{f.name: getattr(self, f.name) for f in dataclasses.fields(CharucoBoardSpec)})


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class TactileSensorConfig:
    """One optical tactile fingertip (``rig: real``)."""

    finger: Text  # index | middle | ring | thumb: whose fingertip frame it is mounted on
    source: DeviceSource
    calibration: Text  # TactileCalibration file (tacsplat calibrate tactile)
    T_fingertip_sensor: Pose | None = None  # [4, 4] mounting: sensor frame in the fingertip pad frame; None = identity


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class TactileConfig:
    sensor_name: Text = "digit"  # the scene's sensor model name
    gel_thickness_m: float = positive(0.002, 0.02, "m")
    timeout_s: float = positive(2.0, 60.0, "s")
    sensors: tuple[TactileSensorConfig, ...] = ()
    mounts: Text | None = None  # mounts file (tacsplat calibrate mounts): each sensor's T_fingertip_sensor


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class GraspControl:
    """How the logger closes the hand: a speed-limited ramp toward ``close_pose``, each finger stopping when it
    stalls, then a wait until the joints settle; then the read, then ``open_pose``."""

    close_pose: tuple[float, ...] = bounded(
        (0.0, 1.2, 1.0, 1.0) * 3 + (1.2, 0.6, 0.6, 0.8), -math.pi, math.pi, "rad"
    )  # [16] joint positions
    open_pose: tuple[float, ...] = bounded((0.0,) * 16, -math.pi, math.pi, "rad")  # [16] joint positions
    close_speed_rad_s: float = positive(1.5, 10.0, "rad/s")  # largest joint speed of the commanded ramp
    poll_s: float = positive(0.02, 1.0, "s")  # joint polling period (through the rig's clock)
    stall_error_rad: float = positive(0.15, math.pi, "rad")  # a finger lagging its ramp by this much has stalled
    settle_tol_rad: float = positive(0.004, math.pi, "rad")  # joints moving less than this per poll ...
    settle_polls: int = bounded(3, 1, 1000)  # ... for this many polls in a row have settled
    max_close_s: float = positive(5.0, 60.0, "s")  # give up waiting (the reading is still taken, with a warning)
    open_s: float = bounded(0.3, 0, 60.0, "s")  # wait after opening


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class ViewPlan:
    train: int = bounded(20, 1)  # a scene needs a view to train on
    test: int = bounded(5, 0)
    mode: Text = "operator"  # operator (a person places the camera) | hemisphere (the twin places it)
    radius_m: float | None = positive(None, 10.0, "m")  # hemisphere radius; None = the twin's default for the object


GRASP_MODES = ("operator", "random", "next-best")


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class GraspPlan:
    """Where the grasps go: ``operator`` (a person places the hand), ``random`` (the twin samples an approach per
    grasp) or ``next-best`` (the twin samples ``candidates`` approaches per grasp and executes the one whose
    fingertips land where a reconstruction of the scene so far, ``selection_steps`` training steps, is least sure
    by the ``uncertainty`` score; :mod:`tacsplat.acquisition.next_touch`)."""

    count: int = bounded(5, 0)
    mode: Text = "operator"  # one of GRASP_MODES
    seed: int = bounded(0, 0)
    candidates: int = bounded(16, 1, 1000)  # next-best: approaches scored per grasp
    selection_steps: int = bounded(300, 1, 1_000_000)  # next-best: training steps of each reconstruction so far
    uncertainty: Text = "depth-variance"  # next-best: the score (reconstruction.uncertainty.SCORES)

    def to_json(self) -> dict:
        """As scene.json records it: the next-best parameters only with the next-best mode."""
        data = dataclasses.asdict(self)
        return data if self.mode == "next-best" else {k: data[k] for k in ("count", "mode", "seed")}


TOUCH_MODELS = ("gel", "paper")


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class TouchPlan:
    """How touches are made: ``gel``, the hand's grasps (each pad's gel contact patch, one touch per finger), or
    ``paper``, the touches of the paper's official code, four per planned grasp, with no hand (``rig: sim`` only;
    :mod:`tacsplat.acquisition.paper_touches`)."""

    model: Text = "gel"  # one of TOUCH_MODELS
    surface_points: int = bounded(20_000, 1, 10_000_000)  # paper: samples spread evenly on the surface (pc_num)
    points_per_touch: int = bounded(50, 1, 10_000)  # paper: the samples nearest to the hit that make one touch

    def to_json(self) -> dict:
        """As scene.json records it: the paper model's parameters only with the paper model."""
        return dataclasses.asdict(self) if self.model == "paper" else {"model": self.model}


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class CapturePlan:
    views: ViewPlan = field(default_factory=ViewPlan)
    grasps: GraspPlan = field(default_factory=GraspPlan)
    touches: TouchPlan = field(default_factory=TouchPlan)

    def to_json(self) -> dict:
        return {**dataclasses.asdict(self), "grasps": self.grasps.to_json(), "touches": self.touches.to_json()}


MAX_POSE_ERROR_M = 0.05  # the largest true mounting error a twin may hide, per axis (an error, not another rig)
MAX_POSE_ERROR_DEG = 30.0


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class PoseError:
    """A rigid error: the true transform is the nominal one followed by this one, ``T_true = T_nominal @ E`` (``E``
    in the child frame: the camera's for the hand-eye, the sensor's for a mount)."""

    translation_m: tuple[float, float, float] = bounded((0.0, 0.0, 0.0), -MAX_POSE_ERROR_M, MAX_POSE_ERROR_M, "m")
    rotation_deg: tuple[float, float, float] = bounded(
        (0.0, 0.0, 0.0), -MAX_POSE_ERROR_DEG, MAX_POSE_ERROR_DEG, "deg"
    )  # a rotation vector (axis times angle), degrees

    def matrix(self) -> np.ndarray:
        """``E`` [4, 4]."""
        from scipy.spatial.transform import Rotation

        E = np.eye(4)
        E[:3, :3] = Rotation.from_rotvec(self.rotation_deg, degrees=True).as_matrix()
        E[:3, 3] = self.translation_m
        return E


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class TrueErrors:
    """What the twin's (or ``--mock``'s) hardware hides from its nominal model, so that each calibration step is
    checked against a known truth: the hardware differs from the model by these, the calibration files must find
    them. Joint errors are the servos': a servo reads ``sign * q + offset`` at true joint angle ``q`` (the
    nominal hand: sign 1, offset 0), as a horn fitted off its zero or a servo mounted reversed does."""

    joint_offsets_rad: dict[str, float] = field(default_factory=dict)  # joint name -> offset in [-pi, pi] rad
    joint_signs: dict[str, int] = field(default_factory=dict)  # joint name -> -1 (a reversed servo) or 1
    hand_eye: PoseError = field(default_factory=PoseError)  # the wrist camera's T_hand_cam
    mounts: dict[str, PoseError] = field(default_factory=dict)  # finger -> its sensor's T_fingertip_sensor

    def servo_offsets(self) -> tuple[float, ...]:
        """[16] true offsets in the twin's joint order."""
        return tuple(float(self.joint_offsets_rad.get(name, 0.0)) for name in JOINT_NAMES)

    def servo_signs(self) -> tuple[int, ...]:
        """[16] true signs in the twin's joint order."""
        return tuple(int(self.joint_signs.get(name, 1)) for name in JOINT_NAMES)


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class SimConfig:
    """The twin (``rig: sim``); ``true_errors`` also applies to ``--mock``'s emulated hardware of a real rig file."""

    object: Text = "teapot"
    mesh: Text | None = None
    object_radius: float = bounded(0.08, *OBJECT_RADIUS_RANGE_M, "m")  # bounding-sphere radius the hand can grasp
    resolution: int = bounded(200, 8, 4096, "px")
    seed: int = bounded(0, 0)
    texture: Text = "none"  # the object's surface: its one colour, or "checker" (tacsplat.sim.objects.TEXTURES)
    true_errors: TrueErrors = field(default_factory=TrueErrors)


@with_config(YAML_SECTION)
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
    # the hand's reply timeout (its bus watchdog is sized from it): an emulator shares a host that may be busy with
    # other work, where it can answer hundreds of ms late; a real servo answers within a millisecond
    servo_timeout_s: float = positive(0.5, 1.0, "s")
    servo_port: Text | None = None  # the pty of a servo emulator in its own process (python -m
    # tacsplat.drivers.dxl_emulator), which outlives this one; None: an emulator in this process
    # faults, to see rig check name them: devices left unplugged (a sensor's finger, camera, or servo ID) ...
    unplugged: tuple[Text, ...] = ()
    board_in_view: bool = True  # ... and a wrist camera that does not see the board


@with_config(YAML_SECTION)
@dataclass(frozen=True)
class RigConfig:
    rig: Text  # real | sim
    object: Text = "object"  # the scene's object name
    hand: HandConfig = field(default_factory=HandConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    board: BoardConfig = field(default_factory=BoardConfig)
    tactile: TactileConfig = field(default_factory=TactileConfig)
    grasp: GraspControl = field(default_factory=GraspControl)
    plan: CapturePlan = field(default_factory=CapturePlan)
    sim: SimConfig = field(default_factory=SimConfig)
    mock_devices: MockConfig = field(default_factory=MockConfig)
    # when the hardware last changed (a servo, a mount, the camera): every calibration file must be younger
    hardware_changed: When | None = None
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

_SET_BY_LOAD_RIG = ("source", "mock")  # RigConfig fields that come from load_rig, not from the file
_SECTIONS = tuple(f.name for f in dataclasses.fields(RigConfig) if f.default_factory is not dataclasses.MISSING)
_EXPECTED = {  # what each kind of pydantic error means in the YAML's terms
    "int_type": "expected an integer",
    "int_parsing": "expected an integer",
    "int_from_float": "expected an integer",
    "float_type": "expected a finite number",
    "float_parsing": "expected a finite number",
    "finite_number": "expected a finite number",
    "bool_type": "expected true or false",
    "bool_parsing": "expected true or false",
    "string_type": "expected a non-empty string",
    "string_pattern_mismatch": "expected a non-empty string",
    "tuple_type": "expected a list",
    "list_type": "expected a list",
    "dataclass_type": "expected a mapping",
    "dict_type": "expected a mapping",
}


@functools.cache
def _rig_adapter() -> TypeAdapter:
    return TypeAdapter(RigConfig)


def _key(loc: tuple) -> str:
    """A pydantic error location as the YAML's field path: ``tactile.sensors[2].T_fingertip_sensor``."""
    key = ""
    for part in loc:
        key += f"[{part}]" if isinstance(part, int) else (f".{part}" if key else str(part))
    return key


def _section_fields(loc: tuple) -> list[str]:
    """The keys the section at ``loc`` (a path of field names, list indices and mapping keys) may hold."""
    cls, in_mapping = RigConfig, False
    for part in loc:
        if isinstance(part, int) or in_mapping:  # a list index, or the key of a mapping (mounts.index)
            in_mapping = False
            continue
        hint = get_type_hints(cls)[part]
        in_mapping = get_origin(hint) is dict
        cls = get_args(hint)[-1] if get_args(hint) else hint  # tuple[Item, ...], dict[str, Item] -> Item
    return [f.name for f in dataclasses.fields(cls) if cls is not RigConfig or f.name not in _SET_BY_LOAD_RIG]


def _config_error(exc: ValidationError, source) -> ConfigError:
    """The first of pydantic's errors as one ConfigError naming the field path and what it expects."""
    error = exc.errors(include_url=False)[0]
    loc, kind = error["loc"], error["type"]
    if kind == "unexpected_keyword_argument":
        return ConfigError(_key(loc), f"unknown key (expected one of {sorted(_section_fields(loc[:-1]))})", source)
    if kind == "missing":
        if isinstance(loc[-1], int):  # a fixed-length list that is too short
            return ConfigError(_key(loc[:-1]), f"expected a list of more than {loc[-1]} values", source)
        return ConfigError(_key(loc), "missing (a required key)", source)
    if kind in _EXPECTED:
        return ConfigError(_key(loc), f"{_EXPECTED[kind]}, got {error['input']!r}", source)
    if kind == "value_error":  # one of the validators above
        return ConfigError(_key(loc), str(error["ctx"]["error"]), source)
    return ConfigError(_key(loc) or "(top level)", error["msg"], source)


def parse_rig(data: Any, source: str | Path | None = None, mock: bool = False, check_files: bool = True) -> RigConfig:
    """A :class:`RigConfig` from the YAML's data (``source`` names the file in errors; ``check_files=False`` leaves
    the calibration files unchecked: the commands that write them or report on them)."""
    src = None if source is None else str(source)
    if not isinstance(data, dict) or "rig" not in data:
        raise ConfigError("rig", "missing: the file must say `rig: real` or `rig: sim`", src)
    for key in _SET_BY_LOAD_RIG:
        if key in data:
            raise ConfigError(key, f"unknown key (expected one of {sorted(_section_fields(()))})", src)
    data = {k: v for k, v in data.items() if not (v is None and k in _SECTIONS)}  # an empty section: the defaults
    try:  # as JSON, whose strict mode still reads a list as a tuple and a mapping as a dataclass
        config = _rig_adapter().validate_json(json.dumps(data, default=str), strict=True)
    except ValidationError as exc:
        raise _config_error(exc, src) from None
    config = dataclasses.replace(config, source=src, mock=bool(mock))
    validate(config, check_files)
    return config


def load_rig(path: str | Path, mock: bool = False, check_files: bool = True) -> RigConfig:
    """Read and validate a rig YAML file (``check_files``: that the calibration files it names exist)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError("rig", f"cannot read the rig file: {exc.strerror}", path) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError("rig", f"not valid YAML: {exc}", path) from None
    return parse_rig(data, path, mock, check_files)


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


def validate(c: RigConfig, check_files: bool = True) -> None:
    """Every value against its physical and logical range (field bounds first, then cross-field checks) and, with
    ``check_files``, that a real rig's calibration files exist; each failure is one ConfigError naming its key."""
    src = c.source
    if c.rig not in ("real", "sim"):
        raise ConfigError("rig", f"must be 'real' or 'sim', got {c.rig!r}", src)
    _check_bounds(c, "", src)
    v, g = c.plan.views, c.plan.grasps
    if v.mode not in ("operator", "hemisphere"):
        raise ConfigError("plan.views.mode", f"must be 'operator' or 'hemisphere', got {v.mode!r}", src)
    if g.mode not in GRASP_MODES:
        raise ConfigError("plan.grasps.mode", f"must be {' or '.join(map(repr, GRASP_MODES))}, got {g.mode!r}", src)
    if g.mode == "next-best":
        from tacsplat.reconstruction.uncertainty import SCORES

        if g.uncertainty not in SCORES:
            raise ConfigError(
                "plan.grasps.uncertainty", f"must be one of {', '.join(map(repr, SCORES))}, got {g.uncertainty!r}", src
            )
        if c.plan.touches.model != "gel":
            raise ConfigError(
                "plan.grasps.mode",
                "next-best chooses where the hand grasps: it needs the gel touch model (plan.touches.model: gel)",
                src,
            )
    if c.rig == "real" and (v.mode != "operator" or g.mode != "operator"):
        key = "plan.views.mode" if v.mode != "operator" else "plan.grasps.mode"
        hint = " (tacsplat capture --suggest RUN shows where the next grasp should go)" if g.mode == "next-best" else ""
        raise ConfigError(key, f"a real rig is positioned by the operator: use 'operator'{hint}", src)
    gc = c.grasp
    for key in ("close_pose", "open_pose"):
        if len(getattr(gc, key)) != 16:
            raise ConfigError(f"grasp.{key}", f"expected 16 joint positions, got {len(getattr(gc, key))}", src)
    if not gc.settle_tol_rad < gc.stall_error_rad:
        raise ConfigError(
            "grasp.settle_tol_rad",
            f"must be smaller than grasp.stall_error_rad ({gc.stall_error_rad:g}), got {gc.settle_tol_rad:g}",
            src,
        )
    if not gc.max_close_s > gc.poll_s:
        raise ConfigError(
            "grasp.max_close_s", f"must be longer than grasp.poll_s ({gc.poll_s:g}), got {gc.max_close_s:g}", src
        )
    validate_touches(c.plan.touches, "plan.touches.", src)
    if c.plan.touches.model == "paper" and c.rig != "sim":
        raise ConfigError(
            "plan.touches.model", "the paper's touches are sampled on the twin's mesh: use 'gel' on a real rig", src
        )
    _validate_board(c.board, src)
    _validate_true_errors(c.sim.true_errors, src)
    if c.rig == "real":
        _validate_real(c, src, check_files)
    else:
        _validate_sim(c, src)


def validate_touches(t: TouchPlan, prefix: str = "", src=None) -> None:
    """A touch plan's model and numbers (``prefix`` names its place: ``plan.touches.``)."""
    if t.model not in TOUCH_MODELS:
        raise ConfigError(
            f"{prefix}model", f"must be one of {', '.join(map(repr, TOUCH_MODELS))}, got {t.model!r}", src
        )
    _check_bounds(t, prefix, src)
    if t.surface_points < t.points_per_touch:
        raise ConfigError(
            f"{prefix}surface_points",
            f"must be at least the {t.points_per_touch} points of a touch "
            f"({prefix}points_per_touch), got {t.surface_points}",
            src,
        )


def _validate_board(b: BoardConfig, src) -> None:
    problem = b.spec().problem()
    if problem:
        raise ConfigError(f"board.{problem[0]}", problem[1], src)
    inner = (b.squares_x - 1) * (b.squares_y - 1)
    if b.min_corners > inner:
        raise ConfigError(
            "board.min_corners",
            f"a {b.squares_x} x {b.squares_y} board has {inner} inner corners; "
            f"must be in [4, {inner}], got {b.min_corners}",
            src,
        )


def _validate_true_errors(e: TrueErrors, src) -> None:
    """Known joints and fingers, offsets in [-pi, pi], signs +-1, mounting errors within their bounds."""
    prefix = "sim.true_errors."
    for key, allowed in (("joint_offsets_rad", JOINT_NAMES), ("joint_signs", JOINT_NAMES), ("mounts", FINGER_NAMES)):
        unknown = [name for name in getattr(e, key) if name not in allowed]
        if unknown:
            what = "joint" if key != "mounts" else "finger"
            raise ConfigError(f"{prefix}{key}.{unknown[0]}", f"unknown {what} (one of {list(allowed)})", src)
    for name, offset in e.joint_offsets_rad.items():
        if not -math.pi <= offset <= math.pi:
            raise ConfigError(f"{prefix}joint_offsets_rad.{name}", f"must be in [-pi, pi] rad, got {offset:g}", src)
    for name, sign in e.joint_signs.items():
        if sign not in (1, -1):
            raise ConfigError(f"{prefix}joint_signs.{name}", f"must be 1 or -1 (a reversed servo), got {sign}", src)
    for finger, mount in e.mounts.items():
        _check_bounds(mount, f"{prefix}mounts.{finger}.", src)


def _validate_real(c: RigConfig, src, check_files: bool) -> None:
    if c.hand.baudrate not in DYNAMIXEL_BAUDRATES:
        raise ConfigError(
            "hand.baudrate", f"must be one of the Dynamixel rates {DYNAMIXEL_BAUDRATES}, got {c.hand.baudrate}", src
        )
    if len(c.hand.ids) != 16 or len(set(c.hand.ids)) != 16:
        raise ConfigError("hand.ids", f"expected 16 distinct servo ids, got {list(c.hand.ids)}", src)
    if not c.tactile.sensors:
        raise ConfigError("tactile.sensors", "a real rig needs at least one tactile sensor", src)
    seen = set()
    for i, s in enumerate(c.tactile.sensors):
        if s.finger not in FINGER_NAMES:
            raise ConfigError(f"tactile.sensors[{i}].finger", f"must be one of {FINGER_NAMES}, got {s.finger!r}", src)
        if s.finger in seen:
            raise ConfigError(f"tactile.sensors[{i}].finger", f"{s.finger!r} has two sensors", src)
        seen.add(s.finger)
    known = [s.finger for s in c.tactile.sensors] + ["camera"] + [f"servo {i}" for i in c.hand.ids]
    for i, name in enumerate(c.mock_devices.unplugged):
        if name not in known:
            raise ConfigError(f"mock_devices.unplugged[{i}]", f"unknown device {name!r} (one of {known})", src)
    if check_files and not c.mock:  # the mock generates its own calibrations; a real rig's files must exist
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
    from tacsplat.sim.objects import OBJECT_NAMES, texture_problem

    if problem := texture_problem(s.texture):
        raise ConfigError("sim.texture", problem, src)
    if s.mesh is None:
        if s.object not in OBJECT_NAMES:
            raise ConfigError("sim.object", f"unknown library object {s.object!r} (one of {list(OBJECT_NAMES)})", src)
    radius = c.plan.views.radius_m
    if radius is not None and not radius > s.object_radius:
        raise ConfigError(
            "plan.views.radius_m",
            f"the camera must stay outside the object: must be larger than "
            f"sim.object_radius ({s.object_radius:g}), got {radius:g}",
            src,
        )
