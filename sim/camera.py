"""MuJoCo cameras in the OpenCV convention: RGB and ground-truth depth, intrinsics from fovy.

MuJoCo cameras look along their -z with y up (OpenGL); the OpenCV camera of
the same view is ``T_world_cv = T_world_gl @ diag(1, -1, -1, 1)``. MuJoCo's
``fovy`` is the full vertical field of view and pixels are square, so
``fx = fy = H / (2 tan(fovy / 2))``, ``cx = W / 2``, ``cy = H / 2`` (pixel
centres at +0.5, DESIGN.md).
"""

from __future__ import annotations

import os

import mujoco
import numpy as np

from tacsplat.errors import CameraError
from tacsplat.geometry import focal_from_fov, intrinsics_matrix, make_pose, opengl_to_opencv
from tacsplat.types import CameraIntrinsics


def intrinsics_from_fovy(fovy_deg: float, width: int, height: int) -> CameraIntrinsics:
    """OpenCV intrinsics of a MuJoCo camera with vertical field of view ``fovy_deg``."""
    f = focal_from_fov(np.deg2rad(fovy_deg), height)
    return CameraIntrinsics(intrinsics_matrix(f, f, width / 2, height / 2), width, height)


def make_renderer(model: mujoco.MjModel, width: int, height: int, device: str) -> mujoco.Renderer:
    """An offscreen renderer (EGL, or whatever MUJOCO_GL names), with one clear error if none works."""
    try:
        return mujoco.Renderer(model, height=height, width=width)
    except Exception as exc:  # GL backends raise various types
        raise CameraError(
            device,
            f"cannot open a {width}x{height} offscreen renderer with MUJOCO_GL={os.environ.get('MUJOCO_GL')}: "
            f"{exc} (try MUJOCO_GL=osmesa)",
        ) from exc


class MujocoCamera:
    """One named MuJoCo camera of a twin, rendering RGB and z-depth (implements ``Camera``).

    ``visible_groups`` lists the geom groups drawn (the views hide the hand: group 1).
    """

    def __init__(self, twin, camera_name: str, width: int, height: int, visible_groups=(0, 1, 2)):
        self._twin = twin
        self.name = camera_name
        self._cam_id = twin.model.camera(camera_name).id
        fovy = float(twin.model.cam_fovy[self._cam_id])
        self.intrinsics = intrinsics_from_fovy(fovy, width, height)
        self.width, self.height = width, height
        self._renderer = make_renderer(twin.model, width, height, f"camera {camera_name}")
        self._option = mujoco.MjvOption()
        self._option.geomgroup[:] = 0
        for g in visible_groups:
            self._option.geomgroup[g] = 1
        self._option.sitegroup[:] = 0

    @property
    def K(self) -> np.ndarray:
        return self.intrinsics.K.copy()

    def pose(self) -> np.ndarray:
        """OpenCV camera-to-world pose [4, 4] from the simulation state."""
        data = self._twin.data
        return opengl_to_opencv(make_pose(data.cam_xmat[self._cam_id].reshape(3, 3), data.cam_xpos[self._cam_id]))

    def read(self) -> tuple[np.ndarray, float]:
        """``(image [H, W, 3] uint8 RGB, simulated time in seconds)``."""
        self._renderer.disable_depth_rendering()
        self._renderer.update_scene(self._twin.data, camera=self._cam_id, scene_option=self._option)
        return self._renderer.render().copy(), float(self._twin.data.time)

    def read_depth(self) -> np.ndarray:
        """Ground-truth z-depth [H, W] float32 metres along the optical axis, 0 where nothing is hit."""
        self._renderer.enable_depth_rendering()
        self._renderer.update_scene(self._twin.data, camera=self._cam_id, scene_option=self._option)
        depth = self._renderer.render().astype(np.float64)
        self._renderer.disable_depth_rendering()
        far = self._twin.model.vis.map.zfar * self._twin.model.stat.extent
        depth[~np.isfinite(depth) | (depth >= 0.999 * far)] = 0.0
        return depth.astype(np.float32)

    def close(self) -> None:
        self._renderer.close()
