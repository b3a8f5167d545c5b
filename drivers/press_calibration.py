"""The wrist camera's pose on the hand (``T_hand_cam``) and each tactile sensor's pose on its fingertip
(``T_fingertip_sensor``) from fingertip presses on a sphere, without an arm.

The calibration board lies face up and defines the world (its printed face is the plane ``z = 0``, DESIGN.md). A
press is a fingertip pressed on a sphere of known radius (resting on the board, or on a stand of known height)
while the wrist camera sees the board: the board's PnP gives ``T_world_cam``, the joints as read give the
fingertip's pose on the hand, and the sensor's depth map gives the contact points in the sensor frame. Through the
unknowns, each contact point must lie at the sphere's radius from its centre:
``T_world_cam @ inv(T_hand_cam) @ T_hand_fingertip @ T_fingertip_sensor @ p``.

- :func:`fit_presses` (``calibrate hand-eye``): ``T_hand_cam`` and the sphere's place, the sensors at the rig's
  mounts: the pads' centres pressed on the sphere by many fingers and hand poses.
- :func:`fit_mounts` (``calibrate mounts``): every pressed sensor's ``T_fingertip_sensor`` and ``T_hand_cam``
  together (a hand-eye solved with the pads at their nominal mounts takes up part of their errors): a patch's
  curvature fixes the sphere's centre in the sensor frame, patches at places of the gel not in a line fix the
  mount's six numbers (the yaw about the gel's normal and the in-plane offset included, which a plane cannot), and
  the stand's known height fixes the offset along the direction a fingertip keeps vertical.

Each refuses a press set that leaves an axis undetermined, naming the presses to add, and one that its best fit
leaves further off the sphere than the gel's noise and the mounts' errors explain, naming what to check;
``fit_presses`` searches every orientation of the camera for its start (one start can end in a local minimum);
``fit_mounts`` drops presses whose board pose is off the others' (PnP can flip with few corners).

Files (JSON): ``{"format": "tacsplat-hand-eye", "version": 1, "T_hand_cam": [[4x4]], "presses": n, "rms_mm": x}``
(from an arm, ``tacsplat calibrate hand-eye --arm-poses``: ``"stations": n`` instead of ``"presses"``, and ``rms_mm``
the rms spread of the board's position in the arm's base over them) and ``{"format": "tacsplat-mounts", "version": 1,
"sensors": {finger: {"T_fingertip_sensor": [[4x4]], "presses": n, "rms_mm": x}}}``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Collection

import numpy as np
from pydantic import Field
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from tacsplat.drivers.calibration import read_calibration
from tacsplat.drivers.calibration_files import CalibrationFile, Rigid
from tacsplat.errors import ConfigError, InvalidInputError
from tacsplat.files import atomic_file, atomic_write
from tacsplat.geometry import invert_pose, make_pose, transform_points

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
MAX_STD = (np.radians(0.1), 1e-4)  # rad, m: a parameter known worse than this is undetermined
PARAM_NAMES = tuple(f"{kind} {axis}" for kind in ("rotation about", "offset along") for axis in "xyz")


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


def _world_sensor(p: Press, T_cam_hand: np.ndarray, T_fingertip_sensor: np.ndarray) -> np.ndarray:
    """``T_world_sensor`` of a press: ``T_world_cam @ T_cam_hand @ T_hand_fingertip @ T_fingertip_sensor``."""
    return p.T_world_cam @ T_cam_hand @ p.T_hand_fingertip @ T_fingertip_sensor


def check_presses(presses: list[Press], what: str) -> None:
    """Refuse an empty set and a press without contact."""
    if not presses:
        raise InvalidInputError(f"{what}: no presses recorded: every press was skipped (its line above says why)")
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
    calibrated_mounts: Collection[str] = (),
) -> PressFit:
    """Solve ``T_hand_cam`` and each sphere placement's centre on the board (``z = radius``) together from every
    contact point lying on its surface (scipy ``least_squares``), the sensors at ``mounts`` (the rig's; the identity
    for a finger not named; ``calibrated_mounts``: the fingers whose mount is calibrated, not nominal). The solve is
    started at ``T_hand_cam`` (the nominal or last calibration) and at the best of a search over every orientation
    (:func:`_global_start`), and the lower rms kept: from one start it can stop in a local minimum about a
    millimetre off the sphere (a camera turned 10 degrees about its optical axis did). A parameter the presses leave
    undetermined (its standard deviation at :data:`NOISE_M` per point over :data:`MAX_STD`) is refused, naming it
    and the presses to add; so is a best fit whose rms is over what the gel's noise and the mounts' errors explain
    (:func:`_max_press_rms_m`), naming what to check."""
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
            world = transform_points(_world_sensor(p, T_cam_hand, mounts.get(p.finger, np.eye(4))), pts)
            if p.surface == "board":
                out.append(world[:, 2])
            else:
                out.append(np.linalg.norm(world - centres[p.placement], axis=1) - sphere_radius_m)
        return np.concatenate(out)

    def solve(T_start):
        x0 = [_params(T_start)]
        for c in placements:  # the sphere's centre one radius behind the first patch that touched it
            p = next(p for p in presses if p.surface == "sphere" and p.placement == c)
            T = _world_sensor(p, invert_pose(T_start), mounts.get(p.finger, np.eye(4)))
            x0.append(transform_points(T, np.r_[p.points_sensor.mean(axis=0)[:2], sphere_radius_m][None])[0, :2])
        scale = np.r_[[0.01] * 3 + [0.001] * 3, [0.001] * 2 * len(placements)]
        return least_squares(residuals, np.concatenate(x0), x_scale=scale, method="lm")

    starts = [T_hand_cam, _global_start(presses, sphere_radius_m, mounts)]
    fit = min((solve(T) for T in starts), key=lambda f: f.cost)
    if weak := _undetermined(fit.jac, ["hand-eye"], NOISE_M, MAX_STD):
        hint = "press the sphere with more fingers, bent differently, the hand reaching it from other directions"
        raise InvalidInputError(f"{what}: the presses leave undetermined: {', '.join(map(' '.join, weak))}; {hint}")
    rms = float(np.sqrt(np.mean(fit.fun**2)))
    nominal = [f for f in fingers if f not in calibrated_mounts]
    if rms > (limit := _max_press_rms_m(sphere_radius_m, not nominal)):
        mounting = "the calibrated mounts" if not nominal else f"the {', '.join(nominal)} pads' nominal mounting"
        raise InvalidInputError(
            f"{what}: at the best T_hand_cam found the contact points lie {1000 * rms:.2f} mm (rms) off the sphere, "
            f"more than the gel's noise and {mounting} explain ({1000 * limit:.2f} mm); check that the ball is "
            f"{2000 * sphere_radius_m:.0f} mm across and did not move between presses, the hand calibration "
            "(calibrate hand) and each pad's mounting (calibrate mounts solves T_hand_cam with the mounts)"
        )
    X, centres = unpack(fit.x)
    offsets = np.cumsum([0] + [len(s) for s in samples])
    per = {
        f: np.concatenate([fit.fun[offsets[i] : offsets[i + 1]] for i, p in enumerate(presses) if p.finger == f])
        for f in fingers
    }
    return PressFit(
        X,
        [centres[c] for c in placements],
        1000 * rms,
        {f: 1000 * float(np.sqrt(np.mean(r**2))) for f, r in per.items()},
        {f: sum(p.finger == f for p in presses) for f in fingers},
    )


# A sensor's mount before calibrate mounts is off its nominal place by up to this (the chain is built and tested for
# pads up to 2 mm and 3 degrees off); a calibrated one is known to MOUNT_MAX_STD.
MOUNT_TOLERANCE_M = 0.002


def _max_press_rms_m(sphere_radius_m: float, mounts_calibrated: bool) -> float:
    """The most a hand-eye press set's rms can be at the right ``T_hand_cam``: the gel's depth noise plus the
    sensors' mounting errors, which move each patch as a whole. A nominal mount moves its patches by up to
    :data:`MOUNT_TOLERANCE_M`; a calibrated one by its offset's standard deviation plus its rotation's over the
    sphere's radius (:data:`MOUNT_MAX_STD`), three of which bound it."""
    if not mounts_calibrated:
        return NOISE_M + MOUNT_TOLERANCE_M
    degrees, mm = MOUNT_MAX_STD
    return 3 * (NOISE_M + mm / 1000 + sphere_radius_m * np.radians(degrees))


