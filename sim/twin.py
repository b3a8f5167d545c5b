"""The MuJoCo twin: the hand on a mocap base, a static glossy object, cameras and tactile pads.

It implements the device Protocols (``Hand``, ``TactileSensor``, ``Camera``)
so acquisition code cannot tell it from the real rig. The object is fixed in
the world with its bounding-sphere centre at the origin (z up); the hand base
is a mocap body placed with :meth:`SimTwin.set_hand_base_pose`. Physics:
``implicitfast`` integration, soft contacts whose ``solref`` time constant is
at least twice the timestep, position servos whose natural frequency times the
timestep stays under ``MAX_SERVO_OMEGA_DT``; :func:`check_physics` rejects
anything stiffer with a :class:`SimulationError`.
"""

from __future__ import annotations

import logging
from contextlib import AbstractContextManager
from dataclasses import dataclass, field

import cv2
import mujoco
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from tacsplat.datasets import SensorModel
from tacsplat.drivers.calibration import HandCalibration
from tacsplat.errors import ConfigError, InvalidInputError, SimulationError
from tacsplat.geometry import check_rigid, invert_pose, make_pose, opencv_to_opengl
from tacsplat.sim import VIEW_ZNEAR_M
from tacsplat.sim.camera import MujocoCamera
from tacsplat.sim.collision import DecompositionConfig, convex_decomposition, hull_offset, is_closed
from tacsplat.sim.hand import (
    FINGER_NAMES,
    HAND_MATERIALS,
    JOINT_LIMITS,
    JOINT_NAMES,
    ActuatorGains,
    HandGeometry,
    HandKinematics,
    hand_body_xml,
    joint_vector,
    nominal_T_hand_cam,
    site_pose,
)
from tacsplat.sim.objects import (
    DEFAULT_OBJECT_RADIUS,
    SimObject,
    checker_texture,
    load_mesh_object,
    make_object,
    texture_problem,
)
from tacsplat.sim.tactile import TactileConfig, TactileDepthRenderer
from tacsplat.types import TactileReading

log = logging.getLogger(__name__)

SENSOR_MODEL_NAME = "sim-digit"  # the scene's name of the twin's tactile pads

MAX_SERVO_OMEGA_DT = 0.5  # servo natural frequency x timestep: the stiffest gains allowed
MIN_TIMECONST_STEPS = 2.0  # contact solref time constant >= this many timesteps
# contact solref damping ratio >= this: 0.01 blows up a grasp on the library bell at 2 ms steps, 0.05 does not
MIN_CONTACT_DAMPRATIO = 0.1

# Warnings MuJoCo counts in data.warning that mean the simulation went wrong.
_FATAL_WARNINGS = [
    getattr(mujoco.mjtWarning, f"mjWARN_{w}") for w in ("BADQACC", "BADQVEL", "BADQPOS", "CONTACTFULL", "CNSTRFULL")
]


def pad_sensor_model(tactile: TactileConfig, scale: float = 1.0) -> SensorModel:
    """The scene's sensor model of pads made as ``tactile`` says, in a scene whose lengths are the twin's divided by
    ``scale``."""
    t = tactile
    return SensorModel(SENSOR_MODEL_NAME, t.width_px, t.height_px, t.pixel_size_m / scale, t.gel_thickness_m / scale)


