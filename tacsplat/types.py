"""Readings and camera models shared by drivers, the twin, datasets and reconstruction."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from tacsplat.errors import InvalidInputError
from tacsplat.geometry import as_pose, compose, tactile_depth_to_points


@dataclass(frozen=True)
class CameraIntrinsics:
    """OpenCV pinhole intrinsics of undistorted images (pixel centres at +0.5)."""

    K: np.ndarray  # [3, 3] float64
    width: int
    height: int

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise InvalidInputError(f"K: expected [3, 3], got shape {K.shape}")
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
            raise InvalidInputError(f"K: focal lengths must be finite and positive, got {K.tolist()}")
        if self.width < 1 or self.height < 1:
            raise InvalidInputError(f"image size must be positive, got {self.width}x{self.height}")
        object.__setattr__(self, "K", K)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])


@dataclass(frozen=True)
class TactileReading:
    """One optical tactile reading, modelled as an orthographic depth camera behind the gel.

    ``depth`` [h, w] float32 is the indentation in metres (0 = no contact).
    ``T_ref_sensor`` maps sensor-frame points into the frame named ``frame``:
    ``"hand"`` as a sensor driver or the twin returns it, ``"world"`` once the
    logger has placed it with ``T_world_hand``. The sensor frame has its origin
    at the centre of the undeformed gel, z along the gel's outward normal,
    x along image columns and y along image rows (DESIGN.md).
    """

    depth: np.ndarray  # [h, w] float32, metres
    pixel_size_m: float
    T_ref_sensor: np.ndarray  # [4, 4] float64
    frame: str = "hand"
    timestamp: float = 0.0
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        depth = np.asarray(self.depth, dtype=np.float32)
        if depth.ndim != 2:
            raise InvalidInputError(f"TactileReading.depth: expected [h, w], got shape {depth.shape}")
        if not np.all(np.isfinite(depth)) or (depth < 0).any():
            raise InvalidInputError("TactileReading.depth: must be finite and non-negative")
        if not self.pixel_size_m > 0:
            raise InvalidInputError(f"TactileReading.pixel_size_m must be positive, got {self.pixel_size_m}")
        object.__setattr__(self, "depth", depth)
        object.__setattr__(self, "T_ref_sensor", as_pose(self.T_ref_sensor, "TactileReading.T_ref_sensor"))

    @property
    def in_contact(self) -> bool:
        return bool((self.depth > 0).any())

    @property
    def T_world_sensor(self) -> np.ndarray:
        if self.frame != "world":
            raise InvalidInputError(
                f"TactileReading is in the '{self.frame}' frame; call to_world(T_world_{self.frame}) first"
            )
        return self.T_ref_sensor

    def to_world(self, T_world_ref) -> "TactileReading":
        """The same reading with its pose expressed in the world frame."""
        return replace(self, T_ref_sensor=compose(T_world_ref, self.T_ref_sensor), frame="world")

    def contact_points(self, threshold_m: float = 1e-5) -> np.ndarray:
        """World contact points [M, 3] (see :func:`tacsplat.geometry.tactile_depth_to_points`)."""
        return tactile_depth_to_points(self.depth, self.pixel_size_m, self.T_world_sensor, threshold_m)
