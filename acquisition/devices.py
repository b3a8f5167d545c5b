"""The device factory: a rig config becomes a Hand, TactileSensors, a Camera, a clock and a pose source.

This is the only place where the real rig, its ``--mock`` emulation and the
twin differ; :class:`~tacsplat.acquisition.logger.CaptureLogger` and the
operator session see the same :class:`Rig` for all three.
"""

from __future__ import annotations

import logging
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from tacsplat.acquisition.config import GraspControl, RigConfig
from tacsplat.acquisition.logger import BoardPoseSource, TwinPoseSource, WallClock
from tacsplat.datasets import SensorModel
from tacsplat.errors import ConfigError
from tacsplat.interrupts import signals_held
from tacsplat.types import CameraIntrinsics

log = logging.getLogger(__name__)


@dataclass
class Rig:
    """Open devices of one capture (the Protocol objects plus what the scene needs to know about them)."""

    kind: str  # "real" | "sim"
    hand: object  # Hand
    sensors: list  # [TactileSensor]
    camera: object  # Camera
    clock: object  # Clock
    poses: object  # PoseSource
    intrinsics: CameraIntrinsics
    sensor_model: SensorModel
    control: GraspControl
    extra: dict = field(default_factory=dict)  # provenance for scene.json
    twin: object | None = None  # SimTwin on rig: sim
    mock: object | None = None  # MockDevices on --mock


def uncalibrated_hand(config: RigConfig) -> str | None:
    """Why the rig needs a hand calibration it does not name: a real hand's servos are mounted with unknown offsets
    and signs, and so are the emulated ones of --mock or the twin's when ``sim.true_errors`` hides joint errors;
    None when it names one or needs none."""
    if config.hand.calibration:
        return None
    e = config.sim.true_errors
    hidden = any(e.servo_offsets()) or any(s != 1 for s in e.servo_signs())
    if config.rig == "real" and not config.mock:
        return (
            "none named: the joints are read as the servos' raw angles (sign +1, offset 0), and every fingertip and "
            "touch is placed by them; tacsplat calibrate hand writes it"
        )
    if hidden:
        return "none named, and the twin hides joint errors (sim.true_errors): tacsplat calibrate hand writes it"
    return None


def import_device_modules(config: RigConfig) -> None:
    """Import what opening ``config``'s devices imports, the ending signals held meanwhile and raised after
    (:func:`~tacsplat.interrupts.signals_held`): MuJoCo, SciPy, OpenCV and trimesh load native modules, and a signal
    raised inside one comes out as an ImportError (a traceback), or is dropped and the hand connects after it. First
    in every command that opens the hand, so that its own imports load nothing native after it (with ``--mock``, the
    mock's module too: its SciPy and trimesh)."""
    with signals_held():
        if config.rig == "sim":
            import tacsplat.sim.twin  # noqa: F401

            return
        if config.mock:
            import tacsplat.acquisition.mock  # noqa: F401
        import tacsplat.drivers.dynamixel_hand  # noqa: F401
        import tacsplat.drivers.optical_tactile  # noqa: F401
        import tacsplat.drivers.wrist_camera  # noqa: F401
        from tacsplat.sim.hand import import_mujoco

        import_mujoco()