@dataclass
class TwinConfig:
    """Settings of a twin (defaults: the library teapot, 2 ms steps, 200x200 views)."""

    object: str = "teapot"  # a library name (tacsplat.sim.objects.OBJECT_NAMES); ignored with mesh_path
    mesh_path: str | None = None  # any .obj/.ply/.stl instead of a library object
    object_radius: float = DEFAULT_OBJECT_RADIUS  # bounding-sphere radius in metres
    seed: int = 0  # default seed of the twin's random grasps
    camera_width: int = 200
    camera_height: int = 200
    view_fovy_deg: float = 40.0  # the free view camera
    wrist_fovy_deg: float = 60.0
    timestep: float = 0.002  # s
    contact_timeconst: float = 0.005  # s, solref[0]: contacts settle in about this time (2.5 steps)
    contact_dampratio: float = 1.0  # solref[1], critical damping
    contact_solimp: tuple[float, float, float] = (0.95, 0.99, 0.001)
    gains: ActuatorGains = field(default_factory=ActuatorGains)
    hand_geometry: HandGeometry = field(default_factory=HandGeometry)
    tactile: TactileConfig = field(default_factory=TactileConfig)
    decomposition: DecompositionConfig = field(default_factory=DecompositionConfig)
    background: str = "gradient"  # "gradient" skybox or plain "white"
    texture: str = "none"  # the object's surface (sim.objects.TEXTURES): its one colour, or "checker" (textured)
    # the hand's servos as built (true errors, hidden from the rig): at true joint angle q a servo reads
    # sign * q + offset radians (its motor angle); the nominal hand reads q
    servo_offsets_rad: tuple[float, ...] = (0.0,) * 16
    servo_signs: tuple[int, ...] = (1,) * 16
    hand_calibration: str | None = None  # the hand.json the rig reads the servos with (None: sign 1, offset 0)
    # the wrist camera and the pads as mounted (true errors, hidden from the rig): T_true = T_nominal @ E, E [4, 4]
    # in the camera's (OpenCV) or the sensor's frame; a finger not named is mounted as designed
    hand_eye_error: tuple | None = None
    mount_errors: dict[str, tuple] = field(default_factory=dict)
    # what the rig believes (its calibration files): T_hand_cam (None: the design's, nominal_T_hand_cam) and each
    # finger's T_fingertip_sensor (a finger not named: the identity, the design's)
    T_hand_cam: tuple | None = None
    mounts: dict[str, tuple] = field(default_factory=dict)


def check_physics(config: TwinConfig, model: mujoco.MjModel | None = None) -> None:
    """Reject settings that make the simulation stiff or unstable, naming the setting at fault."""
    dt = config.timestep
    if not (np.isfinite(dt) and 0 < dt <= 0.01):
        raise SimulationError(f"timestep: {dt} s is outside (0, 0.01] s")
    if not (np.isfinite(config.contact_timeconst) and config.contact_timeconst >= MIN_TIMECONST_STEPS * dt):
        raise SimulationError(
            f"contact_timeconst: {config.contact_timeconst} s is stiffer than {MIN_TIMECONST_STEPS:g} timesteps "
            f"({MIN_TIMECONST_STEPS * dt:g} s); raise it or lower the timestep"
        )
    if not (np.isfinite(config.contact_dampratio) and config.contact_dampratio >= MIN_CONTACT_DAMPRATIO):
        raise SimulationError(
            f"contact_dampratio: must be at least {MIN_CONTACT_DAMPRATIO:g} (1: critically damped), "
            f"got {config.contact_dampratio}"
        )
    solimp = np.asarray(config.contact_solimp, dtype=np.float64)
    if not (solimp.shape == (3,) and 0 < solimp[0] < 1 and 0 < solimp[1] < 1 and 0 <= solimp[2] < np.inf):
        raise SimulationError(
            f"contact_solimp: must be (dmin, dmax, width) with dmin and dmax in (0, 1) and width >= 0 m, "
            f"got {tuple(config.contact_solimp)}"
        )
    mass = config.hand_geometry.link_mass
    if not (np.isfinite(mass) and mass > 0):
        raise SimulationError(f"hand_geometry.link_mass: must be a finite positive number of kg, got {mass}")
    g = config.gains
    for key in ("kp", "kv", "damping", "armature", "force_limit"):
        value = getattr(g, key)
        if not (np.isfinite(value) and value >= 0) or (key in ("kp", "force_limit") and value == 0):
            raise SimulationError(f"gains.{key}: must be a finite positive number, got {value}")
    if model is not None:
        omega_dt = servo_omega_dt(model, g.kp)
        if omega_dt > MAX_SERVO_OMEGA_DT:
            kp_max = g.kp * (MAX_SERVO_OMEGA_DT / omega_dt) ** 2
            raise SimulationError(
                f"gains.kp: {g.kp} N m/rad gives a servo natural frequency x timestep of {omega_dt:.3f} "
                f"> {MAX_SERVO_OMEGA_DT}; use kp <= {kp_max:.3g} or a smaller timestep"
            )