# The orientations :func:`_global_start` tries: every rotation, on a 20-degree grid of Euler angles. The sphere
# centres' model has a far wider basin than that (on a twin, refined from 90 degrees off its optimum it reached it),
# and its optimum lies within a degree or so of the full solve's, well inside that one's basin.
GRID_DEG = 20.0
GLOBAL_REFINED = 8  # grid points refined, best first


def _global_start(presses: list[Press], sphere_radius_m: float, mounts: dict[str, np.ndarray]) -> np.ndarray:
    """A ``T_hand_cam`` near the presses' global optimum, from the sphere's centre that each patch's curvature gives
    (a board press: the patch's centre at ``z = 0``), found in the hand through the fingertip and its mount and in
    the world through the camera: ``T_world_cam @ inv(T_hand_cam) @ h = c``. For a given rotation of
    ``inv(T_hand_cam)`` that is linear in its translation and the centres' places on the board, so every orientation
    of a grid is scored at once; the best few are refined and the best of those returned."""
    placements = sorted({p.placement for p in presses if p.surface == "sphere"})
    # one equation per world axis a press fixes (a sphere's centre: x, y, z; the board: z), of the unknowns u (the
    # translation of inv(T_hand_cam), then each placement's centre x, y): M u = d - A R h for the rotation R
    M, d, A, h = [], [], [], []
    for p in presses:
        on_sphere = p.surface == "sphere"
        point = sphere_centre_in_sensor(p.points_sensor, sphere_radius_m) if on_sphere else p.points_sensor.mean(0)
        in_hand = transform_points(p.T_hand_fingertip @ mounts.get(p.finger, np.eye(4)), point[None])[0]
        R_world, t_world = p.T_world_cam[:3, :3], p.T_world_cam[:3, 3]
        for axis in range(3) if on_sphere else [2]:
            row = np.zeros(3 + 2 * len(placements))
            row[:3] = R_world[axis]
            if on_sphere and axis < 2:
                row[3 + 2 * placements.index(p.placement) + axis] = -1.0
            M.append(row)
            d.append((sphere_radius_m if on_sphere and axis == 2 else 0.0) - t_world[axis])
            A.append(R_world[axis])
            h.append(in_hand)
    M, d, A, h = map(np.array, (M, d, A, h))
    project = np.eye(len(M)) - M @ np.linalg.pinv(M)  # the residual left once the linear unknowns are solved

    def residuals(R):  # [..., equations] for rotations R [..., 3, 3] of inv(T_hand_cam)
        return (d - np.einsum("ea,...ab,eb->...e", A, R, h)) @ project.T

    angles = np.radians(np.arange(-180.0, 180.0, GRID_DEG))
    tilts = np.radians(np.arange(-90.0 + GRID_DEG / 2, 90.0, GRID_DEG))
    grid = Rotation.from_euler("zyx", np.array(np.meshgrid(angles, tilts, angles)).reshape(3, -1).T).as_matrix()
    cost = np.sum(residuals(grid) ** 2, axis=1)
    refined = [
        least_squares(lambda v: residuals(Rotation.from_rotvec(v).as_matrix()), Rotation.from_matrix(R).as_rotvec())
        for R in grid[np.argsort(cost)[:GLOBAL_REFINED]]
    ]
    R = Rotation.from_rotvec(min(refined, key=lambda f: f.cost).x).as_matrix()
    u = np.linalg.lstsq(M, d - np.einsum("ea,ab,eb->e", A, R, h), rcond=None)[0]
    return invert_pose(make_pose(R, u[:3]))


