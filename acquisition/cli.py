"""`tacsplat` subcommands of tacsplat.acquisition: capture, sim-capture, simulate-touches (see tacsplat.cli); their
options are the dataclasses below (tacsplat.options)."""

from __future__ import annotations

import os
import signal
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from tacsplat.errors import ConfigError, UsageError
from tacsplat.sim import OBJECT_RADIUS_RANGE_M

_RADIUS_RANGE = "({:g} to {:g}: the sizes the twin's hand grasps)".format(*OBJECT_RADIUS_RANGE_M)


@dataclass
class Capture:
    """operator capture session on a rig (real, --mock, or the twin): views and grasps into a scene directory

    Guides a person at the rig from the terminal. A status line shows the board (seen or not, reprojection
    error), the hand and the counts against the plan. Keys: Enter = take a view, g = grasp, u = undo the last
    record, q = stop. A device fault leaves the hand with torque off and prints the command that carries on
    (--resume once a scene was written). --resume refuses a rig file whose object, plan, board, mounting or
    calibrations differ from the scene's. Example rigs: acquisition/rigs/{real,mock,sim}.yaml."""

    rig: Path
    """rig YAML file (devices, calibrations, board, capture plan)"""
    out: Path
    """scene directory to create (or continue with --resume)"""
    resume: bool = False
    """continue a capture that stopped or was killed"""
    mock: bool = False
    """emulated devices instead of the real rig's (servo emulator on a pty, video-file tactile sensors, a camera
    that sees a rendered board)"""


@dataclass
class CalibrateHand:
    """the hand's joint signs, zeros and ranges, from each joint's hard stops (writes the rig's hand.json)

    With the hand's torque off, each joint in turn is held against its upper, then its lower stop (the model's joint
    limits); a status line per joint gives its sign, offset and measured range. On a real rig a person moves the
    joints and presses Enter at each stop; with --mock the servo emulator and on a rig: sim file the twin play the
    person, so it runs to its end with standard input closed. Refuses, naming the joint and what to do, a joint
    that does not move or whose range is not the model's. The hand is left with torque off however it ends."""

    rig: Path
    """rig YAML file (the hand's port and servo ids; sim.true_errors on a twin or --mock)"""
    out: Path
    """hand calibration file to write (.json; the rig's hand.calibration)"""
    mock: bool = False
    """the servo emulator instead of the real hand"""


@dataclass
class CalibrateHandEye:
    """the wrist camera's pose on the hand (T_hand_cam) from fingertip presses, or from arm poses (--arm-poses)

    The fingertips press a 25 mm sphere resting on the board while the wrist camera sees the board (a board of
    small squares: the camera is about 10 cm from it); the contact points must lie on the sphere, which fixes
    T_hand_cam and the sphere's place together. Refuses presses that leave an axis undetermined, naming what to
    add. On a real rig the hand holds each press's joints and a line says which fingertip to press where; a press
    is taken once its contact is steady and the camera sees the board, so no key is needed. On --mock the emulated
    devices and on a rig: sim twin the twin make the presses (standard input may be closed). With --arm-poses (a
    hand on an arm) nothing is pressed: the board is found in each station's image with the rig's
    camera.calibration and T_hand_cam solved from the hand's poses (Park & Martin); a line per station, then
    T_hand_cam and the spread of the board's pose in the arm's base over the stations. Refuses fewer than 3
    stations that see the board, and stations where the hand turns about one axis only."""

    rig: Path
    """rig YAML file (its board; sim.true_errors on a twin or --mock; camera.calibration with --arm-poses)"""
    out: Path
    """hand-eye file to write (.json; the rig's camera.hand_eye)"""
    mock: bool = False
    """the emulated devices instead of the real rig's"""
    arm_poses: Annotated[Path | None, tyro.conf.arg(metavar="FILE")] = None
    """a YAML or JSON file of stations, each the hand's pose in the arm's base (T_base_hand, 4x4 in metres, as the
    arm's controller reports it) and the wrist camera's raw image taken there (image, a path relative to the file):
    stations: [{T_base_hand: [[...], [...], [...], [0, 0, 0, 1]], image: station_01.png}, ...]"""


