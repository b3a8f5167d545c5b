"""WristCamera: the RGB camera on the hand, its calibration on ChArUco or chessboard photos, board pose by PnP,
hand-eye calibration.

Calibration (:func:`calibrate_intrinsics`): board corners at sub-pixel accuracy in every photo, then
``cv2.calibrateCameraExtended`` with the distortion model of ``DISTORTION_MODELS`` (default OpenCV's five
coefficients, k3 free). Photo sets that cannot determine the intrinsics (:func:`view_set_problem`: too few
distinct poses or board orientations) and results that are no camera (:func:`calibration_problem`) are refused.
The result knows its own uncertainty: the standard deviations of fx, fy, cx, cy (``K_std_px``), and ``warnings``
(:func:`calibration_warnings`) when the focal length is poorly constrained (standard deviation above 1 %),
corners are missing from parts of the image or the lens model fails beyond them, or photos repeat a pose, each
naming what to add.

Pixel centres: OpenCV's calibration and detectors put pixel centres at integer
coordinates; tacsplat's ``K`` (``tacsplat.geometry``) puts them at +0.5. OpenCV
matrices (``K_opencv``) stay inside this module for OpenCV calls; the one
conversion to tacsplat's convention is :func:`tacsplat_K_from_opencv`, used by
:attr:`WristCamera.K`, and back :func:`opencv_K_from_tacsplat`.

World frame of a real capture (DESIGN.md): the board frame turned so that z is
up when the board lies face up: origin at the outer corner of the first square,
x along the board's squares_x direction, y opposite to OpenCV's board y, z out
of the printed face (``T_WORLD_BOARD``).
"""

from __future__ import annotations

import itertools
import json
import logging
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple, Sequence

import cv2
import numpy as np
from pydantic import Field, PlainValidator

from tacsplat.drivers.calibration import is_json_number, read_calibration
from tacsplat.drivers.calibration_files import Array, CalibrationFile, NonNegative, Rigid
from tacsplat.drivers.video import VideoReader
from tacsplat.errors import CameraError, ConfigError, InvalidInputError
from tacsplat.files import atomic_write
from tacsplat.geometry import invert_pose, make_pose

log = logging.getLogger(__name__)

FORMAT = "tacsplat-camera-calibration"
_PIXEL_CENTRES = "opencv (integer)"
T_WORLD_BOARD = np.diag([1.0, -1.0, -1.0, 1.0])  # rotation of pi about the board's x axis


def tacsplat_K_from_opencv(K_opencv: np.ndarray) -> np.ndarray:
    """The one conversion: OpenCV intrinsics (pixel centres at integers) -> tacsplat's (centres at +0.5)."""
    K = np.array(K_opencv, dtype=np.float64)
    K[:2, 2] += 0.5
    return K


