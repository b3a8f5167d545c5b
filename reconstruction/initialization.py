"""Initial Gaussians (paper Sec. 4.1): G_c from SfM points triangulated with the known poses, G_t on touch points.

A scene with sparse points (an import's COLMAP points3D, ``Scene.sparse_points``)
starts from them, as 3DGS does, when there are at least ``min_sfm_points``
(``Trainer._sfm``); otherwise SfM is pycolmap's: SIFT features, exhaustive
matching, and point triangulation into a reconstruction built from the
scene's known cameras (no pose estimation). Glossy objects seen in few views
often give almost no points, so when fewer than ``min_sfm_points`` come back,
random points are drawn in the scene bounds instead; nothing here crashes on a
featureless scene.
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from tacsplat.errors import StorageError
from tacsplat.files import storage_error
from tacsplat.geometry import invert_pose
from tacsplat.reconstruction.gaussians import Gaussians

log = logging.getLogger(__name__)


@dataclass
class InitConfig:
    """Initialisation settings."""

    use_sfm: bool = True
    """start from the scene's sparse points, or run pycolmap; False -> random points only"""
    min_sfm_points: int = 100
    """fewer of the scene's sparse points than this -> run pycolmap; fewer SfM points -> random points in the
    bounds"""
    num_random_points: int = 2000
    """how many random points replace a failed SfM"""
    use_silhouette_hull: bool = True
    """failed SfM: draw them on the visual hull of the object's silhouettes (views whose border fits a smooth
    backdrop) rather than in the whole bounding box"""
    hull_resolution: int = 64
    """voxels along the longest side of the bounds when carving the hull"""
    colors_from_views: bool = True
    """G_t and the fallback's points start with the median colour of the training pixels they project to (on the
    object's silhouette where a view has one; occlusion ignored); False: random colours (paper Sec. 4.1, for
    G_t)"""
    initial_opacity: float = 0.1
    """of G_c, and of G_t unless touch_initial_opacity is set (paper Sec. 4.1)"""
    touch_initial_opacity: float | None = None
    """of G_t; None: initial_opacity"""
    touch_voxel_size: float = 0.001
    """metres: touch points are thinned to one per voxel"""
    max_touch_points: int = 1000
    """then capped at this many (random subset)"""
    sift_max_features: int = 4096
    """SfM: SIFT features kept per image"""
    min_triangulation_angle_deg: float = 1.5
    """SfM: a point's rays must meet at least at this angle"""


@dataclass
class SfmResult:
    points: np.ndarray  # [M, 3] world
    colors: np.ndarray  # [M, 3] in [0, 1]


def _temporary_folder_error(exc: OSError) -> StorageError:
    """The StorageError of a full or read-only temporary folder, where SfM writes its images: names the folder and
    TMPDIR, which chooses another."""
    error = storage_error(exc, tempfile.gettempdir())
    return StorageError(error.path, f"{error.reason} (SfM's temporary files; TMPDIR chooses another folder)")


