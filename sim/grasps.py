"""Simulated grasps: approach, preshape, tap until the pads touch or the fingers stall, read, open, retreat.

Finger motion goes through the twin's Protocol-level operations (hand
commands, the twin's clock, tactile reads). Simulator-only help: placing the
hand base (mocap), choosing each finger's preshape against the known mesh and
the collision model, and seeing pad contacts in MuJoCo's contact list. The
acquisition logger runs the same preshape and tap through the Protocols
(:mod:`tacsplat.acquisition.sim_capture`), detecting contact by stall.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from tacsplat.errors import ConfigError
from tacsplat.geometry import make_pose, transform_points
from tacsplat.sim.hand import FINGER_NAMES, JOINT_LIMITS, site_pose
from tacsplat.sim.twin import SimTwin, world_readings
from tacsplat.types import TactileReading

log = logging.getLogger(__name__)

# Stated bounds on the penetration of hand and object collision geometry in a grasp
# (soft contacts, solref time constant 5 ms at 2 ms steps). Measured: 0.1-0.3 mm at the
# default gains and tap speed; 1.2 mm at the impact of a 4 rad/s tap with the stiffest
# gains check_physics allows.
PENETRATION_BOUND_M = 0.0015  # any allowed gains and tap speeds up to 4 rad/s (tested)
DEFAULT_PENETRATION_BOUND_M = 0.0005  # default gains and tap speed (tested)


@dataclass(frozen=True)
class GraspConfig:
    """How a simulated grasp is made (times are simulated seconds, angles radians)."""

    palm_gap_m: float = 0.012  # palm surface to the nearest object point under the hand
    min_approach_elevation_deg: float = -30.0  # approach directions from above this elevation
    preshape_grid: int = 13  # samples per flexion joint when searching each finger's pre-touch pose
    preshape_abduction: tuple[float, ...] = (-0.3, 0.0, 0.3)  # abduction angles searched, radians
    max_pretouch_gap_m: float = 0.03  # the pad stops at most this far in front of the surface
    min_alignment_cos: float = 0.85  # pad normal against the surface normal, at least this cosine
    tap_speed: float = 0.6  # rad/s along the tap direction of the flexion joints
    max_tap_rad: float = 0.8  # give up a tap after this much motion
    press_rad: float = 0.04  # keep pushing this much past the first pad contact
    control_period_s: float = 0.01  # how often the tapping loop checks the pads
    stall_error_rad: float = 0.2  # a finger whose joints lag their targets by this much has stalled
    settle_s: float = 0.15  # wait after tapping before reading the pads
    open_s: float = 0.2  # wait after opening before retreating
    max_preshape_tries: int = 100  # preshape candidates tried against the collision model per finger
    retreat_m: float = 0.1

    def __post_init__(self):
        for key in ("palm_gap_m", "tap_speed", "max_tap_rad", "control_period_s", "stall_error_rad"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"grasp.{key}", f"must be positive, got {getattr(self, key)}")
        if self.preshape_grid < 2:
            raise ConfigError("grasp.preshape_grid", f"must be at least 2, got {self.preshape_grid}")


# Tap direction in the flexion joints (1, 2, 3): mostly the distal joint, which moves the pad
# along its own normal.
_TAP_DIRECTION = np.array([0.0, 0.25, 0.35, 1.0]) / np.linalg.norm([0.25, 0.35, 1.0])


@dataclass
class GraspResult:
    """One grasp: the four readings in the world frame, and what the physics did."""

    T_world_hand: np.ndarray  # [4, 4] hand base at the grasp
    readings: dict[str, TactileReading]  # finger -> reading with frame == "world"
    joint_positions: np.ndarray  # [16] at the time of reading
    stopped_by: dict[str, str]  # finger -> "contact" | "stall" | "limit" | "unreachable"
    max_penetration_m: float  # deepest hand-object contact of the collision model while tapping
    contacts: list = field(default_factory=list)

    @property
    def fingers_in_contact(self) -> list[str]:
        return [f for f, r in self.readings.items() if r.in_contact]


class PreshapeTable:
    """Pad poses in the hand frame over a grid of each finger's joints (a few abduction angles)."""

    def __init__(self, twin: SimTwin, per_joint: int, abduction=(0.0,)):
        import mujoco

        model, data = twin.model, mujoco.MjData(twin.model)
        data.mocap_pos[:] = 0.0
        data.mocap_quat[:] = [1.0, 0.0, 0.0, 0.0]
        self.q: dict[str, np.ndarray] = {}  # finger -> [N, 4]
        self.T_hand_sensor: dict[str, np.ndarray] = {}  # finger -> [N, 4, 4]
        for i, finger in enumerate(FINGER_NAMES):
            lim = JOINT_LIMITS[4 * i : 4 * i + 4]
            axes = [np.clip(abduction, lim[0, 0], lim[0, 1])]
            axes += [np.linspace(max(lim[j, 0], 0.0), lim[j, 1], per_joint) for j in (1, 2, 3)]
            q = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 4)
            qadr = [model.jnt_qposadr[model.joint(f"{finger}_{j}").id] for j in range(4)]
            site = model.site(f"{finger}_tactile").id
            poses = np.empty((len(q), 4, 4))
            for k, qk in enumerate(q):
                data.qpos[qadr] = qk
                mujoco.mj_kinematics(model, data)
                poses[k] = site_pose(data, site)
            self.q[finger], self.T_hand_sensor[finger] = q, poses