def servo_omega_dt(model: mujoco.MjModel, kp: float) -> float:
    """Largest natural frequency of the position servos (sqrt(kp / inertia)) times the timestep."""
    dofs = [model.jnt_dofadr[model.joint(n).id] for n in JOINT_NAMES]
    inv_inertia = model.dof_invweight0[dofs].max()
    return float(np.sqrt(kp * inv_inertia) * model.opt.timestep)


def _mesh_asset(name: str, mesh: trimesh.Trimesh) -> str:
    verts = " ".join(f"{v:.7g}" for v in np.asarray(mesh.vertices).ravel())
    faces = " ".join(str(int(i)) for i in np.asarray(mesh.faces).ravel())
    return f'<mesh name="{name}" vertex="{verts}" face="{faces}"/>'


CHECKER_FILE = "object_checker.png"  # the "checker" texture's file among the model's assets


def twin_assets(config: TwinConfig, obj: SimObject) -> dict[str, bytes]:
    """The files :func:`build_twin_mjcf`'s model refers to, by name (its texture's image, if it has one)."""
    if config.texture != "checker":
        return {}
    return {CHECKER_FILE: cv2.imencode(".png", checker_texture(obj.material.rgba)[..., ::-1])[1].tobytes()}


def build_twin_mjcf(config: TwinConfig, obj: SimObject, hulls: list[trimesh.Trimesh]) -> str:
    """The full scene: lights, background, the static object (visual mesh + convex hulls), cameras, hand (its
    physics settings checked by :func:`check_physics` first, as :class:`SimTwin` does)."""
    body, actuators = hand_body_xml(config.hand_geometry, config.gains, pos=(0, 0, 1.0))
    m = obj.material
    solref = f"{config.contact_timeconst:.6g} {config.contact_dampratio:.6g}"
    solimp = " ".join(f"{v:.6g}" for v in config.contact_solimp)
    if config.background == "gradient":
        sky = '<texture name="sky" type="skybox" builtin="gradient" rgb1="0.93 0.94 0.97" rgb2="0.45 0.5 0.6" width="256" height="256"/>'
    elif config.background == "white":
        sky = '<texture name="sky" type="skybox" builtin="flat" rgb1="1 1 1" rgb2="1 1 1" width="16" height="16"/>'
    else:
        raise ConfigError("background", f"must be 'gradient' or 'white', got {config.background!r}")
    if problem := texture_problem(config.texture):
        raise ConfigError("texture", problem)
    textured = config.texture == "checker"  # a cube map: MuJoCo projects it onto a mesh without texture coordinates
    texture = f'<texture name="object" type="cube" file="{CHECKER_FILE}"/>' if textured else ""
    color = "1 1 1 1" if textured else " ".join(f"{c:.4g}" for c in m.rgba)  # the texture holds the colour
    hull_assets = "\n".join(_mesh_asset(f"hull{i}", h) for i, h in enumerate(hulls))
    hull_geoms = "\n".join(
        f'<geom name="object_hull{i}" type="mesh" mesh="hull{i}" group="3" contype="0" conaffinity="1"/>'
        for i in range(len(hulls))
    )
    size = max(config.camera_width, config.camera_height, 256)
    return f"""<mujoco model="tacsplat_twin">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{config.timestep:.6g}" integrator="implicitfast" gravity="0 0 -9.81"/>
  <statistic extent="1" center="0 0 0"/>
  <visual>
    <global offwidth="{size}" offheight="{size}"/>
    <map znear="{VIEW_ZNEAR_M:g}" zfar="20"/>
    <headlight ambient="0.12 0.12 0.12" diffuse="0.25 0.25 0.25" specular="0.3 0.3 0.3"/>
    <quality shadowsize="0"/>
  </visual>
  <default>
    <geom solref="{solref}" solimp="{solimp}" friction="0.8 0.01 0.001"/>
  </default>
  <asset>
    {sky}
    {HAND_MATERIALS}
    {texture}
    <material name="object" rgba="{color}" specular="{m.specular:.4g}" shininess="{m.shininess:.4g}"
              reflectance="{m.reflectance:.4g}"{' texture="object"' if textured else ""}/>
    {_mesh_asset("object_visual", obj.mesh)}
{hull_assets}
  </asset>
  <worldbody>
    <light name="key" directional="true" dir="-0.5 -0.4 -0.8" diffuse="0.6 0.6 0.6" specular="0.9 0.9 0.9" castshadow="false"/>
    <light name="fill" directional="true" dir="0.7 -0.3 -0.4" diffuse="0.35 0.35 0.4" specular="0.6 0.6 0.6" castshadow="false"/>
    <light name="rim" directional="true" dir="0.1 0.8 -0.3" diffuse="0.3 0.3 0.3" specular="0.7 0.7 0.7" castshadow="false"/>
    <light name="under" directional="true" dir="0 0 1" diffuse="0.15 0.15 0.15" specular="0.2 0.2 0.2" castshadow="false"/>
    <camera name="view" pos="0 -0.5 0.2" xyaxes="1 0 0 0 0.37 0.93" fovy="{config.view_fovy_deg:.6g}"/>
    <body name="object">
      <geom name="object_visual" type="mesh" mesh="object_visual" material="object" group="0" contype="0" conaffinity="0"/>
{hull_geoms}
    </body>
{body}
  </worldbody>
  <actuator>
{actuators}
  </actuator>
</mujoco>
"""