@dataclass
class CalibrateMounts:
    """each tactile sensor's pose on its fingertip (T_fingertip_sensor), with T_hand_cam, from presses on a sphere

    Every fingertip presses a 25 mm sphere resting on the board with its pad's centre, then each pad presses the
    sphere on a stand of known height (its centre --stand-height-mm up: measure it) with six places of the gel (its
    two ends, two sides and two corners), bent and spread two ways, while the wrist camera sees the board. The patches' curvature and lever arm fix
    each sensor's six parameters; they and T_hand_cam (coupled to them) are solved together with the sphere's place,
    started at the rig's (run calibrate hand-eye first). A residual line per sensor. Refuses presses that leave an
    axis undetermined, naming the presses to add. Guided on a real rig as calibrate hand-eye is; on --mock and a
    rig: sim twin the presses are made for the person (standard input may be closed)."""

    rig: Path
    """rig YAML file (camera.hand_eye; sim.true_errors on a twin or --mock)"""
    out: Path
    """mounts file to write (.json; the rig's tactile.mounts)"""
    hand_eye: Annotated[
        Path | None,
        tyro.conf.arg(
            metavar="PATH",
            help_behavior_hint="(default: the rig's camera.hand_eye file; a rig that names none is refused)",
        ),
    ] = None
    """the hand-eye file to write the T_hand_cam solved with the mounts to (.json); both files are written, or
    neither"""
    stand_height_mm: float = 60.0  # 1000 * tacsplat.acquisition.presses.STAND_HEIGHT_M (not imported: a slow import)
    """the height of the sphere's centre over the board's printed face with the sphere on its stand, in mm, as
    measured (the sphere's top less its 12.5 mm radius); the twin's and --mock's stand is at the default"""
    mock: bool = False
    """the emulated devices instead of the real rig's"""


@dataclass
class RigCheck:
    """checks a rig before a capture: devices, calibration files, the board (one table; exit 1 naming what is wrong)

    Every device answers (the servos, with torque off; the wrist camera and each tactile sensor, at their frame
    rates), every calibration file the rig names is there, parses, holds values in range and is younger than the
    rig file's hardware_changed date, the hand reads inside its joint limits with its calibration, T_hand_cam is
    known, and the wrist camera sees the board well enough to capture. --mock checks the emulated devices (the
    rig file's mock_devices.unplugged and board_in_view stage faults)."""

    rig: Path
    """rig YAML file"""
    mock: bool = False
    """emulated devices instead of the real rig's"""


@dataclass
class TouchModel:
    """The touches of a grasp (sim-capture, simulate-touches)."""

    touch_model: str = "gel"
    """gel: the hand grasps, each pad's gel contact patch is a touch; paper: the paper's touches, 4 per grasp and no
    hand (the official code's: the 50 surface samples nearest to where a random ray from the centroid leaves the
    mesh)"""
    surface_points: Annotated[
        int | None,
        tyro.conf.arg(
            metavar="INT",
            help_behavior_hint="(default: 20000, the official code's for Glossy Synthetic; it used 10000 for Shiny "
            "Blender)",
        ),
    ] = None
    """paper touches: points sampled evenly on the surface, 50 (a touch's) to 10000000"""

    def touch_args(self) -> dict:
        """The keyword arguments of sim_rig_config and simulate_touches (defaults left to them)."""
        given = {"surface_points": self.surface_points} if self.surface_points is not None else {}
        return {"touch_model": self.touch_model, **given}


