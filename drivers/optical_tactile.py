"""OpticalTactileSensor: a DIGIT/GelSight-like fingertip camera, and its depth reconstruction.

Depth the GelSight way (Johnson & Adelson 2009; Yuan et al. 2017):

1. calibration: presses of a ball of known radius; in each, the contact circle
   is found in the colour change against the no-contact reference frame, the
   sphere gives the true surface gradient at every pixel inside it (zero
   outside), and a lookup table from colour change (dR, dG, dB) to gradient
   (dd/dx, dd/dy) is filled with the mean gradient per colour bin, empty bins
   taking their nearest filled neighbour;
2. reading: colour change -> gradients by the table -> depth by Poisson
   integration (``laplacian(d) = div(g)``, zero depth on the image border)
   solved exactly with a type-I discrete sine transform (``scipy.fft``).

Depth is the indentation in metres (>= 0) of the sensor model of DESIGN.md;
x along image columns, y along image rows.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np
from scipy import fft, ndimage

from tacsplat.drivers.video import VideoReader
from tacsplat.errors import InvalidInputError, TactileError
from tacsplat.geometry import as_pose
from tacsplat.types import TactileReading

log = logging.getLogger(__name__)

FORMAT = "tacsplat-tactile-calibration"


def poisson_integrate(gx: np.ndarray, gy: np.ndarray, pixel_size_m: float) -> np.ndarray:
    """Depth [h, w] metres whose gradient best matches ``(gx, gy)`` [h, w] (dimensionless slopes).

    Solves the 5-point ``laplacian(d) = div(g)`` with ``d = 0`` on the border by
    a type-I DST (exact for Dirichlet boundaries, O(N log N)).
    """
    gx = np.asarray(gx, dtype=np.float64)
    gy = np.asarray(gy, dtype=np.float64)
    if gx.shape != gy.shape or gx.ndim != 2 or min(gx.shape) < 3:
        raise InvalidInputError(f"poisson_integrate: gx {gx.shape} and gy {gy.shape} must be the same [h>=3, w>=3]")
    if not (np.all(np.isfinite(gx)) and np.all(np.isfinite(gy))):
        raise InvalidInputError("poisson_integrate: gradients contain NaN or infinite values")
    h, w = gx.shape
    # divergence in metres per pixel^2 -> right-hand side of the pixel-grid Laplacian of d (metres)
    div = (np.gradient(gx, axis=1) + np.gradient(gy, axis=0)) * pixel_size_m
    rhs = div[1:-1, 1:-1]
    ky = np.arange(1, h - 1)
    kx = np.arange(1, w - 1)
    eig = (2 * np.cos(np.pi * ky / (h - 1)) - 2)[:, None] + (2 * np.cos(np.pi * kx / (w - 1)) - 2)[None, :]
    interior = fft.idstn(fft.dstn(rhs, type=1) / eig, type=1)
    depth = np.zeros((h, w))
    depth[1:-1, 1:-1] = interior
    return depth


def find_contact_circle(diff: np.ndarray, min_change: float = 12.0) -> tuple[float, float, float] | None:
    """Centre (cx, cy) and radius in pixels of the largest contact blob in a colour change [h, w, 3], or None.

    Pixel centres at integer coordinates (array indices), like ``np.indices``.
    """
    magnitude = ndimage.gaussian_filter(np.linalg.norm(diff, axis=-1), 1.0)
    mask = (magnitude > min_change).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5)))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    contour = max(contours, key=cv2.contourArea)
    if len(contour) < 8:
        return None
    filled = np.zeros_like(mask)
    cv2.drawContours(filled, [contour], -1, 1, thickness=-1)
    ys, xs = np.nonzero(filled)
    # circle of the same area and centroid: robust to the ring-shaped colour change of a sphere
    return float(xs.mean()), float(ys.mean()), float(np.sqrt(len(xs) / np.pi))


def sphere_press_gradients(shape, centre, contact_radius_px: float, ball_radius_px: float):
    """Ideal depth gradients (gx, gy) [h, w] of a sphere pressed into the gel, and the contact mask."""
    ys, xs = np.indices(shape, dtype=np.float64)
    dx, dy = xs - centre[0], ys - centre[1]
    rho2 = dx**2 + dy**2
    inside = rho2 < contact_radius_px**2
    root = np.sqrt(np.maximum(ball_radius_px**2 - rho2, 1e-12))
    # depth = sqrt(R^2 - rho^2) - const inside the contact: slope = -(x - cx) / sqrt(R^2 - rho^2)
    gx = np.where(inside, -dx / root, 0.0)
    gy = np.where(inside, -dy / root, 0.0)
    return gx, gy, inside, np.sqrt(rho2)


@dataclass
class TactileCalibration:
    """Lookup table colour change -> surface gradient, for one sensor at one image size."""

    lut: np.ndarray  # [B, B, B, 2] float32 (gx, gy) per (dR, dG, dB) bin
    bin_size: float  # grey levels per bin
    pixel_size_m: float
    image_size: tuple[int, int]  # (height, width)
    ball_radius_m: float = 0.0
    noise_floor_m: float = 5e-6  # reconstructed depth below this is no contact
    presses: list[dict] = field(default_factory=list)  # per-press diagnostics (centre, radius)

    @property
    def bins(self) -> int:
        return self.lut.shape[0]

    def _bin_index(self, diff: np.ndarray) -> np.ndarray:
        half = self.bins // 2
        return np.clip(np.floor(diff / self.bin_size).astype(np.int64) + half, 0, self.bins - 1)

    @classmethod
    def fit(cls, reference: np.ndarray, presses: Sequence[np.ndarray], ball_radius_m: float, pixel_size_m: float,
            bin_size: float = 4.0, rim_margin_px: float = 1.5, min_change: float = 12.0) -> "TactileCalibration":
        """Fit the table from a no-contact ``reference`` [h, w, 3] RGB and ball-press images [h, w, 3] RGB."""
        if not (ball_radius_m > 0 and pixel_size_m > 0):
            raise InvalidInputError(f"ball_radius_m ({ball_radius_m}) and pixel_size_m ({pixel_size_m}) must be > 0")
        reference = _as_rgb(reference, "reference")
        bins = int(np.ceil(256 / bin_size))  # colour changes within +-128 grey levels
        bins += bins % 2
        sums = np.zeros((bins**3, 2))
        counts = np.zeros(bins**3)
        ball_px = ball_radius_m / pixel_size_m
        calib = cls(np.zeros((bins, bins, bins, 2), np.float32), bin_size, pixel_size_m, reference.shape[:2],
                    ball_radius_m)
        for k, image in enumerate(presses):
            image = _as_rgb(image, f"press {k}")
            if image.shape != reference.shape:
                raise TactileError("calibration", f"press {k} is {image.shape}, the reference {reference.shape}")
            diff = image.astype(np.float64) - reference
            circle = find_contact_circle(diff, min_change)
            if circle is None or circle[2] < 3 or circle[2] >= ball_px:
                log.warning("press %d: no usable contact circle (%s), skipped", k, circle)
                continue
            cx, cy, r = circle
            gx, gy, inside, rho = sphere_press_gradients(diff.shape[:2], (cx, cy), r, ball_px)
            use = (rho < r - rim_margin_px) | (rho > r + 2 * rim_margin_px)  # the rim is ambiguous
            idx = calib._bin_index(diff[use])
            flat = (idx[:, 0] * bins + idx[:, 1]) * bins + idx[:, 2]
            np.add.at(sums, flat, np.stack([gx[use], gy[use]], axis=1))
            np.add.at(counts, flat, 1.0)
            calib.presses.append({"index": k, "centre_px": [cx, cy], "contact_radius_px": r})
        if not calib.presses:
            raise TactileError("calibration", "no ball press with a detectable contact circle")
        means = sums / np.maximum(counts, 1.0)[:, None]
        # empty bins take the mean of the nearest filled bin (Euclidean in colour space)
        empty = (counts == 0).reshape(bins, bins, bins)
        nearest = ndimage.distance_transform_edt(empty, return_distances=False, return_indices=True)
        flat = np.ravel_multi_index(tuple(nearest), (bins,) * 3)
        calib.lut = means[flat].astype(np.float32)
        return calib

    def gradients(self, image: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Surface gradients (gx, gy) [h, w] of the gel in ``image`` against ``reference`` (RGB uint8)."""
        diff = _as_rgb(image, "image").astype(np.float64) - _as_rgb(reference, "reference")
        idx = self._bin_index(diff)
        g = self.lut[idx[..., 0], idx[..., 1], idx[..., 2]]
        return g[..., 0].astype(np.float64), g[..., 1].astype(np.float64)

    def depth(self, image: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Indentation [h, w] float32 metres (>= 0) of ``image`` against the no-contact ``reference``."""
        if image.shape[:2] != tuple(self.image_size):
            raise TactileError("calibration", f"image is {image.shape[:2]}, the calibration is for {self.image_size}")
        gx, gy = self.gradients(image, reference)
        depth = poisson_integrate(gx, gy, self.pixel_size_m)
        depth[depth < self.noise_floor_m] = 0.0
        return depth.astype(np.float32)

    def save(self, path: str | Path) -> None:
        path = Path(path)
        meta = {"format": FORMAT, "version": 1, "bin_size": self.bin_size, "pixel_size_m": self.pixel_size_m,
                "image_size": list(self.image_size), "ball_radius_m": self.ball_radius_m,
                "noise_floor_m": self.noise_floor_m, "presses": self.presses}
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, lut=self.lut, meta=json.dumps(meta))
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> "TactileCalibration":
        path = Path(path)
        try:
            with np.load(path) as data:
                lut, meta = data["lut"], json.loads(str(data["meta"]))
        except FileNotFoundError:
            raise TactileError("calibration", f"{path}: file not found") from None
        except (KeyError, ValueError, OSError) as exc:
            raise TactileError("calibration", f"{path}: not a tactile calibration file ({exc})") from None
        if meta.get("format") != FORMAT:
            raise TactileError("calibration", f"{path} [format]: expected {FORMAT!r}")
        if lut.ndim != 4 or lut.shape[-1] != 2 or len(set(lut.shape[:3])) != 1:
            raise TactileError("calibration", f"{path} [lut]: expected [B, B, B, 2], got {lut.shape}")
        return cls(lut, float(meta["bin_size"]), float(meta["pixel_size_m"]), tuple(meta["image_size"]),
                   float(meta["ball_radius_m"]), float(meta["noise_floor_m"]), list(meta["presses"]))


def _as_rgb(image, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InvalidInputError(f"{name}: expected an [h, w, 3] RGB image, got shape {image.shape}")
    return image


class OpticalTactileSensor:
    """A fingertip tactile camera implementing the ``TactileSensor`` Protocol; a context manager.

    ``T_hand_sensor`` is the sensor pose in the hand frame: a fixed [4, 4] or a
    callable returning it (e.g. ``lambda: hand.fingertip_poses()["index"]``).
    On open, the mean of ``reference_frames`` frames becomes the no-contact
    reference: the gel must be untouched then.
    """

    def __init__(self, name: str, source: int | str, calibration: TactileCalibration | str | Path,
                 T_hand_sensor: np.ndarray | Callable[[], np.ndarray] = np.eye(4), *, width: int | None = None,
                 height: int | None = None, fps: float | None = None, timeout_s: float = 2.0,
                 reference_frames: int = 5, capture_factory=cv2.VideoCapture):
        self._name = name
        self.calibration = calibration if isinstance(calibration, TactileCalibration) else TactileCalibration.load(calibration)
        self._pose = T_hand_sensor if callable(T_hand_sensor) else (lambda T=as_pose(T_hand_sensor, "T_hand_sensor"): T)
        self.reference_frames = int(reference_frames)
        self._video = VideoReader(source, width=width, height=height, fps=fps, timeout_s=timeout_s,
                                  name=f"tactile sensor {name!r}", capture_factory=capture_factory)
        self.reference: np.ndarray | None = None  # [h, w, 3] float64 RGB

    @property
    def name(self) -> str:
        return self._name

    def __enter__(self) -> "OpticalTactileSensor":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        self._video.open()
        if (self._video.height, self._video.width) != tuple(self.calibration.image_size):
            size = (self._video.height, self._video.width)
            self._video.close()
            raise TactileError(self._name, f"camera delivers {size[1]}x{size[0]}, the calibration is for "
                                           f"{self.calibration.image_size[1]}x{self.calibration.image_size[0]}")
        self.capture_reference()

    def close(self) -> None:
        self._video.close()

    def capture_reference(self) -> None:
        """Average ``reference_frames`` frames of the untouched gel into the no-contact reference."""
        frames = [self._read_rgb()[0].astype(np.float64) for _ in range(self.reference_frames)]
        self.reference = np.mean(frames, axis=0)

    def _read_rgb(self):
        frame = self._video.read()
        return cv2.cvtColor(frame.image, cv2.COLOR_BGR2RGB), frame

    def read_image(self) -> tuple[np.ndarray, float]:
        """The raw tactile image [h, w, 3] uint8 RGB and its timestamp."""
        rgb, frame = self._read_rgb()
        return rgb, frame.timestamp

    def read(self) -> TactileReading:
        """A reading with depth from the newest frame, its pose in the hand frame."""
        if self.reference is None:
            raise TactileError(self._name, "not open (no reference frame)")
        rgb, frame = self._read_rgb()
        depth = self.calibration.depth(rgb, self.reference)
        return TactileReading(depth=depth, pixel_size_m=self.calibration.pixel_size_m, T_ref_sensor=self._pose(),
                              frame="hand", timestamp=frame.timestamp,
                              meta={"sensor": self._name, "frame_index": frame.index})