@contextmanager
def open_rig(
    config: RigConfig, on_hand=None, hand_eye_required: bool = True, calibrating: bool = False
) -> Iterator[Rig]:
    """Open every device of ``config`` (emulated ones with ``config.mock``); closing leaves the hand safe.

    ``on_hand(hand)``: called with a real rig's hand before it connects, so that the caller can tell what its
    closing confirmed (``hand.torque_off_report``) however the opening ends. ``hand_eye_required=False``: a real
    rig that does not know ``T_hand_cam`` yet opens with the hand model's designed one (calibrate hand-eye).
    ``calibrating``: a hand-eye or mounts file the rig names that is not written yet counts as none (a calibration
    command, which may be about to write it)."""
    if config.rig == "sim":
        from tacsplat.sim.twin import SimTwin

        with SimTwin(twin_config(config, calibrating)) as twin:
            yield twin_rig(twin)
        return
    from tacsplat.drivers.optical_tactile import OpticalTactileSensor, TactileCalibration
    from tacsplat.drivers.wrist_camera import CameraCalibration, WristCamera

    with ExitStack() as stack:
        mock = None
        if config.mock:
            from tacsplat.acquisition.mock import MockDevices

            mock = stack.enter_context(MockDevices(config))
        cam_cal = str(mock.camera_calibration if mock else config.path(config.camera.calibration))
        calibration = CameraCalibration.load(cam_cal)
        T_hand_cam = rig_T_hand_cam(config, calibration, calibrating)
        if T_hand_cam is None and not hand_eye_required:
            from tacsplat.sim.hand import nominal_T_hand_cam

            T_hand_cam = nominal_T_hand_cam()
        if T_hand_cam is None:
            raise ConfigError(
                "camera.T_hand_cam",
                f"not given, and {cam_cal} has no hand-eye calibration (run tacsplat calibrate hand-eye and name its "
                "file as camera.hand_eye, or set it here)",
                config.source,
            )
        if calibration.board != config.board.spec():
            log.warning(
                "the camera calibration's board %s differs from the rig's board %s; using the rig's",
                calibration.board,
                config.board.spec(),
            )
        cam_source, reader = device_source(mock, "camera", config.camera.source)
        camera = stack.enter_context(
            WristCamera(cam_source, calibration, fps=config.camera.fps, timeout_s=config.camera.timeout_s, **reader)
        )
        hand_cal = config.path(config.hand.calibration) if config.hand.calibration else None  # --mock: as real
        if not calibrating and (why := uncalibrated_hand(config)):
            log.warning("hand.calibration: %s", why)
        hand = dynamixel_hand(config, mock, hand_cal)
        if on_hand is not None:
            on_hand(hand)
        stack.enter_context(hand)  # torque on now; off when the stack unwinds, whatever happens
        clock = WallClock()
        if not calibrating:  # a capture: each sensor's reference below needs a gel that touches nothing
            open_hand(hand, config.grasp, clock)
        sensors, model, mounts = [], None, rig_mounts(config, calibrating)
        for i, s in enumerate(config.tactile.sensors):
            T_mount = mounts.get(s.finger, np.eye(4))
            source, reader = device_source(mock, s.finger, s.source)
            tcal = TactileCalibration.load(str(mock.tactile_calibration if mock else config.path(s.calibration)))
            h, w = (int(n) for n in tcal.image_size)
            this = SensorModel(
                config.tactile.sensor_name, w, h, float(tcal.pixel_size_m), config.tactile.gel_thickness_m
            )
            if model is not None and this != model:
                raise ConfigError(
                    f"tactile.sensors[{i}].calibration",
                    f"{this} differs from the first sensor's {model}: a scene holds one sensor model",
                    config.source,
                )
            model = this
            pose = lambda finger=s.finger, T=T_mount: hand.fingertip_poses()[finger] @ T
            sensor = OpticalTactileSensor(s.finger, source, tcal, pose, timeout_s=config.tactile.timeout_s, **reader)
            sensors.append(stack.enter_context(sensor))
        yield Rig(
            kind="real",
            hand=hand,
            sensors=sensors,
            camera=camera,
            clock=clock,
            poses=BoardPoseSource(camera, config.board, T_hand_cam),
            intrinsics=CameraIntrinsics(camera.K, camera.width, camera.height),
            sensor_model=model,
            control=config.grasp,
            extra={
                "rig": str(config.source),
                "mock": config.mock,
                "hand_port": hand.port_name,
                "board_max_reprojection_px": config.board.max_reprojection_px,
                "T_hand_cam": np.asarray(T_hand_cam).tolist(),
            },
            mock=mock,
        )


def open_hand(hand, control: GraspControl, clock) -> None:
    """Command ``control``'s open pose, wait until every joint is within ``stall_error_rad`` of it (at most
    ``max_close_s``), then ``open_s``. A capture cut short (a crash, a signal, a power cut) leaves the fingers where
    they stood, perhaps on the object; a tactile reference taken there would bias every reading after it."""
    target = np.asarray(control.open_pose, float)  # [16]
    hand.command_joint_positions(target)
    t_end = clock.time + control.max_close_s
    while (off := np.max(np.abs(hand.read_joint_state()[0] - target))) > control.stall_error_rad:
        if clock.time >= t_end:
            log.warning(
                "the hand did not reach its open pose within %g s (a joint %.2f rad away): a fingertip still "
                "touching something biases its tactile reference",
                control.max_close_s,
                off,
            )
            break
        clock.sleep(control.poll_s)
    clock.sleep(control.open_s)