def _undetermined(J: np.ndarray, blocks: list[str], noise: float, limits: tuple[float, float]) -> list[tuple]:
    """(block, parameter name) of each parameter (six per block: rotations, then offsets) whose standard deviation
    at ``noise`` per residual is over its limit (``limits``: rotations', offsets')."""
    std = _std(J, noise)[: 6 * len(blocks)].reshape(-1, 6)  # a row per block
    return [
        (block, PARAM_NAMES[k]) for block, row in zip(blocks, std) for k in range(6) if not row[k] <= limits[k >= 3]
    ]


MOUNT_MAX_STD = (0.2, 0.1)  # degrees, mm: a parameter known worse than this is undetermined
OUTLIER_FACTOR, OUTLIER_MIN_MM = 3.0, 0.05  # a press this far off the others' fit is dropped (its board pose is bad)
MAX_DROPPED = 0.2  # at most this share of the presses is dropped
START_OUTLIER_M = 0.015  # a press whose sphere centre lands this far from the others' at the start is dropped
# mm, degrees: nothing is mounted further off its design by hand; a solution this far from its start is kept (it is
# judged by its rms and its undetermined parameters) but said
LARGE_CHANGE = (10.0, 20.0)
MOUNT_SPREAD_M = 0.004  # the spots pressed on a pad must span this along both of its axes