def sfm_points(
    images: list[np.ndarray],  # each [H, W, 3] float in [0, 1] or uint8
    Ks: list[np.ndarray],  # each [3, 3]
    T_world_cams: list[np.ndarray],  # each [4, 4] OpenCV camera-to-world
    config: InitConfig = InitConfig(),
    seed: int = 0,
) -> SfmResult:
    """Triangulate coloured SfM points from images with known intrinsics and poses (may return none)."""
    import pycolmap

    empty = SfmResult(np.zeros((0, 3)), np.zeros((0, 3)))
    if len(images) < 2:
        return empty
    # COLMAP's INFO lines, and its warnings about fixing the gauge of a bundle whose poses are all known, are noise here
    pycolmap.logging.minloglevel = max(pycolmap.logging.minloglevel, 2)
    try:
        workspace = tempfile.TemporaryDirectory(prefix="tacsplat-sfm-")
    except OSError as exc:
        raise _temporary_folder_error(exc) from None
    with workspace as tmp:
        tmp = Path(tmp)
        image_dir = tmp / "images"
        names = [f"{i:05d}.png" for i in range(len(images))]
        try:  # (cv2.imwrite would only return False on a full or read-only temporary folder)
            image_dir.mkdir()
            for name, image in zip(names, images):
                image = np.asarray(image)
                if image.dtype != np.uint8:
                    image = np.clip(np.round(image * 255.0), 0, 255).astype(np.uint8)
                (image_dir / name).write_bytes(cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))[1])
        except OSError as exc:
            raise _temporary_folder_error(exc) from None
        database = tmp / "database.db"
        sift = pycolmap.SiftExtractionOptions(max_num_features=config.sift_max_features)
        # (1 thread, as matching: deterministic)
        extraction = pycolmap.FeatureExtractionOptions(sift=sift, num_threads=1)
        pycolmap.extract_features(
            database,
            image_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        matching = pycolmap.FeatureMatchingOptions(num_threads=1)
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)

        reconstruction = pycolmap.Reconstruction()
        db = pycolmap.Database.open(database)
        try:
            by_name = {image.name: image for image in db.read_all_images()}
            for name, K, T_world_cam, image in zip(names, Ks, T_world_cams, images):
                record = by_name[name]
                height, width = np.asarray(image).shape[:2]
                params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
                camera = pycolmap.Camera(
                    model="PINHOLE", width=width, height=height, params=params, camera_id=record.camera_id
                )
                db.update_camera(camera)  # the known intrinsics replace the extractor's guess
                reconstruction.add_camera_with_trivial_rig(camera)
                keypoints = np.asarray(db.read_keypoints(record.image_id))[:, :2].astype(np.float64)
                colmap_image = pycolmap.Image(
                    name=name, keypoints=keypoints, camera_id=record.camera_id, image_id=record.image_id
                )
                T_cam_world = invert_pose(T_world_cam)
                cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(T_cam_world[:3, :3]), T_cam_world[:3, 3])
                reconstruction.add_image_with_trivial_frame(colmap_image, cam_from_world)
        finally:
            db.close()

        options = pycolmap.IncrementalPipelineOptions()
        options.triangulation.ignore_two_view_tracks = False  # few views: two-view tracks are most of what there is
        options.triangulation.min_angle = config.min_triangulation_angle_deg
        options.triangulation.random_seed = seed
        output = tmp / "sparse"
        output.mkdir()
        result = pycolmap.triangulate_points(reconstruction, database, image_dir, output, options=options)
        if result.num_points3D() == 0:
            return empty
        points = np.array([p.xyz for p in result.points3D.values()], dtype=np.float64)
        colors = np.array([p.color for p in result.points3D.values()], dtype=np.float64) / 255.0
        return SfmResult(points, colors)


def thin_touch_points(points: np.ndarray, config: InitConfig, rng: np.random.Generator) -> np.ndarray:
    """Indices [M] of the touch points [P, 3] kept: one per ``touch_voxel_size`` voxel, at most
    ``max_touch_points`` (random subset), in their original order."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    _, first = np.unique(np.floor(points / config.touch_voxel_size).astype(np.int64), axis=0, return_index=True)
    kept = np.sort(first)
    if len(kept) > config.max_touch_points:
        kept = kept[np.sort(rng.choice(len(kept), config.max_touch_points, replace=False))]
    return kept


def neighbour_scales(points: np.ndarray, k: int = 3, floor: float = 1e-5) -> np.ndarray:
    """Isotropic initial scales [N]: root mean squared distance to the ``k`` nearest other points."""
    if len(points) < 2:
        return np.full(len(points), 0.01)
    k = min(k, len(points) - 1)
    distances, _ = cKDTree(points).query(points, k=k + 1)
    return np.maximum(np.sqrt(np.mean(distances[:, 1:] ** 2, axis=1)), floor)


def initial_gaussians(
    color_points: np.ndarray,  # [M, 3]
    color_rgb: np.ndarray,  # [M, 3]
    touch_points: np.ndarray,  # [P, 3]
    sh_degree: int,
    config: InitConfig,
    rng: np.random.Generator,
) -> Gaussians:
    """G_c at the coloured points and G_t at the touch points (random colours), scales from neighbour distances."""
    points = np.concatenate([color_points, touch_points])
    colors = np.concatenate([color_rgb, rng.uniform(0.0, 1.0, size=(len(touch_points), 3))])
    from_touch = np.concatenate([np.zeros(len(color_points), bool), np.ones(len(touch_points), bool)])
    touch_opacity = config.initial_opacity if config.touch_initial_opacity is None else config.touch_initial_opacity
    opacities = np.where(from_touch, touch_opacity, config.initial_opacity)
    return Gaussians.from_points(points, colors, neighbour_scales(points), from_touch, sh_degree, opacities)


def view_colors(
    points: np.ndarray,  # [N, 3] world
    images: list[np.ndarray],  # each [H, W, 3] float in [0, 1]
    Ks: list[np.ndarray],  # each [3, 3]
    T_world_cams: list[np.ndarray],  # each [4, 4] OpenCV camera-to-world
    silhouettes: list[np.ndarray | None],  # each [H, W] bool (True on the object) or None: the whole frame counts
) -> np.ndarray:
    """Per point, the median colour [N, 3] of the pixels it projects to in the views where it lands on the object
    (occlusion ignored); NaN where it lands on no view's object."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    samples = np.full((len(images), len(points), 3), np.nan)  # [V, N, 3]
    for k, (image, K, T_world_cam, silhouette) in enumerate(zip(images, Ks, T_world_cams, silhouettes)):
        rows, cols, inside = _pixels(points, K, T_world_cam, image.shape)
        inside = np.flatnonzero(inside)
        rows, cols = rows[inside], cols[inside]
        if silhouette is not None:
            on_object = silhouette[rows, cols]
            inside, rows, cols = inside[on_object], rows[on_object], cols[on_object]
        samples[k, inside] = np.asarray(image, dtype=np.float64)[rows, cols]
    seen = np.isfinite(samples[..., 0]).any(axis=0)  # [N]
    colors = np.full((len(points), 3), np.nan)
    colors[seen] = np.nanmedian(samples[:, seen], axis=0)
    return colors