def _pretouch_candidates(twin: SimTwin, table: PreshapeTable, finger: str, T_world_hand, config: GraspConfig):
    """Indices of grid poses whose pad faces the object from a small gap, nearest first."""
    T = T_world_hand @ table.T_hand_sensor[finger]  # [N, 4, 4]
    origins, normals = T[:, :3, 3], T[:, :3, 2]
    mesh = twin.object_mesh
    tri, ray = twin.tactile_renderer.intersector.intersects_id(origins, normals, multiple_hits=False)
    face_n = mesh.face_normals[tri]
    cos = -np.einsum("ij,ij->i", face_n, normals[ray])
    gap = np.einsum("ij,ij->i", mesh.triangles[tri, 0] - origins[ray], face_n) / np.where(cos == 0, 1, -cos)
    ok = (cos >= config.min_alignment_cos) & (gap > 0) & (gap <= config.max_pretouch_gap_m)
    ray, gap = ray[ok], gap[ok]
    return ray[np.argsort(gap)]


def sample_hand_pose(twin: SimTwin, rng: np.random.Generator, config: GraspConfig = GraspConfig()) -> np.ndarray:
    """A hand base pose ``T_world_hand`` with the palm facing the object from a random direction.

    The direction is uniform over the sphere above ``min_approach_elevation_deg``
    with a random roll; the palm is pushed in until the nearest object point
    under the hand's footprint (palm and open fingers) is ``palm_gap_m`` away.
    """
    z_min = np.sin(np.deg2rad(config.min_approach_elevation_deg))
    z = rng.uniform(z_min, 1.0)
    azimuth = rng.uniform(0, 2 * np.pi)
    u = np.array([np.sqrt(1 - z**2) * np.cos(azimuth), np.sqrt(1 - z**2) * np.sin(azimuth), z])  # object -> hand
    palm_normal = -u
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x0 = np.cross(palm_normal, helper)
    x0 /= np.linalg.norm(x0)
    roll = rng.uniform(0, 2 * np.pi)
    x = np.cos(roll) * x0 + np.sin(roll) * np.cross(palm_normal, x0)
    R = np.stack([x, np.cross(palm_normal, x), palm_normal], axis=1)
    g = twin.config.hand_geometry
    reach = g.palm_half_length + g.knuckle_length + g.proximal_length + g.middle_length + g.distal_length
    local = twin.object_mesh.vertices @ R  # object points in the hand's axes, relative to the object centre
    under = (np.abs(local[:, 0]) < reach) & (np.abs(local[:, 1]) < 2.0 * g.finger_spacing + g.link_half_width)
    height = (twin.object_mesh.vertices[under] @ u).max() if under.any() else 0.0
    return make_pose(R, u * (height + config.palm_gap_m))


def preshape_fingers(twin: SimTwin, table: PreshapeTable, T_world_hand: np.ndarray,
                     config: GraspConfig = GraspConfig()) -> tuple[np.ndarray, list[str]]:
    """Place the hand base at ``T_world_hand`` and each finger at the grid pose whose pad is nearest the surface
    along its normal (within ``max_pretouch_gap_m``, aligned within ``min_alignment_cos``) and whose finger does
    not touch the object's collision hulls; returns ``(q_preshape [16], fingers that found one)``."""
    hand = twin.hand
    hand.set_joint_positions(np.zeros(16))
    twin.set_hand_base_pose(T_world_hand)
    q_pre, reachable = np.zeros(16), []
    for i, finger in enumerate(FINGER_NAMES):
        sl = slice(4 * i, 4 * i + 4)
        for k in _pretouch_candidates(twin, table, finger, T_world_hand, config)[: config.max_preshape_tries]:
            q_try = q_pre.copy()
            q_try[sl] = table.q[finger][k]
            hand.set_joint_positions(q_try)
            if not any(name.startswith(finger + "_") for name, _ in twin.hand_object_contacts()):
                q_pre = q_try
                reachable.append(finger)
                break
    hand.set_joint_positions(q_pre)
    return q_pre, reachable