@dataclass
class MountsFit:
    """What a press set gave: ``T_hand_cam`` (solved, or the start's), each pressed sensor's
    ``T_fingertip_sensor``, each sphere placement's centre (world), the rms of each sensor's contact points'
    distances to the sphere, its presses used and dropped (off the others, its board pose bad)."""

    T_hand_cam: np.ndarray
    mounts: dict[str, np.ndarray]
    sphere_centres: dict[int, np.ndarray]
    rms_mm: dict[str, float]
    presses: dict[str, int]
    dropped: dict[str, int]


def sphere_centre_in_sensor(points: np.ndarray, radius_m: float) -> np.ndarray:
    """The centre [3] (sensor frame) of the sphere of ``radius_m`` that a contact patch lies on: the gel faces
    along the sensor's +z, so the centre lies one radius above the patch's deepest point."""
    start = np.r_[points[:, :2].mean(axis=0), points[:, 2].min() + radius_m]
    return least_squares(lambda c: np.linalg.norm(points - c, axis=1) - radius_m, start, method="lm").x


def _correction(x: np.ndarray) -> np.ndarray:
    """A rigid [4, 4] from (rotation vector in degrees [3], translation in mm [3])."""
    return _pose(np.r_[np.radians(x[:3]), x[3:6] / 1000])


