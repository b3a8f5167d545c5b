"""Next-best touch: the grasp whose fingertips land where the reconstruction is least sure.

The selector, shared by the twin's closed loop and the operator session:

1. **candidates**: on the twin, ``candidates`` approaches of its sampler per grasp
   (:meth:`~tacsplat.acquisition.twin_planner.TwinPlanner.approach`; candidate ``k`` of grasp ``g`` from a
   generator seeded with ``(seed, g, k)``, candidate 0 the random strategy's grasp ``g``), each tapping fingertip
   a :class:`Pad` at its preshape pose; at a real
   rig, approach directions spread over the sphere around the reconstruction, one fingertip each
   (:func:`approach_candidates`);
2. **predicted contact patches** (:func:`predict_patch`): a near-orthographic camera behind the pad looks along
   its normal over the pad's area and renders the per-Gaussian uncertainty
   (:mod:`tacsplat.reconstruction.uncertainty`; with the ``depth-variance`` score, combined with the spread of
   depth along these candidate rays) and the expected depth; the surface the pad meets first within reach, with
   every pixel whose surface lies within the gel's contact depth beyond it, is the patch;
3. **expected information**: the uncertain area touched, the sum over patch pixels of area x uncertainty x
   (1 - coverage), the coverage ``exp(-d^2 / 2 r^2)`` of the distance ``d`` to the nearest earlier touch point:
   what earlier touches cover counts for little;
4. the best candidate is executed (the next best when it touches nothing); ties go to the lower candidate number.

The closed loop (:class:`NextTouchPlanner`, ``sim-capture --grasp-strategy next-best``): before grasp ``g`` the
scene so far (its train views and the touches of the grasps before ``g``) is reconstructed for ``selection_steps``
steps (:func:`~tacsplat.reconstruction.uncertainty.brief_reconstruction`: the same Gaussians from the same scene
on every CPU run), the candidates are scored, and the decision is recorded through the scene's writer, in
scene.json's ``annotations["next_touch"]``, before the hand moves. A resumed capture reuses the decision of a grasp
cut short (the writer's journal holds it) and re-creates the reconstruction of the later ones from the scene, so it
chooses the grasps an uninterrupted capture chooses.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from tacsplat.acquisition.config import GraspPlan
from tacsplat.acquisition.logger import CaptureLogger, CaptureRejected, GraspOutcome, finger_joints
from tacsplat.acquisition.twin_planner import MAX_ATTEMPTS_PER_GRASP, TwinPlanner
from tacsplat.datasets import Scene, SceneWriter, SensorModel
from tacsplat.geometry import invert_pose, make_pose
from tacsplat.reconstruction.gaussians import Gaussians
from tacsplat.reconstruction.uncertainty import (
    Views,
    brief_reconstruction,
    depth_moments,
    depth_tolerance,
    extent,
    gaussian_uncertainty,
    one_thread,
    render_uncertainty,
)
from tacsplat.sim.views import fibonacci_directions

log = logging.getLogger(__name__)

DECISIONS_KEY = "next_touch"  # the decisions of a next-best capture: this key of its scene.json's annotations
STANDOFF_M = 0.5  # the patch camera's distance behind the pad: a near-orthographic view of the pad's area


@dataclass(frozen=True)
class PatchModel:
    """How a fingertip's contact is predicted: the pad's area, how far it reaches along its normal, the gel's contact
    depth, and how far from an earlier touch point a surface point counts as covered (metres)."""

    width_m: float
    height_m: float
    reach_m: float = 0.04  # the twin's pre-touch gap (at most 0.03) and a margin for a rough reconstruction
    contact_depth_m: float = 0.0015  # the surface within this of the first contact is pressed too
    behind_m: float = 0.005  # surface up to this far behind the pad's plane is in contact already
    coverage_radius_m: float = 0.002
    pixels: int = 24  # across the pad's width

    @classmethod
    def of_sensor(cls, sensor: SensorModel, **changes) -> "PatchModel":
        """The patch model of a scene's tactile sensor (``changes``: other fields)."""
        return cls(sensor.width_px * sensor.pixel_size_m, sensor.height_px * sensor.pixel_size_m, **changes)