def tap_close_pose(q_pre: np.ndarray, reachable: list[str], config: GraspConfig = GraspConfig()) -> np.ndarray:
    """The farthest tap target [16]: each reachable finger ``max_tap_rad`` along the tap direction from its
    preshape (a controller stops it where its pad meets the surface); the others stay at ``q_pre``."""
    q = np.array(q_pre, dtype=np.float64)
    for i, finger in enumerate(FINGER_NAMES):
        if finger in reachable:
            q[4 * i : 4 * i + 4] += config.max_tap_rad * _TAP_DIRECTION
    return np.clip(q, JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1])


def execute_grasp(
    twin: SimTwin, T_world_hand: np.ndarray, config: GraspConfig = GraspConfig(), table: PreshapeTable | None = None
) -> GraspResult:
    """Place the hand, preshape each finger with its pad facing the surface, tap until contact, read, open, retreat.

    The preshape is the grid pose whose pad is nearest the surface along its
    normal (within ``max_pretouch_gap_m``, aligned within ``min_alignment_cos``)
    and whose finger does not touch the object's collision hulls. Each finger
    then taps along ``_TAP_DIRECTION`` under its position servos until its pad
    touches (then presses ``press_rad`` further), it stalls, or it has moved
    ``max_tap_rad``.
    """
    table = table or PreshapeTable(twin, config.preshape_grid, config.preshape_abduction)
    hand = twin.hand
    q_pre, reachable = preshape_fingers(twin, table, T_world_hand, config)
    stopped: dict[str, str] = {f: "unreachable" for f in FINGER_NAMES if f not in reachable}

    travel = np.zeros(4)
    max_pen = twin.max_penetration()
    for _ in range(int(np.ceil(config.max_tap_rad / (config.tap_speed * config.control_period_s))) + 2):
        touching = {name[: -len("_pad")] for name, _ in twin.hand_object_contacts() if name.endswith("_pad")}
        q, target = hand.read_joint_positions(), hand.read_joint_targets()
        for i, finger in enumerate(FINGER_NAMES):
            if finger in stopped:
                continue
            sl = slice(4 * i, 4 * i + 4)
            if finger in touching:
                stopped[finger] = "contact"
                target[sl] = q_pre[sl] + (travel[i] + config.press_rad) * _TAP_DIRECTION
            elif np.abs(target[sl] - q[sl]).max() > config.stall_error_rad:
                stopped[finger] = "stall"
            elif travel[i] >= config.max_tap_rad:
                stopped[finger] = "limit"
            else:
                travel[i] += config.tap_speed * config.control_period_s
                target[sl] = q_pre[sl] + travel[i] * _TAP_DIRECTION
        hand.command_joint_positions(np.clip(target, JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1]))
        if len(stopped) == 4:
            break
        twin.sleep(config.control_period_s)
        max_pen = max(max_pen, twin.max_penetration())
    for finger in FINGER_NAMES:
        stopped.setdefault(finger, "limit")
    twin.sleep(config.settle_s)
    max_pen = max(max_pen, twin.max_penetration())
    result = GraspResult(
        T_world_hand=twin.T_world_hand(),
        readings=world_readings(twin),
        joint_positions=hand.read_joint_positions(),
        stopped_by=stopped,
        max_penetration_m=max_pen,
        contacts=twin.hand_object_contacts(),
    )
    # open, then retreat along the palm normal
    hand.command_joint_positions(np.zeros(16))
    twin.sleep(config.open_s)
    retreat = T_world_hand.copy()
    retreat[:3, 3] = transform_points(T_world_hand, [[0.0, 0.0, -config.retreat_m]])[0]
    twin.set_hand_base_pose(retreat)
    return result


def generate_grasps(
    twin: SimTwin, count: int, seed: int | None = None, config: GraspConfig = GraspConfig(), max_attempts_factor: int = 4
) -> list[GraspResult]:
    """``count`` grasps in which at least one pad touched, from random approaches seeded by ``seed``
    (default: the twin's seed)."""
    rng = np.random.default_rng(twin.config.seed if seed is None else seed)
    table = PreshapeTable(twin, config.preshape_grid, config.preshape_abduction)
    results: list[GraspResult] = []
    attempts = 0
    while len(results) < count and attempts < max_attempts_factor * max(count, 1):
        attempts += 1
        result = execute_grasp(twin, sample_hand_pose(twin, rng, config), config, table)
        if result.fingers_in_contact:
            results.append(result)
        else:
            log.info("grasp attempt %d touched nothing (stopped by %s); retrying", attempts, result.stopped_by)
    if len(results) < count:
        log.warning("only %d of %d grasps touched the object in %d attempts", len(results), count, attempts)
    return results