@dataclass
class SimCapture(TouchModel):
    """simulated capture: train views, test views with ground truth, and grasps, into a scene directory

    Captures a scene on the MuJoCo twin through the same logger as a real capture (the twin places the camera on
    the hemisphere and the hand on sampled approaches; the logger closes the hand until the fingers stall, reads
    the pads and writes). --touch-model paper makes the paper's touches instead of grasping, four per grasp.
    Deterministic in --seed; --resume continues a killed capture with the same options (any other value is refused, naming the option).
    --rig reads the object, the plan and the calibration files from a rig: sim file instead of these options:
    its sim.true_errors make the twin's hardware differ from its model, and every pose is computed as on the real
    rig, from the calibration files the rig names."""

    out: Path = tyro.MISSING
    """scene directory to create (or continue with --resume)"""
    rig: Path | None = None
    """a rig: sim YAML file (acquisition/rigs/sim.yaml) giving the object, the plan, the hidden hardware errors and
    the calibration files; no other capture option may be given with it"""
    object: str = "teapot"
    """library object (teapot, toaster, bell, helmet, torus, car)"""
    mesh: Path | None = None
    """any .obj/.ply/.stl mesh instead of a library object"""
    object_radius: Annotated[float, tyro.conf.arg(help=f"bounding-sphere radius in metres {_RADIUS_RANGE}")] = 0.08
    keep_size: bool = False
    """with --mesh: simulate the mesh at its own size, its units read as metres (a mesh exported by tacsplat export
    mesh), instead of at --object-radius"""
    views: int = 5
    """train views (at least 1)"""
    test_views: int = 24
    """held-out test views (with GT depth in gt/; 0 or more)"""
    grasps: int = 5
    """grasps of four touches each (0 or more)"""
    resolution: int = 200
    """image width and height in pixels (8 to 4096)"""
    seed: int = 0
    """seed of the views and grasps (0 or more)"""
    texture: str = "none"
    """the object's surface: none (its one colour, the glossy library's) or checker (a checker of its colour and a
    contrasting grey, for measuring on a textured object)"""
    resume: bool = False
    """continue a capture that was interrupted"""


@dataclass
class SimulateTouches(TouchModel):
    """add simulated grasps of a mesh to a scene (e.g. an imported Shiny Blender or Glossy Synthetic scene)

    Grasps the mesh on the MuJoCo twin (at a graspable size, --object-radius) through the same logger and grasp
    controller as sim-capture (or, with --touch-model paper, makes four of the paper's touches per grasp on it),
    and writes the touches in the scene's frame and units. A scene with this sensor model is extended in place; one
    without (an import) is copied into --out first."""

    scene: Annotated[tyro.conf.Positional[Path], tyro.conf.arg(metavar="SCENE")] = tyro.MISSING
    """scene directory"""
    mesh: Annotated[
        Path | None,
        tyro.conf.arg(
            metavar="PATH",
            help_behavior_hint="(default: the scene's ground-truth mesh, or, for --touch-model paper, its ground-truth "
            "points: an imported Shiny Blender or Glossy Synthetic scene)",
        ),
    ] = None
    """the object's mesh, in the scene's world frame and units"""
    grasps: int = 5
    """grasps to add (at least 1)"""
    out: Path | None = None
    """new scene directory (needed when SCENE has no tactile sensor model)"""
    object_radius: Annotated[
        float,
        tyro.conf.arg(
            help=f"graspable size the mesh is simulated at: its bounding-sphere radius in metres {_RADIUS_RANGE}"
        ),
    ] = 0.08
    seed: int = 0
    """seed of the grasps (0 or more)"""


def register(cli) -> None:
    """Add this package's commands to the tree."""
    cli.typed("capture", Capture, _capture)
    cli.typed("calibrate hand", CalibrateHand, _calibrate_hand)
    cli.typed("calibrate hand-eye", CalibrateHandEye, _calibrate_hand_eye)
    cli.typed("calibrate mounts", CalibrateMounts, _calibrate_mounts)
    cli.typed("rig check", RigCheck, _rig_check)
    cli.typed("sim-capture", SimCapture, _sim_capture)
    cli.typed("simulate-touches", SimulateTouches, _simulate_touches)


def _capture(o: Capture) -> int:
    from tacsplat.acquisition.config import load_rig, validate
    from tacsplat.acquisition.operator_session import run_capture

    config = load_rig(o.rig, mock=o.mock, check_files=False)
    if config.rig == "real":  # its drivers (a --mock rig's too): a missing hardware extra is named before the files
        import tacsplat.drivers.dynamixel_hand  # noqa: F401
    validate(config)
    return run_capture(config, o.out, resume=o.resume)