@dataclass
class Pad:
    """A fingertip about to tap: its sensor frame (z along the gel's outward normal, towards the object)."""

    finger: str
    T_world_sensor: np.ndarray  # [4, 4]


@dataclass
class Candidate:
    """A grasp that could be made: its number among the candidates, its tapping pads, its approach direction."""

    index: int
    pads: list[Pad]
    approach_from: np.ndarray  # [3] unit, from the object towards the hand


@dataclass
class Belief:
    """What is known: the reconstruction, its per-Gaussian uncertainty [N] and the earlier touch points [M, 3];
    with ``ray_tolerance_m``, also the spread of depth along each candidate ray (the ``depth-variance`` score's
    ``Var / (Var + tol^2)``, combined with the rendered uncertainty as ``1 - (1 - a)(1 - b)``)."""

    gaussians: Gaussians
    uncertainty: torch.Tensor
    touch_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    ray_tolerance_m: float | None = None
    _tree: object = field(default=None, repr=False)

    def coverage(self, points: np.ndarray, radius: float) -> np.ndarray:
        """How much of each point [P, 3] earlier touches cover: ``exp(-d^2 / 2 radius^2)``, ``d`` the distance to
        the nearest touch point (0 without touches)."""
        if len(self.touch_points) == 0 or len(points) == 0:
            return np.zeros(len(points))
        if self._tree is None:
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.touch_points)
        distance, _ = self._tree.query(points)
        return np.exp(-0.5 * (distance / radius) ** 2)


@dataclass
class Patch:
    """A pad's predicted contact: surface points [P, 3] with their uncertainty, coverage and area (m^2)."""

    finger: str
    points: np.ndarray
    uncertainty: np.ndarray
    coverage: np.ndarray
    area_m2: np.ndarray
    distance_m: float  # how far the pad moves along its normal to the first contact

    @property
    def score(self) -> float:
        """The uncertain area it touches (m^2)."""
        return float((self.area_m2 * self.uncertainty * (1.0 - self.coverage)).sum())


@dataclass
class ScoredCandidate:
    candidate: Candidate
    patches: list[Patch]

    @property
    def score(self) -> float:
        """Expected information: the uncertain area its pads touch (m^2)."""
        return float(sum(p.score for p in self.patches))

    def to_json(self) -> dict:
        return {
            "candidate": self.candidate.index,
            "score_mm2": round(self.score * 1e6, 4),
            "approach_from": [round(float(v), 6) for v in self.candidate.approach_from],
            "patches": {
                p.finger: {
                    "score_mm2": round(p.score * 1e6, 4),
                    "centre": [round(float(v), 6) for v in p.points.mean(axis=0)],
                    "area_mm2": round(float(p.area_m2.sum()) * 1e6, 3),
                }
                for p in self.patches
            },
        }


def _patch_camera(pad: Pad, model: PatchModel, device) -> tuple[torch.Tensor, torch.Tensor, int, int, float]:
    """``(viewmat, K, width, height, footprint)`` of the camera ``STANDOFF_M`` behind the pad looking along its normal,
    whose pixels cover ``footprint`` metres each on the pad's plane."""
    width = model.pixels
    height = max(1, round(model.pixels * model.height_m / model.width_m))
    footprint = model.width_m / width
    focal = STANDOFF_M / footprint
    T_world_cam = pad.T_world_sensor @ make_pose(np.eye(3), [0.0, 0.0, -STANDOFF_M])
    viewmat = torch.tensor(invert_pose(T_world_cam), dtype=torch.float32, device=device)
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float32, device=device)
    return viewmat, K, width, height, footprint


