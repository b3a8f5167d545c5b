"""Shared geometry: poses, camera conventions, projection, depth and touch lifting.

Conventions (DESIGN.md):

* Poses are 4x4 float64 homogeneous matrices named ``T_a_b``: they map points
  from frame b into frame a (``p_a = T_a_b @ p_b``).
* Cameras are OpenCV pinhole inside the code (x right, y down, z forward).
  OpenGL (x right, y up, z backward: nerfstudio, Blender) is converted only at
  a format boundary, with :func:`opencv_to_opengl` / :func:`opengl_to_opencv`.
* Continuous image coordinates: pixel (row r, column c) covers
  ``[c, c + 1) x [r, r + 1)`` and its centre is ``(c + 0.5, r + 0.5)``, as in
  gsplat and nerfstudio (so a centred camera has ``cx = width / 2``).
"""

from __future__ import annotations

import logging

import numpy as np

from tacsplat.errors import InvalidInputError

log = logging.getLogger(__name__)

# Flips y and z: OpenCV camera axes <-> OpenGL camera axes (an involution).
_CV_GL_FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def as_pose(T, name: str = "pose") -> np.ndarray:
    """Return ``T`` as a float64 [4, 4] array, or raise naming ``name``."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise InvalidInputError(f"{name}: expected a 4x4 matrix, got shape {T.shape}")
    return T


def rigidity_problem(T, atol: float = 1e-5) -> str | None:
    """Why ``T`` is not a rigid transform (finite, orthonormal, det +1, last row 0 0 0 1), or None."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {T.shape}"
    if not np.all(np.isfinite(T)):
        return "contains NaN or infinite values"
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
        return f"last row is {T[3].tolist()}, expected [0, 0, 0, 1]"
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > atol:
        return f"rotation is not orthonormal (max |R^T R - I| = {err:.3g})"
    det = np.linalg.det(R)
    if abs(det - 1.0) > atol:
        return f"rotation determinant is {det:.6g}, expected 1"
    return None


def check_rigid(T, name: str = "pose", atol: float = 1e-5) -> np.ndarray:
    """Return ``T`` as float64 [4, 4] if it is rigid, else raise naming ``name``."""
    T = as_pose(T, name)
    if problem := rigidity_problem(T, atol):
        raise InvalidInputError(f"{name}: not a rigid transform: {problem}")
    return T


def make_pose(R, t) -> np.ndarray:
    """Homogeneous pose from a rotation [3, 3] and a translation [3]."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def invert_pose(T) -> np.ndarray:
    """Inverse of a rigid transform (``T_b_a`` from ``T_a_b``), exact for rotations."""
    T = as_pose(T)
    R, t = T[:3, :3], T[:3, 3]
    return make_pose(R.T, -R.T @ t)


def compose(*poses) -> np.ndarray:
    """``compose(T_a_b, T_b_c, ...) = T_a_b @ T_b_c @ ...``."""
    out = np.eye(4)
    for i, T in enumerate(poses):
        out = out @ as_pose(T, f"pose {i}")
    return out


def transform_points(T, points) -> np.ndarray:
    """Apply ``T`` [4, 4] to points [N, 3]; returns [N, 3] float64."""
    T = as_pose(T)
    return np.asarray(points, dtype=np.float64).reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]


def opencv_to_opengl(T_world_cam) -> np.ndarray:
    """Camera-to-world pose with OpenCV camera axes -> the same camera with OpenGL axes, and back
    (:func:`opengl_to_opencv` is the same flip)."""
    return as_pose(T_world_cam) @ _CV_GL_FLIP


opengl_to_opencv = opencv_to_opengl  # OpenGL camera axes -> OpenCV: the flip is its own inverse


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera-to-world pose at ``eye`` looking at ``target``, image-up towards ``up``."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    norm = np.linalg.norm(z)
    if norm == 0:
        raise InvalidInputError("look_at: eye and target coincide")
    z /= norm
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along `up`: pick any perpendicular
        x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)


def focal_from_fov(fov_rad: float, size_px: int) -> float:
    """Focal length in pixels of a pinhole with full field of view ``fov_rad`` over ``size_px``."""
    return 0.5 * size_px / np.tan(0.5 * fov_rad)


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def project_points(points_world, K, T_world_cam) -> tuple[np.ndarray, np.ndarray]:
    """Project world points [N, 3] into an OpenCV camera.

    Returns ``(uv [N, 2], z [N])``: continuous pixel coordinates (pixel centres
    at +0.5) and camera-frame depth. Points with ``z <= 0`` get ``uv = nan``.
    """
    p_cam = transform_points(invert_pose(T_world_cam), points_world)
    z = p_cam[:, 2]
    K = np.asarray(K, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p_cam[:, :2] / z[:, None]) @ K[:2, :2].T + K[:2, 2]
    uv[z <= 0] = np.nan
    return uv, z


def pixel_centres(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous coordinates (u [H, W], v [H, W]) of every pixel centre."""
    v, u = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return u, v


