"""Where the twin's hand goes for a grasp: the approach, each finger's preshape, and the tap's far target.

Simulator-only help for the grasp controller of the acquisition logger
(:mod:`tacsplat.acquisition.twin_planner`), which closes the hand through the
Protocols and stops each finger when it stalls on the object: placing the hand
base (mocap) on a sampled approach, choosing each finger's preshape against
the known mesh and the collision model, and the tap direction of the fingers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tacsplat.errors import SimulationError
from tacsplat.geometry import make_pose, transform_points
from tacsplat.sim.hand import FINGER_NAMES, JOINT_LIMITS, site_pose
from tacsplat.sim.twin import SimTwin
from tacsplat.sim.views import unit_vectors


@dataclass(frozen=True)
class GraspConfig:
    """Where a simulated grasp starts and how far it taps (angles in radians)."""

    palm_gap_m: float = 0.012  # palm surface to the nearest object point under the hand
    min_approach_elevation_deg: float = -30.0  # approach directions from above this elevation
    preshape_grid: int = 13  # samples per flexion joint when searching each finger's pre-touch pose
    preshape_abduction: tuple[float, ...] = (-0.3, 0.0, 0.3)  # abduction angles searched, radians
    max_pretouch_gap_m: float = 0.03  # the pad stops at most this far in front of the surface
    min_alignment_cos: float = 0.85  # pad normal against the surface normal, at least this cosine
    max_tap_rad: float = 0.8  # the tap's target: this far along the tap direction from the preshape
    max_preshape_tries: int = 100  # preshape candidates tried against the collision model per finger


MAX_APPROACH_DRAWS = 50  # approach directions drawn for one hand pose before giving up
FOOTPRINT_RAY_SPACING_M = 0.002  # the grid of rays measuring the surface's height under the hand's footprint

# Tap direction in the flexion joints (1, 2, 3): mostly the distal joint, which moves the pad
# along its own normal.
_TAP_DIRECTION = np.array([0.0, 0.25, 0.35, 1.0]) / np.linalg.norm([0.25, 0.35, 1.0])


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
    return ray[ok][np.argsort(gap[ok])]


def _surface_height(twin: SimTwin, R: np.ndarray, reach: float, half_width: float) -> float:
    """Height along the approach (``-R[:, 2]``, from the object centre) of the highest surface point under the hand's
    footprint (``|x| < reach``, ``|y| < half_width`` in the hand's axes): the highest of its vertices there and of a
    grid of rays cast down onto it (a low-poly mesh's faces can cover the footprint with no vertex under it)."""
    mesh, u = twin.object_mesh, -R[:, 2]
    local = mesh.vertices @ R  # object points in the hand's axes, relative to the object centre
    under = (np.abs(local[:, 0]) < reach) & (np.abs(local[:, 1]) < half_width)
    x, y = (np.linspace(-h, h, int(np.ceil(2 * h / FOOTPRINT_RAY_SPACING_M)) + 1) for h in (reach, half_width))
    x, y = (a.reshape(-1, 1) for a in np.meshgrid(x, y, indexing="ij"))
    start = np.linalg.norm(mesh.vertices, axis=1).max() + 0.01  # outside the object's bounding sphere
    origins = x * R[:, 0] + y * R[:, 1] + start * u
    tri, ray = twin.tactile_renderer.intersector.intersects_id(
        origins, np.broadcast_to(-u, origins.shape), multiple_hits=False
    )
    # each hit's height, in float64 on the hit triangle's plane (n . p = n . v0 at p = origin - t u, edge-on hits
    # dropped): where a ray meets the surface exactly at a vertex it measures that vertex's height
    n, v0 = mesh.face_normals[tri], mesh.triangles[tri, 0]
    cos = n @ u
    hit = cos != 0
    t = np.einsum("ij,ij->i", origins[ray[hit]] - v0[hit], n[hit]) / cos[hit]
    heights = np.concatenate([mesh.vertices[under] @ u, start - t])
    return float(heights.max()) if len(heights) else 0.0


def _meets_object(twin: SimTwin, T_world_hand: np.ndarray) -> bool:
    """Place the open hand at ``T_world_hand``; whether its palm or knuckles meet the object: a knuckle in contact
    with the collision hulls, or a point of the palm's face inside the mesh (the palm, on the mocap base, never
    collides in MuJoCo)."""
    twin.hand.set_joint_positions(np.zeros(16))
    twin.set_hand_base_pose(T_world_hand)
    if any(name.endswith("_knuckle") for name, _ in twin.hand_object_contacts()):
        return True
    g = twin.config.hand_geometry
    grid = [(sx * g.palm_half_length, sy * 1.5 * g.finger_spacing, 0.0) for sx in (-1, 0, 1) for sy in (-1, 0, 1)]
    return bool(twin.tactile_renderer.inside(transform_points(T_world_hand, grid), T_world_hand[:3, 2]).any())


def sample_hand_pose(twin: SimTwin, rng: np.random.Generator, config: GraspConfig = GraspConfig()) -> np.ndarray:
    """A hand base pose ``T_world_hand`` with the palm facing the object from a random direction; the open hand is
    left there.

    The direction is uniform over the sphere above ``min_approach_elevation_deg``
    with a random roll; the palm is pushed in until the highest surface point
    under the hand's footprint (palm and open fingers) is ``palm_gap_m`` away.
    A direction where the open hand's palm or knuckles still meet the object
    (a feature between the footprint's rays, hulls standing far off the mesh)
    is drawn again, up to ``MAX_APPROACH_DRAWS`` times (then a SimulationError).
    """
    z_min = np.sin(np.deg2rad(config.min_approach_elevation_deg))
    g = twin.config.hand_geometry
    reach = g.palm_half_length + g.knuckle_length + g.proximal_length + g.middle_length + g.distal_length
    for _ in range(MAX_APPROACH_DRAWS):
        u = unit_vectors(rng.uniform(z_min, 1.0), rng.uniform(0, 2 * np.pi))  # object -> hand
        palm_normal = -u
        helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x0 = np.cross(palm_normal, helper)
        x0 /= np.linalg.norm(x0)
        roll = rng.uniform(0, 2 * np.pi)
        x = np.cos(roll) * x0 + np.sin(roll) * np.cross(palm_normal, x0)
        R = np.stack([x, np.cross(palm_normal, x), palm_normal], axis=1)
        height = _surface_height(twin, R, reach, 2.0 * g.finger_spacing + g.link_half_width)
        T_world_hand = make_pose(R, u * (height + config.palm_gap_m))
        if not _meets_object(twin, T_world_hand):
            return T_world_hand
    raise SimulationError(
        f"no approach found: in {MAX_APPROACH_DRAWS} directions the open hand's palm or knuckles met the object "
        f"{config.palm_gap_m * 1e3:g} mm off its surface (collision hulls standing far outside the mesh?)"
    )


def preshape_fingers(
    twin: SimTwin, table: PreshapeTable, T_world_hand: np.ndarray, config: GraspConfig = GraspConfig()
) -> tuple[np.ndarray, list[str]]:
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