def fit_mounts(
    presses: list[Press],
    sphere_radius_m: float,
    centre_heights_m: dict[int, float],
    T_hand_cam: np.ndarray,
    mounts: dict[str, np.ndarray] | None = None,
    what: str = "mounts",
) -> MountsFit:
    """Each pressed sensor's ``T_fingertip_sensor`` and ``T_hand_cam``, solved together with each
    sphere placement's centre on the board (its height over the board known, ``centre_heights_m[placement]``: one
    radius when resting on it, a measured stand's otherwise): every contact point ``T_world_cam @ inv(T_hand_cam) @
    T_hand_fingertip @ T_fingertip_sensor @ p`` at the radius from its centre (scipy ``least_squares`` on
    corrections to the start, ``T_hand_cam`` and ``mounts``, the rig's, in degrees and millimetres).

    A sphere's patch fixes the centre's place in the sensor frame, three numbers; patches at three or more places of
    the gel not in a line fix the mount (their lever arm fixes the rotations, the yaw about the gel's normal
    included); the known heights fix the offset along the direction a fingertip keeps vertical, and the fingertips'
    different poses on the hand separate ``T_hand_cam`` from the mounts and the sphere's place. A press whose
    sphere centre lands far from the others' (a bad board pose) is dropped. A press set that leaves a parameter
    undetermined (its standard deviation at :data:`NOISE_M` per point over :data:`MOUNT_MAX_STD`) is refused,
    naming it and the presses to add; so is a sensor whose rms is over what the gel's noise and a calibrated mount
    explain (:func:`_max_press_rms_m`)."""
    check_presses(presses, what)
    if any(p.surface != "sphere" for p in presses):
        raise InvalidInputError(f"{what}: fit_mounts takes presses on the sphere only")
    mounts = {f: np.asarray(T, dtype=np.float64) for f, T in (mounts or {}).items()}
    fingers = list(dict.fromkeys(p.finger for p in presses))
    placements = sorted({p.placement for p in presses})
    if missing := [k for k in placements if k not in centre_heights_m]:
        raise InvalidInputError(f"{what}: no height given for sphere placements {missing}")
    T_cam_hand = invert_pose(T_hand_cam)
    start = [_world_sensor(p, T_cam_hand, mounts.get(p.finger, np.eye(4))) for p in presses]
    samples = [p.sample() for p in presses]
    bounds = np.cumsum([0] + [len(s) for s in samples])
    centres_s = [sphere_centre_in_sensor(p.points_sensor, sphere_radius_m) for p in presses]
    # each patch's sphere centre in the world at the start; one far from the others' has a bad board pose (PnP can
    # flip with few corners) and is dropped
    world = np.array([transform_points(T, c[None])[0] for T, c in zip(start, centres_s)])
    c0 = {k: np.median(world[[p.placement == k for p in presses], :2], axis=0) for k in placements}
    far = [np.linalg.norm(w - np.r_[c0[p.placement], centre_heights_m[p.placement]]) for w, p in zip(world, presses)]
    dropped = np.array(far) > START_OUTLIER_M
    n_he = 6

    def unpack(x):
        X = T_hand_cam @ _correction(x[:6])
        M = {
            f: mounts.get(f, np.eye(4)) @ _correction(x[n_he + 6 * i : n_he + 6 * i + 6]) for i, f in enumerate(fingers)
        }
        k0 = n_he + 6 * len(fingers)
        centres = {
            k: np.r_[x[k0 + 2 * j : k0 + 2 * j + 2] / 1000, centre_heights_m[k]] for j, k in enumerate(placements)
        }
        return X, M, centres

    def residuals(x, use=None):  # millimetres; 0 for the presses dropped and those not in ``use``
        X, M, centres = unpack(x)
        T_cam_hand = invert_pose(X)
        out = [
            np.linalg.norm(
                transform_points(_world_sensor(p, T_cam_hand, M[p.finger]), pts) - centres[p.placement], axis=1
            )
            - sphere_radius_m
            for p, pts in zip(presses, samples)
        ]
        keep = ~dropped if use is None else ~dropped & use
        return 1000 * np.concatenate(out) * np.repeat(keep, np.diff(bounds))

    def solve(x, free, use=None):
        """``x`` with the parameters ``free`` (indices) solved on the presses ``use`` (plain Levenberg-Marquardt)."""

        def sub(y):
            z = x.copy()
            z[free] = y
            return residuals(z, use)

        fit = least_squares(sub, x[free], method="lm")
        out = x.copy()
        out[free] = fit.x
        return out, fit

    x = np.r_[np.zeros(n_he + 6 * len(fingers)), 1000 * np.concatenate([c0[k] for k in placements])]
    centre_params = np.arange(n_he + 6 * len(fingers), len(x))
    for i, f in enumerate(fingers):  # each mount alone first, T_hand_cam held: a start near the joint solution
        x, _ = solve(x, np.r_[n_he + 6 * i + np.arange(6), centre_params], np.array([p.finger == f for p in presses]))
    x, fit = solve(x, np.arange(len(x)))
    while dropped.sum() < len(presses) * MAX_DROPPED:  # the worst press, while far off the others: a bad board pose
        press_rms = np.array([np.sqrt(np.mean(fit.fun[a:b] ** 2)) for a, b in zip(bounds[:-1], bounds[1:])])
        worst = int(np.argmax(np.where(dropped, -1.0, press_rms)))
        if press_rms[worst] <= max(OUTLIER_FACTOR * np.median(press_rms[~dropped]), OUTLIER_MIN_MM):
            break
        dropped[worst] = True
        x, fit = solve(x, np.arange(len(x)))
    _refuse_unfixed(fit.jac, presses, fingers, dropped, centres_s, what)
    X, M, centres = unpack(x)
    mine = {f: np.array([p.finger == f for p in presses]) & ~dropped for f in fingers}
    rms = {f: float(np.sqrt(np.mean(fit.fun[np.repeat(m, np.diff(bounds))] ** 2))) for f, m in mine.items()}
    limit = 1000 * _max_press_rms_m(sphere_radius_m, mounts_calibrated=True)  # each mount is now known to MOUNT_MAX_STD
    if off := {f: r for f, r in rms.items() if r > limit}:
        said = ", ".join(f"the {f} sensor's {r:.2f} mm" for f, r in off.items())
        raise InvalidInputError(
            f"{what}: at the best solution found the contact points lie off the sphere by (rms) {said}, more than the "
            f"gel's noise and a calibrated mount explain ({limit:.2f} mm); check that the ball is "
            f"{2000 * sphere_radius_m:.0f} mm across and did not move on its stand, the stand's height as given, and "
            "the hand calibration (calibrate hand)"
        )
    return MountsFit(
        X,
        M,
        centres,
        rms,
        {f: int(m.sum()) for f, m in mine.items()},
        {f: int(sum(d and p.finger == f for d, p in zip(dropped, presses))) for f in fingers},
    )