def unproject_depth(depth, K, T_world_cam, mask=None) -> np.ndarray:
    """Lift a z-depth map [H, W] (metres along the optical axis) to world points [M, 3].

    Pixels with depth <= 0, non-finite depth, or ``mask == False`` are skipped.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise InvalidInputError(f"depth: expected [H, W], got shape {depth.shape}")
    keep = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)
    u, v = pixel_centres(*depth.shape)
    K = np.asarray(K, dtype=np.float64)
    z = depth[keep]
    x = (u[keep] - K[0, 2]) / K[0, 0] * z
    y = (v[keep] - K[1, 2]) / K[1, 1] * z
    return transform_points(T_world_cam, np.stack([x, y, z], axis=1))


def tactile_pixel_grid(height: int, width: int, pixel_size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame (x [h, w], y [h, w]) of every tactile pixel centre (DESIGN.md)."""
    y, x = np.meshgrid(
        (np.arange(height) + 0.5 - height / 2) * pixel_size_m,
        (np.arange(width) + 0.5 - width / 2) * pixel_size_m,
        indexing="ij",
    )
    return x, y


def _tactile_depth(depth) -> np.ndarray:
    """A tactile depth map as float64 [h, w], or an InvalidInputError."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2 or not np.all(np.isfinite(depth)):
        raise InvalidInputError(f"tactile depth: expected a finite [h, w] map, got shape {depth.shape}")
    return depth


def tactile_depth_to_points(depth, pixel_size_m: float, T_world_sensor, threshold_m: float = 1e-5) -> np.ndarray:
    """The one lifting of a tactile depth map to contact points [M, 3] in the world.

    A pixel with indentation ``d > threshold_m`` is the contact point
    ``T_world_sensor @ (x, y, -d, 1)`` (the sensor's z is the gel's outward
    normal, so the touched surface lies *behind* the undeformed gel plane).
    """
    depth = _tactile_depth(depth)
    x, y = tactile_pixel_grid(*depth.shape, pixel_size_m)
    hit = depth > threshold_m
    return transform_points(T_world_sensor, np.stack([x[hit], y[hit], -depth[hit]], axis=1))


def tactile_depth_to_normals(depth, pixel_size_m: float, T_world_sensor, threshold_m: float = 1e-5) -> np.ndarray:
    """The touched surface's outward normals [M, 3] (world, unit) at the points of :func:`tactile_depth_to_points`,
    in the same order; NaN where a contact pixel has a neighbour out of contact (the slope there is not known).

    The surface under the gel is ``(x, y, -d(x, y))``; its outward normal (out of the object, towards the
    sensor) is ``-(dd/dx, dd/dy, 1)`` normalised, from central differences of the indentation map.
    """
    depth = _tactile_depth(depth)
    hit = depth > threshold_m
    dd_dy, dd_dx = np.gradient(depth, pixel_size_m)
    normals = -np.stack([dd_dx, dd_dy, np.ones_like(depth)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    from scipy.ndimage import binary_erosion

    normals[~binary_erosion(hit)] = np.nan  # where the 4 neighbours the central differences use are in contact too
    R = np.asarray(T_world_sensor, dtype=np.float64)[:3, :3]
    return normals[hit] @ R.T


def rotation_angle_between(R_a, R_b) -> float:
    """Angle in radians of the rotation taking ``R_a`` to ``R_b``."""
    c = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


# trimesh.nsphere.minimum_nsphere tries the sphere about each vertex of the furthest-site Voronoi diagram of the
# convex-hull points against every hull point at once (a distance matrix it counts at 9 bytes an entry), and past
# 4e9 bytes falls back to a Python loop over the Voronoi vertices (133 s on a 200k-face torus). The diagram has
# up to about 3 vertices a hull point (2.3 to 2.9 on the library and the YCB meshes), so it stays on its fast path up
# to sqrt(4e9 / (9 * 3)) hull points; above, Welzl's algorithm takes over.
TRIMESH_SPHERE_MAX_HULL_POINTS = int(np.sqrt(4e9 / (9 * 3)))  # 12171


def minimum_sphere(points) -> tuple[np.ndarray, float, bool]:
    """Centre [3] and radius of a sphere enclosing ``points`` [N, 3], and whether it is the exact minimum sphere
    (Welzl's, which moves and scales with the points).

    trimesh's furthest-site Voronoi method (``trimesh.nsphere.minimum_nsphere``) up to
    :data:`TRIMESH_SPHERE_MAX_HULL_POINTS` convex-hull points (as every capture and evaluation so far has had it),
    the exact minimum sphere (:func:`welzl_sphere`) above, where trimesh's method would take minutes. trimesh's is
    the minimum sphere when four points hold it; when two or three do (the teapot's spout and handle), it can be a
    little larger (1.7 % for the teapot)."""
    import trimesh

    points = np.asarray(points, dtype=np.float64)
    hull = trimesh.convex.hull_points(points)  # as trimesh's method takes them
    if len(hull) <= TRIMESH_SPHERE_MAX_HULL_POINTS:
        centre, radius = trimesh.nsphere.minimum_nsphere(hull)  # (the same sphere: the hull holds it)
        return np.asarray(centre, dtype=np.float64), float(radius), False
    log.info("the minimum bounding sphere of %d convex-hull points (Welzl's algorithm, seconds) ...", len(hull))
    return *welzl_sphere(hull), True


def welzl_sphere(points, seed: int = 0) -> tuple[np.ndarray, float]:
    """The minimum sphere enclosing ``points`` [N, 3] (centre [3], radius), by Welzl's algorithm (1991) in expected
    linear time; pass the convex hull's vertices, the only points that can hold it.

    In a random order (fixed by ``seed``), the sphere of the first ``i`` points is that of the first ``i - 1`` if
    point ``i`` lies in it, else the smallest sphere of the first ``i - 1`` with point ``i`` on its surface: the same
    problem with one more support point, at most four (:func:`_welzl`). The test "lies in" allows 1e-12 of the
    points' size squared, so that points on a common sphere (a tessellated sphere or torus) do not pile up as
    support; the radius returned is the largest distance from the centre, so every point is inside."""
    points = np.asarray(points, dtype=np.float64)
    points = points[np.random.default_rng(seed).permutation(len(points))]
    tolerance = 1e-12 * float(np.ptp(points, axis=0).max()) ** 2
    centre, _ = _welzl(points, len(points), [], tolerance)
    return centre, float(np.sqrt(((points - centre) ** 2).sum(axis=1).max()))


def _welzl(points: np.ndarray, n: int, support: list, tolerance: float) -> tuple[np.ndarray, float]:
    """Centre and squared radius of the smallest sphere enclosing ``points[:n]`` with every ``support`` point on its
    surface. Vectorised: the first point outside the current sphere is found among all the rest at once."""
    centre, r2 = _circumsphere(np.array(support)) if support else (points[0], 0.0)
    if len(support) == 4:  # four support points fix the sphere
        return centre, r2
    i = 0 if support else 1
    while i < n:
        outside = np.flatnonzero(((points[i:n] - centre) ** 2).sum(axis=1) > r2 + tolerance)
        if not len(outside):
            break
        j = i + int(outside[0])
        centre, r2 = _welzl(points, j, [*support, points[j]], tolerance)
        i = j + 1
    return centre, r2


def _circumsphere(support: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and squared radius of the smallest sphere through the 1 to 4 points ``support`` [k, 3]: its centre is
    ``p0 + U.T @ lam`` (``U``: the other points less ``p0``), as far from each point: ``2 U U.T lam = |U|^2`` (least
    squares, for a support that is almost degenerate)."""
    p0, u = support[0], support[1:] - support[0]
    if not len(u):
        return p0.copy(), 0.0
    offset = u.T @ np.linalg.lstsq(2.0 * (u @ u.T), (u * u).sum(axis=1), rcond=None)[0]
    return p0 + offset, float(offset @ offset)
