"""A scene directory drawn in viser: camera frusta with thumbnails, touches by grasp with their gel frames, the
ground-truth mesh and the object's bounding sphere."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tacsplat.geometry import minimum_sphere

THUMBNAIL_PX = 96  # longest side of a frustum's image
SPLIT_COLORS = {"train": (40, 90, 220), "test": (230, 120, 20)}
MESH_COLOR = (150, 150, 150)
SPHERE_COLOR = (120, 200, 120)


@dataclass
class Sphere:
    centre: np.ndarray  # [3] metres
    radius: float
    source: str  # what it was fitted to


@dataclass
class SceneNodes:
    """The scene nodes of one scene, by what a toggle shows or hides."""

    sphere: Sphere
    groups: dict[str, list] = field(default_factory=dict)  # "cameras", "touches", "mesh", "sphere" -> nodes


def load_mesh(scene):
    """The scene's ground-truth mesh (trimesh), or None when it has none."""
    path = scene.gt_mesh_path
    if path is None or not path.is_file():
        return None
    import trimesh

    return trimesh.load(str(path), force="mesh")


def bounding_sphere(scene, mesh=None) -> Sphere:
    """The object's bounding sphere: the minimum sphere of the ground-truth mesh when the scene has one, else
    the sphere through the corners of the region every camera sees and every touch reaches (``Scene.bounds``)."""
    if mesh is not None:
        centre, radius, _ = minimum_sphere(mesh.vertices)
        return Sphere(np.asarray(centre, dtype=np.float64), float(radius), "ground-truth mesh")
    lo, hi = scene.bounds()
    return Sphere((lo + hi) / 2, float(np.linalg.norm(hi - lo) / 2), "cameras and touches (no ground-truth mesh)")


def grasp_colors(grasps: list[int]) -> dict[int, tuple[int, int, int]]:
    """One colour per grasp (matplotlib's tab10, cycled)."""
    import matplotlib

    palette = matplotlib.colormaps["tab10"].colors
    return {g: tuple(int(round(255 * c)) for c in palette[i % len(palette)]) for i, g in enumerate(sorted(grasps))}


def _thumbnail(image: np.ndarray) -> np.ndarray:
    import cv2

    h, w = image.shape[:2]
    factor = THUMBNAIL_PX / max(h, w)
    if factor < 1:
        image = cv2.resize(image, (max(1, round(w * factor)), max(1, round(h * factor))), interpolation=cv2.INTER_AREA)
    return (np.clip(image, 0, 1) * 255).round().astype(np.uint8)


def add_cameras(scene_api, name: str, scene, size: float) -> list:
    """A frustum per frame (OpenCV pose, its field of view) with the frame's image, coloured by split."""
    import viser.transforms as vtf

    return [
        scene_api.add_camera_frustum(
            f"{name}/{frame.split}/frame_{frame.id:04d}",
            fov=float(2 * np.arctan2(0.5 * frame.intrinsics.height, frame.intrinsics.fy)),
            aspect=frame.intrinsics.width / frame.intrinsics.height,
            scale=size,
            thickness=0.03 * size,
            color=SPLIT_COLORS[frame.split],
            image=_thumbnail(scene.load_image(frame)),
            wxyz=vtf.SO3.from_matrix(frame.T_world_cam[:3, :3]).wxyz,
            position=frame.T_world_cam[:3, 3],
        )
        for frame in scene.frames
    ]


def add_touches(scene_api, name: str, scene) -> list:
    """Each grasp's contact points in its colour, and each sensor's gel frame (axes at the undeformed gel's
    centre, z towards the object) with the gel pad behind it."""
    import viser.transforms as vtf

    from tacsplat.geometry import tactile_depth_to_points

    if not scene.touches:
        return []
    sensor = scene.sensor
    colors = grasp_colors([t.grasp for t in scene.touches])
    pad = (sensor.width_px * sensor.pixel_size_m, sensor.height_px * sensor.pixel_size_m, sensor.gel_thickness_m)
    nodes = []
    for grasp, color in colors.items():
        touches = [t for t in scene.touches if t.grasp == grasp]
        group = f"{name}/grasp_{grasp:02d}"
        points = [
            tactile_depth_to_points(scene.load_touch_depth(t), sensor.pixel_size_m, t.T_world_sensor)
            for t in touches
            if t.in_contact
        ]
        if points:
            nodes.append(
                scene_api.add_point_cloud(
                    f"{group}/points",
                    np.concatenate(points).astype(np.float32),
                    color,
                    point_size=2 * sensor.pixel_size_m,
                    point_shape="circle",
                    precision="float32",
                )
            )
        for t in touches:
            frame = f"{group}/{t.finger}_{t.id:04d}"
            nodes += [
                scene_api.add_frame(
                    frame,
                    axes_length=0.5 * max(pad[:2]),
                    axes_radius=0.02 * max(pad[:2]),
                    wxyz=vtf.SO3.from_matrix(t.T_world_sensor[:3, :3]).wxyz,
                    position=t.T_world_sensor[:3, 3],
                ),
                scene_api.add_box(
                    f"{frame}/gel", color, dimensions=pad, opacity=0.35, position=(0.0, 0.0, -0.5 * pad[2])
                ),
            ]
    return nodes


def add_scene(scene_api, name: str, scene, show_mesh: bool = True, show_sphere: bool = True) -> SceneNodes:
    """Everything of ``scene`` under ``name``: ``cameras``, ``touches``, ``mesh`` (when the scene has one) and
    ``sphere`` groups of nodes."""
    mesh = load_mesh(scene)
    sphere = bounding_sphere(scene, mesh)
    nodes = SceneNodes(sphere)
    nodes.groups["cameras"] = add_cameras(scene_api, f"{name}/cameras", scene, size=0.4 * sphere.radius)
    nodes.groups["touches"] = add_touches(scene_api, f"{name}/touches", scene)
    if mesh is not None:
        nodes.groups["mesh"] = [
            scene_api.add_mesh_simple(
                f"{name}/gt_mesh",
                np.asarray(mesh.vertices, np.float32),
                np.asarray(mesh.faces, np.uint32),
                color=MESH_COLOR,
                visible=show_mesh,
            )
        ]
    nodes.groups["sphere"] = [
        scene_api.add_icosphere(
            f"{name}/bounding_sphere",
            radius=sphere.radius,
            color=SPHERE_COLOR,
            wireframe=True,
            position=sphere.centre,
            visible=show_sphere,
        )
    ]
    return nodes