def _calibrate(o: CalibrateHand | CalibrateHandEye | CalibrateMounts, job, outputs: dict | None = None) -> int:
    """A calibration command: the rig file, ``--out`` and the other ``outputs`` ({option: a .json file, or None})
    checked writable, then ``job(config)``, exit 0; interrupted (Ctrl-C, or the hand driver's SignalInterrupt:
    SIGTERM, SIGHUP, ...) after the hand was left with torque off: one line saying ``--out`` was not written, exit
    128 + the signal."""
    from tacsplat.acquisition.config import load_rig
    from tacsplat.datasets.outputs import ensure_output_dir

    outputs = {"--out": o.out, **{option: path for option, path in (outputs or {}).items() if path is not None}}
    for option, path in outputs.items():
        if path.is_dir():
            raise ConfigError(option, f"{path} is a folder; give a .json file")
    config = load_rig(o.rig, mock=o.mock, check_files=False)
    for option, path in outputs.items():
        ensure_output_dir(path.parent, option)
    try:
        job(config)
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        print(f"interrupted ({signal.Signals(signum).name}): {o.out} not written", file=sys.stderr)
        return 128 + signum
    return 0


def _calibrate_hand(o: CalibrateHand) -> int:
    from tacsplat.acquisition.calibrate import calibrate_hand

    return _calibrate(o, lambda config: calibrate_hand(config, o.out))


def _calibrate_hand_eye(o: CalibrateHandEye) -> int:
    if o.arm_poses is None:
        from tacsplat.acquisition.calibrate import calibrate_hand_eye

        return _calibrate(o, lambda config: calibrate_hand_eye(config, o.out))
    if o.mock:
        raise UsageError("--mock", "--arm-poses reads its stations' images, no devices: leave out --mock")
    from tacsplat.acquisition.arm_hand_eye import calibrate_hand_eye_from_arm

    return _calibrate(o, lambda config: calibrate_hand_eye_from_arm(config, o.arm_poses, o.out))


def _calibrate_mounts(o: CalibrateMounts) -> int:
    import math

    from tacsplat.acquisition.calibrate import calibrate_mounts

    if not (math.isfinite(o.stand_height_mm) and o.stand_height_mm > 0):
        raise UsageError("--stand-height-mm", f"must be a positive, finite height in mm, got {o.stand_height_mm:g}")
    # one file under two names ('..', a symbolic link) too; realpath, unlike Path.resolve, takes a symlink loop as is
    if o.hand_eye is not None and os.path.realpath(o.hand_eye) == os.path.realpath(o.out):
        raise UsageError("--hand-eye", f"{o.hand_eye} is --out's file too: give the hand-eye file another name")

    def job(config):
        return calibrate_mounts(config, o.out, o.hand_eye, stand_height_m=o.stand_height_mm / 1000)

    return _calibrate(o, job, {"--hand-eye": o.hand_eye})


def _rig_check(o: RigCheck) -> int:
    from tacsplat.acquisition.config import load_rig
    from tacsplat.acquisition.rig_check import check_rig, check_twin, table

    config = load_rig(o.rig, mock=o.mock, check_files=False)
    rows = check_rig(config) if config.rig == "real" else check_twin(config)
    print(table(rows))
    if failed := [row.item for row in rows if not row.ok]:
        print(f"error: rig check: {len(failed)} of {len(rows)} checks failed: {'; '.join(failed)}", file=sys.stderr)
        return 1
    print(f"all {len(rows)} checks passed")
    return 0


def _sim_capture(args: SimCapture) -> int:
    import json

    from tacsplat.acquisition.sim_capture import sim_capture

    config = _sim_capture_config(args) if args.rig is None else _sim_capture_rig(args)
    try:
        timings = sim_capture(config, args.out, resume=args.resume)
    except ConfigError as exc:
        raise _naming_options(exc, _SIM_OPTIONS if args.rig is None else {}) from None
    print(json.dumps({"scene": str(args.out), **{k: round(v, 2) for k, v in timings.items()}}))
    return 0


