"""The wrist camera's pose on the hand (``T_hand_cam``) from fingertip presses, without an arm; the file format of
each tactile sensor's pose on its fingertip (``T_fingertip_sensor``).

The calibration board lies face up and defines the world (its printed face is the plane ``z = 0``, DESIGN.md). A
press is a fingertip pressed on the board (or on a sphere of known radius resting on it) while the wrist camera
sees the board: the board's PnP gives ``T_world_cam``, the joints as read give the fingertip's pose on the hand,
and the sensor's depth map gives the contact points in the sensor frame. Through the unknowns, each contact point
must lie on the surface pressed: ``T_world_cam @ inv(T_hand_cam) @ T_hand_fingertip @ T_fingertip_sensor @ p``
on the plane ``z = 0``, or at the sphere's radius from its centre. ``T_hand_cam`` and each sphere placement's
centre are solved together by scipy's ``least_squares`` on every contact point, the sensors at the rig's mounts.

A press set that leaves an axis undetermined is refused, naming the presses to add.

Files (JSON): ``{"format": "tacsplat-hand-eye", "version": 1, "T_hand_cam": [[4x4]], "presses": n, "rms_mm": x}``;
the rig's ``tactile.mounts`` file: ``{"format": "tacsplat-mounts", "version": 1, "sensors": {finger:
{"T_fingertip_sensor": [[4x4]], ...}}}``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from tacsplat.drivers.calibration import json_array, read_calibration_json
from tacsplat.errors import ConfigError, InvalidInputError
from tacsplat.files import atomic_write
from tacsplat.geometry import invert_pose, make_pose, rigidity_problem, transform_points

HAND_EYE_FORMAT = "tacsplat-hand-eye"
MOUNTS_FORMAT = "tacsplat-mounts"
MIN_CONTACT_POINTS = 30  # a press with fewer contact pixels is not a press
POINTS_PER_PRESS = 400  # contact points of a press the refinement uses (evenly subsampled)


@dataclass(frozen=True)
class Press:
    """One fingertip press: which sensor, on what (``"board"`` or ``"sphere"`` with ``placement``, the sphere's
    placement on the board it rests at), the fingertip's pose on the hand from the joints as read, the contact
    points in the sensor frame and the wrist camera's pose from the board."""

    finger: str
    T_hand_fingertip: np.ndarray  # [4, 4]
    points_sensor: np.ndarray  # [M, 3]
    T_world_cam: np.ndarray  # [4, 4]
    surface: str = "board"
    placement: int = 0  # sphere presses: which placement of the sphere

    def sample(self) -> np.ndarray:
        """At most :data:`POINTS_PER_PRESS` contact points, evenly spread over the patch."""
        step = max(1, len(self.points_sensor) // POINTS_PER_PRESS)
        return self.points_sensor[::step]


NOISE_M = 5e-5  # a contact point's error the press set is judged against (an optical gel's depth noise)
MAX_STD = {"rotation": np.radians(0.1), "translation": 1e-4}  # a parameter known worse than this is undetermined
PARAM_NAMES = (
    "rotation about x",
    "rotation about y",
    "rotation about z",
    "offset along x",
    "offset along y",
    "offset along z",
)


@dataclass
class PressFit:
    """What a hand-eye press set gave: ``T_hand_cam``, each sphere placement's centre (world), and the rms of the
    contact points' distances to the surfaces pressed (all, and per finger)."""

    T_hand_cam: np.ndarray
    sphere_centres: list
    rms_mm: float
    finger_rms_mm: dict[str, float] = field(default_factory=dict)
    presses: dict[str, int] = field(default_factory=dict)


def _pose(x: np.ndarray) -> np.ndarray:
    """A rigid [4, 4] from (rotation vector [3], translation [3])."""
    return make_pose(Rotation.from_rotvec(x[:3]).as_matrix(), x[3:6])


def _params(T: np.ndarray) -> np.ndarray:
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def check_presses(presses: list[Press], what: str) -> None:
    """Refuse an empty set and a press without contact."""
    if not presses:
        raise InvalidInputError(f"{what}: no presses recorded; press the fingertips on the sphere and the board")
    for i, p in enumerate(presses):
        if len(p.points_sensor) < MIN_CONTACT_POINTS:
            raise InvalidInputError(
                f"{what}: press {i + 1} ({p.finger} on the {p.surface}) has {len(p.points_sensor)} contact pixels "
                f"(< {MIN_CONTACT_POINTS}): press the fingertip firmly, then take it again"
            )


def fit_presses(
    presses: list[Press],
    sphere_radius_m: float,
    T_hand_cam: np.ndarray,
    mounts: dict[str, np.ndarray] | None = None,
    what: str = "hand-eye",
) -> PressFit:
    """Solve ``T_hand_cam`` and each sphere placement's centre on the board (``z = radius``) together from every
    contact point lying on its surface (scipy ``least_squares``, started at ``T_hand_cam``, the nominal or last
    calibration), the sensors at ``mounts`` (the rig's; the identity for a finger not named). A parameter the presses
    leave undetermined (its standard deviation at :data:`NOISE_M` per point over :data:`MAX_STD`) is refused,
    naming it and the presses to add."""
    check_presses(presses, what)
    mounts = {f: np.asarray(T, dtype=np.float64) for f, T in (mounts or {}).items()}
    fingers = list(dict.fromkeys(p.finger for p in presses))
    placements = sorted({p.placement for p in presses if p.surface == "sphere"})
    samples = [p.sample() for p in presses]

    def unpack(x):
        centres = {c: np.r_[x[6 + 2 * j : 8 + 2 * j], sphere_radius_m] for j, c in enumerate(placements)}
        return _pose(x[:6]), centres

    def residuals(x):
        X, centres = unpack(x)
        T_cam_hand = invert_pose(X)
        out = []
        for p, pts in zip(presses, samples):
            T = p.T_world_cam @ T_cam_hand @ p.T_hand_fingertip @ mounts.get(p.finger, np.eye(4))
            world = transform_points(T, pts)
            if p.surface == "board":
                out.append(world[:, 2])
            else:
                out.append(np.linalg.norm(world - centres[p.placement], axis=1) - sphere_radius_m)
        return np.concatenate(out)

    x0 = [_params(T_hand_cam)]
    for c in placements:  # the sphere's centre one radius behind the first patch that touched it
        p = next(p for p in presses if p.surface == "sphere" and p.placement == c)
        T = p.T_world_cam @ invert_pose(T_hand_cam) @ p.T_hand_fingertip @ mounts.get(p.finger, np.eye(4))
        x0.append(transform_points(T, np.r_[p.points_sensor.mean(axis=0)[:2], sphere_radius_m][None])[0, :2])
    x0 = np.concatenate(x0)
    scale = np.r_[[0.01] * 3 + [0.001] * 3, [0.001] * 2 * len(placements)]
    fit = least_squares(residuals, x0, x_scale=scale, method="lm")
    _refuse_undetermined(fit.jac, ["hand-eye"], what)
    X, centres = unpack(fit.x)
    offsets = np.cumsum([0] + [len(s) for s in samples])
    per = {
        f: np.concatenate([fit.fun[offsets[i] : offsets[i + 1]] for i, p in enumerate(presses) if p.finger == f])
        for f in fingers
    }
    return PressFit(
        X,
        [centres[c] for c in placements],
        1000 * float(np.sqrt(np.mean(fit.fun**2))),
        {f: 1000 * float(np.sqrt(np.mean(r**2))) for f, r in per.items()},
        {f: sum(p.finger == f for p in presses) for f in fingers},
    )


def _refuse_undetermined(J: np.ndarray, blocks: list[str], what: str) -> None:
    """The parameters' standard deviations at :data:`NOISE_M` per point; one error naming those over
    :data:`MAX_STD`, with the presses that fix them."""
    std = _std(J, NOISE_M)
    weak = []
    for b, block in enumerate(blocks):
        for k in range(6):
            limit = MAX_STD["rotation" if k < 3 else "translation"]
            if not std[6 * b + k] <= limit:
                weak.append(f"{block} {PARAM_NAMES[k]}")
    if weak:
        hint = "press the sphere with more fingers, bent differently, the hand reaching it from other directions"
        raise InvalidInputError(f"{what}: the presses leave undetermined: {', '.join(weak)}; {hint}")


MOUNT_MAX_STD = (0.2, 0.1)  # degrees, mm: a mount parameter known worse than this is undetermined
OUTLIER_FACTOR, OUTLIER_MIN_MM = 3.0, 0.05  # a press this far off the others' fit is dropped (its board pose is bad)
START_OUTLIER_M = 0.006  # a press whose sphere centre lands this far from the others' at the start is dropped
MAX_CHANGE = (10.0, 20.0)  # mm, degrees: a mount found further than this from its start is refused
MOUNT_SPREAD_M = 0.004  # the spots pressed on a pad must span this along both of its axes


@dataclass
class MountFit:
    """What a sensor's presses gave: its ``T_fingertip_sensor``, the sphere placements' centres (world) and the rms
    of its contact points' distances to the sphere."""

    T_fingertip_sensor: np.ndarray
    sphere_centres: list
    rms_mm: float
    presses: int
    dropped: int = 0  # presses left out, off the others' fit by more than OUTLIER_FACTOR times their median rms


def sphere_centre_in_sensor(points: np.ndarray, radius_m: float) -> np.ndarray:
    """The centre [3] (sensor frame) of the sphere of ``radius_m`` that a contact patch lies on: the gel faces
    along the sensor's +z, so the centre lies one radius above the patch's deepest point."""
    start = np.r_[points[:, :2].mean(axis=0), points[:, 2].min() + radius_m]
    fit = least_squares(lambda c: np.linalg.norm(points - c, axis=1) - radius_m, start, method="lm")
    return fit.x


def fit_mount(
    presses: list[Press],
    sphere_radius_m: float,
    T_hand_cam: np.ndarray,
    T_start: np.ndarray | None = None,
    centre_height_m: float | None = None,
    what: str = "mounts",
) -> MountFit:
    """One sensor's ``T_fingertip_sensor`` from its presses on a sphere of ``sphere_radius_m`` whose centre stands
    ``centre_height_m`` over the board (a measured stand; None: resting on the board, one radius), solved with each
    sphere placement's centre on the board: every contact point ``T_world_cam @
    inv(T_hand_cam) @ T_hand_fingertip @ T_fingertip_sensor @ p`` at the radius from its centre (scipy
    ``least_squares`` on a correction to ``T_start``, the nominal or last mount, in degrees and millimetres).

    A sphere's patch fixes the centre's place in the sensor frame, three numbers; patches at three or more places of
    the gel that are not in a line fix the mount (the spots' lever arm fixes the rotations, the yaw about the gel's
    normal included); the known height fixes the offset along the direction the fingertip keeps vertical, and the
    fingertip's different poses separate the sphere's place on the board from the mount's other offsets. A
    press set that leaves a parameter undetermined (its standard deviation at :data:`NOISE_M` per point over
    :data:`MOUNT_MAX_STD`) is refused, naming it and the presses to add."""
    check_presses(presses, what)
    fingers = {p.finger for p in presses}
    if len(fingers) != 1 or any(p.surface != "sphere" for p in presses):
        raise InvalidInputError(f"{what}: fit_mount takes one sensor's presses on the sphere, got {sorted(fingers)}")
    finger = presses[0].finger
    height = sphere_radius_m if centre_height_m is None else centre_height_m
    T0 = np.eye(4) if T_start is None else np.asarray(T_start, dtype=np.float64)
    T_cam_hand = invert_pose(T_hand_cam)
    T_world_tip = [p.T_world_cam @ T_cam_hand @ p.T_hand_fingertip @ T0 for p in presses]
    samples = [p.sample() for p in presses]
    placements = sorted({p.placement for p in presses})
    centres_s = [sphere_centre_in_sensor(p.points_sensor, sphere_radius_m) for p in presses]
    # each patch's sphere centre in the world at the start mount; a press whose centre is far from the others' has a
    # bad board pose (PnP can flip with few corners) and is dropped
    world = np.array([transform_points(T, c[None])[0] for T, c in zip(T_world_tip, centres_s)])
    c0 = [np.median(world[[p.placement == k for p in presses], :2], axis=0) for k in placements]
    start = {k: np.r_[c, height] for k, c in zip(placements, c0)}
    outliers = np.array([np.linalg.norm(w - start[p.placement]) > START_OUTLIER_M for w, p in zip(world, presses)])
    if len(presses) - outliers.sum() < 3:
        outliers[:] = False
    bounds = np.cumsum([0] + [len(s) for s in samples])

    def unpack(x):
        D = make_pose(Rotation.from_rotvec(np.radians(x[:3])).as_matrix(), x[3:6] / 1000)
        centres = {k: np.r_[x[6 + 2 * j : 8 + 2 * j] / 1000, height] for j, k in enumerate(placements)}
        return D, centres

    def residuals(x):  # millimetres, 0 for the presses dropped
        D, centres = unpack(x)
        out = [
            np.linalg.norm(transform_points(T @ D, pts) - centres[p.placement], axis=1) - sphere_radius_m
            for T, pts, p in zip(T_world_tip, samples, presses)
        ]
        return 1000 * np.concatenate(out) * np.repeat(~outliers, np.diff(bounds))

    x0 = np.r_[np.zeros(6), 1000 * np.concatenate(c0)]
    fit = least_squares(residuals, x0, loss="soft_l1", f_scale=1000 * NOISE_M)  # robust to a press's bad board pose
    press_rms = np.array([np.sqrt(np.mean(fit.fun[a:b] ** 2)) for a, b in zip(bounds[:-1], bounds[1:])])
    worse = press_rms > max(OUTLIER_FACTOR * np.median(press_rms[~outliers]), OUTLIER_MIN_MM)
    if worse.any() and len(presses) - (outliers | worse).sum() >= 3:
        outliers |= worse
    fit = least_squares(residuals, fit.x, method="lm")
    std = _std(fit.jac, 1000 * NOISE_M)[:6]
    weak = [f"{finger} mount {PARAM_NAMES[k]}" for k in range(6) if not std[k] <= MOUNT_MAX_STD[k >= 3]]
    if weak:
        spots = np.array(centres_s)[~outliers, :2]
        spans = spots.max(axis=0) - spots.min(axis=0) if len(spots) else np.zeros(2)
        short = [axis for axis, span in zip("xy", spans) if span < MOUNT_SPREAD_M]
        where = (
            f"press the sphere with places of the {finger} pad further apart along its {' and '.join(short)} axis "
            f"(at least {1000 * MOUNT_SPREAD_M:.0f} mm apart, say its two ends and a side)"
            if short
            else f"press the sphere with at least three places of the {finger} pad not in a line, the finger bent "
            "two ways"
        )
        raise InvalidInputError(f"{what}: the presses leave undetermined: {', '.join(weak)}; {where}")
    D, centres = unpack(fit.x)
    moved_mm, moved_deg = 1000 * np.linalg.norm(D[:3, 3]), np.degrees(Rotation.from_matrix(D[:3, :3]).magnitude())
    if moved_mm > MAX_CHANGE[0] or moved_deg > MAX_CHANGE[1]:  # no pad sits that far off; the solve ran off
        raise InvalidInputError(
            f"{what}: the {finger} mount came out {moved_mm:.1f} mm, {moved_deg:.1f} deg from its start, more than a "
            f"pad is mounted off ({MAX_CHANGE[0]:.0f} mm, {MAX_CHANGE[1]:.0f} deg); take its presses again, the "
            "board in full view"
        )
    kept = np.repeat(~outliers, np.diff(bounds))
    rms = float(np.sqrt(np.mean(fit.fun[kept] ** 2)))
    return MountFit(T0 @ D, [centres[k] for k in placements], rms, int((~outliers).sum()), int(outliers.sum()))


def _std(J: np.ndarray, noise: float) -> np.ndarray:
    """The parameters' standard deviations [n] at ``noise`` per residual (inf where undetermined)."""
    normal = J.T @ J
    try:
        cov = noise**2 * np.linalg.inv(normal + 1e-18 * np.eye(len(normal)))
        return np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        return np.full(len(normal), np.inf)


# --- files -----------------------------------------------------------------------------------------------


def _rigid(value, key: str, path: Path) -> np.ndarray:
    T = json_array(value, key, path, (4, 4))
    problem = rigidity_problem(T)
    if problem:
        raise ConfigError(key, f"not a rigid transform: {problem}", source=path)
    return T


def save_hand_eye(fit: PressFit, path: str | Path) -> None:
    data = {
        "format": HAND_EYE_FORMAT,
        "version": 1,
        "T_hand_cam": fit.T_hand_cam.tolist(),
        "presses": sum(fit.presses.values()),
        "rms_mm": fit.rms_mm,
    }
    atomic_write(path, (json.dumps(data, indent=2) + "\n").encode())


def load_hand_eye(path: str | Path) -> np.ndarray:
    """``T_hand_cam`` [4, 4] of a hand-eye file; one ConfigError names the file and field."""
    path = Path(path)
    data = read_calibration_json(path, HAND_EYE_FORMAT)
    return _rigid(data.get("T_hand_cam"), "T_hand_cam", path)


def save_mounts(fits: dict[str, MountFit], path: str | Path) -> None:
    sensors = {
        f: {"T_fingertip_sensor": fit.T_fingertip_sensor.tolist(), "presses": fit.presses, "rms_mm": fit.rms_mm}
        for f, fit in fits.items()
    }
    data = {"format": MOUNTS_FORMAT, "version": 1, "sensors": sensors}
    atomic_write(path, (json.dumps(data, indent=2) + "\n").encode())


def load_mounts(path: str | Path, fingers) -> dict[str, np.ndarray]:
    """``{finger: T_fingertip_sensor}`` of a mounts file (fingers among ``fingers``); one ConfigError names the
    file and field."""
    path = Path(path)
    data = read_calibration_json(path, MOUNTS_FORMAT)
    sensors = data.get("sensors")
    if not isinstance(sensors, dict) or not sensors:
        raise ConfigError("sensors", "expected an object mapping fingers to {T_fingertip_sensor}", source=path)
    out = {}
    for finger, entry in sensors.items():
        if finger not in fingers:
            raise ConfigError(f"sensors.{finger}", f"unknown finger (one of {list(fingers)})", source=path)
        if not isinstance(entry, dict):
            raise ConfigError(f"sensors.{finger}", "expected an object with T_fingertip_sensor", source=path)
        out[finger] = _rigid(entry.get("T_fingertip_sensor"), f"sensors.{finger}.T_fingertip_sensor", path)
    return out
