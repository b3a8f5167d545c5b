"""The one Allegro-style hand model, generated as MJCF by code, and its forward kinematics.

Hand frame: origin at the centre of the palm surface, z along the palm normal
(the side the object is on), x towards the three fingers (index, middle, ring,
index on +y), the thumb at the heel of the palm opposing them (a claw layout).
Each finger has four joints: 0 abduction (about the palm normal), 1-3 flexion
(positive curls the finger towards +z). Link lengths and flexion limits are the
Allegro hand's; the thumb's first joint is an abduction like the fingers' (the
Allegro thumb rotates about its own axis instead), with the fingers' limits.

At each fingertip a tactile pad (DIGIT/GelSight-like gel) carries a site
``<finger>_tactile`` whose frame is the sensor frame of DESIGN.md: origin at the
centre of the undeformed gel surface, z along the gel's outward normal, x along
image columns (along the finger), y along image rows (across it).

This module imports MuJoCo only inside functions, so the real hand driver can
import it at module level without loading the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tacsplat.errors import InvalidInputError
from tacsplat.geometry import make_pose

FINGER_NAMES = ["index", "middle", "ring", "thumb"]
JOINT_NAMES = [f"{finger}_{i}" for finger in FINGER_NAMES for i in range(4)]

# Allegro hand joint limits (radians): abduction, then three flexions.
_FINGER_LIMITS = [(-0.47, 0.47), (-0.196, 1.61), (-0.174, 1.709), (-0.227, 1.618)]
_THUMB_LIMITS = [(-0.47, 0.47), (-0.105, 1.163), (-0.189, 1.644), (-0.162, 1.719)]
JOINT_LIMITS = np.array(_FINGER_LIMITS * 3 + _THUMB_LIMITS, dtype=np.float64)  # [16, 2]


@dataclass(frozen=True)
class HandGeometry:
    """Dimensions of the hand in metres (defaults: Allegro link lengths, DIGIT-like pads)."""

    palm_half_length: float = 0.055  # knuckles at +-this along x
    palm_thickness: float = 0.02
    finger_spacing: float = 0.03  # y offset between neighbouring fingers
    link_half_width: float = 0.012
    link_half_thickness: float = 0.01
    knuckle_length: float = 0.016  # abduction joint -> first flexion joint
    proximal_length: float = 0.054
    middle_length: float = 0.0384
    thumb_proximal_length: float = 0.0514
    thumb_middle_length: float = 0.0423
    distal_length: float = 0.045
    pad_length: float = 0.024  # along the finger = image columns (160 px of 0.15 mm)
    pad_width: float = 0.0192  # across the finger = image rows (128 px of 0.15 mm)
    pad_centre_from_joint: float = 0.027  # along the distal link
    gel_thickness: float = 0.002
    # The rigid collision face of the pad sits this far behind the gel surface:
    # the object may sink this deep into the soft gel before the contact pushes back.
    gel_compliance: float = 0.001
    link_mass: float = 0.03


@dataclass(frozen=True)
class ActuatorGains:
    """Position actuators and joint properties (defaults are stable at a 2 ms timestep)."""

    kp: float = 2.0  # N m / rad
    kv: float = 0.05  # N m s / rad
    damping: float = 0.05  # joint damping, N m s / rad
    armature: float = 0.002  # kg m^2, rotor inertia reflected at the joint
    force_limit: float = 1.0  # N m


def _fmt(*values: float) -> str:
    return " ".join(f"{v:.6g}" for v in values)


def _finger_xml(i: int, geom: HandGeometry, gains: ActuatorGains) -> str:
    """Body tree of finger ``i`` (of FINGER_NAMES): its base on the palm, then its links from the knuckle (in the
    finger's own frame, x along it)."""
    g = geom
    finger, limits = FINGER_NAMES[i], JOINT_LIMITS[4 * i : 4 * i + 4]
    thumb = finger == "thumb"
    if thumb:  # at the heel of the palm, turned to face the fingers
        base_pos, base_quat = (-g.palm_half_length, 0.0, -g.link_half_thickness), (0, 0, 0, 1)
    else:  # index +y, middle 0, ring -y
        base_pos, base_quat = (g.palm_half_length, g.finger_spacing * (1 - i), -g.link_half_thickness), (1, 0, 0, 0)
    prox = g.thumb_proximal_length if thumb else g.proximal_length
    mid = g.thumb_middle_length if thumb else g.middle_length
    w, t = g.link_half_width, g.link_half_thickness
    joint = 'limited="true" damping="{d}" armature="{a}"'.format(d=_fmt(gains.damping), a=_fmt(gains.armature))
    link = 'type="box" group="1" contype="1" conaffinity="0" material="hand" mass="{m}"'.format(m=_fmt(g.link_mass))

    def box(name, length):
        return f'<geom name="{name}" {link} pos="{_fmt(length / 2, 0, 0)}" size="{_fmt(length / 2, w, t)}"/>'

    pad_z = t + g.gel_thickness  # gel surface height above the link axis
    solid_half = (g.gel_thickness - g.gel_compliance) / 2
    return f"""
      <body name="{finger}_base" pos="{_fmt(*base_pos)}" quat="{_fmt(*base_quat)}" gravcomp="1">
        <joint name="{finger}_0" axis="0 0 1" range="{_fmt(*limits[0])}" {joint}/>
        {box(f"{finger}_knuckle", g.knuckle_length)}
        <body name="{finger}_proximal" pos="{_fmt(g.knuckle_length, 0, 0)}" gravcomp="1">
          <joint name="{finger}_1" axis="0 -1 0" range="{_fmt(*limits[1])}" {joint}/>
          {box(f"{finger}_proximal", prox)}
          <body name="{finger}_middle" pos="{_fmt(prox, 0, 0)}" gravcomp="1">
            <joint name="{finger}_2" axis="0 -1 0" range="{_fmt(*limits[2])}" {joint}/>
            {box(f"{finger}_middle", mid)}
            <body name="{finger}_distal" pos="{_fmt(mid, 0, 0)}" gravcomp="1">
              <joint name="{finger}_3" axis="0 -1 0" range="{_fmt(*limits[3])}" {joint}/>
              {box(f"{finger}_distal", g.distal_length)}
              <geom name="{finger}_gel" type="box" group="1" contype="0" conaffinity="0" mass="0"
                    material="gel" pos="{_fmt(g.pad_centre_from_joint, 0, t + g.gel_thickness / 2)}"
                    size="{_fmt(g.pad_length / 2, g.pad_width / 2, g.gel_thickness / 2)}"/>
              <geom name="{finger}_pad" type="box" group="3" contype="1" conaffinity="0" mass="0"
                    pos="{_fmt(g.pad_centre_from_joint, 0, t + solid_half)}"
                    size="{_fmt(g.pad_length / 2, g.pad_width / 2, solid_half)}"/>
              <site name="{finger}_tactile" pos="{_fmt(g.pad_centre_from_joint, 0, pad_z)}"
                    size="0.002" group="4"/>
            </body>
          </body>
        </body>
      </body>"""


def nominal_T_hand_cam(geom: HandGeometry = HandGeometry()) -> np.ndarray:
    """The wrist camera's designed pose [4, 4] in the hand frame (OpenCV axes): the rig's hand-eye transform
    before any calibration. The camera sits at the heel of the palm, looking along the palm normal tilted towards
    the fingers."""
    pos = np.array([-geom.palm_half_length - 0.02, 0.0, 0.05])
    forward = np.array([0.35, 0.0, 1.0])
    forward /= np.linalg.norm(forward)
    x_axis = np.array([0.0, -1.0, 0.0])  # image right
    y_axis = np.cross(-forward, x_axis)  # MuJoCo's image up (its cameras look along -z: z = -forward)
    return make_pose(np.column_stack([x_axis, -y_axis, -np.cross(x_axis, y_axis)]), pos)  # OpenGL -> OpenCV: y, z flip


def hand_body_xml(geom: HandGeometry, gains: ActuatorGains, pos=(0, 0, 0)) -> tuple[str, str]:
    """``(body_xml, actuator_xml)``: the mocap hand body tree and its 16 position actuators."""
    g = geom
    T_cam = nominal_T_hand_cam(g)  # MuJoCo's x and y axes: OpenCV's x and -y
    body = f"""
    <body name="hand" mocap="true" pos="{_fmt(*pos)}" quat="1 0 0 0">
      <geom name="palm" type="box" group="1" contype="1" conaffinity="0" material="hand"
            pos="{_fmt(0, 0, -g.palm_thickness / 2)}"
            size="{_fmt(g.palm_half_length, g.finger_spacing * 1.5, g.palm_thickness / 2)}"/>
      <camera name="wrist" pos="{_fmt(*T_cam[:3, 3])}" xyaxes="{_fmt(*T_cam[:3, 0], *-T_cam[:3, 1])}" fovy="60"/>
      {"".join(_finger_xml(i, g, gains) for i in range(len(FINGER_NAMES)))}
    </body>"""
    actuators = "\n".join(
        f'<position name="{name}" joint="{name}" kp="{_fmt(gains.kp)}" kv="{_fmt(gains.kv)}" '
        f'ctrlrange="{_fmt(*JOINT_LIMITS[k])}" forcerange="{_fmt(-gains.force_limit, gains.force_limit)}"/>'
        for k, name in enumerate(JOINT_NAMES)
    )
    return body, actuators


HAND_MATERIALS = """
    <material name="hand" rgba="0.15 0.15 0.17 1" specular="0.3" shininess="0.3"/>
    <material name="gel" rgba="0.75 0.8 0.85 1" specular="0.5" shininess="0.6"/>"""


def build_hand_mjcf(geom: HandGeometry = HandGeometry(), gains: ActuatorGains = ActuatorGains()) -> str:
    """The Allegro-style hand alone as a complete MJCF document (hand base = world origin)."""
    body, actuators = hand_body_xml(geom, gains)
    return f"""<mujoco model="tacsplat_hand">
  <compiler angle="radian" autolimits="true"/>
  <option integrator="implicitfast" gravity="0 0 -9.81"/>
  <asset>{HAND_MATERIALS}
  </asset>
  <worldbody>{body}
  </worldbody>
  <actuator>
{actuators}
  </actuator>
</mujoco>
"""


def import_mujoco() -> None:
    """Import MuJoCo, as :class:`HandKinematics` does when made, for a module outside tacsplat.sim (which may not
    import it): :func:`~tacsplat.acquisition.devices.import_device_modules`, which holds the ending signals."""
    import mujoco  # noqa: F401


def site_pose(data, site_id: int) -> np.ndarray:
    """World pose [4, 4] of a MuJoCo site from ``data``."""
    return make_pose(np.reshape(data.site_xmat[site_id], (3, 3)), data.site_xpos[site_id])


def joint_vector(q, what: str) -> np.ndarray:
    """``q`` as [16] float64 radians; an InvalidInputError naming ``what`` unless it is 16 finite numbers."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape != (16,):
        raise InvalidInputError(f"{what}: q must have shape (16,), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise InvalidInputError(f"{what}: q contains NaN or infinite values")
    return q


class HandKinematics:
    """Forward kinematics of the hand model: fingertip sensor frames in the hand frame."""

    finger_names = list(FINGER_NAMES)
    joint_names = list(JOINT_NAMES)

    def __init__(self, geom: HandGeometry = HandGeometry()):
        import mujoco

        model = mujoco.MjModel.from_xml_string(build_hand_mjcf(geom))
        self._mujoco, self._model, self._data = mujoco, model, mujoco.MjData(model)
        self._qadr = np.array([model.joint(n).qposadr[0] for n in JOINT_NAMES])
        self._sites = {f: model.site(f"{f}_tactile").id for f in FINGER_NAMES}
        self._boxes = np.flatnonzero((model.geom_type == mujoco.mjtGeom.mjGEOM_BOX) & (model.geom_group == 1))
        self.link_names = [model.geom(g).name for g in self._boxes]  # palm, then each finger's links and gel
        self._half_extents = model.geom_size[self._boxes].copy()  # [L, 3]

    @property
    def joint_limits(self) -> np.ndarray:
        """[16, 2] lower and upper limits in radians."""
        return JOINT_LIMITS.copy()

    def _at(self, q: np.ndarray, what: str) -> None:
        self._data.qpos[self._qadr] = joint_vector(q, f"HandKinematics.{what}")
        self._mujoco.mj_kinematics(self._model, self._data)

    def fingertip_poses(self, q: np.ndarray) -> dict[str, np.ndarray]:
        """``{finger: T_hand_sensor [4, 4]}`` for joint positions ``q`` [16] radians."""
        self._at(q, "fingertip_poses")
        return {f: site_pose(self._data, sid) for f, sid in self._sites.items()}

    def link_boxes(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The hand's solid shape at joint positions ``q`` [16]: ``(T_hand_box [L, 4, 4], half_extents [L, 3])``,
        one box per :attr:`link_names` (the palm, every link, and each gel up to its undeformed surface)."""
        self._at(q, "link_boxes")
        T = np.tile(np.eye(4), (len(self._boxes), 1, 1))
        T[:, :3, :3] = self._data.geom_xmat[self._boxes].reshape(-1, 3, 3)
        T[:, :3, 3] = self._data.geom_xpos[self._boxes]
        return T, self._half_extents.copy()