def _refuse_unfixed(J, presses, fingers, dropped, centres_s, what) -> None:
    """One error naming each parameter the presses leave undetermined (:data:`MOUNT_MAX_STD`) and what to press."""
    weak = _undetermined(J, ["hand-eye"] + [f"{f} mount" for f in fingers], 1000 * NOISE_M, MOUNT_MAX_STD)
    if not weak:
        return
    hints = []
    for f in dict.fromkeys(block[: -len(" mount")] for block, _ in weak if block.endswith(" mount")):
        spots = np.array([c[:2] for c, p, d in zip(centres_s, presses, dropped) if p.finger == f and not d])
        spans = spots.max(axis=0) - spots.min(axis=0) if len(spots) else np.zeros(2)
        short = [axis for axis, span in zip("xy", spans) if span < MOUNT_SPREAD_M]
        hints.append(
            f"press the sphere with places of the {f} pad further apart along its {' and '.join(short)} axis (at "
            f"least {1000 * MOUNT_SPREAD_M:.0f} mm apart, say its two ends and a side)"
            if short
            else f"press the sphere with at least three places of the {f} pad not in a line, the finger bent two ways"
        )
    if any(block == "hand-eye" for block, _ in weak):
        hints.append("press with more fingers, bent differently, the hand reaching the sphere from other directions")
    names = ", ".join(f"{block} {name}" for block, name in weak)
    raise InvalidInputError(f"{what}: the presses leave undetermined: {names}; {'; '.join(hints)}")


def _std(J: np.ndarray, noise: float) -> np.ndarray:
    """The parameters' standard deviations [n] at ``noise`` per residual (inf where undetermined)."""
    normal = J.T @ J
    try:
        cov = noise**2 * np.linalg.inv(normal + 1e-18 * np.eye(len(normal)))
        return np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        return np.full(len(normal), np.inf)