def undistort(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """A raw image undistorted by :meth:`CameraCalibration.undistort_maps`, as every wrist-camera frame is."""
    return cv2.remap(image, maps[0], maps[1], cv2.INTER_LINEAR)


def opencv_K_from_tacsplat(K: np.ndarray) -> np.ndarray:
    """The inverse, for OpenCV calls on tacsplat's intrinsics (a camera's ``K``)."""
    K_opencv = np.array(K, dtype=np.float64)
    K_opencv[:2, 2] -= 0.5
    return K_opencv


MAX_BOARD_SQUARES = 100  # per side
MAX_SQUARE_LENGTH_M = 1.0


def _size_problem(spec, counts: tuple[str, ...], lengths: tuple[str, ...]) -> tuple[str, str] | None:
    """``(field, what is wrong)`` of the first of ``counts`` (integers in [2, MAX_BOARD_SQUARES]) and ``lengths``
    (metres in (0, MAX_SQUARE_LENGTH_M]) that is out of its range, or None."""
    for name in counts:
        n = getattr(spec, name)
        if not isinstance(n, int) or isinstance(n, bool) or not 2 <= n <= MAX_BOARD_SQUARES:
            return name, f"must be an integer in [2, {MAX_BOARD_SQUARES}], got {n!r}"
    for name in lengths:
        x = getattr(spec, name)
        if not is_json_number(x) or not 0 < x <= MAX_SQUARE_LENGTH_M:  # (NaN and inf fail too)
            return name, f"must be in (0, {MAX_SQUARE_LENGTH_M:g}] m, got {x!r}"
    return None


@dataclass(frozen=True)
class CharucoBoardSpec:
    """A printed ChArUco board (OpenCV >= 4.6 pattern unless ``legacy_pattern``); :meth:`problem` tells
    whether it can be made."""

    squares_x: int = 7
    squares_y: int = 5
    square_length_m: float = 0.03
    marker_length_m: float = 0.022  # smaller than the square
    dictionary: str = "DICT_5X5_100"  # with at least one marker per white square
    legacy_pattern: bool = False

    def problem(self) -> tuple[str, str] | None:
        """``(field, what is wrong and the allowed range)`` of the first impossible value, or None."""
        problem = _size_problem(self, ("squares_x", "squares_y"), ("square_length_m", "marker_length_m"))
        if problem:
            return problem
        if not self.marker_length_m < self.square_length_m:
            return "marker_length_m", (
                f"must be smaller than square_length_m ({self.square_length_m:g} m), got {self.marker_length_m:g}"
            )
        name = self.dictionary
        if not (isinstance(name, str) and name.startswith("DICT_") and hasattr(cv2.aruco, name)):
            return "dictionary", f"unknown ArUco dictionary {self.dictionary!r}"
        markers = len(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList)
        needed = self.squares_x * self.squares_y // 2
        if needed > markers:
            return "dictionary", (
                f"{self.dictionary} has {markers} markers; a {self.squares_x} x {self.squares_y} "
                f"board needs {needed} (choose a larger dictionary or fewer squares)"
            )
        if not isinstance(self.legacy_pattern, bool):
            return "legacy_pattern", f"expected true or false, got {self.legacy_pattern!r}"
        return None

    def board(self) -> "cv2.aruco.CharucoBoard":
        if problem := self.problem():
            raise ConfigError(*problem)
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        size = (self.squares_x, self.squares_y)
        board = cv2.aruco.CharucoBoard(size, self.square_length_m, self.marker_length_m, dictionary)
        board.setLegacyPattern(self.legacy_pattern)
        return board

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Corners seen in an image: (object points [N, 3] board metres, image points [N, 2] OpenCV pixels)."""
        return detect_charuco(image, self.board())

    def describe(self) -> str:
        return f"ChArUco board ({self.squares_x}x{self.squares_y} squares, {self.dictionary})"


@dataclass(frozen=True)
class ChessboardSpec:
    """A printed chessboard, by its inner corners (where four squares meet) along x and y; :meth:`problem` tells
    whether it can be used. Give one odd and one even count, so that the board's orientation is unambiguous."""

    inner_corners_x: int = 9
    inner_corners_y: int = 6
    square_length_m: float = 0.025

    def problem(self) -> tuple[str, str] | None:
        """``(field, what is wrong and the allowed range)`` of the first impossible value, or None."""
        return _size_problem(self, ("inner_corners_x", "inner_corners_y"), ("square_length_m",))

    def object_points(self) -> np.ndarray:
        """[N, 3] board metres of the inner corners, row by row (OpenCV's detection order)."""
        grid = np.mgrid[0 : self.inner_corners_x, 0 : self.inner_corners_y].T.reshape(-1, 2)
        return np.column_stack([grid * self.square_length_m, np.zeros(len(grid))])

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All inner corners, refined to sub-pixel (``cv2.cornerSubPix``, an 11x11 px window, smaller when the
        corners are closer), or none: (object points [N, 3] board metres, image points [N, 2] OpenCV pixels)."""
        if problem := self.problem():
            raise ConfigError(*problem)
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        size = (self.inner_corners_x, self.inner_corners_y)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        # (a photo under 15 px a side shows no board: OpenCV's adaptive threshold refuses it with an assertion)
        found, corners = cv2.findChessboardCorners(gray, size, flags) if min(gray.shape[:2]) >= 15 else (False, None)
        if not found:
            return np.zeros((0, 3)), np.zeros((0, 2))
        grid = corners.reshape(self.inner_corners_y, self.inner_corners_x, 2)
        spacing = min(np.linalg.norm(np.diff(grid, axis=axis), axis=2).min() for axis in (0, 1))
        half = int(max(1, min(5, spacing / 2 - 1)))  # the window must not reach the next corner
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.1)
        corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), criteria)
        return self.object_points(), corners.reshape(-1, 2).astype(np.float64)

    def describe(self) -> str:
        return f"chessboard ({self.inner_corners_x}x{self.inner_corners_y} inner corners)"


BoardSpec = CharucoBoardSpec | ChessboardSpec
BOARD_TYPES = {"charuco": CharucoBoardSpec, "chessboard": ChessboardSpec}


def detect_charuco(image: np.ndarray, board: "cv2.aruco.CharucoBoard") -> tuple[np.ndarray, np.ndarray]:
    """Board corners in an image: (object points [N, 3] board metres, image points [N, 2] OpenCV pixels)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    if ids is None or len(ids) == 0:
        return np.zeros((0, 3)), np.zeros((0, 2))
    obj, img = board.matchImagePoints(corners, ids)
    return obj.reshape(-1, 3).astype(np.float64), img.reshape(-1, 2).astype(np.float64)


DISTORTION_MODELS = {  # name -> (cv2.calibrateCamera flags, coefficients)
    "opencv5": (0, 5),  # k1 k2 p1 p2 k3, all free (OpenCV's default)
    "opencv4": (cv2.CALIB_FIX_K3, 5),  # k1 k2 p1 p2, k3 held at zero (narrow lenses, few views)
    "rational8": (cv2.CALIB_RATIONAL_MODEL, 8),  # k1 k2 p1 p2 k3 k4 k5 k6 (wide-angle lenses)
}
MAX_FOCAL_STD = 0.01  # of the focal length: above it the calibration is poorly constrained
MIN_GOOD_TILT_DEG = 30.0  # a set of views should hold at least one board tilted this much
# Degenerate photo sets, refused before calibrating (view_set_problem). Zhang's method reads the intrinsics off
# the homographies of the board, two equations per view: a board parallel to the image plane gives an affine
# homography, whose equations fix the aspect ratio but say nothing of the focal length, and boards parallel to
# each other repeat the same equations. Three board planes that are not parallel determine the intrinsics, so the
# board must be seen in MIN_ORIENTATIONS orientations MIN_ORIENTATION_DEG apart (hence two of them tilted at least
# that much from facing the camera). The focal length shows through the foreshortening, ~ sin(tilt): below 10
# degrees its error grows as 1 / tilt. The tilt is estimated with a nominal focal length (the image's larger
# side), good to a factor of 2 for webcams and phones, which moves a 10-degree tilt by a few degrees only.
MIN_ORIENTATIONS = 3
MIN_ORIENTATION_DEG = 10.0
SAME_POSE_FRACTION = 0.01  # two photos whose common corners lie within 1 % of the image diagonal (RMS): one pose
# A result that is no camera, refused after calibrating (calibration_problem): a field of view outside 2-170
# degrees (a lens beyond either end needs another model), a standard deviation of zero or NaN (OpenCV's
# covariance was singular: a parameter is unobservable), or distortion that folds the image or scales its corner
# beyond MAX_CORNER_SCALE (distorted over undistorted radius; real perspective lenses stay within ~1.3).
FIELD_OF_VIEW_DEG = (2.0, 170.0)
MAX_CORNER_SCALE = 2.0
_K_NAMES = ("fx", "fy", "cx", "cy")
CELL_NAMES = (("top-left", "top", "top-right"), ("left", "centre", "right"), ("bottom-left", "bottom", "bottom-right"))


@dataclass
class CameraCalibration:
    """Intrinsics of the raw (distorted) images, in OpenCV's pixel convention, and the undistortion."""

    K_opencv: np.ndarray  # [3, 3]
    dist: np.ndarray  # [5] k1 k2 p1 p2 k3 (or [8] for rational8)
    width: int
    height: int
    rms_px: float = float("nan")
    board: BoardSpec = field(default_factory=CharucoBoardSpec)
    per_image_rms_px: dict[str, float] = field(default_factory=dict)
    T_hand_cam: np.ndarray | None = None  # [4, 4] from hand-eye calibration, if done
    K_std_px: dict[str, float] | None = None  # standard deviations of fx, fy, cx, cy (cv2.calibrateCameraExtended)
    distortion_model: str | None = None  # a key of DISTORTION_MODELS (None: not recorded)
    warnings: list[str] = field(default_factory=list)  # what makes the calibration poorly constrained

    def undistorted_K_opencv(self) -> np.ndarray:
        """Intrinsics of the undistorted images (all pixels valid: alpha = 0), OpenCV convention."""
        K, _ = cv2.getOptimalNewCameraMatrix(self.K_opencv, self.dist, (self.width, self.height), 0.0)
        return K

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.remap``'s maps from raw frames to undistorted ones (intrinsics :meth:`undistorted_K_opencv`)."""
        K_new, size = self.undistorted_K_opencv(), (self.width, self.height)
        return cv2.initUndistortRectifyMap(self.K_opencv, self.dist, None, K_new, size, cv2.CV_16SC2)

    def save(self, path: str | Path) -> None:
        board = {"type": next(k for k, v in BOARD_TYPES.items() if isinstance(self.board, v)), **asdict(self.board)}
        data = {"format": FORMAT, "version": 1, "pixel_centres": _PIXEL_CENTRES, **vars(self), "board": board}
        data |= {"K_opencv": self.K_opencv.tolist(), "dist": self.dist.ravel().tolist()}
        data["T_hand_cam"] = None if self.T_hand_cam is None else np.asarray(self.T_hand_cam).tolist()
        atomic_write(path, (json.dumps(data, indent=2) + "\n").encode())

    @classmethod
    def load(cls, path: str | Path) -> "CameraCalibration":
        """Read a calibration file; every value is checked here, and one ConfigError names the file and field."""
        path = Path(path)
        f = read_calibration(path, _CameraFile, FORMAT)
        K, width, height, dist = f.K_opencv, f.width, f.height, f.dist
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ConfigError(
                "K_opencv", f"focal lengths must be positive, got fx {K[0, 0]}, fy {K[1, 1]}", source=path
            )
        if not (-0.5 <= K[0, 2] <= width - 0.5 and -0.5 <= K[1, 2] <= height - 0.5):
            raise ConfigError(
                "K_opencv",
                f"principal point ({K[0, 2]}, {K[1, 2]}) is outside the {width}x{height} image (OpenCV pixel centres)",
                source=path,
            )
        if K[1, 0] != 0 or K[2].tolist() != [0.0, 0.0, 1.0]:
            raise ConfigError(
                "K_opencv", f"must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}", source=path
            )
        if dist.size not in (4, 5, 8, 12, 14):
            raise ConfigError("dist", f"expected 4, 5, 8, 12 or 14 coefficients (OpenCV), got {dist.size}", source=path)
        model = f.distortion_model
        if model is not None and DISTORTION_MODELS[model][1] != dist.size:
            raise ConfigError(
                "distortion_model", f"{model!r} does not match the {dist.size} coefficients of dist", source=path
            )
        board = dict(f.board)
        kind = board.pop("type", "charuco")
        if not isinstance(kind, str) or kind not in BOARD_TYPES:  # (a list is unhashable)
            raise ConfigError("board.type", f"expected one of {list(BOARD_TYPES)}, got {kind!r}", source=path)
        names = [field.name for field in fields(BOARD_TYPES[kind])]
        if unknown := [key for key in board if key not in names]:
            raise ConfigError(f"board.{unknown[0]}", f"unknown field of a {kind} board (expected {names})", source=path)
        spec = BOARD_TYPES[kind](**board)
        if problem := spec.problem():
            raise ConfigError(f"board.{problem[0]}", problem[1], source=path)
        std = f.K_std_px and f.K_std_px.model_dump()
        return cls(K, dist, width, height, f.rms_px, spec, f.per_image_rms_px, f.T_hand_cam, std, model, f.warnings)


def _rms(value) -> float:
    """Not recorded (null or NaN), or a finite number of pixels >= 0."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return float("nan")
    if not is_json_number(value) or not 0 <= value < math.inf:
        raise ValueError(f"must be a finite number of pixels >= 0, got {value!r}")
    return float(value)


class _KStd(CalibrationFile):
    fx: NonNegative
    fy: NonNegative
    cx: NonNegative
    cy: NonNegative


class _CameraFile(CalibrationFile):
    pixel_centres: Literal[_PIXEL_CENTRES] = _PIXEL_CENTRES  # K_opencv is in OpenCV's convention
    K_opencv: Array(3, 3)
    dist: Array(None)
    width: Annotated[int, Field(ge=1)]
    height: Annotated[int, Field(ge=1)]
    rms_px: Annotated[Any, PlainValidator(_rms)] = float("nan")
    board: dict = {}
    per_image_rms_px: dict[str, NonNegative] = {}
    T_hand_cam: Rigid | None = None
    K_std_px: _KStd | None = None
    distortion_model: Literal[tuple(DISTORTION_MODELS)] | None = None
    warnings: list[str] = []


@dataclass
class BoardView:
    """The board corners found in one photo."""

    name: str
    object_points: np.ndarray  # [N, 3] board metres
    image_points: np.ndarray  # [N, 2] OpenCV pixels


def detect_board_views(
    images: Sequence[np.ndarray], board_spec: BoardSpec, names: Sequence[str], min_corners: int = 8
) -> tuple[list[BoardView], tuple[int, int]]:
    """The views of ``images`` (RGB or gray, one size) that show at least ``min_corners`` corners, and (w, h)."""
    views, size = [], None
    for name, image in zip(names, images):
        h, w = image.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise InvalidInputError(f"{name}: {w}x{h}, but the first image is {size[0]}x{size[1]}")
        obj, img = board_spec.detect(image)
        if len(obj) < min_corners:
            log.warning("%s: %d board corners found (< %d), skipped", name, len(obj), min_corners)
            continue
        views.append(BoardView(name, obj, img))
    return views, size


def calibrate_views(
    views: Sequence[BoardView], size: tuple[int, int], board_spec: BoardSpec, distortion: str = "opencv5"
) -> CameraCalibration:
    """Intrinsics, distortion and their uncertainty from board views by ``cv2.calibrateCameraExtended``."""
    if distortion not in DISTORTION_MODELS:
        raise ConfigError("distortion", f"expected one of {list(DISTORTION_MODELS)}, got {distortion!r}")
    if len(views) < 3:
        raise CameraError("calibration", f"the board was found in {len(views)} images; at least 3 are needed")
    obj_points = [v.object_points.astype(np.float32) for v in views]
    img_points = [v.image_points.astype(np.float32) for v in views]
    distinct, repeats = distinct_views(views, size)
    if problem := view_set_problem(views, distinct, repeats, size):
        raise CameraError("calibration", problem)
    flags, count = DISTORTION_MODELS[distortion]
    rms, K, dist, rvecs, tvecs, std_intrinsics, _, _ = cv2.calibrateCameraExtended(
        obj_points, img_points, size, None, None, flags=flags
    )
    dist = dist.ravel()[:count]  # OpenCV may return 14, the rest zeros
    per_image = {}
    for view, obj, img, r, t in zip(views, obj_points, img_points, rvecs, tvecs):
        proj, _ = cv2.projectPoints(obj, r, t, K, dist)
        per_image[view.name] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    std = {key: float(value) for key, value in zip(_K_NAMES, std_intrinsics.ravel()[:4])}
    calib = CameraCalibration(
        K, dist, size[0], size[1], float(rms), board_spec, per_image, K_std_px=std, distortion_model=distortion
    )
    if problem := calibration_problem(calib, views):
        raise CameraError(
            "calibration",
            f"not written: the result is no camera ({problem}); the photos hold too "
            "little information: add views with the board tilted 20-45 degrees towards each side",
        )
    tilts = [float(np.degrees(np.arccos(min(1.0, abs(cv2.Rodrigues(r)[0][2, 2]))))) for r in rvecs]
    calib.warnings = calibration_warnings(calib, views, tilts) + [
        f"{', '.join(names[1:])} show{'s' * (len(names) == 2)} the board where {names[0]} does (within "
        f"{SAME_POSE_FRACTION:.0%} of the image), adding nothing: take each photo from a new pose"
        for names in repeats
    ]
    return calib


def _same_pose(a: BoardView, b: BoardView, tolerance_px: float) -> bool:
    """Whether two views show the board in one place: at least 4 common corners, within ``tolerance_px`` RMS."""
    index = {key: k for k, key in enumerate(map(tuple, np.round(a.object_points, 9)))}
    pairs = [(index[key], k) for k, key in enumerate(map(tuple, np.round(b.object_points, 9))) if key in index]
    if len(pairs) < 4:
        return False
    ia, ib = np.array(pairs).T
    return float(np.sqrt(np.mean(np.sum((a.image_points[ia] - b.image_points[ib]) ** 2, axis=1)))) < tolerance_px


def distinct_views(views: Sequence[BoardView], size: tuple[int, int]) -> tuple[list[BoardView], list[list[str]]]:
    """The views that show the board in a pose of its own (the first of each pose), and the names of the views
    of each pose seen more than once (the first view's name first)."""
    tolerance = SAME_POSE_FRACTION * math.hypot(*size)
    distinct, repeats = [], {}
    for view in views:
        twin = next((other for other in distinct if _same_pose(other, view, tolerance)), None)
        if twin is None:
            distinct.append(view)
        else:
            repeats.setdefault(twin.name, [twin.name]).append(view.name)
    return distinct, list(repeats.values())


def board_normals(views: Sequence[BoardView], size: tuple[int, int]) -> np.ndarray:
    """[n, 3] unit normal of the board in each view, camera frame, by planar PnP (IPPE) with a nominal camera: focal
    length the image's larger side, principal point at the centre, no distortion."""
    f = float(max(size))
    K = np.array([[f, 0.0, (size[0] - 1) / 2], [0.0, f, (size[1] - 1) / 2], [0.0, 0.0, 1.0]])
    normals = []
    for view in views:
        ok, rvec, _ = cv2.solvePnP(view.object_points, view.image_points, K, None, flags=cv2.SOLVEPNP_IPPE)
        normals.append(cv2.Rodrigues(rvec)[0][:, 2] if ok else np.array([0.0, 0.0, 1.0]))
    return np.array(normals)


def view_set_problem(
    views: Sequence[BoardView], distinct: Sequence[BoardView], repeats: Sequence[Sequence[str]], size: tuple[int, int]
) -> str | None:
    """Why the views cannot determine the intrinsics (fewer than MIN_ORIENTATIONS distinct poses or board
    orientations), naming the photos and what to add; None when they can."""
    advice = "take each photo from a new pose, the board tilted 20-45 degrees towards each side"
    if len(distinct) < MIN_ORIENTATIONS:
        same = "; ".join(", ".join(names) for names in repeats)
        return (
            f"the {len(views)} photos show the board in {len(distinct)} distinct pose(s) ({same} show it in "
            f"one place, within {SAME_POSE_FRACTION:.0%} of the image); calibration needs at least "
            f"{MIN_ORIENTATIONS}: {advice}"
        )
    normals = board_normals(distinct, size)
    kept = []  # one normal per orientation, MIN_ORIENTATION_DEG apart
    for normal in normals:
        if all(np.degrees(np.arccos(min(1.0, abs(normal @ other)))) >= MIN_ORIENTATION_DEG for other in kept):
            kept.append(normal)
    if len(kept) < MIN_ORIENTATIONS:
        tilts = ", ".join(
            f"{view.name} {np.degrees(np.arccos(min(1.0, abs(n[2])))):.0f}" for view, n in zip(distinct, normals)
        )
        return (
            f"the board is seen in {len(kept)} orientation(s) at least {MIN_ORIENTATION_DEG:g} degrees apart "
            f"(tilt from facing the camera, degrees: {tilts}); calibration needs {MIN_ORIENTATIONS}: a board "
            f"facing the camera, or boards parallel to each other, leave the focal length unobservable: {advice}"
        )
    return None


def _lens_problem(calib: CameraCalibration, radius: float) -> str | None:
    """Why the lens model does not map the ray to the farthest image corner one to one onto the image out to
    ``radius`` (distorted, normalised): it folds back first, or scales that radius beyond MAX_CORNER_SCALE."""
    corners = _normalised(calib, _image_corners(calib))
    direction = corners[np.argmax(np.hypot(*corners.T))]
    direction = direction / np.hypot(*direction)
    r = np.linspace(0.0, MAX_CORNER_SCALE * radius, 401)  # undistorted radii
    pixels = cv2.projectPoints(
        np.column_stack([np.outer(r, direction), np.ones(len(r))]), np.zeros(3), np.zeros(3), calib.K_opencv, calib.dist
    )[0].reshape(-1, 2)
    distorted = np.hypot(*_normalised(calib, pixels).T)
    reached = np.flatnonzero(distorted >= radius)
    end = reached[0] if reached.size else len(r) - 1
    dist = "[" + ", ".join(f"{k:.4g}" for k in calib.dist) + "]"
    folds = np.flatnonzero(np.diff(distorted[: end + 1]) <= 0)
    if folds.size:
        return (
            f"the distortion {dist} folds the image back at radius {distorted[folds[0]]:.3g} (normalised; "
            f"pixels out to {radius:.3g} would see two rays or none)"
        )
    scale = radius / r[end] if reached.size else 0.0
    if not 1 / MAX_CORNER_SCALE <= scale <= MAX_CORNER_SCALE:
        return (
            f"the distortion {dist} scales radius {radius:.3g} (normalised) by {scale:.3g}, beyond "
            f"1/{MAX_CORNER_SCALE:g} to {MAX_CORNER_SCALE:g}"
        )
    return None


def _normalised(calib: CameraCalibration, pixels: np.ndarray) -> np.ndarray:
    """OpenCV pixels [N, 2] -> normalised (distorted) image coordinates [N, 2]."""
    K = calib.K_opencv
    return (pixels - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T


def _image_corners(calib: CameraCalibration) -> np.ndarray:
    """[4, 2] OpenCV pixels of the image's outer corners."""
    w, h = calib.width, calib.height
    return np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])


def _radii(calib: CameraCalibration, views: Sequence[BoardView]) -> tuple[float, float]:
    """Distorted normalised radius of the outermost corner seen, and of the farthest image corner."""
    seen = np.concatenate([view.image_points for view in views])
    return tuple(float(np.hypot(*_normalised(calib, points).T).max()) for points in (seen, _image_corners(calib)))


def calibration_problem(calib: CameraCalibration, views: Sequence[BoardView]) -> str | None:
    """Why a calibration result is no camera (see FIELD_OF_VIEW_DEG, MAX_CORNER_SCALE; the lens model is judged
    where the views saw corners: beyond, calibration_warnings says so), or None."""
    K, std = calib.K_opencv, calib.K_std_px or {}
    values = np.concatenate([K.ravel(), calib.dist.ravel(), list(std.values())])
    if not np.isfinite(values).all():
        return f"K {K.tolist()}, distortion {calib.dist.tolist()} or their standard deviations {std} are not finite"
    for key, (value, side) in {"fx": (K[0, 0], calib.width), "fy": (K[1, 1], calib.height)}.items():
        fov = math.degrees(2 * math.atan(side / (2 * value))) if value > 0 else float("nan")
        if not FIELD_OF_VIEW_DEG[0] <= fov <= FIELD_OF_VIEW_DEG[1]:
            return (
                f"{key} {value:.6g} px gives a field of view of {fov:.3g} degrees over {side} px, outside "
                f"{FIELD_OF_VIEW_DEG[0]:g}-{FIELD_OF_VIEW_DEG[1]:g}"
            )
    if not (0 <= K[0, 2] <= calib.width and 0 <= K[1, 2] <= calib.height):
        return f"the principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) px is outside the image"
    if zero := [key for key, value in std.items() if not value > 0]:
        return f"the standard deviation of {', '.join(zero)} is zero: OpenCV found it unobservable"
    return _lens_problem(calib, _radii(calib, views)[0])


def empty_image_cells(views: Sequence[BoardView], size: tuple[int, int]) -> list[str]:
    """Names of the parts of the image (a 3x3 grid: top-left ... bottom-right) where no corner was seen."""
    seen = np.zeros((3, 3), bool)
    for view in views:
        u, v = view.image_points[:, 0], view.image_points[:, 1]
        seen[np.clip((v * 3 / size[1]).astype(int), 0, 2), np.clip((u * 3 / size[0]).astype(int), 0, 2)] = True
    return [CELL_NAMES[r][c] for r in range(3) for c in range(3) if not seen[r, c]]


def calibration_warnings(calib: CameraCalibration, views: Sequence[BoardView], tilts_deg: Sequence[float]) -> list[str]:
    """Why a calibration is poorly constrained, each naming what to add; empty when it is well constrained."""
    warnings = []
    K, std = calib.K_opencv, calib.K_std_px or {}
    loose = [
        f"{key} {K[i, i]:.1f} +- {std[key]:.1f} px ({std[key] / K[i, i]:.1%})"
        for i, key in enumerate(("fx", "fy"))
        if key in std and std[key] > MAX_FOCAL_STD * K[i, i]
    ]
    if loose:
        advice = f"add more views ({len(views)} now; 15-30 make a good calibration)"
        if max(tilts_deg) < MIN_GOOD_TILT_DEG:
            advice += (
                f" and more tilt: the most tilted board is {max(tilts_deg):.0f} deg from facing the camera; "
                f"tilt it {MIN_GOOD_TILT_DEG:.0f}-45 deg towards each side"
            )
        warnings.append(
            f"the focal length is poorly constrained: {', '.join(loose)}, more than {MAX_FOCAL_STD:.0%}: {advice}"
        )
    if lens := _lens_problem(calib, _radii(calib, views)[1]):
        warnings.append(
            f"the image corners lie beyond the outermost board corner seen and the lens model fails "
            f"there: {lens}; add views with the board near the image corners"
        )
    if empty := empty_image_cells(views, (calib.width, calib.height)):
        warnings.append(
            f"corner coverage of the image is poor, so the lens distortion there is poorly constrained: "
            f"no corner was seen in the {', '.join(empty)} of the image; add views with the board "
            "near those image borders and corners"
        )
    return warnings


def calibrate_intrinsics(
    images: Sequence[np.ndarray],
    board_spec: BoardSpec = CharucoBoardSpec(),
    names: Sequence[str] | None = None,
    min_corners: int = 8,
    distortion: str = "opencv5",
) -> CameraCalibration:
    """Intrinsics and distortion from board images (RGB or gray): :func:`detect_board_views`, :func:`calibrate_views`."""
    names = list(names) if names is not None else [f"image {i}" for i in range(len(images))]
    views, size = detect_board_views(images, board_spec, names, min_corners)
    return calibrate_views(views, size, board_spec, distortion)


class BoardPose(NamedTuple):
    """A camera pose from the board, with what it is worth."""

    T_world_cam: np.ndarray  # [4, 4]
    rms_px: float  # reprojection error of the board's corners
    corners: int
    position_std_m: float  # the camera position's standard deviation (3D, metres) from the PnP's covariance


def board_pose(
    image: np.ndarray, board_spec: BoardSpec, K_opencv: np.ndarray, dist=None, min_corners: int = 6
) -> BoardPose:
    """Camera pose in the world (board) frame by PnP, with its reprojection error and uncertainty."""
    obj, img = board_spec.detect(image)
    if len(obj) < min_corners:
        raise CameraError(
            "wrist camera", f"board not found: {len(obj)} corners of the {board_spec.describe()} (< {min_corners})"
        )
    dist = np.zeros(5) if dist is None else np.asarray(dist, dtype=np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K_opencv, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CameraError("wrist camera", "solvePnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K_opencv, dist, rvec, tvec)
    proj, J = cv2.projectPoints(obj, rvec, tvec, K_opencv, dist)
    residuals = proj.reshape(-1, 2) - img  # [N, 2]
    rms = float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))
    R, dR = cv2.Rodrigues(rvec)  # dR [3, 9]: d vec(R) / d r_i, row-major
    T_cam_board = make_pose(R, tvec.ravel())
    return BoardPose(
        T_WORLD_BOARD @ invert_pose(T_cam_board), rms, len(obj), _position_std(residuals, J[:, :6], R, dR, tvec.ravel())
    )


def _position_std(residuals: np.ndarray, J: np.ndarray, R: np.ndarray, dR: np.ndarray, t: np.ndarray) -> float:
    """Standard deviation (3D, metres) of the camera centre c = -R^T t of a PnP fit: the Gauss-Newton covariance
    s^2 (J^T J)^-1 of (rvec, tvec), with s^2 the residual variance, carried to c (infinite where the fit leaves
    the pose undetermined). Few corners, a small board in the image or a far board make it large."""
    dof = residuals.size - 6
    if dof <= 0:
        return float("inf")
    normal = J.T @ J  # [6, 6]
    if not np.all(np.isfinite(normal)) or np.linalg.cond(normal) > 1e12:
        return float("inf")
    cov = float(np.sum(residuals**2)) / dof * np.linalg.inv(normal)
    dc = np.column_stack([*(-dR[i].reshape(3, 3).T @ t for i in range(3)), -R.T])  # [3, 6]: dc / d(rvec, tvec)
    return float(np.sqrt(max(np.trace(dc @ cov @ dc.T), 0.0)))


def hand_eye_calibration(T_base_hand: Sequence[np.ndarray], T_world_cam: Sequence[np.ndarray]) -> np.ndarray:
    """``T_hand_cam`` of a camera rigid on the hand, from hand poses in the robot base and camera poses in the world.

    Eye-in-hand ``A X = X B`` by Park & Martin (1994): for each pair of
    stations, ``A = T_hand_j^-1 T_hand_i`` (hand motion) and ``B = T_cam_j^-1 T_cam_i``
    (camera motion, from the board poses); the rotation aligns the rotation
    vectors of A and B (``scipy`` Kabsch), the translation solves
    ``(R_A - I) t = R_X t_B - t_A`` by least squares. (OpenCV 5's Python
    bindings no longer ship ``cv2.calibrateHandEye``.) Needs >= 3 stations with
    rotations about non-parallel axes.
    """
    from scipy.spatial.transform import Rotation

    if len(T_base_hand) != len(T_world_cam) or len(T_base_hand) < 3:
        raise InvalidInputError(
            f"hand_eye_calibration: need >= 3 matching pose pairs, got {len(T_base_hand)} and {len(T_world_cam)}"
        )
    hands = [np.asarray(T, dtype=np.float64) for T in T_base_hand]
    cams = [np.asarray(T, dtype=np.float64) for T in T_world_cam]
    alphas, betas, motions = [], [], []
    for i, j in itertools.combinations(range(len(hands)), 2):
        A = invert_pose(hands[j]) @ hands[i]
        B = invert_pose(cams[j]) @ cams[i]
        alpha, beta = (Rotation.from_matrix(T[:3, :3]).as_rotvec() for T in (A, B))
        if np.linalg.norm(alpha) > 1e-3 and np.linalg.norm(beta) > 1e-3:
            alphas.append(alpha)
            betas.append(beta)
            motions.append((A, B))
    if len(alphas) < 2 or np.linalg.matrix_rank(np.array(alphas), tol=1e-3) < 2:
        raise InvalidInputError("hand_eye_calibration: the hand rotations must span at least two axes")
    R_X = Rotation.align_vectors(np.array(alphas), np.array(betas))[0].as_matrix()
    lhs = np.concatenate([A[:3, :3] - np.eye(3) for A, _ in motions])
    rhs = np.concatenate([R_X @ B[:3, 3] - A[:3, 3] for A, B in motions])
    t_X = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return make_pose(R_X, t_X)


class WristCamera:
    """The wrist camera implementing the ``Camera`` Protocol: undistorted RGB frames and ``K`` of those frames."""

    def __init__(
        self,
        source: int | str,
        calibration: CameraCalibration | str | Path,
        *,
        fps: float | None = None,
        fourcc: str | None = None,
        timeout_s: float = 2.0,
        capture_factory=cv2.VideoCapture,
    ):
        c = self.calibration = (
            calibration if isinstance(calibration, CameraCalibration) else CameraCalibration.load(calibration)
        )
        self._K_new_opencv = c.undistorted_K_opencv()
        self._maps = c.undistort_maps()
        video = dict(fps=fps, fourcc=fourcc, timeout_s=timeout_s, capture_factory=capture_factory)
        self._video = VideoReader(source, width=c.width, height=c.height, name="wrist camera", **video)

    @property
    def K(self) -> np.ndarray:
        """[3, 3] intrinsics of the undistorted images, tacsplat convention (pixel centres at +0.5)."""
        return tacsplat_K_from_opencv(self._K_new_opencv)

    @property
    def width(self) -> int:
        return self.calibration.width

    @property
    def height(self) -> int:
        return self.calibration.height

    def __enter__(self) -> "WristCamera":
        self._video.open()
        return self

    def __exit__(self, *exc) -> None:
        self._video.close()

    def undistort(self, image: np.ndarray) -> np.ndarray:
        return undistort(image, self._maps)

    def read(self) -> tuple[np.ndarray, float]:
        """``(image [H, W, 3] uint8 RGB undistorted, timestamp: time.monotonic() seconds when it was received)``;
        CameraError if frames stop."""
        frame = self._video.read()
        return self.undistort(cv2.cvtColor(frame.image, cv2.COLOR_BGR2RGB)), frame.timestamp

    def pose_in_world(self, image: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """``(T_world_cam, rms reprojection px)`` from the board in an undistorted image (a new frame if None)."""
        if image is None:
            image, _ = self.read()
        pose = board_pose(image, self.calibration.board, self._K_new_opencv, None)
        return pose.T_world_cam, pose.rms_px