def predict_patch(belief: Belief, pad: Pad, model: PatchModel) -> Patch | None:
    """Where ``pad`` meets the reconstruction when it moves along its normal: the first surface within
    ``model.reach_m`` and everything within the contact depth beyond it; None when it meets nothing."""
    viewmat, K, width, height, footprint = _patch_camera(pad, model, belief.gaussians.means.device)
    near = STANDOFF_M - model.behind_m
    uncertainty, alpha, depth = render_uncertainty(
        belief.gaussians, belief.uncertainty, viewmat, K, width, height, near_plane=near
    )
    if belief.ray_tolerance_m is not None:
        _, _, variance = depth_moments(belief.gaussians, viewmat, K, width, height, near_plane=near)
        spread = variance / (variance + belief.ray_tolerance_m**2)
        uncertainty = 1.0 - (1.0 - uncertainty) * (1.0 - spread)
    uncertainty, alpha, depth = (t.cpu().numpy().astype(np.float64) for t in (uncertainty, alpha, depth))
    travel = depth - STANDOFF_M  # along the pad's normal, from its plane
    met = (alpha > 0.5) & (travel >= -model.behind_m) & (travel <= model.reach_m)
    if not met.any():
        return None
    first = float(travel[met].min())
    rows, cols = np.nonzero(met & (travel <= first + model.contact_depth_m))
    t = travel[rows, cols]
    scale = footprint * (STANDOFF_M + t) / STANDOFF_M  # a pixel's size on the surface
    local = np.stack([(cols + 0.5 - width / 2) * scale, (rows + 0.5 - height / 2) * scale, t], axis=1)
    points = local @ pad.T_world_sensor[:3, :3].T + pad.T_world_sensor[:3, 3]
    return Patch(
        pad.finger,
        points,
        uncertainty[rows, cols],
        belief.coverage(points, model.coverage_radius_m),
        scale**2,
        max(first, 0.0),
    )


def score_candidate(belief: Belief, candidate: Candidate, model: PatchModel) -> ScoredCandidate:
    patches = [patch for pad in candidate.pads if (patch := predict_patch(belief, pad, model)) is not None]
    return ScoredCandidate(candidate, patches)


def rank_candidates(belief: Belief, candidates: list[Candidate], model: PatchModel) -> list[ScoredCandidate]:
    """The candidates scored, best first (ties: the lower candidate number first)."""
    scored = [score_candidate(belief, c, model) for c in candidates]
    return sorted(scored, key=lambda s: (-s.score, s.candidate.index))


def belief_of(scene, gaussians: Gaussians, score: str, seed: int = 0) -> Belief:
    """The belief of a reconstruction of ``scene``: its ``score`` under the scene's train views (``depth-variance``:
    and along the candidate rays), and the scene's touch points."""
    views = Views.of_frames(scene, scene.split("train"), gaussians.means.device)
    tolerance = depth_tolerance(gaussians, views) if score == "depth-variance" else None
    return Belief(
        gaussians,
        gaussian_uncertainty(gaussians, views, score, seed=seed, tolerance_m=tolerance),
        scene.touch_points(),
        tolerance,
    )


# --- the twin's closed loop --------------------------------------------------------------------------------


class ChoiceLog:
    """The decisions of a next-best capture: ``{"grasps": [...]}`` under ``DECISIONS_KEY`` in scene.json's
    annotations, recorded (journaled) and read back through the scene's writer.

    One entry per grasp: the scene it was decided on (train views, touches), every candidate's score, the
    ranking, the candidate executed, and the seconds the decision took."""

    def __init__(self, writer: SceneWriter):
        self.writer = writer

    @property
    def grasps(self) -> list[dict]:
        return self.writer.annotations.get(DECISIONS_KEY, {"grasps": []})["grasps"]

    def decision(self, index: int, state: dict) -> dict | None:
        """The decision of grasp ``index`` taken on a scene in ``state``, if there is one."""
        return next((d for d in self.grasps if d["grasp"] == index and d["scene"] == state), None)

    def save(self, decision: dict) -> None:
        others = [d for d in self.grasps if d["grasp"] != decision["grasp"]]
        self.writer.annotate(DECISIONS_KEY, {"grasps": sorted([*others, decision], key=lambda d: d["grasp"])})


def scene_state(scene) -> dict:
    """What a decision depends on: the train views and touches of the scene so far."""
    return {"train_views": len(scene.split("train")), "touches": len(scene.touches)}


