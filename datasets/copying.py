"""Copying a scene into a new one through :class:`~tacsplat.datasets.SceneWriter`, optionally keeping only some
touches, with new provenance or a new sensor model (e.g. before simulated touches are added to an import)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from tacsplat.errors import InvalidInputError
from tacsplat.progress import progress_bar

from .reader import Scene
from .records import Frame, SceneMeta, SensorModel, Touch
from .writer import SceneWriter, removed_on_failure


def copy_scene(
    src: Scene | str | os.PathLike,
    dst: str | os.PathLike,
    *,
    touches: Sequence[Touch] | None = None,
    meta: SceneMeta | None = None,
    sensor: SensorModel | None = None,
    gt_mesh=None,
    frames: Sequence[Frame] | None = None,
    progress: bool = False,
) -> Path:
    """Write a new scene in ``dst`` (a new or empty folder) holding ``frames`` of ``src`` (a scene folder or a
    loaded :class:`Scene`; in the order given, default all) with their intrinsics, ground-truth depth and normals, and
    ``touches`` (records of ``src``, in the order given; default all), grasp and finger kept, ids renumbered.
    The ground-truth point cloud, if any, is copied; the sparse points (an import's SfM points) only when the copy
    keeps every frame: they were built from every image, so a copy of some frames (fewer training views, say)
    drops them and training triangulates from its own views.

    ``meta``, ``sensor`` and ``gt_mesh`` (a mesh path or ``trimesh.Trimesh``) default to the source's; a new
    sensor model is refused while touches of the old one are copied. Every record is written crash-safely; when
    the copy fails (SIGTERM and SIGHUP included), the new folder is removed again, and readers refuse a copy that
    never finished (SIGKILL). Returns ``dst``.
    """
    scene = src if isinstance(src, Scene) else Scene.load(src)
    dst = Path(dst)
    touches = list(scene.touches if touches is None else touches)
    frames = list(scene.frames if frames is None else frames)
    for frame in frames:
        if frame not in scene.frames:
            raise InvalidInputError(f"frames: frame {frame.id} ({frame.file_path}) is not a frame of {scene.path}")
    if not frames:
        raise InvalidInputError("frames: a scene needs at least one frame")
    for touch in touches:
        if touch not in scene.touches:
            raise InvalidInputError(
                f"touches: touch {touch.id} (grasp {touch.grasp}, {touch.finger}) is not a touch of {scene.path}"
            )
    sensor = scene.sensor if sensor is None else sensor
    if touches and sensor != scene.sensor:
        raise InvalidInputError(
            f"sensor: {sensor} differs from {scene.path}'s {scene.sensor}, whose touches are "
            "copied; copy no touches to give the scene another sensor model"
        )
    gt_mesh = scene.gt_mesh_path if gt_mesh is None else gt_mesh
    intrinsics = scene.intrinsics or frames[0].intrinsics
    with (
        removed_on_failure(dst),
        SceneWriter.create(dst, intrinsics, meta or scene.meta, sensor, job="copy") as writer,
    ):
        for frame in progress_bar(frames, desc="copy frames", unit="frame", enabled=progress):
            image = np.rint(scene.load_image(frame) * 255).astype(np.uint8)
            depth, mask, normal = scene.gt_depth(frame), scene.load_mask(frame), scene.gt_normal(frame)
            writer.add_frame(image, frame.T_world_cam, frame.split, depth, frame.intrinsics, mask, normal)

        motions = {}  # the source's hand file -> the copy's
        for touch in touches:
            if touch.hand_file is not None and touch.hand_file not in motions:
                motions[touch.hand_file] = writer.add_hand_motion(scene.load_hand_motion(touch))
            hand_file = motions.get(touch.hand_file)
            writer.add_touch(scene.load_touch_depth(touch), touch.T_world_sensor, touch.grasp, touch.finger, hand_file)
        if gt_mesh is not None:
            writer.set_gt_mesh(gt_mesh)
        if scene.gt_points_path is not None:
            writer.set_gt_points(scene.gt_points())
        if scene.sparse_points_path is not None and {f.id for f in frames} == {f.id for f in scene.frames}:
            writer.set_sparse_points(*scene.sparse_points())
        writer.finish()
    return dst
