"""Evaluation of a reconstruction by the design's protocol: PSNR, SSIM, Chamfer distance, renders.

The ground truth of the Chamfer distance is the visible surface of the test
cameras: the scene's ``gt/`` depth maps, or depth rendered by ray casting a
mesh given by path (imported scenes), or a point cloud given by path. The
normaliser is the ground-truth object's bounding-sphere radius (of the mesh
when there is one, else of the scene's ground-truth points, else of the
ground-truth cloud).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from tacsplat.errors import SceneFormatError, UsageError
from tacsplat.files import atomic_write
from tacsplat.geometry import project_points
from tacsplat.reconstruction import losses, shading
from tacsplat.reconstruction.baking import bake_appearance
from tacsplat.reconstruction.gaussians import Gaussians
from tacsplat.reconstruction.methods import mechanisms, method_of
from tacsplat.reconstruction.metrics import (
    SSIM_WINDOW,
    ReferenceCloud,
    bounding_sphere_radius,
    chamfer_distance_parts,
    chamfer_terms_paper,
    depth_to_points,
    finite_or_none,
    ground_truth_surface,
    mesh_metrics,
    psnr,
    ssim,
)
from tacsplat.reconstruction.ply import load_ply, make_parent, outward_normals, save_ply
from tacsplat.reconstruction.raster import rendering as raster  # the module: tests spy on its calls
from tacsplat.reconstruction.run_dir import MESH_FILES, load_run, render_backend, run_scene
from tacsplat.reconstruction.shading import Look
from tacsplat.reconstruction.views import (
    camera_tensors,
    known_backdrop,
    mesh_depth,
    over_black,
    scene_at,
    training_frames,
    warn_no_backdrop,
)

log = logging.getLogger(__name__)

ALPHA_MASK_THRESHOLD = 0.5  # rendered pixels with alpha above this give predicted surface points
PAPER_MAX_POINTS = 200_000  # cd_paper: the predicted cloud is subsampled to at most this many points (official code)
PAPER_GT_POINTS = 200_000  # cd_paper: points sampled on the ground-truth mesh surface
SEEN_TOLERANCE = 1e-3  # of the GT radius: a mesh hit this little in front of a surface point does not hide it
# a --gt-mesh this many times larger than its cameras' distances from the scene's centre is in other units: a
# millimetre file is 1000x; a forward-facing capture's (its cameras side by side, the scene's centre theirs) or an
# inside-out one's correct mesh is 10-50x
GT_SIZE_FACTOR = 100


@dataclass
class FrameRender:
    """A rendered view, as numpy on the CPU."""

    rgb: np.ndarray  # [H, W, 3] in [0, 1], composited over the backdrop
    depth: np.ndarray | None  # [H, W] expected depth, 0 where alpha <= 0.5
    alpha: np.ndarray  # [H, W]
    normal: np.ndarray | None  # [H, W, 3] unit camera-frame normals towards the camera, 0 where alpha <= 0.5
    median_depth: np.ndarray | None = None  # [H, W] as render_median_depth's, where the backend found it


@torch.no_grad()
def render_frame(
    gaussians: Gaussians,
    frame,
    background: torch.Tensor,
    backend: str,
    with_depth: bool = True,
    with_normals: bool = False,
    look: Look | None = None,
) -> FrameRender:
    """One view of ``gaussians`` (``look``: their appearance, default SH); ``background`` [H, W, 3] is the view's
    backdrop (see :func:`~.views.background_image`)."""
    look = look or Look()
    viewmat, K = (t.to(gaussians.means.device) for t in camera_tensors([frame]))
    intr = frame.intrinsics
    out = shading.render(
        gaussians,
        viewmat,
        K,
        intr.width,
        intr.height,
        sh_degree=gaussians.sh_degree,
        backend=backend,
        depth_mode="ED" if with_depth else None,
        normals=with_normals,
        appearance=look.appearance,
        light=look.light,
    )
    alpha = out.alpha.cpu()
    rgb = (out.rgb.cpu() + (1.0 - alpha[..., None]) * background.cpu()).clamp(0, 1).numpy()
    drawn = alpha.numpy() > ALPHA_MASK_THRESHOLD
    depth = None if out.depth is None else np.where(drawn, out.depth.cpu().numpy(), 0.0).astype(np.float32)
    normal = None if out.normal is None else (out.normal.cpu().numpy() * drawn[..., None]).astype(np.float32)
    median = out.meta.get("median_depths")
    median = None if median is None else median[0, ..., 0].cpu().numpy().astype(np.float32)
    return FrameRender(rgb, depth, alpha.numpy(), normal, median)


def normal_error_degrees(rendered: np.ndarray, ground_truth: np.ndarray) -> np.ndarray:
    """Angles [M] in degrees between rendered and ground-truth unit normals [H, W, 3] where both are known."""
    known = (np.linalg.norm(rendered, axis=-1) > 0.5) & (np.linalg.norm(ground_truth, axis=-1) > 0.5)
    cos = np.clip(np.einsum("ij,ij->i", rendered[known], ground_truth[known]), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def ground_truth_normals(scene, frame, gt_depth: np.ndarray) -> np.ndarray:
    """A test view's true unit normals [H, W, 3] in its camera frame: the scene's own (a dataset's normal maps)
    where it has them, else from its depth map (:func:`~.losses.depth_normals`)."""
    normal = scene.gt_normal(frame)
    if normal is not None:
        return normal.astype(np.float64) @ frame.T_world_cam[:3, :3]  # world -> camera: R^T n
    return losses.depth_normals(torch.from_numpy(gt_depth).double(), torch.from_numpy(frame.intrinsics.K)).numpy()


@torch.no_grad()
def render_median_depth(gaussians: Gaussians, frame, backend: str) -> np.ndarray:
    """Median depth [H, W] of a view (the paper's evaluation depth; 0 where the transmittance stays >= 0.5)."""
    viewmat, K = (t.to(gaussians.means.device) for t in camera_tensors([frame]))
    g, size = gaussians, (frame.intrinsics.width, frame.intrinsics.height)
    splats = (g.means, g.quats, g.scales, g.opacities, g.sh_coefficients())
    depth, _, _ = raster.rasterization(
        *splats, viewmat, K, *size, sh_degree=g.sh_degree, render_mode="MD", backend=backend
    )
    return depth[0, ..., 0].cpu().numpy().astype(np.float32)


def facing_normals(gaussians: Gaussians, frames: list, backend: str) -> torch.Tensor:
    """Unit normals [N, 3] for ``splat.ply``: each Gaussian's shortest axis, turned towards the cameras of
    ``frames`` that see its centre (no rendered median depth at its pixel nearer than it by more than its largest
    scale), so the inside of a bowl or a torus's hole faces out too; a Gaussian no camera sees takes
    the side its seen neighbours agree on, or else faces away from the centroid (:func:`.ply.outward_normals`)."""
    from scipy.spatial import cKDTree

    g = gaussians
    normals = outward_normals(g.means.detach(), g.quats.detach(), g.scales.detach()).cpu().double().numpy()  # [N, 3]
    means = g.means.detach().cpu().double().numpy()  # [N, 3]
    tolerance = g.scales.detach().cpu().double().amax(dim=-1).numpy()  # [N]
    votes = np.zeros(len(means))  # [N] sum of cos(normal, to the camera) over the cameras that see it
    for frame in frames:
        depth = render_median_depth(g, frame, backend)  # [H, W]
        uv, z = project_points(means, frame.intrinsics.K, frame.T_world_cam)  # [N, 2], [N]
        pixel = np.nan_to_num(np.floor(uv), nan=-1).astype(int)  # (behind the camera: -1, outside)
        inside = (z > 0) & (pixel >= 0).all(axis=1) & (pixel < [depth.shape[1], depth.shape[0]]).all(axis=1)
        surface = np.zeros(len(means))
        surface[inside] = depth[pixel[inside, 1], pixel[inside, 0]]
        seen = inside & (surface > 0) & (z <= surface + tolerance)
        towards = frame.T_world_cam[:3, 3] - means  # [N, 3]
        votes += np.where(seen, (towards * normals).sum(-1) / np.linalg.norm(towards, axis=1).clip(1e-12), 0.0)
    decided = np.abs(votes) > 0.1
    sign = np.where(votes < 0, -1.0, 1.0)
    if decided.any() and not decided.all():  # the rest: the side of the nearest decided ones, where they agree
        oriented = normals[decided] * sign[decided, None]  # [D, 3]
        k = min(8, int(decided.sum()))
        _, nearest = cKDTree(means[decided]).query(means[~decided], k=k)
        agreement = (oriented[nearest.reshape(-1, k)] * normals[~decided, None]).sum(-1).mean(-1)  # [U]
        sign[~decided] = np.where(agreement < -0.5, -1.0, 1.0)
    return torch.from_numpy(normals * sign[:, None]).float()


@dataclass
class GroundTruth:
    """Ground-truth surface points per test frame and the CD normaliser."""

    points: dict[int, np.ndarray]  # frame id -> [M, 3] visible GT surface
    radius: float
    source: str
    shared: np.ndarray | None = None  # [M, 3] one cloud for every view (a GT point cloud given by path)
    surface: np.ndarray | None = None  # [S, 3] cd_paper's ground truth: points on the whole object surface
    seen: dict[int, np.ndarray] | None = None  # frame id -> [M] bool: the point is in a training camera's view
    _references: dict = field(default_factory=dict, repr=False, compare=False)  # k-d trees, built once each

    def cloud(self, frame_ids: list[int]) -> np.ndarray:
        if self.shared is not None:
            return self.shared
        return np.concatenate([self.points[i] for i in frame_ids if i in self.points] or [np.zeros((0, 3))])

    def reference(self, frame_ids: list[int] | None) -> ReferenceCloud | None:
        """:meth:`cloud` of ``frame_ids`` (None: :attr:`surface`) with its k-d tree, made on first use and kept;
        None when that cloud is empty."""
        key = None if frame_ids is None else tuple(frame_ids)
        if key not in self._references:
            cloud = self.surface if key is None else self.cloud(list(key))
            empty = cloud is None or len(cloud) == 0
            self._references[key] = (
                None if empty else ReferenceCloud(cloud, self.radius, f"ground truth ({self.source})")
            )
        return self._references[key]

    def seen_mask(self, frame_ids: list[int]) -> np.ndarray | None:
        """[M] bool along :meth:`cloud`: which points a training camera sees; None without a mesh to tell."""
        if self.shared is not None or self.seen is None:
            return None
        return np.concatenate([self.seen[i] for i in frame_ids if i in self.points] or [np.zeros(0, bool)])


def seen_by_cameras(mesh, points: dict[int, np.ndarray], cameras: list, radius: float) -> dict[int, np.ndarray]:
    """Per frame, which of its surface points [M, 3] at least one of ``cameras`` sees: inside its image, and the
    mesh hit first by the ray from that camera's centre towards the point lies no nearer than the point
    (within ``SEEN_TOLERANCE`` radii)."""
    seen = {i: np.zeros(len(p), bool) for i, p in points.items()}
    for camera in cameras:
        world_to_camera = np.linalg.inv(camera.T_world_cam)
        K, centre = camera.intrinsics.K, camera.T_world_cam[:3, 3]
        for i, p in points.items():
            z = p @ world_to_camera[2, :3] + world_to_camera[2, 3]  # [M]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = (p @ world_to_camera[0, :3] + world_to_camera[0, 3]) / z * K[0, 0] + K[0, 2]
                v = (p @ world_to_camera[1, :3] + world_to_camera[1, 3]) / z * K[1, 1] + K[1, 2]
            w, h = camera.intrinsics.width, camera.intrinsics.height
            candidates = np.flatnonzero((z > 0) & (u >= 0) & (v >= 0) & (u < w) & (v < h) & ~seen[i])
            if not len(candidates):
                continue
            towards = p[candidates] - centre  # [K, 3]
            distance = np.linalg.norm(towards, axis=1)
            hits, ray, _ = mesh.ray.intersects_location(
                np.broadcast_to(centre, towards.shape), towards / distance[:, None], multiple_hits=False
            )
            first = np.full(len(candidates), np.inf)
            first[ray] = np.linalg.norm(hits - centre, axis=1)
            seen[i][candidates] = first >= distance - SEEN_TOLERANCE * radius
    return seen


def load_ground_truth(
    scene, frames: list, gt_path: str | Path | None = None, train_frames: list | None = None
) -> GroundTruth | None:
    """The CD ground truth of ``frames``: from ``gt_path`` (mesh or point cloud; refused by :func:`check_gt_size` where
    its size is far from the scene's) or the scene's gt/ (its mesh or points alone where the frames' depth shows no
    surface); None if absent. With ``train_frames`` and a mesh, it also marks which points those cameras see
    (:func:`seen_by_cameras`)."""
    import trimesh

    if gt_path is not None:
        loaded = read_ground_truth(gt_path)
        if isinstance(loaded, trimesh.Trimesh):
            radius = bounding_sphere_radius(loaded.vertices)
            check_gt_size(scene, gt_path, loaded.vertices, radius)
            points = {f.id: depth_to_points(mesh_depth(loaded, f), f.intrinsics.K, f.T_world_cam) for f in frames}
            seen = None if train_frames is None else seen_by_cameras(loaded, points, train_frames, radius)
            return GroundTruth(points, radius, f"mesh {gt_path}", surface=surface_points(loaded), seen=seen)
        radius = bounding_sphere_radius(loaded)
        check_gt_size(scene, gt_path, loaded, radius)
        return GroundTruth({}, radius, f"points {gt_path}", shared=loaded, surface=loaded)
    points, has_depth = {}, False
    for f in frames:
        depth = scene.gt_depth(f)
        has_depth |= depth is not None
        if depth is not None and (depth > 0).any():  # (a view that misses the object has no surface to compare)
            points[f.id] = depth_to_points(depth, f.intrinsics.K, f.T_world_cam)
    if not has_depth:
        return None
    # the scene's mesh, else a dataset's points on the object (NeRO's eval_pts.ply), else neither: cd_paper
    # compares with the visible surface of the test views, like cd; where their depth shows no surface (a needle
    # at a few pixels), cd_paper and the radius are the scene's mesh's or points' alone, as a --gt-mesh gives them
    own = ground_truth_surface(scene)
    if not points and own is None:
        return None
    surface, radius = own or (np.concatenate(list(points.values())), None)
    radius = bounding_sphere_radius(surface) if radius is None else radius
    mesh = surface if isinstance(surface, trimesh.Trimesh) else None
    surface = surface if mesh is None else surface_points(mesh)
    if not radius > 0:
        log.warning("the ground-truth surface of the test views is a single point: no Chamfer distance")
        return None
    seen = None if mesh is None or train_frames is None else seen_by_cameras(mesh, points, train_frames, radius)
    return GroundTruth(points, radius, "scene gt/", surface=surface, seen=seen)


def check_gt_size(scene, gt_path: str | Path, points: np.ndarray, radius: float) -> None:
    """A UsageError naming ``--gt-mesh`` when the ground truth at ``gt_path`` (its vertices or points [N, 3], their
    bounding-sphere ``radius``) and ``scene`` disagree in size by far, as a file in other units (millimetres) does:
    its radius is over ``GT_SIZE_FACTOR`` times the farthest camera's distance from the scene's centre (its
    bounds'), or it would span under a pixel in every view, seen from the nearer of the scene's centre and its own.
    """
    lo, hi = scene.bounds()
    points = np.asarray(points, dtype=np.float64)
    centres = [(lo + hi) / 2, (points.min(axis=0) + points.max(axis=0)) / 2]
    cameras = np.array([f.T_world_cam[:3, 3] for f in scene.frames])
    distances = np.stack([np.linalg.norm(cameras - c, axis=1) for c in centres])  # [2, F]
    farthest = float(distances[0].max())
    nearest = distances.min(axis=0)  # [F]
    focal = np.array([f.intrinsics.K[0, 0] for f in scene.frames])
    pixels = float((2 * radius * focal / np.maximum(nearest, 1e-12)).max())
    if radius > GT_SIZE_FACTOR * farthest:
        why = f"the scene's cameras are at most {farthest:.3g} m from the scene's centre, inside it by far"
    elif pixels < 1:
        why = f"the scene's cameras are {nearest.min():.3g} m or more from it: it would span {pixels:.2g} px at most"
    else:
        return
    raise UsageError(
        "--gt-mesh", f"{gt_path}: its bounding sphere's radius is {radius:.3g} m while {why}: wrong units? (metres)"
    )


def read_ground_truth(gt_path: str | Path):
    """A ground truth given by path (``--gt-mesh``): its mesh (a ``trimesh.Trimesh`` with faces), else its points
    [N, 3]; a SceneFormatError naming the file when it cannot be read, holds neither, has a NaN or infinite
    vertex (naming the first), or has no extent (every vertex at one point: no radius to measure distances in)."""
    import trimesh

    gt_path = Path(gt_path)
    try:
        loaded = trimesh.load(str(gt_path), process=False)  # (processing would drop a NaN vertex and its faces)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise SceneFormatError(gt_path, None, f"cannot read a ground-truth mesh or point cloud: {exc}") from exc
    if isinstance(loaded, trimesh.Scene):
        loaded = loaded.to_geometry()
    cloud = np.asarray(getattr(loaded, "vertices", []), dtype=np.float64).reshape(-1, 3)
    if len(cloud) == 0:
        raise SceneFormatError(gt_path, None, "no faces and no points")
    bad = np.flatnonzero(~np.isfinite(cloud).all(axis=1))
    if len(bad):
        raise SceneFormatError(gt_path, f"vertex {bad[0]}", f"coordinates {cloud[bad[0]].tolist()} are not finite")
    if not np.ptp(cloud, axis=0).any():
        at = cloud[0].round(6).tolist()
        raise SceneFormatError(gt_path, None, f"no extent: all its {len(cloud)} vertices lie at {at}, not on a surface")
    if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces):
        return loaded.process()  # (what trimesh.load does by default: duplicate vertices merged)
    return cloud


def surface_points(mesh, count: int = PAPER_GT_POINTS, seed: int = 0) -> np.ndarray:
    """``count`` points [count, 3] spread uniformly by area over a mesh's surface (fixed seed)."""
    import trimesh

    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, dtype=np.float64)