class SimHand(AbstractContextManager):
    """The twin's hand (implements ``Hand``): position servos on the sixteen joints.

    Its servos are the real hand's as the twin's config builds them (``servo_signs``, ``servo_offsets_rad``: motor
    angle ``sign * q + offset`` at true joint angle ``q``), read and commanded through the rig's hand calibration
    as the real driver does; :meth:`fingertip_poses` is the model's forward kinematics at the joints so read.
    """

    def __init__(self, twin: "SimTwin"):
        self._twin = twin
        cfg = twin.config
        self._servo_signs = np.asarray(cfg.servo_signs, dtype=np.float64)
        self._servo_offsets = np.asarray(cfg.servo_offsets_rad, dtype=np.float64)
        if self._servo_signs.shape != (16,) or self._servo_offsets.shape != (16,):
            raise ConfigError("servo_signs", "the twin's servo signs and offsets need 16 values each")
        if cfg.hand_calibration:
            self.calibration = HandCalibration.load(cfg.hand_calibration, JOINT_NAMES)
        else:
            self.calibration = HandCalibration.identity(JOINT_NAMES)
        model = twin.model
        self._qadr = np.array([model.jnt_qposadr[model.joint(n).id] for n in JOINT_NAMES])
        self._dofadr = np.array([model.jnt_dofadr[model.joint(n).id] for n in JOINT_NAMES])
        self._act = np.array([model.actuator(n).id for n in JOINT_NAMES])
        self._kinematics = HandKinematics(twin.config.hand_geometry)
        self.joint_names, self.link_names = list(JOINT_NAMES), list(self._kinematics.link_names)

    effort_unit = "N m"  # the position servos' torque

    @property
    def joint_limits(self) -> np.ndarray:
        return JOINT_LIMITS.copy()

    def read_motor_angles(self) -> np.ndarray:
        """[16] the servos' motor angles in radians (before the hand calibration)."""
        return self._servo_signs * self._twin.data.qpos[self._qadr] + self._servo_offsets

    def read_joint_positions(self) -> np.ndarray:
        """[16] radians, as the hand calibration reads the servos."""
        return self.calibration.joint_angles(self.read_motor_angles())

    def read_joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        """``(positions [16] radians, actuator torques [16] N m)``."""
        return self.read_joint_positions(), self._twin.data.actuator_force[self._act].copy()

    def read_joint_targets(self) -> np.ndarray:
        return self.calibration.joint_angles(self._servo_signs * self._twin.data.ctrl[self._act] + self._servo_offsets)

    def command_joint_positions(self, q: np.ndarray) -> None:
        q = joint_vector(q, "command_joint_positions")
        clamped = np.clip(q, JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1])
        if names := [JOINT_NAMES[i] for i in np.flatnonzero(np.abs(clamped - q) > 1e-9)]:
            log.info("joint command clamped to the limits on %s", ", ".join(names))
        true = self._servo_signs * (self.calibration.motor_angles(clamped) - self._servo_offsets)
        self._twin.data.ctrl[self._act] = np.clip(true, JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1])  # the hard stops

    def dof_of(self, joint: int) -> int:
        """The MuJoCo degree of freedom of joint ``joint`` (an index into ``data.qvel``, ``data.qfrc_applied``)."""
        return int(self._dofadr[joint])

    def set_torque(self, on: bool) -> None:
        """Torque on (the position servos act) or off (they exert nothing: the joints move freely)."""
        flag = mujoco.mjtDisableBit.mjDSBL_ACTUATION
        opt = self._twin.model.opt
        opt.disableflags = opt.disableflags & ~flag if on else opt.disableflags | flag

    def set_joint_positions(self, q: np.ndarray) -> None:
        """Teleport the joints (and their servo targets) to the command ``q``, at rest: a simulator-only reset."""
        self.command_joint_positions(q)
        self._twin.data.qpos[self._qadr] = self._twin.data.ctrl[self._act]
        self._twin.data.qvel[self._dofadr] = 0.0
        self._twin.forward()

    def fingertip_poses(self) -> dict[str, np.ndarray]:
        """``{finger: T_hand_sensor}`` by the model's forward kinematics at the joints as read (as the real driver)."""
        return self._kinematics.fingertip_poses(self.read_joint_positions())

    def link_boxes(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The hand's solid shape at joint positions ``q`` [16]: boxes [L, 4, 4] in the hand frame, [L, 3]."""
        return self._kinematics.link_boxes(q)

    def close(self) -> None:
        """Hold the current joint positions (the twin's equivalent of a safe stop): the servo targets are the true
        joint angles, not the reading through the rig's calibration."""
        self._twin.data.ctrl[self._act] = self._twin.data.qpos[self._qadr].clip(JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1])

    def __exit__(self, *exc) -> None:
        self.close()