def _sim_capture_config(args: SimCapture):
    """The ``rig: sim`` config of sim-capture's options."""
    import inspect

    from tacsplat.acquisition.sim_capture import sim_rig_config

    object_radius = args.object_radius
    if args.keep_size:
        if args.mesh is None:
            raise UsageError("--keep-size", "keeps a mesh's own size: give the mesh with --mesh")
        from tacsplat.sim.objects import bounding_sphere, object_radius_problem, read_mesh

        object_radius = _option_values(lambda: bounding_sphere(read_mesh(args.mesh))[1], _SIM_OPTIONS)
        if problem := object_radius_problem(object_radius):
            raise UsageError("--keep-size", f"{args.mesh}'s own bounding radius, read in metres, {problem}")
    keys = inspect.signature(sim_rig_config).parameters
    given = {k: v for k, v in vars(args).items() if k in keys and v is not None} | {"object_radius": object_radius}
    return _option_values(lambda: sim_rig_config(**given), _SIM_OPTIONS)


def _sim_capture_rig(args: SimCapture):
    """``sim-capture --rig``'s config: everything but the scene folder and --resume from the rig file."""
    import dataclasses

    from tacsplat.acquisition.config import load_rig

    for f in dataclasses.fields(SimCapture):
        if f.name not in ("out", "rig", "resume") and getattr(args, f.name) != f.default:
            raise UsageError(
                _option(f.name), f"{args.rig} sets the capture with --rig: set it there, or leave out --rig"
            )
    return load_rig(args.rig, kind="sim")


def _simulate_touches(args: SimulateTouches) -> int:
    from tacsplat.acquisition.touch_simulation import simulate_touches, touch_settings

    _option_values(
        lambda: touch_settings(args.grasps, args.object_radius, args.seed, **args.touch_args()), _TOUCH_OPTIONS
    )
    try:
        target = simulate_touches(
            args.mesh, args.scene, args.grasps, args.out, args.object_radius, args.seed, **args.touch_args()
        )
    except ConfigError as exc:
        raise _naming_options(exc, _TOUCH_OPTIONS) from None
    print(f"touches written to {target}")
    return 0


def _option_values(check, options: dict[str, str]):
    """``check()``, which checks the command's option values: a value it refuses is a UsageError (exit 2) naming
    the option; a file named by an option (``--mesh``) that is missing stays an error of the run (exit 1)."""
    try:
        return check()
    except ConfigError as exc:
        named = _naming_options(exc, options)
        if named.key == "--mesh":
            raise named from None
        raise UsageError(named.key, str(named).removeprefix(f"{named.key}: ")) from None


def _naming_options(exc: ConfigError, options: dict[str, str]) -> ConfigError:
    """The same error (a usage error stays one) naming the command-line option behind a key (``sim.object_radius``
    -> ``--object-radius``)."""
    from tacsplat.acquisition.capture_scene import ResumeMismatch

    if isinstance(exc, ResumeMismatch):
        return exc.renamed(options)
    if exc.key not in options:
        return exc
    message = str(exc).removeprefix(f"{exc.source}: " if exc.source else "").removeprefix(f"{exc.key}: ")
    return (UsageError if isinstance(exc, UsageError) else ConfigError)(options[exc.key], message)


def _option(name: str) -> str:
    """The command-line option of a setting or field name (``object_radius`` -> ``--object-radius``)."""
    return "--" + name.replace("_", "-")


_SIM_OPTIONS = {  # sim_rig_config's keys
    "object": "--object",
    **{f"sim.{k}": _option(k) for k in ("object", "mesh", "object_radius", "resolution", "seed", "texture")},
    "sim.mesh_sha256": "--mesh",
    "plan.views.train": "--views",
    "plan.views.test": "--test-views",
    "plan.grasps.count": "--grasps",
    "plan.grasps.seed": "--seed",
    "plan.touches.model": "--touch-model",
    "plan.touches.surface_points": "--surface-points",
}
_TOUCH_OPTIONS = {  # simulate_touches' keys
    **{k: _option(k) for k in ("surface_points", "grasps", "object_radius", "seed", "out", "mesh")},
    "model": "--touch-model",
}