def evaluate_views(
    gaussians: Gaussians,
    scene,
    frames: list,
    background_color: tuple[float, float, float] | None,
    backend: str,
    ground_truth: GroundTruth | None,
    render_dir: Path | None = None,
    look: Look | None = None,
    progress: bool = False,
) -> dict:
    """PSNR, SSIM over ``frames`` (a view smaller than SSIM's window has none, with a warning), CD and cd_paper
    against ``ground_truth``, and the mean angle between rendered and ground-truth normals (``normal_error_deg``;
    :func:`ground_truth_normals`), and ``depth_bias``: the median over the pixels where both have surface of the
    rendered (expected) depth minus the true one, in units of the ground-truth radius, positive behind the truth
    (where reflections modelled as geometry put it) (NaN where not available).
    ``progress``: only what a training's progress row records (PSNR, CD and cd_paper; the rest NaN).

    ``cd`` (the design's): expected depth (alpha > 0.5) of the views against their visible ground-truth
    surface, mean distance each way, halved; where the ground truth knows which of that surface the training
    cameras see, ``cd_seen`` and ``cd_unseen`` split it there (:func:`chamfer_distance_parts`) and
    ``unseen_fraction`` is the share of the surface no training camera sees (nothing but priors and touches
    can place it). ``cd_paper`` (the paper's official code): median depth of the
    views, subsampled to at most ``PAPER_MAX_POINTS`` (fixed seed), against points on the whole ground-truth
    surface, mean squared distance each way, summed. Both in units of the ground-truth bounding-sphere radius.
    Each view's backdrop is ``background_color``, or (None) fitted to that view's image border (black where the
    border is not a smooth backdrop: a warning names those images, except in ``progress``).
    """
    psnrs, ssims, predicted, predicted_median, angles, signed = [], [], [], [], [], []
    too_small = []  # the sizes of the views smaller than SSIM's window: no SSIM for them
    no_backdrop = []  # the images of the views without a known backdrop: rendered over black
    for f in frames:
        gt_rgb = scene.load_image(f)
        backdrop = known_backdrop(gt_rgb, background_color)
        if backdrop is None:
            no_backdrop.append(scene.path / f.file_path)
        background = torch.from_numpy(over_black(backdrop, gt_rgb))
        view = render_frame(gaussians, f, background, backend, with_depth=True, with_normals=not progress, look=look)
        rgb, depth = view.rgb, view.depth
        gt_depth = scene.gt_depth(f)
        if gt_depth is not None and not progress:
            angles.append(normal_error_degrees(view.normal, ground_truth_normals(scene, f, gt_depth)))
            if ground_truth is not None:
                both = (depth > 0) & np.isfinite(gt_depth) & (gt_depth > 0)  # [H, W]
                signed.append((depth - gt_depth)[both] / ground_truth.radius)
        psnrs.append(psnr(torch.from_numpy(rgb), torch.from_numpy(gt_rgb)))
        if not progress and min(gt_rgb.shape[:2]) < SSIM_WINDOW:
            too_small.append(f"{gt_rgb.shape[1]}x{gt_rgb.shape[0]}")
        elif not progress:
            ssims.append(ssim(torch.from_numpy(rgb), torch.from_numpy(gt_rgb)))
        predicted.append(depth_to_points(depth, f.intrinsics.K, f.T_world_cam))
        if ground_truth is not None and ground_truth.surface is not None:
            median = view.median_depth if view.median_depth is not None else render_median_depth(gaussians, f, backend)
            predicted_median.append(depth_to_points(median, f.intrinsics.K, f.T_world_cam))
        if render_dir is not None:
            seen = None if ground_truth is None or ground_truth.seen is None else ground_truth.seen.get(f.id)
            radius = None if ground_truth is None else ground_truth.radius
            save_comparison(render_dir / f"view_{f.id:04d}.png", rgb, gt_rgb, depth, gt_depth, radius, seen)
    if not progress:
        warn_no_backdrop("test", no_backdrop)
    if too_small:
        message = "test views of %s px are smaller than the %dx%d window of SSIM: not measured (ssim null)"
        log.warning(message, ", ".join(sorted(set(too_small))), SSIM_WINDOW, SSIM_WINDOW)
    cd = accuracy = completeness = cd_seen = cd_unseen = unseen_fraction = float("nan")
    reference = None if ground_truth is None else ground_truth.reference([f.id for f in frames])
    if reference is not None:
        seen = None if progress else ground_truth.seen_mask([f.id for f in frames])
        cd, cd_seen, cd_unseen = chamfer_distance_parts(np.concatenate(predicted), reference, seen)
        if seen is not None:
            unseen_fraction = 1.0 - float(seen.mean())
    if predicted_median:
        cloud = np.concatenate(predicted_median)
        if len(cloud) > PAPER_MAX_POINTS:
            cloud = cloud[np.random.default_rng(0).choice(len(cloud), PAPER_MAX_POINTS, replace=False)]
        accuracy, completeness = chamfer_terms_paper(cloud, ground_truth.reference(None))
    return {
        "psnr": float(np.mean(psnrs)) if psnrs else float("nan"),
        "ssim": float(np.mean(ssims)) if ssims else float("nan"),
        "cd": cd,
        "cd_paper": accuracy + completeness,
        "cd_paper_accuracy": accuracy,  # its two summands: predicted -> ground truth ...
        "cd_paper_completeness": completeness,  # ... and ground truth -> predicted (includes unseen surface)
        "cd_seen": cd_seen,  # cd on the test views' surface that a training camera sees ...
        "cd_unseen": cd_unseen,  # ... and on the rest
        "unseen_fraction": unseen_fraction,
        "normal_error_deg": float(np.mean(np.concatenate(angles))) if sum(map(len, angles)) else float("nan"),
        "depth_bias": float(np.median(np.concatenate(signed))) if sum(map(len, signed)) else float("nan"),
    }