# --- files -----------------------------------------------------------------------------------------------


class _HandEyeFile(CalibrationFile, extra="ignore"):
    T_hand_cam: Rigid


class _Mount(CalibrationFile, extra="ignore"):
    T_fingertip_sensor: Rigid


class _MountsFile(CalibrationFile, extra="ignore"):
    sensors: Annotated[dict[str, _Mount], Field(min_length=1)]


def save_hand_eye(
    path: str | Path, T_hand_cam: np.ndarray, presses: int | None, rms_mm: float, stations: int | None = None
) -> None:
    """Write a hand-eye file saying what ``T_hand_cam`` came from: fingertip ``presses`` or arm ``stations``."""
    atomic_write(path, _hand_eye_json(T_hand_cam, presses, rms_mm, stations))


def _hand_eye_json(T_hand_cam: np.ndarray, presses: int | None, rms_mm: float, stations: int | None = None) -> bytes:
    data = {"format": HAND_EYE_FORMAT, "version": 1, "T_hand_cam": np.asarray(T_hand_cam).tolist()}
    counts = {"presses": presses, "stations": stations}
    data |= {key: n for key, n in counts.items() if n is not None} | {"rms_mm": rms_mm}
    return (json.dumps(data, indent=2) + "\n").encode()


def load_hand_eye(path: str | Path, key: str = "calibration") -> np.ndarray:
    """``T_hand_cam`` [4, 4] of a hand-eye file; one ConfigError names the file and field (``key``, the rig file's
    key or the option that names the file, when it cannot be read)."""
    return read_calibration(Path(path), _HandEyeFile, HAND_EYE_FORMAT, key=key).T_hand_cam


def save_mounts(fit: MountsFit, path: str | Path) -> None:
    sensors = {
        f: {"T_fingertip_sensor": T.tolist(), "presses": fit.presses[f], "rms_mm": fit.rms_mm[f]}
        for f, T in fit.mounts.items()
    }
    data = {"format": MOUNTS_FORMAT, "version": 1, "sensors": sensors}
    atomic_write(path, (json.dumps(data, indent=2) + "\n").encode())


def save_mounts_and_hand_eye(fit: MountsFit, path: str | Path, hand_eye_path: str | Path) -> None:
    """Write the mounts file and a hand-eye file of ``fit.T_hand_cam`` (its rms: the sensors' together), both or
    neither: the hand-eye file is written in full to its temporary file and synced, then the mounts file is written
    (atomically), and only then is the hand-eye file renamed over its target, so a full disk or an unwritable
    target leaves both old files as they were."""
    rms = float(np.sqrt(np.mean([r**2 for r in fit.rms_mm.values()])))
    with atomic_file(hand_eye_path) as hand_eye:  # renamed over its target only if the mounts file was written
        hand_eye.write(_hand_eye_json(fit.T_hand_cam, sum(fit.presses.values()), rms))
        hand_eye.flush()
        os.fsync(hand_eye.fileno())  # (a full disk shows here, before the mounts file is replaced)
        save_mounts(fit, path)


def load_mounts(path: str | Path, fingers, key: str = "calibration") -> dict[str, np.ndarray]:
    """``{finger: T_fingertip_sensor}`` of a mounts file (fingers among ``fingers``); one ConfigError names the
    file and field (``key`` when it cannot be read, as :func:`load_hand_eye`'s)."""
    path = Path(path)
    sensors = read_calibration(path, _MountsFile, MOUNTS_FORMAT, key=key).sensors
    if unknown := [finger for finger in sensors if finger not in fingers]:
        raise ConfigError(f"sensors.{unknown[0]}", f"unknown finger (one of {list(fingers)})", source=path)
    return {finger: entry.T_fingertip_sensor for finger, entry in sensors.items()}