def dynamixel_hand(config: RigConfig, mock=None, calibration: Path | None = None):
    """The rig's :class:`~tacsplat.drivers.DynamixelHand`, not yet connected: on ``hand.port``, or on ``mock``'s
    emulated servos (:class:`~tacsplat.acquisition.mock.MockDevices`), read through ``calibration`` (a hand.json;
    None: the raw servos)."""
    from tacsplat.drivers.dynamixel_hand import MAX_BUS_WATCHDOG_S, DynamixelHand, DynamixelHandConfig
    from tacsplat.sim.hand import HandKinematics

    port, settings = config.hand.port, None
    if mock is not None:
        # the emulator shares this host's CPUs (and, in this process, its GIL): on a busy host the heartbeat and the
        # emulator's answers can both wait over a second, which a real servo's clock never does; so the Bus
        # Watchdog's longest period (a hand whose host died still stops within 2.54 s)
        port = mock.servo_port
        settings = DynamixelHandConfig(
            min_packet_timeout_s=config.mock_devices.servo_timeout_s, bus_watchdog_s=MAX_BUS_WATCHDOG_S
        )
    h = config.hand
    return DynamixelHand(port, h.baudrate, h.ids, calibration, config=settings, kinematics=HandKinematics())


# The twin's grasp control, every twin capture's (a rig: sim file's grasp section is refused: config.TWIN_GRASP): its
# soft position servos lag a 0.6 rad/s ramp by about 0.03 rad in free motion.
TWIN_CONTROL = GraspControl(
    close_speed_rad_s=0.6, poll_s=0.01, stall_error_rad=0.08, settle_tol_rad=0.002, max_close_s=2.0, open_s=0.2
)


def twin_config(config: RigConfig, calibrating: bool = False):
    """The :class:`~tacsplat.sim.twin.TwinConfig` of a ``rig: sim`` config (``calibrating``: as
    :func:`rig_T_hand_cam`'s). Of the real rig's sections it reads what :data:`~tacsplat.acquisition.config.TWIN_READS`
    lets a ``rig: sim`` file set; a file that sets another key is refused."""
    from tacsplat.sim.twin import TwinConfig

    s = config.sim
    return TwinConfig(
        object=s.object,
        mesh_path=str(config.path(s.mesh)) if s.mesh else None,
        object_radius=s.object_radius,
        seed=s.seed,
        camera_width=s.resolution,
        camera_height=s.resolution,
        texture=s.texture,
        servo_offsets_rad=s.true_errors.servo_offsets(),
        servo_signs=s.true_errors.servo_signs(),
        hand_calibration=str(config.path(config.hand.calibration)) if config.hand.calibration else None,
        hand_eye_error=_rows(s.true_errors.hand_eye.matrix()),
        T_hand_cam=None if (T := rig_T_hand_cam(config, calibrating=calibrating)) is None else _rows(T),
        mounts={finger: _rows(T) for finger, T in rig_mounts(config, calibrating).items()},
        mount_errors={finger: _rows(e.matrix()) for finger, e in s.true_errors.mounts.items()},
    )


def inline_T_hand_cam(config: RigConfig) -> str:
    """What to say when the rig file gives ``camera.T_hand_cam`` itself, which a capture takes over any hand-eye
    file a calibration writes (``""`` when it does not)."""
    if config.camera.T_hand_cam is None:
        return ""
    return f"{config.source} gives camera.T_hand_cam, which a capture uses instead of a hand-eye file: remove it"


def inline_mounts(config: RigConfig) -> str:
    """What to say when the rig file gives a sensor its own ``T_fingertip_sensor``, which a capture takes over the
    mounts file's (``""`` when none)."""
    keys = [
        f"tactile.sensors[{i}].T_fingertip_sensor"
        for i, s in enumerate(config.tactile.sensors)
        if s.T_fingertip_sensor is not None
    ]
    if not keys:
        return ""
    them = "it" if len(keys) == 1 else "them"
    return f"{config.source} gives {', '.join(keys)}, which a capture uses instead of the mounts file: remove {them}"


