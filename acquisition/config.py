"""The rig YAML: which devices, their ports and calibration files, the mounting transforms, the board,
the grasp controller, and the capture plan, as dataclasses.

``rig: real`` describes the Dynamixel hand, the optical tactile sensors and the
wrist camera; ``rig: sim`` the MuJoCo twin (its file sets only the keys the twin
reads, :data:`TWIN_READS`). ``--mock`` (``load_rig(..., mock=True)``) keeps a
real rig's file and swaps in emulated devices (see :mod:`tacsplat.acquisition.mock`).
A file is read into the dataclasses by pydantic (:func:`checked`: strict types, no string for a number (but a number
YAML reads as a string, ``1e-9`` with no dot, is the number, as in ``reconstruct
--config``), no number for a string, no unknown key, and the physical and logical
range each field declares, :func:`bounded`); then :func:`validate` (also for configs built in code) checks
the board and the cross-field rules. Each invalid value raises one
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
from typing import Annotated, Any, dataclass_transform, get_args, get_origin, get_type_hints

import numpy as np
import yaml
from pydantic import (
    AfterValidator,
    ConfigDict,
    PlainValidator,
    StringConstraints,
    TypeAdapter,
    ValidationError,
    with_config,
)

from tacsplat.config_files import yaml_number
from tacsplat.drivers.wrist_camera import CharucoBoardSpec
from tacsplat.errors import ConfigError, pydantic_problem
from tacsplat.geometry import make_pose, rigidity_problem
from tacsplat.sim import OBJECT_RADIUS_RANGE_M
from tacsplat.sim.hand import FINGER_NAMES, JOINT_NAMES

RIGS_DIR = Path(__file__).parent / "rigs"
DYNAMIXEL_BAUDRATES = (9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000)  # X-series rates the SDK opens
DYNAMIXEL_MAX_ID = 252  # protocol 2.0: 253 is reserved, 254 is the broadcast id


@dataclass(frozen=True)
class Bounds:
    """The values a number (or each number of a list) may take: ``lo <= x <= hi``, ``lo < x`` when ``lo_open``; as
    a pydantic validator (``Annotated[float, Bounds(0, 60, "s", lo_open=True)]``), a value outside is an error."""

    lo: float
    hi: float = math.inf
    unit: str = ""
    lo_open: bool = False

    def __call__(self, x):
        try:
            finite = math.isfinite(x)
        except OverflowError:  # an integer too large for a float
            finite = False
        if not (finite and (x > self.lo if self.lo_open else x >= self.lo) and x <= self.hi):
            raise ValueError(f"must be {self}, got {x if isinstance(x, int) else f'{x:g}'}")
        return x

    def __str__(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if math.isinf(self.hi):
            return f"{'>' if self.lo_open else '>='} {self.lo:g}{unit}"
        return f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}]{unit}"


def bounded(lo: float, hi: float = math.inf, unit: str = "", lo_open: bool = False) -> AfterValidator:
    """The validator of a number that must lie within :class:`Bounds`."""
    return AfterValidator(Bounds(lo, hi, unit, lo_open))


def positive(hi: float = math.inf, unit: str = "") -> AfterValidator:
    """The validator of a number that must be > 0 (and <= ``hi``)."""
    return bounded(0, hi, unit, lo_open=True)


def one_of(values, told: str = "must be one of {choices}, got {value!r}") -> AfterValidator:
    """The validator of a value that must be one of ``values``; ``told``: the error, formatted with ``value``,
    ``values`` (a list) and ``choices`` (their reprs, comma-separated)."""

    def check(value):
        if value not in values:
            raise ValueError(told.format(value=value, values=list(values), choices=", ".join(map(repr, values))))
        return value

    return AfterValidator(check)


# --- the types of the YAML's values beyond numbers, booleans and lists --------------------------------


def _pose(value) -> tuple:
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"expected a 4x4 matrix of numbers, got {value!r}") from None
    if problem := rigidity_problem(T):
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
    """A naive datetime in local time (what file times are compared in): one with a UTC offset (``...Z``,
    ``...+01:00``) is turned into local time."""
    try:
        when = datetime.fromisoformat(str(value))
    except ValueError:
        raise ValueError(f"expected a date (2025-03-14) or a date and time (2025-03-14 15:30), got {value!r}") from None
    return when if when.tzinfo is None else when.astimezone().replace(tzinfo=None)


Text = Annotated[str, StringConstraints(pattern=r"\S")]  # a non-empty string
When = Annotated[datetime, PlainValidator(_when)]  # a YAML date or date and time (naive, local time)
Pose = Annotated[tuple, PlainValidator(_pose)]  # a rigid 4x4 transform, as a tuple of rows
DeviceSource = Annotated[int | str, PlainValidator(_device_source)]  # a device index, file path or URL
JointAngle = Annotated[float, bounded(-math.pi, math.pi, "rad")]
JointName = Annotated[str, one_of(JOINT_NAMES, "unknown joint (one of {values})")]
FingerName = Annotated[str, one_of(FINGER_NAMES, "unknown finger (one of {values})")]
ServoSign = Annotated[int, one_of((1, -1), "must be 1 or -1 (a reversed servo), got {value}")]
YAML_SECTION = ConfigDict(extra="forbid", allow_inf_nan=False)  # every section: no unknown key, finite numbers


@dataclass_transform(frozen_default=True)
def yaml_section(cls: type) -> type:
    """A section of the rig YAML: a frozen dataclass that pydantic reads with :data:`YAML_SECTION`."""
    return with_config(YAML_SECTION)(dataclass(frozen=True)(cls))


@yaml_section
class HandConfig:
    """The Dynamixel hand (``rig: real``)."""

    port: Text = "/dev/ttyUSB0"  # the U2D2 adapter
    baudrate: int = 4_000_000  # one of DYNAMIXEL_BAUDRATES
    # the servo of each joint, in the twin's joint order
    ids: tuple[Annotated[int, bounded(0, DYNAMIXEL_MAX_ID)], ...] = tuple(range(16))
    calibration: Text | None = None  # HandCalibration JSON (offsets, signs); None = identity


@yaml_section
class CameraConfig:
    """The wrist camera (``rig: real``)."""

    source: DeviceSource = 0
    calibration: Text = "wrist_camera.json"  # CameraCalibration JSON (intrinsics, distortion, board)
    T_hand_cam: Pose | None = None  # [4, 4] camera in the hand frame; None = hand_eye's, else the calibration file's
    hand_eye: Text | None = None  # hand-eye file (tacsplat calibrate hand-eye): T_hand_cam
    fps: Annotated[float, positive(1000.0, "Hz")] | None = None
    timeout_s: Annotated[float, positive(60.0, "s")] = 2.0  # no frame for this long is a CameraError


@yaml_section
class BoardConfig(CharucoBoardSpec):
    """The ChArUco board that defines the world frame (the printed board's fields and defaults are
    :class:`~tacsplat.drivers.wrist_camera.CharucoBoardSpec`'s), and how well a view must see it."""

    # a view or grasp whose board PnP is worse is rejected
    max_reprojection_px: Annotated[float, positive(50.0, "px")] = 1.0
    min_corners: Annotated[int, bounded(4, 10_000)] = 6  # PnP needs 4; at most the board's inner corners

    def spec(self) -> CharucoBoardSpec:
        """The printed board alone."""
        return CharucoBoardSpec(**{f.name: getattr(self, f.name) for f in dataclasses.fields(CharucoBoardSpec)})


@yaml_section
class TactileSensorConfig:
    """One optical tactile fingertip: a real rig's entry gives its source and calibration (required, checked by
    :func:`validate`); a rig: sim file's gives its finger and mounting only (:data:`TWIN_SENSOR_READS`)."""

    finger: Annotated[str, one_of(FINGER_NAMES)]  # whose fingertip frame it is mounted on
    source: DeviceSource | None = None
    calibration: Text | None = None  # TactileCalibration file (tacsplat calibrate tactile)
    T_fingertip_sensor: Pose | None = None  # [4, 4] mounting: sensor frame in the fingertip pad frame; None = identity


@yaml_section
class TactileConfig:
    sensor_name: Text = "digit"  # the scene's sensor model name
    gel_thickness_m: Annotated[float, positive(0.02, "m")] = 0.002
    timeout_s: Annotated[float, positive(60.0, "s")] = 2.0
    sensors: tuple[TactileSensorConfig, ...] = ()
    mounts: Text | None = None  # mounts file (tacsplat calibrate mounts): each sensor's T_fingertip_sensor


@yaml_section
class GraspControl:
    """How the logger closes the hand: a speed-limited ramp toward ``close_pose``, each finger stopping when it
    stalls, then a wait until the joints settle; then the read, then ``open_pose``."""

    close_pose: tuple[JointAngle, ...] = (0.0, 1.2, 1.0, 1.0) * 3 + (1.2, 0.6, 0.6, 0.8)  # [16] joint positions
    open_pose: tuple[JointAngle, ...] = (0.0,) * 16  # [16] joint positions
    close_speed_rad_s: Annotated[float, positive(10.0, "rad/s")] = 1.5  # largest joint speed of the commanded ramp
    poll_s: Annotated[float, positive(1.0, "s")] = 0.02  # joint polling period (through the rig's clock)
    # a finger lagging its ramp by this much has stalled
    stall_error_rad: Annotated[float, positive(math.pi, "rad")] = 0.15
    settle_tol_rad: Annotated[float, positive(math.pi, "rad")] = 0.004  # joints moving less than this per poll ...
    settle_polls: Annotated[int, bounded(1, 1000)] = 3  # ... for this many polls in a row have settled
    # give up waiting (the reading is still taken, with a warning)
    max_close_s: Annotated[float, positive(60.0, "s")] = 5.0
    open_s: Annotated[float, bounded(0, 60.0, "s")] = 0.3  # wait after opening


# A rig: sim file's grasp section would be ignored: the twin grasps with devices.TWIN_CONTROL, the real defaults above
# do not suit its soft servos, and a twin scene records its control as one of the twin's own settings (capture_scene).
TWIN_GRASP = (
    "a rig: sim file does not set the grasp control: the twin closes its hand with its own, tuned to its simulated "
    "servos; remove the grasp section"
)
# What a rig: sim run reads of the real rig's sections (devices.twin_config, rig_T_hand_cam, rig_mounts, the calibration
# commands, rig check; capture_scene records them): section -> (the keys read, why another is refused). A rig: sim file
# that sets other keys of them is one error naming them all (refuse_unread_by_twin): the twin would ignore them. The
# rest of the file (object, board, plan, sim, hardware_changed) is read whole.
TWIN_READS = {
    "hand": (
        ("calibration",),
        "a rig: sim file gives the hand's calibration only: the twin's hand is simulated; remove it",
    ),
    "camera": (
        ("hand_eye", "T_hand_cam", "calibration"),  # calibration: calibrate hand-eye --arm-poses reads it
        "a rig: sim file gives the wrist camera's hand_eye, T_hand_cam and calibration (calibrate hand-eye "
        "--arm-poses) only: the twin renders its own views; remove it",
    ),
    "tactile": (
        ("mounts", "sensors"),
        "a rig: sim file gives the tactile mounts and sensors (each its T_fingertip_sensor) only: the twin's pads are "
        "simulated; remove it",
    ),
    "grasp": ((), TWIN_GRASP),
    "mock_devices": ((), "a rig: sim file has no emulated devices (--mock's, of a real rig): remove mock_devices"),
}
# A rig: sim file's sensor entry gives its finger's T_fingertip_sensor: the keys read, why another is refused (the
# source and calibration a real rig's entry needs).
TWIN_SENSOR_READS = (
    ("finger", "T_fingertip_sensor"),
    "a rig: sim file's sensor gives its finger and T_fingertip_sensor only: the twin's pads are simulated (no device "
    "opened, no calibration read); remove it",
)
TWIN_SENSOR = (
    "missing: a rig: sim file's sensor gives the mounting of its finger's simulated pad, and only that (its source "
    "and calibration are not read); add it, or remove the sensor"
)


@yaml_section
class ViewPlan:
    train: Annotated[int, bounded(1)] = 20  # a scene needs a view to train on
    test: Annotated[int, bounded(0)] = 5
    mode: Annotated[str, one_of(("operator", "hemisphere"))] = "operator"  # a person places the camera | the twin
    # hemisphere radius; None = the twin's default for the object
    radius_m: Annotated[float, positive(10.0, "m")] | None = None


GRASP_MODES = ("operator", "random")
# Mechanisms an ablation showed at no gain were removed (docs/experiments.md); a rig file (or a batch file's capture
# job) that still asks for one is refused with one error naming the key and why (refuse_removed).
# next-best touch: grasps where the reconstruction so far was least sure; it did not beat random grasps at equal
# budgets
REMOVED_NEXT_BEST = (
    "next-best touch was removed (it did not beat random grasps at equal budgets, docs/experiments.md): "
    "use mode 'random' (or 'operator') and drop candidates, selection_steps and uncertainty"
)
# the slide: after each press, every finger in contact slid its pad across the surface, read as it went; 5 slid
# presses did not beat 14 plain ones at equal robot time
SLIDE_WHY = "the slide was removed (it did not beat more presses at equal robot time, docs/experiments.md)"
REMOVED_SLIDE = f"{SLIDE_WHY}: remove the key"
SLIDE_KEYS = ("slide_m", "slide_speed_m_s", "slide_push_m", "stream_period_s")  # GraspControl's, as it had them
# a rig file's keys of the removed mechanisms, in the order they are looked for: key -> (the value refused, or None
# for any value, why)
REMOVED_KEYS = {
    "plan.grasps.mode": ("next-best", REMOVED_NEXT_BEST),
    **{f"plan.grasps.{key}": (None, REMOVED_NEXT_BEST) for key in ("candidates", "selection_steps", "uncertainty")},
    **{f"grasp.{key}": (None, REMOVED_SLIDE) for key in SLIDE_KEYS},
}


def refuse_removed(data: Any, keys: dict = REMOVED_KEYS, prefix: str = "", source=None) -> None:
    """One ConfigError naming the first of ``keys`` (dotted paths into the mapping ``data``, as
    :data:`REMOVED_KEYS`) that ``data`` sets (to the value refused, where one is given), and why it went."""
    for path, (refused, why) in keys.items():
        *sections, key = path.split(".")
        section = data
        for name in sections:
            section = section.get(name) if isinstance(section, dict) else None
        if isinstance(section, dict) and key in section and (refused is None or section[key] == refused):
            raise ConfigError(prefix + path, why, source)


@yaml_section
class GraspPlan:
    """Where the grasps go: ``operator`` (a person places the hand) or ``random`` (the twin samples an approach per
    grasp)."""

    count: Annotated[int, bounded(0)] = 5
    mode: Annotated[str, one_of(GRASP_MODES, "must be 'operator' or 'random', got {value!r}")] = "operator"
    seed: Annotated[int, bounded(0)] = 0


TOUCH_MODELS = ("gel", "paper")


@yaml_section
class TouchPlan:
    """How touches are made: ``gel``, the hand's grasps (each pad's gel contact patch, one touch per finger), or
    ``paper``, the touches of the paper's official code, four per planned grasp, with no hand (``rig: sim`` only;
    :mod:`tacsplat.acquisition.paper_touches`)."""

    model: Annotated[str, one_of(TOUCH_MODELS)] = "gel"
    # paper: samples spread evenly on the surface (pc_num)
    surface_points: Annotated[int, bounded(1, 10_000_000)] = 20_000
    # paper: the samples nearest to the hit that make one touch
    points_per_touch: Annotated[int, bounded(1, 10_000)] = 50

    def to_json(self) -> dict:
        """As scene.json records it: the paper model's parameters only with the paper model."""
        return dataclasses.asdict(self) if self.model == "paper" else {"model": self.model}


@yaml_section
class CapturePlan:
    views: ViewPlan = field(default_factory=ViewPlan)
    grasps: GraspPlan = field(default_factory=GraspPlan)
    touches: TouchPlan = field(default_factory=TouchPlan)

    def to_json(self) -> dict:
        return {**dataclasses.asdict(self), "touches": self.touches.to_json()}


MAX_POSE_ERROR_M = 0.05  # the largest true mounting error a twin may hide, per axis (an error, not another rig)
MAX_POSE_ERROR_DEG = 30.0
Shift = Annotated[float, bounded(-MAX_POSE_ERROR_M, MAX_POSE_ERROR_M, "m")]
Turn = Annotated[float, bounded(-MAX_POSE_ERROR_DEG, MAX_POSE_ERROR_DEG, "deg")]


@yaml_section
class PoseError:
    """A rigid error: the true transform is the nominal one followed by this one, ``T_true = T_nominal @ E`` (``E``
    in the child frame: the camera's for the hand-eye, the sensor's for a mount)."""

    translation_m: tuple[Shift, Shift, Shift] = (0.0, 0.0, 0.0)
    rotation_deg: tuple[Turn, Turn, Turn] = (0.0, 0.0, 0.0)  # a rotation vector (axis times angle), degrees

    def matrix(self) -> np.ndarray:
        """``E`` [4, 4]."""
        from scipy.spatial.transform import Rotation

        return make_pose(Rotation.from_rotvec(self.rotation_deg, degrees=True).as_matrix(), self.translation_m)


@yaml_section
class TrueErrors:
    """What the twin's (or ``--mock``'s) hardware hides from its nominal model, so that each calibration step is
    checked against a known truth: the hardware differs from the model by these, the calibration files must find
    them. Joint errors are the servos': a servo reads ``sign * q + offset`` at true joint angle ``q`` (the
    nominal hand: sign 1, offset 0), as a horn fitted off its zero or a servo mounted reversed does."""

    joint_offsets_rad: dict[JointName, JointAngle] = field(default_factory=dict)  # joint name -> offset
    joint_signs: dict[JointName, ServoSign] = field(default_factory=dict)  # joint name -> -1 (a reversed servo) or 1
    hand_eye: PoseError = field(default_factory=PoseError)  # the wrist camera's T_hand_cam
    mounts: dict[FingerName, PoseError] = field(default_factory=dict)  # finger -> its sensor's T_fingertip_sensor

    def servo_offsets(self) -> tuple[float, ...]:
        """[16] true offsets in the twin's joint order."""
        return tuple(float(self.joint_offsets_rad.get(name, 0.0)) for name in JOINT_NAMES)

    def servo_signs(self) -> tuple[int, ...]:
        """[16] true signs in the twin's joint order."""
        return tuple(int(self.joint_signs.get(name, 1)) for name in JOINT_NAMES)


@yaml_section
class SimConfig:
    """The twin (``rig: sim``); ``true_errors`` also applies to ``--mock``'s emulated hardware of a real rig file."""

    object: Text = "teapot"
    mesh: Text | None = None
    # bounding-sphere radius the hand can grasp
    object_radius: Annotated[float, bounded(*OBJECT_RADIUS_RANGE_M, "m")] = 0.08
    resolution: Annotated[int, bounded(8, 4096, "px")] = 200
    seed: Annotated[int, bounded(0)] = 0
    texture: Text = "none"  # the object's surface: its one colour, or "checker" (tacsplat.sim.objects.TEXTURES)
    true_errors: TrueErrors = field(default_factory=TrueErrors)


@yaml_section
class MockConfig:
    """The emulated devices of ``--mock`` (a real rig's file, no hardware)."""

    # the wrist camera: the twin's (presses.CAMERA_PX, 60 degrees high), which sees the fine board of real-rig.md from
    # the presses' 4-10 cm and from a capture's 30-40 cm (at 320 x 240, f 280 px, the latter showed no corner)
    camera_width: Annotated[int, bounded(16, 4096, "px")] = 640
    camera_height: Annotated[int, bounded(16, 4096, "px")] = 480
    camera_focal_px: Annotated[float, positive(1e5, "px")] = 416.0
    camera_frames: Annotated[int, bounded(1, 1000)] = 24  # board renders in the looping video
    tactile_width: Annotated[int, bounded(8, 4096, "px")] = 160
    tactile_height: Annotated[int, bounded(8, 4096, "px")] = 120
    tactile_pixel_size_m: Annotated[float, positive(1e-3, "m")] = 1.6e-4
    # the hand's reply timeout (its bus watchdog is sized from it): an emulator shares a host that may be busy with
    # other work, where it can answer hundreds of ms late; a real servo answers within a millisecond
    servo_timeout_s: Annotated[float, positive(1.0, "s")] = 0.5
    servo_port: Text | None = None  # the pty of a servo emulator in its own process (python -m
    # tacsplat.drivers.dxl_emulator), which outlives this one; None: an emulator in this process
    # faults, to see rig check name them: devices left unplugged (a sensor's finger, camera, or servo ID) ...
    unplugged: tuple[Text, ...] = ()
    board_in_view: bool = True  # ... and a wrist camera that does not see the board


@yaml_section
class RigConfig:
    rig: Annotated[str, one_of(("real", "sim"), "must be 'real' or 'sim', got {value!r}")]
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
_EXPECTED = {  # what each kind of pydantic error (by its first word) means in the YAML's terms
    "int": "an integer",
    "float": "a finite number",
    "finite": "a finite number",
    "bool": "true or false",
    "string": "a non-empty string",
    "tuple": "a list",
    "list": "a list",
    "dataclass": "a mapping",
    "dict": "a mapping",
}


def _section_fields(cls: type, loc: tuple) -> list[str]:
    """The keys the section at ``loc`` (a path of field names, list indices and mapping keys) of ``cls`` may hold."""
    in_mapping = False
    for part in loc:
        if isinstance(part, int) or in_mapping:  # a list index, or the key of a mapping (mounts.index)
            in_mapping = False
            continue
        hint = get_type_hints(cls)[part]
        in_mapping = get_origin(hint) is dict
        cls = get_args(hint)[-1] if get_args(hint) else hint  # tuple[Item, ...], dict[str, Item] -> Item
    return [f.name for f in dataclasses.fields(cls) if cls is not RigConfig or f.name not in _SET_BY_LOAD_RIG]


@functools.cache
def _adapter(cls: type) -> TypeAdapter:
    return TypeAdapter(cls)


def _yaml_numbers(hint, value):
    """The YAML's ``value`` for a field of type ``hint``, each string where a number goes read as the number it spells
    (:func:`~tacsplat.config_files.yaml_number`: YAML reads ``1e-9``, with no dot, as a string)."""
    if isinstance(value, str):
        return yaml_number(value, hint)
    origin, args = get_origin(hint), get_args(hint)
    if dataclasses.is_dataclass(hint) and isinstance(value, dict):
        hints = get_type_hints(hint)
        return {k: _yaml_numbers(hints[k], v) if k in hints else v for k, v in value.items()}
    if origin is dict and isinstance(value, dict):
        return {k: _yaml_numbers(args[1], v) for k, v in value.items()}
    if origin is tuple and isinstance(value, list):  # tuple[float, ...] or tuple[float, float, float]
        items = [args[0]] * len(value) if args[1:] == (...,) else list(args)
        return [_yaml_numbers(h, v) for h, v in zip(items, value)] + value[len(items) :]
    return value


def checked(cls: type, data: Any, prefix: str = "", source=None):
    """``data`` (the YAML's values, a number it left as a string read as the number; or a ``cls`` built in code) as
    a ``cls``, every value's type and range checked by pydantic; the first value refused is one ConfigError naming
    its field path (after ``prefix``) and what it expects."""
    if dataclasses.is_dataclass(data):
        data = dataclasses.asdict(data)
    else:
        data = _yaml_numbers(cls, data)
    try:  # as JSON, whose strict mode still reads a list as a tuple and a mapping as a dataclass
        return _adapter(cls).validate_json(json.dumps(data, default=str), strict=True)
    except ValidationError as exc:

        def unknown(loc: tuple) -> str:
            return f"expected one of {sorted(_section_fields(cls, loc[:-1]))}"

        raise ConfigError(*pydantic_problem(exc, "key", prefix, unknown, _EXPECTED), source) from None


def parse_rig(
    data: Any, source: str | Path | None = None, mock: bool = False, check_files: bool = True, kind: str | None = None
) -> RigConfig:
    """A :class:`RigConfig` from the YAML's data (``source`` names the file in errors; ``check_files=False`` leaves
    the calibration files unchecked: the commands that write them or report on them; ``kind``: the one ``rig:`` the
    command runs)."""
    src = None if source is None else str(source)
    if not isinstance(data, dict) or "rig" not in data:
        raise ConfigError("rig", "missing: the file must say `rig: real` or `rig: sim`", src)
    if kind is not None and data["rig"] != kind:
        raise ConfigError("rig", f"this command runs a rig: {kind} file, got rig: {data['rig']}", src)
    for key in _SET_BY_LOAD_RIG:
        if key in data:
            raise ConfigError(key, f"unknown key (expected one of {sorted(_section_fields(RigConfig, ()))})", src)
    refuse_removed(data, source=src)
    if data["rig"] == "sim":
        refuse_unread_by_twin(data, src)
    data = {k: v for k, v in data.items() if not (v is None and k in _SECTIONS)}  # an empty section: the defaults
    config = dataclasses.replace(checked(RigConfig, data, "", src), source=src, mock=bool(mock))
    validate(config, check_files)
    return config


def refuse_unread_by_twin(data: dict, source=None) -> None:
    """One ConfigError naming every key of a rig: sim file's ``data`` that the twin never reads (:data:`TWIN_READS`,
    :data:`TWIN_SENSOR_READS`; the first as its key, and why; a section it reads none of once, as the section), so
    that one run lists all there are to remove; else one naming the first sensor without its mounting
    (:data:`TWIN_SENSOR`)."""
    sensors = data["tactile"].get("sensors") if isinstance(data.get("tactile"), dict) else None
    sensors = sensors if isinstance(sensors, list) else []
    mappings = [(section, data.get(section), read, why) for section, (read, why) in TWIN_READS.items()]
    mappings += [(f"tactile.sensors[{i}]", sensor, *TWIN_SENSOR_READS) for i, sensor in enumerate(sensors)]
    unread = []  # (the error's key, as the message lists it, why)
    for prefix, values, read, why in mappings:
        keys = [key for key in values if key not in read] if isinstance(values, dict) else []
        if keys and not read:  # a section the twin reads none of goes whole (grasp, mock_devices)
            unread.append((f"{prefix}.{keys[0]}", f"{prefix} (the whole section)", why))
        else:
            unread += [(f"{prefix}.{key}", f"{prefix}.{key}", why) for key in keys]
    if unread:
        (key, _, why), listed = unread[0], [name for _, name, _ in unread]
        told = f"; the twin reads none of these: {', '.join(listed)} (remove them all)"
        raise ConfigError(key, why + (told if len(listed) > 1 else ""), source)
    for i, sensor in enumerate(sensors):
        if isinstance(sensor, dict) and "T_fingertip_sensor" not in sensor:
            raise ConfigError(f"tactile.sensors[{i}].T_fingertip_sensor", TWIN_SENSOR, source)


def load_rig(path: str | Path, mock: bool = False, check_files: bool = True, kind: str | None = None) -> RigConfig:
    """Read and validate a rig YAML file (``check_files``: that the calibration files it names exist; ``kind``: the
    one ``rig:`` the command runs)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError("rig", f"cannot read the rig file: {exc.strerror}", path) from None
    except UnicodeDecodeError:
        raise ConfigError("rig", "not a text file (YAML, UTF-8): is it the rig file?", path) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError("rig", f"not valid YAML: {exc}", path) from None
    return parse_rig(data, path, mock, check_files, kind)


def validate(c: RigConfig, check_files: bool = True) -> None:
    """Every value against its type and its physical and logical range (:func:`checked`; a config built in code
    too), then the cross-field checks and, with ``check_files``, that a real rig's calibration files exist; each
    failure is one ConfigError naming its key."""
    checked(RigConfig, c, "", c.source)
    src = c.source
    if c.rig == "real":  # the schema's own words: a real rig's sensor opens its source and reads its calibration
        for i, s in enumerate(c.tactile.sensors):
            for key in ("source", "calibration"):
                if getattr(s, key) is None:
                    raise ConfigError(f"tactile.sensors[{i}].{key}", "missing (a required key)", src)
    for key, mode in (("plan.views.mode", c.plan.views.mode), ("plan.grasps.mode", c.plan.grasps.mode)):
        if c.rig == "real" and mode != "operator":
            raise ConfigError(key, "a real rig is positioned by the operator: use 'operator'", src)
    gc = c.grasp
    for key in ("close_pose", "open_pose"):
        if len(getattr(gc, key)) != 16:
            raise ConfigError(f"grasp.{key}", f"expected 16 joint positions, got {len(getattr(gc, key))}", src)
    for key, than, other, ok in (
        ("settle_tol_rad", "smaller", "stall_error_rad", gc.settle_tol_rad < gc.stall_error_rad),
        ("max_close_s", "longer", "poll_s", gc.max_close_s > gc.poll_s),
    ):
        if not ok:
            told = f"must be {than} than grasp.{other} ({getattr(gc, other):g}), got {getattr(gc, key):g}"
            raise ConfigError(f"grasp.{key}", told, src)
    validate_touches(c.plan.touches, "plan.touches.", src)
    if c.plan.touches.model == "paper" and c.rig != "sim":
        raise ConfigError(
            "plan.touches.model", "the paper's touches are sampled on the twin's mesh: use 'gel' on a real rig", src
        )
    _validate_board(c.board, src)
    if c.rig == "real":
        _validate_real(c, src, check_files)
    else:
        _validate_sim(c, src)


def validate_touches(t: TouchPlan, prefix: str = "", src=None) -> None:
    """A touch plan's model and numbers (``prefix`` names its place: ``plan.touches.``)."""
    checked(TouchPlan, t, prefix, src)
    if t.surface_points < t.points_per_touch:
        raise ConfigError(
            f"{prefix}surface_points",
            f"must be at least the {t.points_per_touch} points of a touch "
            f"({prefix}points_per_touch), got {t.surface_points}",
            src,
        )


def _validate_board(b: BoardConfig, src) -> None:
    if problem := b.spec().problem():
        raise ConfigError(f"board.{problem[0]}", problem[1], src)
    inner = (b.squares_x - 1) * (b.squares_y - 1)
    if b.min_corners > inner:
        raise ConfigError(
            "board.min_corners",
            f"a {b.squares_x} x {b.squares_y} board has {inner} inner corners; "
            f"must be in [4, {inner}], got {b.min_corners}",
            src,
        )


def _validate_real(c: RigConfig, src, check_files: bool) -> None:
    if c.hand.baudrate not in DYNAMIXEL_BAUDRATES:
        raise ConfigError(
            "hand.baudrate", f"must be one of the Dynamixel rates {DYNAMIXEL_BAUDRATES}, got {c.hand.baudrate}", src
        )
    if len(c.hand.ids) != 16 or len(set(c.hand.ids)) != 16:
        raise ConfigError("hand.ids", f"expected 16 distinct servo ids, got {list(c.hand.ids)}", src)
    if not c.tactile.sensors:
        raise ConfigError("tactile.sensors", "a real rig needs at least one tactile sensor", src)
    fingers = [s.finger for s in c.tactile.sensors]
    for i, finger in enumerate(fingers):
        if finger in fingers[:i]:
            raise ConfigError(f"tactile.sensors[{i}].finger", f"{finger!r} has two sensors", src)
    known = fingers + ["camera"] + [f"servo {i}" for i in c.hand.ids]
    for i, name in enumerate(c.mock_devices.unplugged):
        if name not in known:
            raise ConfigError(f"mock_devices.unplugged[{i}]", f"unknown device {name!r} (one of {known})", src)
    if check_files and not c.mock:  # the mock generates its own calibrations; a real rig's files must exist
        files = [("camera.calibration", c.camera.calibration), ("hand.calibration", c.hand.calibration)]
        files += [(f"tactile.sensors[{i}].calibration", s.calibration) for i, s in enumerate(c.tactile.sensors)]
        for key, name in files:
            if name and not c.path(name).is_file():  # (no hand calibration: the raw servos)
                raise ConfigError(key, f"file not found: {c.path(name)}", src)


def _validate_sim(c: RigConfig, src) -> None:
    s = c.sim
    if s.mesh is not None and not c.path(s.mesh).is_file():
        raise ConfigError("sim.mesh", f"file not found: {c.path(s.mesh)}", src)
    from tacsplat.sim import VIEW_ZNEAR_M
    from tacsplat.sim.objects import OBJECT_NAMES, texture_problem

    if problem := texture_problem(s.texture):
        raise ConfigError("sim.texture", problem, src)
    if s.mesh is None and s.object not in OBJECT_NAMES:
        raise ConfigError("sim.object", f"unknown library object {s.object!r} (one of {list(OBJECT_NAMES)})", src)
    radius = c.plan.views.radius_m
    # the object's nearest point at least twice the near plane's distance away: off the view's axis a point's depth
    # is less than its distance (MuJoCo clips it, and its ground-truth depth reads the object's far inside)
    nearest = s.object_radius + 2 * VIEW_ZNEAR_M
    if radius is not None and not radius >= nearest:
        raise ConfigError(
            "plan.views.radius_m",
            f"the camera must stay outside the object, and its near plane ({VIEW_ZNEAR_M:g} m) too: must be larger "
            f"than sim.object_radius ({s.object_radius:g}) by {2 * VIEW_ZNEAR_M:g} m or more (>= {nearest:g}), "
            f"got {radius:g}",
            src,
        )