def _pixels(points: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray, shape: tuple) -> tuple:
    """The pixel row and column [N] (int64) each point [N, 3] projects to in a view of ``shape`` (H, W, ...), and
    [N] bool whether that pixel is in the frame and the point in front of the camera."""
    T = invert_pose(T_world_cam)
    cam = points @ T[:3, :3].T + T[:3, 3]
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):  # (behind the camera or at its centre: not inside)
        u = np.floor(K[0, 0] * cam[:, 0] / z + K[0, 2])
        v = np.floor(K[1, 1] * cam[:, 1] / z + K[1, 2])
        inside = (z > 0) & (u >= 0) & (u < shape[1]) & (v >= 0) & (v < shape[0])
        return v.astype(np.int64), u.astype(np.int64), inside


def foreground_mask(backdrop: np.ndarray) -> np.ndarray:
    """The object's silhouette [H, W] bool from a backdrop mask [H, W] (True = shows the backdrop).

    Only backdrop regions connected to the image border count as background:
    a glossy object that mirrors the backdrop colour keeps those pixels.
    """
    _, labels = cv2.connectedComponents(np.asarray(backdrop, dtype=np.uint8), connectivity=4)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    return ~np.isin(labels, border[border != 0])  # label 0: the pixels that are not backdrop


def silhouette_hull_points(
    silhouettes: list[np.ndarray],  # each [H, W] bool, True on the object
    Ks: list[np.ndarray],  # each [3, 3]
    T_world_cams: list[np.ndarray],  # each [4, 4] OpenCV camera-to-world
    lo: np.ndarray,  # [3] bounds of the search
    hi: np.ndarray,  # [3]
    count: int,
    resolution: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """``count`` points [count, 3] on the surface of the silhouettes' visual hull (empty if it is empty).

    Voxel carving: a voxel centre survives when it projects onto the object
    (a silhouette dilated by one pixel, so that thin parts are not carved
    away) in every view; outside a view's frame it survives only if that
    silhouette touches the frame's border (the object may go on there).
    Points are drawn in the voxels on the hull's boundary, jittered within them.
    """
    from scipy import ndimage

    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    voxel = float(np.max(hi - lo)) / resolution
    shape = np.maximum(np.ceil((hi - lo) / voxel).astype(int), 1)
    axes = [lo[i] + (np.arange(shape[i]) + 0.5) * voxel for i in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = np.ones(len(centres), bool)
    kernel = np.ones((3, 3), np.uint8)
    for silhouette, K, T_world_cam in zip(silhouettes, Ks, T_world_cams):
        grown = cv2.dilate(np.asarray(silhouette, np.uint8), kernel) > 0
        survivors = np.flatnonzero(inside)  # a carved voxel stays carved: only the others are projected
        v, u, seen = _pixels(centres[survivors], K, T_world_cam, grown.shape)
        on_object = np.zeros(len(survivors), bool)
        on_object[seen] = grown[v[seen], u[seen]]
        cut_by_frame = grown[0].any() or grown[-1].any() or grown[:, 0].any() or grown[:, -1].any()
        inside[survivors] = (on_object | ~seen) if cut_by_frame else on_object
    hull = inside.reshape(shape)
    boundary = hull & ~ndimage.binary_erosion(hull)
    cells = np.argwhere(boundary)
    if len(cells) == 0:
        return np.zeros((0, 3))
    picked = cells[rng.integers(0, len(cells), size=count)]
    return lo + (picked + rng.uniform(0.0, 1.0, size=(count, 3))) * voxel


def random_points(
    lo: np.ndarray, hi: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` uniform points in the box [lo, hi] with random colours."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    return rng.uniform(lo, hi, size=(count, 3)), rng.uniform(0.0, 1.0, size=(count, 3))
