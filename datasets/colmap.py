"""Import a COLMAP sparse model (text or binary, read with pycolmap) into a scene directory.

COLMAP stores world-to-camera poses with OpenCV camera axes (x right, y down,
z forward) and puts the centre of the top-left pixel at (0.5, 0.5), the same
conventions as tacsplat, so poses are only inverted and intrinsics copied.
Undistortion is out of scope: cameras must be pinhole (``PINHOLE``,
``SIMPLE_PINHOLE``) or a distortion model whose distortion parameters are all
zero (``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``); run ``colmap
image_undistorter`` first otherwise. The test split holds every
``test_every``-th image in name order (the 3DGS/LLFF hold-out convention).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tacsplat.progress import progress_bar
from tacsplat.errors import ConfigError, SceneFormatError
from tacsplat.geometry import intrinsics_matrix, invert_pose
from tacsplat.types import CameraIntrinsics

from .blender import check_scale, composite, read_rgba
from .outputs import claim_output_dir
from .records import SceneMeta
from .writer import SceneWriter, check_new_scene_dir, removed_on_failure

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
ZERO_DISTORTION_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")


def camera_intrinsics(camera, model_path: Path) -> CameraIntrinsics:
    """Intrinsics of a pycolmap camera, or a SceneFormatError naming the camera and its model."""
    model = camera.model_name
    field = f"camera {camera.camera_id}"
    if model not in PINHOLE_MODELS + ZERO_DISTORTION_MODELS:
        raise SceneFormatError(model_path, field, f"camera model {model} is not supported: undistort the images first "
                               "(colmap image_undistorter) to get a PINHOLE model")
    distortion = np.asarray(camera.params)[list(camera.extra_params_idxs())]
    if np.any(distortion != 0):
        raise SceneFormatError(model_path, field, f"camera model {model} has non-zero distortion {distortion.tolist()}: "
                               "undistort the images first (colmap image_undistorter)")
    K = intrinsics_matrix(camera.focal_length_x, camera.focal_length_y, camera.principal_point_x, camera.principal_point_y)
    return CameraIntrinsics(K, int(camera.width), int(camera.height))


def _dataset_name(model_dir: Path) -> str:
    """``garden`` for ``.../garden/sparse/0``: the first folder up that is not ``sparse`` or a model number."""
    for part in (model_dir.resolve(), *model_dir.resolve().parents):
        if part.name and part.name != "sparse" and not part.name.isdigit():
            return part.name
    return "colmap"


def import_colmap(model_dir, images_dir, out, test_every: int = 8, scale: float = 1.0, object_name: str | None = None) -> Path:
    """Convert the COLMAP model in ``model_dir`` (e.g. ``sparse/0``) with images in ``images_dir`` into ``out``.

    ``scale`` multiplies translations (COLMAP's scale is arbitrary; the scene
    claims metres). ``test_every = 0`` puts every image in the train split.
    ``out`` is claimed as the ``--out`` of a writing command (``datasets.outputs``). Returns ``out``.
    """
    import pycolmap

    model_dir, images_dir, out = Path(model_dir), Path(images_dir), Path(out)
    check_scale(scale)
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 0:
        raise ConfigError("test_every", f"must be an integer >= 0 (0: no test split), got {test_every!r}")
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except (ValueError, RuntimeError) as exc:
        raise SceneFormatError(model_dir, None, f"not a readable COLMAP sparse model: {exc}") from exc
    images = sorted((img for img in rec.images.values() if img.has_pose), key=lambda img: img.name)
    if not images:
        raise SceneFormatError(model_dir, "images", "the model has no registered images")
    intrinsics = {cid: camera_intrinsics(cam, model_dir) for cid, cam in rec.cameras.items()}

    meta = SceneMeta(
        source="import",
        object=object_name or _dataset_name(model_dir),
        extra={"importer": "colmap", "source_path": str(model_dir.resolve()), "images_path": str(images_dir.resolve()),
               "scale": scale, "test_every": test_every, "num_points3D": rec.num_points3D(),
               "colmap_names": [img.name for img in images]},
    )
    check_new_scene_dir(out)  # before the claim, which would put its lock file among someone's files
    with claim_output_dir(out), removed_on_failure(out), \
            SceneWriter.create(out, intrinsics[images[0].camera_id], meta) as writer:
        for i, img in enumerate(progress_bar(images, desc=f"import {model_dir}", unit="frame")):
            intr = intrinsics[img.camera_id]
            image_path = images_dir / img.name
            rgb = composite(read_rgba(image_path)[:, :, :3], (0, 0, 0))  # an alpha channel, if any, is dropped
            if rgb.shape[:2] != (intr.height, intr.width):
                raise SceneFormatError(image_path, f"image {img.image_id}", f"image is {rgb.shape[1]}x{rgb.shape[0]} but "
                                       f"camera {img.camera_id} is {intr.width}x{intr.height}")
            T_cam_world = np.eye(4)
            T_cam_world[:3] = img.cam_from_world().matrix()
            T_world_cam = invert_pose(T_cam_world)
            T_world_cam[:3, 3] *= scale
            split = "test" if test_every and i % test_every == 0 else "train"
            writer.add_frame(rgb, T_world_cam, split=split, intrinsics=intr)
    return out