def rig_T_hand_cam(config: RigConfig, calibration=None, calibrating: bool = False) -> np.ndarray | None:
    """The rig's ``T_hand_cam``: the rig file's ``camera.T_hand_cam``, else its ``camera.hand_eye`` file's, else
    the camera ``calibration``'s (if given); None. ``calibrating``: a ``camera.hand_eye`` file that is not written
    yet counts as none (a calibration command may be about to write it); one that is there but unusable is a
    ConfigError naming it either way."""
    return rig_T_hand_cam_origin(config, calibration, calibrating)[0]


def rig_T_hand_cam_origin(
    config: RigConfig, calibration=None, calibrating: bool = False
) -> tuple[np.ndarray | None, str]:
    """``(T_hand_cam, where it came from)``, as :func:`rig_T_hand_cam` finds it; ``(None, why)`` if nowhere."""
    if config.camera.T_hand_cam is not None:
        return np.asarray(config.camera.T_hand_cam, dtype=np.float64), "given in the rig file"
    if path := _named_file(config, config.camera.hand_eye, calibrating):
        from tacsplat.drivers.press_calibration import load_hand_eye

        return load_hand_eye(path, key="camera.hand_eye"), f"from camera.hand_eye ({path})"
    if calibration is not None and calibration.T_hand_cam is not None:
        return calibration.T_hand_cam, "from the camera calibration"
    return None, "none: neither the rig file, a camera.hand_eye file nor the camera calibration gives it"


def _named_file(config: RigConfig, name: str | None, calibrating: bool) -> Path | None:
    """The path of a calibration file the rig names; None if it names none or, ``calibrating``, if it is not
    written yet."""
    if not name:
        return None
    path = config.path(name)
    return None if calibrating and not path.exists() else path


def device_source(mock, name: str, source: str) -> tuple[str, dict]:
    """``(source, reader keywords)`` of video device ``name`` ("camera" or a finger): ``source`` (the rig file's),
    or on ``--mock`` the emulated device's, read through a ``capture_factory`` that loops it."""
    if mock is None:
        return source, {}
    own = mock.camera_source if name == "camera" else str(mock.tactile_video(name))
    return own, {"capture_factory": mock.capture_factory(name)}


def rig_mounts(config: RigConfig, calibrating: bool = False) -> dict[str, np.ndarray]:
    """Each finger's ``T_fingertip_sensor`` from the rig's ``tactile.mounts`` file, then the sensors' own entries
    (``calibrating``: a mounts file not written yet counts as none, as in :func:`rig_T_hand_cam`)."""
    from tacsplat.sim.hand import FINGER_NAMES

    mounts = {}
    if path := _named_file(config, config.tactile.mounts, calibrating):
        from tacsplat.drivers.press_calibration import load_mounts

        mounts = load_mounts(path, FINGER_NAMES, key="tactile.mounts")
    for s in config.tactile.sensors:
        if s.T_fingertip_sensor is not None:
            mounts[s.finger] = np.asarray(s.T_fingertip_sensor, dtype=np.float64)
    return mounts


def _rows(T: np.ndarray) -> tuple:
    """A [4, 4] matrix as a tuple of rows (what scene.json records)."""
    return tuple(map(tuple, np.asarray(T, dtype=np.float64).tolist()))


def twin_rig(twin, control: GraspControl = TWIN_CONTROL) -> Rig:
    """A :class:`Rig` of an open twin: its hand, pads and free view camera, its clock and ground-truth poses."""
    cfg = twin.config
    return Rig(
        kind="sim",
        hand=twin.hand,
        sensors=list(twin.tactile_sensors),
        camera=twin.view_camera,
        clock=twin,  # sleeping advances its physics
        poses=TwinPoseSource(twin),
        intrinsics=twin.view_camera.intrinsics,
        sensor_model=twin.sensor_model(),
        control=control,
        extra={
            "simulator": twin.simulator,
            "timestep_s": cfg.timestep,
            "contact_timeconst_s": cfg.contact_timeconst,
            "collision": f"CoACD convex decomposition ({len(twin.hulls)} hulls)",
            "tactile_depth": "parallel rays against the exact mesh (trimesh + Embree)",
            "gel_compliance_m": cfg.hand_geometry.gel_compliance,
            "object_bounding_radius_m": twin.object.bounding_radius,
        },
        twin=twin,
    )