class SimTactileSensor:
    """One fingertip pad of the twin (implements ``TactileSensor``)."""

    def __init__(self, twin: "SimTwin", finger: str):
        self._twin = twin
        self.name = finger
        self._site = twin.model.site(f"{finger}_tactile").id
        self.config = twin.config.tactile
        self.mount_error = _pose_or_identity(twin.config.mount_errors.get(finger), f"mount_errors.{finger}")
        self.T_fingertip_sensor = _pose_or_identity(twin.config.mounts.get(finger), f"mounts.{finger}")  # the rig's

    def T_world_sensor(self) -> np.ndarray:
        """The pad's true pose: its fingertip's as simulated, off by the hidden mounting error."""
        return site_pose(self._twin.data, self._site) @ self.mount_error

    def read(self) -> TactileReading:
        """The indentation map (at the pad's true pose), its pose in the hand frame as the rig computes it (the
        hand's forward kinematics at its joints as read, then the rig's mounting), the simulated time."""
        depth = self._twin.tactile_renderer.render(self.T_world_sensor())
        T_hand_sensor = self._twin.hand.fingertip_poses()[self.name] @ self.T_fingertip_sensor
        return TactileReading(depth, self.config.pixel_size_m, T_hand_sensor, "hand", float(self._twin.data.time))