class NextTouchPlanner:
    """The twin's grasps of ``plan.mode == "next-best"``, with the :class:`TwinPlanner`'s interface
    (``before_view``, ``grasp``); ``train_config``: the brief reconstruction's (default: ``selection_steps`` steps,
    the plan's seed)."""

    def __init__(self, twin_planner: TwinPlanner, plan: GraspPlan, train_config=None):
        from tacsplat.reconstruction.config import TrainConfig

        self.twin_planner = twin_planner
        self.plan = plan
        self.train_config = train_config or TrainConfig(iterations=plan.selection_steps, seed=plan.seed)

    def before_view(self, split: str, index: int) -> None:
        self.twin_planner.before_view(split, index)

    def _rng(self, index: int, k: int) -> np.random.Generator:
        """Candidate ``k``'s generator; candidate 0 is the random strategy's grasp (TwinPlanner's generator)."""
        return np.random.default_rng([self.plan.seed, index] + ([k] if k else []))

    def candidate(self, index: int, k: int) -> tuple[Candidate, np.ndarray, np.ndarray]:
        """Candidate ``k`` of grasp ``index``, its close pose [16] and its preshape [16]: the twin placed on the
        approach, the pads of the fingers that tap (those the preshape reached) at their preshape poses."""
        twin = self.twin_planner.twin
        q_close, q_pre = self.twin_planner.approach(self._rng(index, k))
        T_world_hand = twin.T_world_hand()
        tips = twin.hand.fingertip_poses()
        pads = [
            Pad(finger, T_world_hand @ tips[finger])
            for finger, j in finger_joints(twin.hand.joint_names).items()
            if finger in tips and not np.allclose(q_close[j], q_pre[j])
        ]
        return Candidate(k, pads, -T_world_hand[:3, 2]), q_close, q_pre

    def decide(self, scene, index: int) -> dict:
        """Reconstruct the scene so far briefly, score the candidates of grasp ``index``; the decision."""
        started = time.perf_counter()
        if not scene.split("train"):
            raise CaptureRejected("next-best grasps need the reconstruction of a train view: take one first")
        gaussians = brief_reconstruction(scene, self.train_config)
        with one_thread():
            belief = belief_of(scene, gaussians, self.plan.uncertainty, self.plan.seed)
            model = PatchModel.of_sensor(scene.sensor)
            candidates = [self.candidate(index, k)[0] for k in range(self.plan.candidates)]
            ranked = rank_candidates(belief, candidates, model)
        best = ranked[0]
        log.info(
            "grasp %d: candidate %d of %d expects %.1f mm^2 of uncertain surface (median candidate %.1f)",
            index,
            best.candidate.index,
            len(ranked),
            best.score * 1e6,
            ranked[len(ranked) // 2].score * 1e6,
        )
        return {
            "grasp": index,
            "scene": scene_state(scene),
            "uncertainty": self.plan.uncertainty,
            "reconstruction": {"steps": self.train_config.iterations, "gaussians": len(gaussians)},
            "ranking": [s.candidate.index for s in ranked],
            "candidates": [s.to_json() for s in sorted(ranked, key=lambda s: s.candidate.index)],
            "executed": None,
            "selection_seconds": round(time.perf_counter() - started, 3),
        }

    def grasp(self, logger: CaptureLogger, index: int) -> GraspOutcome | None:
        """Grasp number ``index``: decide (or reuse the decision taken on this same scene), then execute the best
        candidate, the next best when one touches nothing, up to ``MAX_ATTEMPTS_PER_GRASP``; None when none
        touched."""
        choices = ChoiceLog(logger.writer)
        scene = Scene.load(logger.writer.path)
        decision = choices.decision(index, scene_state(scene))
        if decision is None:
            decision = self.decide(scene, index)
            choices.save(decision)  # before the hand moves: a capture cut short redoes this same grasp
        for k in decision["ranking"][:MAX_ATTEMPTS_PER_GRASP]:
            _, q_close, q_pre = self.candidate(index, k)
            outcome = logger.take_grasp(close_pose=q_close, open_pose=q_pre, index=index)  # released to the preshape
            if outcome.fingers_in_contact:
                choices.save({**decision, "executed": k})
                return outcome
            logger.undo()
            log.info("grasp %d, candidate %d touched nothing; trying the next best", index, k)
        log.warning("grasp %d: the best %d candidates touched nothing; skipped", index, MAX_ATTEMPTS_PER_GRASP)
        return None


# --- suggestions at a real rig -------------------------------------------------------------------------------


def approach_candidates(
    gaussians: Gaussians, count: int, min_elevation_deg: float = -30.0, margin_m: float = 0.02
) -> list[Candidate]:
    """``count`` approaches spread evenly (a Fibonacci spiral) over the directions above ``min_elevation_deg``
    around the reconstruction, each one fingertip facing its centre from ``margin_m`` outside it."""
    means = gaussians.means.detach().cpu().numpy().astype(np.float64)
    centre = np.median(means, axis=0)
    radius = 0.5 * extent(gaussians)
    candidates = []
    for k, d in enumerate(fibonacci_directions(count, np.deg2rad(min_elevation_deg), np.pi / 2)):
        normal = -d
        helper = np.array([0.0, 0.0, 1.0]) if abs(normal[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x = np.cross(helper, normal)
        x /= np.linalg.norm(x)
        pose = make_pose(np.stack([x, np.cross(normal, x), normal], axis=1), centre + d * (radius + margin_m))
        candidates.append(Candidate(k, [Pad("fingertip", pose)], d))
    return candidates


@dataclass
class GraspSuggester:
    """The next grasp at a real rig, from a reconstruction in progress (``run_dir``: a ``tacsplat reconstruct``
    folder; its latest checkpoint is read each time)."""

    run_dir: str | Path
    uncertainty: str = "depth-variance"
    candidates: int = 64

    def suggest(self, scene) -> ScoredCandidate | None:
        """The best approach for ``scene`` (the capture so far: its train views and touches); None when no
        candidate touches anything uncertain."""
        from tacsplat.reconstruction.run_dir import load_run

        if scene.sensor is None:
            raise CaptureRejected(f"{scene.path} has no tactile sensor model: nothing to suggest a touch for")
        gaussians = load_run(self.run_dir).gaussians
        belief = belief_of(scene, gaussians, self.uncertainty)
        radius = 0.5 * extent(gaussians)
        model = PatchModel.of_sensor(scene.sensor, reach_m=2.0 * radius + 0.04)
        best = rank_candidates(belief, approach_candidates(gaussians, self.candidates), model)[0]
        return best if best.score > 0 else None


def draw_suggestion(
    image: np.ndarray, suggestion: ScoredCandidate, T_world_cam: np.ndarray, K: np.ndarray
) -> np.ndarray:
    """``image`` [H, W, 3] uint8 RGB with the suggested patch (its points, outlined, and a ring around it that a
    small patch still shows) and the approach (an arrow from 5 cm out to the patch's centre) drawn in, seen by the
    camera at ``T_world_cam`` with intrinsics ``K``."""
    import cv2

    out = np.ascontiguousarray(image).copy()
    T_cam_world = invert_pose(T_world_cam)

    def project(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cam = points @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
        front = cam[:, 2] > 1e-6
        uv = cam[:, :2] / np.where(front, cam[:, 2], 1.0)[:, None] * np.diag(K)[:2] + K[:2, 2] - 0.5
        return np.round(uv).astype(np.int32), front  # tacsplat's pixel centres (+0.5) -> OpenCV's

    points = np.concatenate([p.points for p in suggestion.patches])
    uv, front = project(points)
    for u, v in uv[front]:
        cv2.circle(out, (int(u), int(v)), 1, (255, 0, 255), -1)
    if front.sum() >= 3:
        cv2.polylines(out, [cv2.convexHull(uv[front])], True, (255, 0, 255), 2)
    centre = points.mean(axis=0)
    ends, seen = project(np.stack([centre + 0.05 * suggestion.candidate.approach_from, centre]))
    if seen[1]:
        spread = np.abs(uv[front] - ends[1]).max() if front.any() else 0
        cv2.circle(out, tuple(map(int, ends[1])), int(max(6, spread + 3)), (255, 0, 255), 1)
    if seen.all():
        cv2.arrowedLine(out, tuple(map(int, ends[0])), tuple(map(int, ends[1])), (0, 255, 255), 2, tipLength=0.25)
    return out