def _depth_color(depth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    scaled = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    colored = cv2.applyColorMap((255 * (1 - scaled)).astype(np.uint8), cv2.COLORMAP_TURBO)
    colored[depth <= 0] = 0
    return cv2.cvtColor(colored, cv2.COLOR_BGR2RGB)


ERROR_SCALE = 0.1  # of the GT radius: the depth-error panel saturates at this signed error


def _error_color(depth: np.ndarray, gt_depth: np.ndarray, scale: float) -> np.ndarray:
    """Signed depth error as RGB [H, W, 3] uint8: white 0, red behind the truth, blue in front (saturating at
    ``scale``); green where the truth has surface and the render none, dark grey the reverse, black neither."""
    both = (depth > 0) & (gt_depth > 0)
    error = np.clip(np.where(both, depth - gt_depth, 0.0) / scale, -1.0, 1.0)[..., None]  # [H, W, 1]
    behind, front = np.clip(error, 0, 1), np.clip(-error, 0, 1)
    image = np.concatenate([1 - front, 1 - behind - front, 1 - behind], axis=-1)
    image[~both] = 0.0
    image[(gt_depth > 0) & ~(depth > 0)] = (0.0, 1.0, 0.0)
    image[~(gt_depth > 0) & (depth > 0)] = (0.25, 0.25, 0.25)
    return (image * 255).round().astype(np.uint8)


def seen_pixels(gt_depth: np.ndarray, seen: np.ndarray) -> np.ndarray | None:
    """``seen`` [M] (along the valid pixels of ``gt_depth``, as :func:`depth_to_points` orders them) as an image
    [H, W] bool; None when the counts differ (the points came from another depth map)."""
    valid = np.isfinite(gt_depth) & (gt_depth > 0)
    if len(seen) != int(valid.sum()):
        return None
    image = np.zeros(gt_depth.shape, bool)
    image[valid] = seen
    return image


def _seen_color(gt_depth: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The ground-truth surface of a view [H, W, 3] uint8: light grey where a training camera sees it (``seen``
    [H, W] bool), magenta where none does, black off the surface."""
    image = np.zeros(gt_depth.shape + (3,), np.uint8)
    surface = np.isfinite(gt_depth) & (gt_depth > 0)
    image[surface & seen] = 200
    image[surface & ~seen] = (230, 0, 200)
    return image


def save_comparison(
    path: Path, rgb, gt_rgb, depth, gt_depth, radius: float | None = None, seen: np.ndarray | None = None
) -> None:
    """One PNG: top row rendered RGB | GT RGB | signed depth error (``_error_color``, saturating at
    ``ERROR_SCALE`` radii), bottom row rendered depth | GT depth (shared colour scale) | where training cameras
    see the surface (``_seen_color``); the third column is black where its input is missing."""
    valid = [d[d > 0] for d in (depth, gt_depth) if d is not None and (d > 0).any()]
    lo, hi = (min(v.min() for v in valid), max(v.max() for v in valid)) if valid else (0.0, 1.0)
    blank = np.zeros_like(gt_rgb, dtype=np.uint8)
    error = blank if gt_depth is None else _error_color(depth, gt_depth, ERROR_SCALE * (radius or max(hi - lo, 1e-9)))
    seen_image = None if gt_depth is None or seen is None else seen_pixels(gt_depth, seen)
    coverage = blank if seen_image is None else _seen_color(gt_depth, seen_image)
    top = np.concatenate([(rgb * 255).round().astype(np.uint8), (gt_rgb * 255).round().astype(np.uint8), error], axis=1)
    bottom = np.concatenate(
        [_depth_color(depth, lo, hi), blank if gt_depth is None else _depth_color(gt_depth, lo, hi), coverage], axis=1
    )
    write_png(path, np.concatenate([top, bottom], axis=0))


def write_png(path: Path, rgb: np.ndarray) -> None:
    """An RGB uint8 image [H, W, 3] as a PNG at ``path`` (its folder created), replaced atomically: a full or
    read-only disk is a StorageError naming the file (``cv2.imwrite`` would only return False)."""
    make_parent(path)
    atomic_write(path, cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))[1].tobytes())


def evaluate_run(run_dir: str | Path, gt_path: str | Path | None = None, backend: str | None = None) -> dict:
    """Evaluate a run on disk (its last checkpoint): writes ``metrics.json`` and ``renders/`` and, where the run's
    ``splat.ply`` is that of a lit run from before the bake (:func:`holds_unbaked`), replaces it with the baked one;
    returns the metrics. A ConfigError if the run's scene has changed since (:func:`~.run_dir.run_scene`)."""
    run = load_run(Path(run_dir))
    scene = scene_at(run_scene(run), run.config.downscale)
    backend = backend or render_backend(run.config, Path(run_dir))  # (an explicit --backend stands as given)
    splat = bake_appearance(run.gaussians, run.look)
    path = Path(run_dir) / "splat.ply"
    if splat is not run.gaussians and holds_unbaked(path, run.gaussians):  # (an SH run's is already right)
        log.info("%s holds the unlit colours of a run from before the bake: replaced by the baked splat", path)
        normals = facing_normals(splat, training_frames(scene, run.config.train_views), backend)
        save_ply(splat, path, normals)
    return evaluate_reconstruction(run, scene, run_dir, splat, gt_path, backend)


def holds_unbaked(path: Path, gaussians: Gaussians) -> bool:
    """Whether the PLY at ``path`` holds exactly ``gaussians`` as saved unbaked (their count, means and SH colours
    at float32), as a lit run's ``splat.ply`` from before the bake does; False for a missing or unreadable file,
    the baked one, or one edited since."""
    try:
        saved = load_ply(path) if path.is_file() else None
    except SceneFormatError:
        return False
    same = saved is not None and len(saved) == len(gaussians)
    return same and all(
        torch.equal(saved.params[k], gaussians.params[k].detach().cpu().float()) for k in ("means", "sh0")
    )


def evaluate_reconstruction(
    run, scene, run_dir: str | Path, splat: Gaussians, gt_path: str | Path | None = None, backend: str | None = None
) -> dict:
    """Evaluate the Gaussians of ``run`` (a :class:`~.run_dir.LoadedRun` or a Trainer: its ``gaussians``, ``config``,
    ``step``, ``train_seconds``, ``look`` and ``touch_points``) on a scene's test views (``psnr_splat``: the PSNR of
    what ``splat.ply`` shows a plain 3DGS renderer, ``splat``, :func:`.baking.bake_appearance` of the Gaussians and
    their look): writes ``metrics.json``, ``renders/`` and, for the sh-lit appearance, ``light.png`` (its diffuse
    light, :func:`save_light`) into ``run_dir``. The method and mechanisms it records are those the run used: touch is
    off where it had no touch points."""
    gaussians, config, look = run.gaussians, run.config, run.look
    test = scene.split("test")
    backend = backend or config.backend
    train_frames = training_frames(scene, config.train_views)
    ground_truth = load_ground_truth(scene, test, gt_path, train_frames=train_frames)
    views = (scene, test, config.background, backend)
    metrics = evaluate_views(gaussians, *views, ground_truth, Path(run_dir) / "renders", look)
    metrics["psnr_splat"] = metrics["psnr"]  # splat.ply holds the Gaussians as they are, or ...
    if look.appearance != "sh":  # ... the shading baked into SH
        metrics["psnr_splat"] = evaluate_views(splat, *views, None, progress=True)["psnr"]
    if look.light is not None:
        save_light(look.light, Path(run_dir) / "light.png")
    if not test:
        log.warning("the scene %s has no test views: PSNR, SSIM and CD are not computed (null)", scene.path)
    elif (why := no_cd_reason(scene, test, ground_truth, gt_path)) is not None:
        log.warning("%s", why)
    metrics.update(exported_mesh_metrics(Path(run_dir), scene, train_frames, gt_path))
    points = getattr(run, "touch_points", None)  # touch as the run used it: none without touch points
    touched = gaussians.num_touch > 0 if points is None else len(points) > 0
    ran = replace(config, iterations=run.step)  # a run stopped early used what started before its last step
    result = {
        **metrics,
        "train_seconds": run.train_seconds,
        "iterations": run.step,
        "num_gaussians": len(gaussians),
        "num_touch_gaussians": gaussians.num_touch,
        "num_test_views": len(test),
        "method": method_of(ran, touched),
        "mechanisms": mechanisms(ran, touched),
        "gt_source": ground_truth.source if ground_truth else None,
        "gt_radius": ground_truth.radius if ground_truth else None,
        "scene": str(scene.path),
        "settings": config.to_json(),
    }
    result = finite_or_none(result)
    atomic_write(Path(run_dir) / "metrics.json", json.dumps(result, indent=2, default=_json_default).encode())
    return result


def no_cd_reason(scene, test: list, ground_truth: GroundTruth | None, gt_path: str | Path | None) -> str | None:
    """Why ``cd`` is NaN, where the ``test`` views have no ground-truth surface to compare with (and what cd_paper
    compares with then); None where they have one."""
    if ground_truth is not None and (any(map(len, ground_truth.points.values())) or ground_truth.shared is not None):
        return None
    outside = "(the object lies outside them, or under a pixel)"
    if gt_path is not None:
        why = f"the test views show no surface of the --gt-mesh {gt_path} {outside}"
    elif ground_truth is None and not any(scene.gt_depth(f) is not None for f in test):
        return "no ground truth for the test views (no gt/ depth and no --gt-mesh): cd is NaN"
    else:
        why = f"the test views' ground-truth depth (gt/depth/) shows no surface {outside}"
    if ground_truth is None:
        return f"{why}, and the scene has no ground-truth mesh or points: cd and cd_paper are NaN"
    return f"{why}: cd is NaN; cd_paper compares with the whole ground-truth surface ({ground_truth.source})"


def exported_mesh_metrics(run_dir: Path, scene, train_frames: list, gt_path: str | Path | None = None) -> dict:
    """The mesh metrics (:func:`~.metrics.mesh_metrics`, split by what ``train_frames`` see) of the meshes
    ``tacsplat export mesh`` wrote into the run (:data:`~.run_dir.MESH_FILES`: ``mesh_*`` of ``RUN/mesh.ply``,
    ``mesh_untouched_*`` of ``RUN/mesh-untouched.ply``), against ``gt_path`` (a mesh or point cloud, ``evaluate
    --gt-mesh``) where given, else the scene's ground truth: the same truth as the rest of the metrics. Empty
    without such a mesh or a ground truth."""
    import trimesh

    meshes = {prefix: run_dir / name for prefix, name in MESH_FILES.items() if (run_dir / name).is_file()}
    if not meshes:
        return {}
    if gt_path is not None:
        gt = read_ground_truth(gt_path)
        truth = gt, bounding_sphere_radius(gt.vertices if isinstance(gt, trimesh.Trimesh) else gt)
    else:
        truth = ground_truth_surface(scene)
    if truth is None:
        return {}
    seen_by = seen_by_training_views(*truth, train_frames)
    result = {}
    for prefix, path in meshes.items():
        metrics = mesh_metrics(trimesh.load(str(path), force="mesh"), *truth, seen_by=seen_by)
        result.update({prefix + key[len("mesh") :]: value for key, value in metrics.items()})
    return result


def seen_by_training_views(gt, radius: float, train_frames: list):
    """:func:`~.metrics.mesh_metrics`'s ``seen_by`` for a ground-truth mesh ``gt``: which of its points [S, 3] the
    training cameras see (:func:`seen_by_cameras`); None for a ground truth of points (nothing occludes)."""
    import trimesh

    if not isinstance(gt, trimesh.Trimesh):
        return None
    return lambda points: seen_by_cameras(gt, {0: points}, train_frames, radius)[0]


def equirect_directions(height: int, device=None) -> torch.Tensor:
    """Unit world directions [H, 2H, 3] through the texel centres of an equirectangular map: zenith at the top row,
    azimuth from -180 degrees at the left."""
    v = (2 * torch.arange(height, device=device, dtype=torch.float64) + 1) / height - 1.0  # [H], -1 at the top
    u = (2 * torch.arange(2 * height, device=device, dtype=torch.float64) + 1) / (2 * height) - 1.0  # [2H]
    elevation, azimuth = torch.meshgrid(-v * (math.pi / 2), u * math.pi, indexing="ij")
    return torch.stack([elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin()], dim=-1)


def save_light(light, path: Path, height: int = 32) -> None:
    """The sh-lit appearance's diffuse light as an equirectangular PNG (:func:`equirect_directions`), 4x
    upscaled, tone-mapped x / (1 + x): the irradiance a normal pointing each way receives, the camera light left out
    (it follows the camera)."""
    with torch.no_grad():
        normals = equirect_directions(height, light.coefficients.device).to(light.coefficients.dtype)
        irradiance = light.irradiance(normals, normals).cpu().numpy()  # views along the normals: no camera light
    image = (255 * irradiance / (1.0 + irradiance)).round().astype(np.uint8)
    write_png(path, cv2.resize(image, (image.shape[1] * 4, image.shape[0] * 4), interpolation=cv2.INTER_NEAREST))


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