class SimTwin(AbstractContextManager):
    """The MuJoCo twin of the rig; a context manager owning the MjModel, MjData and renderers.

    ``peak_penetration_m`` is the deepest hand-object penetration of the collision
    geometry seen after any :meth:`sleep` since the last :meth:`reset` (the error
    of MuJoCo's soft contacts, ideally 0).
    """

    simulator = f"mujoco {mujoco.__version__}"  # for the provenance of scenes

    def __init__(self, config: TwinConfig = TwinConfig()):
        self.config = config
        if config.mesh_path:
            self.object = load_mesh_object(config.mesh_path, config.object_radius)
        else:
            self.object = make_object(config.object, config.object_radius)
        check_physics(config)
        self.hulls = convex_decomposition(self.object.mesh, config.decomposition)
        compliance = config.hand_geometry.gel_compliance
        if config.mesh_path and (offset := hull_offset(self.object.mesh, self.hulls)) > compliance:
            log.warning(
                "%s: its collision hulls stand %.2f mm off its surface, more than the %.2f mm the pads' gel gives: "
                "the fingers will stop on the hulls before their gel reaches the mesh, and grasps read no touch. %s",
                config.mesh_path,
                1e3 * offset,
                1e3 * compliance,
                "The mesh is closed: its convex decomposition (CoACD) is this loose around it"
                if is_closed(self.object.mesh)
                else "CoACD remeshes, coarsely, a mesh that is not closed with consistently wound faces: close its "
                "holes and orient its faces to grasp it",
            )
        xml = build_twin_mjcf(config, self.object, self.hulls)
        try:
            self.model = mujoco.MjModel.from_xml_string(xml, assets=twin_assets(config, self.object))
        except ValueError as exc:
            if not config.mesh_path:
                raise  # not a mesh of the user's: the fault is in the twin's settings or its code
            why = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
            raise ConfigError("mesh", f"{config.mesh_path}: MuJoCo cannot simulate this mesh ({why})") from exc
        check_physics(config, self.model)
        self.data = mujoco.MjData(self.model)
        self._mocap = self.model.body("hand").mocapid[0]
        self._view_cam = self.model.camera("view").id
        self.forward()
        self.object_mesh = self.object.mesh.copy()  # world frame: the object sits at the origin
        self.tactile_renderer = TactileDepthRenderer(self.object_mesh, config.tactile)
        self.hand = SimHand(self)
        self.hand.set_joint_positions(np.zeros(16))
        self.tactile_sensors = [SimTactileSensor(self, f) for f in FINGER_NAMES]
        w, h = config.camera_width, config.camera_height
        nominal = nominal_T_hand_cam(config.hand_geometry)
        self.T_hand_cam = nominal if config.T_hand_cam is None else check_rigid(config.T_hand_cam, "T_hand_cam")
        wrist = self.model.camera("wrist").id  # mounted on the hand, off its design by the hidden hand-eye error
        self._place_camera(wrist, nominal @ _pose_or_identity(config.hand_eye_error, "hand_eye_error"))
        self.model.cam_fovy[self._view_cam] = config.view_fovy_deg
        self.model.cam_fovy[wrist] = config.wrist_fovy_deg
        self.wrist_camera = MujocoCamera(self, "wrist", w, h, visible_groups=(0, 1, 2))
        self.view_camera = MujocoCamera(self, "view", w, h, visible_groups=(0, 2))  # hand hidden
        root = self.model.body_rootid[self.model.geom_bodyid]  # each geom's body's child of the world
        self._geom_is_hand = root == self.model.body("hand").id
        self._geom_is_object = root == self.model.body("object").id
        self.peak_penetration_m = 0.0
        self._clock_target = 0.0  # the time the clock owes: the sum of the sleeps since the start or reset

    def sensor_model(self, scale: float = 1.0) -> SensorModel:
        """The scene's sensor model of the pads, in a scene whose lengths are the twin's divided by ``scale``."""
        return pad_sensor_model(self.config.tactile, scale)

    # --- state -------------------------------------------------------------------------------
    def forward(self) -> None:
        """Recompute positions, cameras and contacts from the current state."""
        mujoco.mj_forward(self.model, self.data)

    def reset(self) -> None:
        """Back to the model's initial state (time 0, joints, servo targets and hand base as the model puts them),
        positions recomputed; ``peak_penetration_m`` starts again from 0, and the clock owes nothing."""
        mujoco.mj_resetData(self.model, self.data)
        self.forward()
        self.peak_penetration_m = 0.0
        self._clock_target = 0.0

    def sleep(self, seconds: float) -> None:
        """Advance the physics by ``seconds`` of simulated time (the twin's clock), in whole timesteps: the clock
        keeps the sleeps' sum and steps to the nearest step of it, so sleeps that are not whole steps add up (a
        sleep under half a step still counts towards the next)."""
        if not (np.isfinite(seconds) and seconds >= 0):
            raise InvalidInputError(f"sleep: seconds must be finite and non-negative, got {seconds}")
        dt = self.model.opt.timestep
        # the target is within half a step of the time after a sleep; further behind, the data was stepped some
        # other way, and the target catches up
        self._clock_target = max(self._clock_target, self.data.time - dt / 2) + seconds
        for _ in range(max(0, round((self._clock_target - self.data.time) / dt))):
            mujoco.mj_step(self.model, self.data)
        self.forward()
        self.check_stable()
        self.peak_penetration_m = max(self.peak_penetration_m, self.max_penetration())

    def check_stable(self) -> None:
        """Raise :class:`SimulationError` if MuJoCo flagged a problem or the state is not finite."""
        raised = {mujoco.mjtWarning(w).name: n for w in _FATAL_WARNINGS if (n := int(self.data.warning[w].number))}
        if raised or not (np.all(np.isfinite(self.data.qpos)) and np.all(np.isfinite(self.data.qvel))):
            raise SimulationError(
                f"simulation unstable at t={self.data.time:.4f} s: warnings {raised or 'none'}, "
                f"finite state {bool(np.all(np.isfinite(self.data.qpos)))}"
            )

    @property
    def time(self) -> float:
        return float(self.data.time)

    # --- hand base -----------------------------------------------------------------------------
    def T_world_hand(self) -> np.ndarray:
        """Ground-truth pose [4, 4] of the hand base."""
        R = Rotation.from_quat(self.data.mocap_quat[self._mocap], scalar_first=True).as_matrix()  # MuJoCo's w, x, y, z
        return make_pose(R, self.data.mocap_pos[self._mocap])

    def set_hand_base_pose(self, T_world_hand: np.ndarray) -> None:
        """Place the hand base (mocap) at ``T_world_hand`` [4, 4]."""
        T = check_rigid(T_world_hand, "T_world_hand")
        self.data.mocap_pos[self._mocap], self.data.mocap_quat[self._mocap] = _pos_quat(T)
        self.forward()

    def _place_camera(self, cam: int, T_parent_cam: np.ndarray) -> None:
        """Place camera ``cam`` at ``T_parent_cam`` [4, 4] (OpenCV axes) in its body's frame (the world's, or the
        hand's for the wrist camera)."""
        self.model.cam_pos[cam], self.model.cam_quat[cam] = _pos_quat(opencv_to_opengl(T_parent_cam))
        self.forward()

    def hand_pose_from_wrist_camera(self) -> np.ndarray:
        """``T_world_hand`` as the rig computes it: the wrist camera's pose in the world (what board PnP measures)
        through the rig's ``T_hand_cam``; off the truth by the hidden hand-eye error."""
        return self.wrist_camera.pose() @ invert_pose(self.T_hand_cam)

    # --- free view camera ----------------------------------------------------------------------
    def move_camera(self, T_world_cam: np.ndarray) -> None:
        """Place the view camera at the OpenCV camera-to-world pose ``T_world_cam`` [4, 4]."""
        self._place_camera(self._view_cam, check_rigid(T_world_cam, "T_world_cam"))

    def camera_pose(self) -> np.ndarray:
        """OpenCV camera-to-world pose [4, 4] of the view camera."""
        return self.view_camera.pose()

    # --- contacts ------------------------------------------------------------------------------
    def hand_object_contacts(self) -> list[tuple[str, float]]:
        """``(hand geom name, signed distance)`` of each hand-object contact (negative = penetration)."""
        out = []
        for c in self.data.contact[: self.data.ncon]:
            g1, g2 = (c.geom2, c.geom1) if self._geom_is_object[c.geom1] else (c.geom1, c.geom2)
            if self._geom_is_hand[g1] and self._geom_is_object[g2]:
                out.append((self.model.geom(g1).name, float(c.dist)))
        return out

    def max_penetration(self) -> float:
        """Deepest hand-object contact penetration in metres (0 when nothing penetrates)."""
        g = self.data.contact.geom  # [ncon, 2]
        is_hand, is_object = self._geom_is_hand, self._geom_is_object
        pair = (is_hand[g[:, 0]] & is_object[g[:, 1]]) | (is_object[g[:, 0]] & is_hand[g[:, 1]])
        return float(max(0.0, -self.data.contact.dist[pair].min(initial=0.0)))

    # --- lifetime ------------------------------------------------------------------------------
    def close(self) -> None:
        self.wrist_camera.close()
        self.view_camera.close()

    def __exit__(self, *exc) -> None:
        self.close()


def _pose_or_identity(T, key: str) -> np.ndarray:
    """``T`` as a checked rigid [4, 4] (an error naming ``key``), or the identity when None."""
    return np.eye(4) if T is None else check_rigid(T, key)


def _pos_quat(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo's position and quaternion (w, x, y, z), w >= 0, of a pose [4, 4]."""
    return T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat(canonical=True, scalar_first=True)
