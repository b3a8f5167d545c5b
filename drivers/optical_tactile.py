"""OpticalTactileSensor: a DIGIT/GelSight-like fingertip camera, and its depth reconstruction.

Depth the GelSight way (Johnson & Adelson 2009; Yuan et al. 2017; GelSight's SDK), made to survive a
real gel (illumination drift since the reference, marker dots, noise, a soft rim around each contact):

1. colour change (:func:`color_change`): marker dots (small dark blobs in the reference and near them in
   the image, found by a black-hat filter, :func:`marker_mask`) are inpainted in both; their difference
   is median-filtered (3x3) and a smooth background of it is subtracted (a normalised Gaussian
   convolution over the pixels that did not change, iterated), which removes slow illumination
   differences. A pixel changed when the magnitude exceeds ``median + 6 x 1.4826 MAD`` of the pixels that
   did not change (a contact covering much of the gel would inflate the statistics of the whole image), and
   at least the calibration's threshold (the 99.5th percentile of the change far from its presses); at most
   twice that, so that the first estimate, from the whole image, still finds a large contact. A pixel that
   got no light (dark in every channel where the reference was lit) is unchanged and left out of both.
2. calibration on presses of a ball of known radius (:meth:`TactileCalibration.fit`): the contact circle
   (:func:`find_contact_circle`) is where the colour change peaks along rays from the changed blob (the
   steepest slope of the gel, the rim of the ball's cap), fitted robustly. Inside it the sphere gives the
   surface gradient at every pixel; beyond twice its radius the gradient is zero; the soft rim in between,
   where the free gel sags towards the ball, is left out. A small MLP maps (colour change, pixel position)
   to the gradient (dd/dx, dd/dy), as GelSight's SDK does.
3. reading (:meth:`TactileCalibration.depth`): gradients from the MLP within the changed region (0
   outside); the contact is where the object holds the gel (:func:`contact_region`: the slope has not
   started to fall going outwards, as inside a ball's print, not in the sagging rim around it); the depth
   by least-squares (Poisson) integration over the contact with zero height at its rim, free where the image
   border cuts it (:func:`poisson_integrate`); a contact shallower than a quarter pixel is noise. The sag of
   the free gel around a contact is not counted: depth is the object's print relative to the rim of its contact.

:func:`fit_ball` checks a calibration on a press: a sphere fitted to the lifted contact points against the
known ball. Depth is the indentation in metres (>= 0) of the sensor model of DESIGN.md; x along image
columns, y along image rows. Circle centres here are in array-index pixels (pixel centres at integers).
"""

from __future__ import annotations

import json
import logging
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Callable, Sequence

import cv2
import numpy as np
from pydantic import Field, ValidationError
from scipy import ndimage, sparse
from scipy.optimize import least_squares
from scipy.sparse.linalg import spsolve

from tacsplat.drivers.calibration import field_error
from tacsplat.drivers.calibration_files import CalibrationFile, NonNegative
from tacsplat.drivers.video import VideoReader
from tacsplat.errors import InvalidInputError, TactileError
from tacsplat.files import atomic_write
from tacsplat.geometry import as_pose, tactile_pixel_grid
from tacsplat.types import TactileReading

log = logging.getLogger(__name__)

FORMAT = "tacsplat-tactile-calibration"
VERSION = 2
CHANGE_MADS = 6.0  # a pixel changed when its colour change exceeds the unchanged pixels' median by this many sigmas
MIN_CHANGE = 6.0  # ... and at least this many grey levels
MAX_CHANGE_FACTOR = 2.0  # ... and at most this times a calibration's (a large contact inflates the first estimate)
MIN_UNCHANGED = 0.25  # ... where at least this fraction of the image is below that (less: no contact, a broken frame)
UNLIT_LEVEL = 8.0  # grey levels: a pixel no brighter in any channel got no light (where its reference's did)
BACKGROUND_SIGMA = 1 / 8  # of the image's larger side: the scale of illumination drift
MARKER_MIN_CONTRAST = 25.0  # grey levels a marker dot is darker than its surroundings
CHANGE_SCALE = 64.0  # grey levels -> MLP input
FLAT_BEYOND = 2.0  # contact radii: beyond this the gel of a ball press is taken as flat
RIM_MARGIN_PX = 0.5  # inside the contact circle, this close to its rim is left out of the fit
CONTACT_SIGMA_PX = 2.0  # smoothing of the gradients before finding the contact's rim (the steepest slope)
MIN_CONTACT_DEPTH_PX = 0.25  # pixel sizes: a shallower contact cannot be told from noise (a ball's contact of
# radius a px is a^2 / 2R px deep: about this for the smallest blob that counts)
# A sensor's image of its gel, smoothed over IMAGE_SIGMA_PX (camera noise out), has light (the brightest 1 % of its
# pixels at least MIN_LIGHT grey levels), colour (its channels MIN_COLOR apart on average: the method reads the slope
# from the colours of lights from several sides) and an illumination gradient or texture (some channel's 1-99 %
# range at least MIN_SPREAD). Real GelSight images: 239, 44, 125 at least; the twin's rendered gel: 139, 20, 29.
IMAGE_SIGMA_PX = 2.0
MIN_LIGHT = 32.0
MIN_COLOR = 3.0
MIN_SPREAD = 10.0
# ball presses are made 0.5-1.5 mm deep (docs/hardware.md). The reconstructed peak reads 50-85 % of a press's depth
# (rendered presses of known depth: 0.5 mm on a 1 mm ball at 0.1245 mm per pixel reads 0.245 mm), so the held-out
# presses' median peak indentation must lie in READ_DEPTH_M, and below SHALLOW_DEPTH_M it is warned of. A wrong scale
# that the radius check shares reads outside (Taxim's 2 mm ball at 0.1245 mm per pixel, given as 4 mm at 0.08 mm:
# 0.16 mm, where its presses read 1.0 mm).
PRESS_DEPTH_M = (0.5e-3, 1.5e-3)
READ_DEPTH_M = (0.2e-3, 3e-3)
SHALLOW_DEPTH_M = 0.3e-3
# what np.load raises on an empty, truncated or damaged file: numpy's EOFError, zipfile's BadZipFile, zlib's error,
# or zipfile's NotImplementedError for a compression method it does not know
_DAMAGED = (KeyError, ValueError, OSError, TypeError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError)


def _dot_kernel(shape) -> tuple[int, np.ndarray]:
    """The scale of a marker dot in an image of ``shape`` (h, w): ``min(h, w) / 16`` px, at least 5, rounded to an
    odd size, and the elliptic structuring element of that size."""
    size = int(round(max(5, min(shape) / 16)))
    size += 1 - size % 2
    return size, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))


def _wxh(shape) -> str:
    """An image's size as ``WxH`` from its shape ``(h, w, ...)``."""
    return f"{shape[1]}x{shape[0]}"


def _as_rgb(image, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InvalidInputError(f"{name}: expected an [h, w, 3] RGB image, got shape {image.shape}")
    return image


def image_problem(rgb: np.ndarray, reference: bool = True) -> str | None:
    """Why ``rgb`` [h, w, 3] cannot be the sensor's colour image of its gel, or None: black, greyscale or flat (see
    MIN_LIGHT). Any image that got light must have colour; only a ``reference`` must be lit and show the gel (a
    press may be a dark frame, which reads as no contact)."""
    smooth = _blur(_as_rgb(rgb, "image"), IMAGE_SIGMA_PX)
    if np.percentile(smooth.max(axis=-1), 99) < MIN_LIGHT:
        return (
            f"black (its brightest pixels under {MIN_LIGHT:g} grey levels): the gel was not lit" if reference else None
        )
    spread = np.percentile(smooth, 99, axis=(0, 1)) - np.percentile(smooth, 1, axis=(0, 1))
    if reference and spread.max() < MIN_SPREAD:
        return (
            f"flat (one colour: each channel's 1-99 % range under {MIN_SPREAD:g} grey levels): no illumination "
            "gradient or gel texture, not the sensor's image of its gel"
        )
    if np.mean(smooth.max(axis=-1) - smooth.min(axis=-1)) < MIN_COLOR:
        return (
            "greyscale (its colour channels equal): the images must be the sensor's colour images, as its camera "
            "gives them (depth is read from the colours of its lights)"
        )
    return None


def _dark_dots(rgb: np.ndarray) -> np.ndarray:
    """Small round blobs (less than ``min(h, w) / 16`` px across) at least 25 grey levels darker than around them."""
    gray = cv2.cvtColor(np.clip(np.rint(rgb), 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    size, kernel = _dot_kernel(gray.shape)
    blackhat = cv2.morphologyEx(gray, cv2.MORPH_BLACKHAT, kernel)
    count, labels, stats, _ = cv2.connectedComponentsWithStats((blackhat > MARKER_MIN_CONTRAST).astype(np.uint8))
    width, height, area = stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT], stats[:, cv2.CC_STAT_AREA]
    dot = (np.maximum(width, height) < size) & (area >= 0.4 * width * height)  # small and round-ish, not a line
    dot[0] = False
    return dot[labels]


def marker_mask(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Marker dots to inpaint in both images [h, w] bool: the dark dots of the untouched gel's ``reference``, and
    the image's dark dots near them (a marker moves a little in a press), grown by a pixel."""
    dots = _dark_dots(reference)
    if not dots.any():
        return dots
    near = cv2.dilate(dots.astype(np.uint8), _dot_kernel(dots.shape)[1]) > 0
    count, labels = cv2.connectedComponents(_dark_dots(image).astype(np.uint8))
    moved = np.zeros(count, bool)
    moved[np.unique(labels[near & (labels > 0)])] = True
    moved[0] = False
    return cv2.dilate((dots | moved[labels]).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0


def _inpaint(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    image = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    return cv2.inpaint(image, mask.astype(np.uint8), 3, cv2.INPAINT_TELEA).astype(np.float64)


def _blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (each channel), edges replicated."""
    return cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma, borderType=cv2.BORDER_REPLICATE).astype(np.float64)


@dataclass
class ColorChange:
    """The normalised colour change of a tactile image against its reference."""

    change: np.ndarray  # [h, w, 3] float32 grey levels, slow illumination differences removed
    magnitude: np.ndarray  # [h, w] float32, the norm of the (lightly smoothed) change
    threshold: float  # grey levels: a pixel whose magnitude exceeds it changed

    @property
    def changed(self) -> np.ndarray:
        return self.magnitude > self.threshold


def color_change(
    image: np.ndarray,
    reference: np.ndarray,
    min_change: float = MIN_CHANGE,
    max_change: float | None = None,
    iterations: int = 6,
) -> ColorChange:
    """The colour change of ``image`` against the no-contact ``reference`` (both [h, w, 3] RGB), see the module doc.

    The threshold is at least ``min_change`` and at most ``max_change`` grey levels (no cap if None); background
    and threshold are estimated again from the pixels that did not change until these settle (``iterations``).
    """
    image = _as_rgb(image, "image").astype(np.float64)
    reference = _as_rgb(reference, "reference").astype(np.float64)
    if image.shape != reference.shape:
        raise InvalidInputError(f"image is {_wxh(image.shape)}, the reference {_wxh(reference.shape)}")
    markers = marker_mask(image, reference)
    if markers.any():
        image, reference = _inpaint(image, markers), _inpaint(reference, markers)
    diff = cv2.medianBlur((image - reference).astype(np.float32), 3).astype(np.float64)
    h, w = diff.shape[:2]
    # A pixel dark in every channel where the reference's was lit got no light (an LED or a cable failing): it
    # says nothing of the gel, so it counts as unchanged and stays out of the background and the noise.
    unlit = (image.max(axis=-1) <= UNLIT_LEVEL) & (reference.max(axis=-1) > UNLIT_LEVEL)
    if unlit.all():
        return ColorChange(np.zeros((h, w, 3), np.float32), np.zeros((h, w), np.float32), float(min_change))
    diff[unlit] = 0.0
    sigma = BACKGROUND_SIGMA * max(h, w)
    still, first = ~unlit, True  # first from the whole image
    for _ in range(iterations):
        weight = _blur(still.astype(np.float64), sigma)
        background = _blur(diff * still[..., None], sigma)
        change = diff - background / np.maximum(weight, 1e-6)[..., None]
        change[unlit] = 0.0
        magnitude = np.linalg.norm(_blur(change, 1.0), axis=-1)
        quiet = magnitude[still]  # the noise, of the pixels that did not change
        median = float(np.median(quiet))
        threshold = max(min_change, median + CHANGE_MADS * (1.4826 * float(np.median(np.abs(quiet - median)))))
        if max_change is not None and first and np.mean(magnitude < max_change) > MIN_UNCHANGED:
            threshold = min(threshold, max_change)  # the first estimate: a contact covering much of the gel inflates it
        settled = ndimage.binary_erosion(magnitude < threshold, iterations=3) & ~unlit  # changed pixels grown 3 px
        if not settled.any() or np.array_equal(settled, still):  # everything changed (no background left), or done
            break
        still, first = settled, False
    return ColorChange(change.astype(np.float32), magnitude.astype(np.float32), threshold)


def _solid_blobs(mask: np.ndarray) -> np.ndarray:
    """``mask`` opened (3x3: specks go), closed (``min(h, w) / 16``: a thin crack, such as the line where a gel's
    colour change vanishes, is bridged), its holes filled, blobs smaller than the minimum area dropped."""
    ellipse = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, ellipse)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, _dot_kernel(mask.shape)[1])
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = np.zeros(count, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= max(20, int(0.002 * mask.shape[0] * mask.shape[1]))  # 0.2 %, >= 20 px
    return ndimage.binary_fill_holes(keep[labels])


@dataclass(frozen=True)
class ContactCircle:
    """A contact circle, in array-index pixels (pixel centres at integers)."""

    cx: float
    cy: float
    radius: float
    rms_px: float  # of the rim points about the circle


def _fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Algebraic (Kasa) least-squares circle through points."""
    A = np.column_stack([x, y, np.ones_like(x)])
    (a, b, c), *_ = np.linalg.lstsq(A, x**2 + y**2, rcond=None)
    cx, cy = a / 2, b / 2
    return cx, cy, float(np.sqrt(max(c + cx**2 + cy**2, 0.0)))


def find_contact_circle(change: ColorChange, rays: int = 90) -> ContactCircle | None:
    """The contact circle of a ball press: the largest changed blob, refined to where the change peaks along rays.

    None when no blob is large enough, or the rim is not a circle (fewer than half the rays find their peak
    inside the image, fewer than a third agree on one circle, or the rim points scatter about it by more
    than 15 % of its radius).
    """
    blobs = _solid_blobs(change.changed)
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(blobs.astype(np.uint8), connectivity=8)
    if count < 2:
        return None
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    (cx, cy), r = centroids[best], float(np.sqrt(stats[best, cv2.CC_STAT_AREA] / np.pi))
    magnitude = change.magnitude.astype(np.float64)
    h, w = magnitude.shape
    angles = np.linspace(0.0, 2 * np.pi, rays, endpoint=False)
    ray = np.arange(rays)
    for _ in range(3):  # centre and radius from the blob, then from the previous circle
        radii = np.arange(0.0, 2.0 * r + 4.0, 0.25)
        xs = cx + radii[None, :] * np.cos(angles)[:, None]
        ys = cy + radii[None, :] * np.sin(angles)[:, None]
        profile = ndimage.gaussian_filter1d(
            ndimage.map_coordinates(magnitude, [ys, xs], order=1, mode="nearest"), 2.0, axis=1
        )
        outside = np.cumsum((xs < 0) | (xs > w - 1) | (ys < 0) | (ys > h - 1), axis=1) > 0  # from leaving on
        profile[outside | (radii < 0.4 * r)] = -np.inf
        peak = np.argmax(profile, axis=1)
        beyond = np.minimum(peak + 4, len(radii) - 1)  # a peak is one only if the ray goes on past it
        usable = np.isfinite(profile[ray, peak]) & ~outside[ray, beyond]
        if usable.sum() < rays // 2:
            return None
        px, py = xs[ray, peak][usable], ys[ray, peak][usable]
        keep = np.ones(len(px), bool)
        for _ in range(3):  # trim rim points off the circle (a shadow, a marker)
            if keep.sum() < rays // 3:
                return None
            cx, cy, r = _fit_circle(px[keep], py[keep])
            residual = np.abs(np.hypot(px - cx, py - cy) - r)
            keep = residual <= max(1.0, 2.5 * 1.4826 * np.median(residual[keep]))
        if not (np.isfinite(r) and r >= 3.0):
            return None
    rms = float(np.sqrt(np.mean(residual[keep] ** 2)))
    if keep.sum() < rays // 3 or rms > 0.15 * r:
        return None
    return ContactCircle(float(cx), float(cy), float(r), rms)


def sphere_press_gradients(shape, centre, contact_radius_px: float, ball_radius_px: float):
    """Depth gradients (gx, gy) [h, w] of a ball pressed into the gel (0 outside the contact), and rho [h, w] px."""
    ys, xs = np.indices(shape, dtype=np.float64)
    dx, dy = xs - centre[0], ys - centre[1]
    rho = np.hypot(dx, dy)
    inside = rho < contact_radius_px
    root = np.sqrt(np.maximum(ball_radius_px**2 - rho**2, 1e-12))
    # indentation d = sqrt(R^2 - rho^2) - const inside the contact: dd/dx = -(x - cx) / sqrt(R^2 - rho^2)
    return np.where(inside, -dx / root, 0.0), np.where(inside, -dy / root, 0.0), rho


def poisson_integrate(
    gx: np.ndarray, gy: np.ndarray, pixel_size_m: float, mask: np.ndarray | None = None
) -> np.ndarray:
    """Depth [h, w] metres whose gradient best matches ``(gx, gy)`` [h, w] (slopes) in ``mask``, 0 outside it.

    Least squares over every pixel edge touching ``mask``: ``d_q - d_p = pixel_size * (g_p + g_q) / 2``, with
    ``g`` taken as 0 outside ``mask``; solved exactly (sparse Cholesky-like factorisation of the normal
    equations, a Poisson problem). The whole image (the default) has depth 0 beyond its border; a ``mask``
    has depth 0 at its rim inside the image and none across the image's border (a contact cut by the border
    goes on beyond it), unless it covers the whole image.
    """
    gx = np.asarray(gx, dtype=np.float64)
    gy = np.asarray(gy, dtype=np.float64)
    if gx.shape != gy.shape or gx.ndim != 2 or min(gx.shape) < 3:
        raise InvalidInputError(f"poisson_integrate: gx {gx.shape} and gy {gy.shape} must be the same [h>=3, w>=3]")
    if not (np.all(np.isfinite(gx)) and np.all(np.isfinite(gy))):
        raise InvalidInputError("poisson_integrate: gradients contain NaN or infinite values")
    mask = np.ones(gx.shape, bool) if mask is None else np.asarray(mask, bool)
    depth = np.zeros(gx.shape)
    if not mask.any():
        return depth
    inside = np.pad(mask, 1)
    index = np.full(inside.shape, -1)  # -1: depth 0 there
    index[inside] = np.arange(int(inside.sum()))
    if not mask.all():  # a rim inside the image holds the mask: no equation across the image's border (-2)
        index[np.pad(np.zeros(mask.shape, bool), 1, constant_values=True)] = -2
    slopes = [np.pad(np.where(mask, g, 0.0), 1) for g in (gx, gy)]
    rows, cols, vals, rhs = [], [], [], []
    edge = 0
    for axis, g in ((1, slopes[0]), (0, slopes[1])):
        first, second = ((slice(None),) * axis + (end,) for end in (slice(0, -1), slice(1, None)))
        p, q = index[first].ravel(), index[second].ravel()
        target = (pixel_size_m * (g[first] + g[second]) / 2).ravel()
        used = ((p >= 0) | (q >= 0)) & (p > -2) & (q > -2)
        p, q, target = p[used], q[used], target[used]
        k = edge + np.arange(len(target))
        for nodes, sign in ((q, 1.0), (p, -1.0)):
            known = nodes >= 0
            rows.append(k[known])
            cols.append(nodes[known])
            vals.append(np.full(int(known.sum()), sign))
        rhs.append(target)
        edge += len(target)
    A = sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(edge, int(inside.sum()))
    )
    solution = spsolve((A.T @ A).tocsc(), A.T @ np.concatenate(rhs))
    depth[mask] = solution[index[1:-1, 1:-1][mask]]
    return depth


def contact_region(gx: np.ndarray, gy: np.ndarray, deformed: np.ndarray) -> np.ndarray:
    """Where the object holds the gel: the slope has not yet started to fall going outwards.

    The rim of a contact is where the gel is steepest: inside a convex object's print the slope grows
    outwards, in the free gel sagging around it the slope falls. A pixel is in contact when its slope
    (smoothed over CONTACT_SIGMA_PX) is at least that of the point one pixel further in (against the outward
    direction ``-g / |g|``); the region is taken within ``deformed`` and made solid (:func:`_solid_blobs`).
    """
    sx, sy = ndimage.gaussian_filter(gx, CONTACT_SIGMA_PX), ndimage.gaussian_filter(gy, CONTACT_SIGMA_PX)
    slope = np.hypot(sx, sy)
    ys, xs = np.indices(slope.shape, dtype=np.float64)
    length = np.maximum(slope, 1e-12)
    inner = ndimage.map_coordinates(slope, [ys + sy / length, xs + sx / length], order=1, mode="nearest")
    return _solid_blobs((slope >= inner) & deformed) & deformed


# --- the gradient model: a small MLP (colour change, pixel position) -> (dd/dx, dd/dy) ---------------------------


def _features(change: np.ndarray) -> np.ndarray:
    """[h * w, 5]: the colour change / CHANGE_SCALE and the pixel position in [-0.5, 0.5]."""
    h, w = change.shape[:2]
    ys, xs = np.indices((h, w), dtype=np.float32)
    position = np.stack([(xs + 0.5) / w - 0.5, (ys + 0.5) / h - 0.5], axis=-1)
    return np.concatenate([change / CHANGE_SCALE, position], axis=-1).reshape(-1, 5).astype(np.float32)


def _mlp(weights: Sequence[np.ndarray], x: np.ndarray, tanh=np.tanh) -> np.ndarray:
    """tanh MLP: weights are (W [in, out], b [out]) pairs (numpy arrays, or torch tensors with ``torch.tanh``)."""
    for i in range(0, len(weights), 2):
        x = x @ weights[i] + weights[i + 1]
        if i + 2 < len(weights):
            x = tanh(x)
    return x


def _train_mlp(
    x: np.ndarray, y: np.ndarray, hidden: int = 32, steps: int = 1500, batch: int = 1024, seed: int = 0
) -> list[np.ndarray]:
    """Fit the MLP (two tanh layers) by Adam on mean squared error; deterministic for a seed."""
    import torch

    generator = torch.Generator().manual_seed(seed)
    sizes = [x.shape[1], hidden, hidden, y.shape[1]]
    layers = []
    for n_in, n_out in zip(sizes[:-1], sizes[1:]):
        bound = 1.0 / np.sqrt(n_in)
        layers += [(torch.rand(n_in, n_out, generator=generator) * 2 - 1) * bound, torch.zeros(n_out)]
    params = [p.requires_grad_() for p in layers]
    inputs, targets = torch.from_numpy(x), torch.from_numpy(y.astype(np.float32))
    optimiser = torch.optim.Adam(params, lr=3e-3)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, steps)
    for _ in range(steps):
        pick = torch.randint(len(inputs), (min(batch, len(inputs)),), generator=generator)
        loss = ((_mlp(params, inputs[pick], torch.tanh) - targets[pick]) ** 2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
    return [p.detach().numpy().astype(np.float32) for p in params]


@dataclass
class TactileCalibration:
    """Colour change -> surface gradient for one sensor at one image size, fitted on ball presses."""

    weights: list[np.ndarray]  # the MLP: (W [in, out], b [out]) pairs, float32
    pixel_size_m: float
    image_size: tuple[int, int]  # (height, width)
    ball_radius_m: float = 0.0
    change_threshold: float = MIN_CHANGE  # grey levels: at least this much colour change is a deformed gel
    noise_floor_m: float = 0.0  # a contact whose deepest point is shallower is none (fit: a quarter pixel)
    presses: list[dict] = field(default_factory=list)  # per press: file, role (fit | check), circle, ball fit
    check_summary: dict | None = None  # the ball fits of the held-out presses (see calibrate_tactile)

    @classmethod
    def fit(
        cls,
        reference: np.ndarray,
        presses: Sequence[np.ndarray],
        ball_radius_m: float,
        pixel_size_m: float,
        names: Sequence[str] | None = None,
        steps: int = 1500,
        seed: int = 0,
    ) -> "TactileCalibration":
        """Fit on a no-contact ``reference`` [h, w, 3] RGB and ball-press images [h, w, 3] RGB (see the module doc)."""
        if not (ball_radius_m > 0 and pixel_size_m > 0):
            raise InvalidInputError(f"ball_radius_m ({ball_radius_m}) and pixel_size_m ({pixel_size_m}) must be > 0")
        reference = _as_rgb(reference, "reference")
        names = list(names) if names is not None else [f"press {k}" for k in range(len(presses))]
        ball_px = ball_radius_m / pixel_size_m
        rng = np.random.default_rng(seed)
        inputs, targets, thresholds, used, too_large = [], [], [], [], []
        for k, (name, image) in enumerate(zip(names, presses)):
            image = _as_rgb(image, name)
            if image.shape != reference.shape:
                raise TactileError(
                    "calibration", f"{name} is {_wxh(image.shape)}, the reference {_wxh(reference.shape)}"
                )
            change = color_change(image, reference)
            circle = find_contact_circle(change)
            record = {"index": k, "file": name, "role": "fit"}
            why = "no contact circle" if circle is None else None
            if circle is not None and circle.radius >= 0.95 * ball_px:
                why = f"contact radius {circle.radius:.1f} px is not smaller than the ball's {ball_px:.1f} px"
                too_large.append(circle.radius)
            if why:
                log.warning("%s: %s, skipped", name, why)
                used.append({**record, "skipped": why})
                continue
            gx, gy, rho = sphere_press_gradients(change.magnitude.shape, (circle.cx, circle.cy), circle.radius, ball_px)
            features = _features(change.change)
            contact = np.flatnonzero(rho.ravel() < circle.radius - RIM_MARGIN_PX)
            flat = np.flatnonzero(rho.ravel() > FLAT_BEYOND * circle.radius)
            flat = rng.choice(flat, min(len(flat), len(contact)), replace=False)
            pick = np.concatenate([contact, flat])
            inputs.append(features[pick])
            targets.append(np.stack([gx.ravel()[pick], gy.ravel()[pick]], axis=1))
            thresholds.append(float(np.percentile(change.magnitude.ravel()[flat], 99.5)) if len(flat) else MIN_CHANGE)
            used.append({**record, "centre_px": [circle.cx, circle.cy], "contact_radius_px": circle.radius})
        if not inputs and too_large:  # every contact circle found is wider than the ball: its size is wrong
            raise TactileError(
                "calibration",
                f"no press fitted: every contact circle found ({len(too_large)}, radius {min(too_large):.1f}-"
                f"{max(too_large):.1f} px) is not smaller than the ball's {ball_px:.1f} px ({ball_radius_m * 1e3:g} "
                f"mm at {pixel_size_m * 1e3:g} mm per pixel): check --ball-radius-mm and --pixel-size-mm",
            )
        if not inputs:
            raise TactileError(
                "calibration",
                "no ball press with a detectable contact circle (press the ball fully inside the image, 0.5-1.5 mm "
                "deep; the reference must show the untouched gel)",
            )
        weights = _train_mlp(np.concatenate(inputs), np.concatenate(targets), steps=steps, seed=seed)
        size, threshold = tuple(int(s) for s in reference.shape[:2]), max(MIN_CHANGE, float(np.median(thresholds)))
        return cls(weights, pixel_size_m, size, ball_radius_m, threshold, MIN_CONTACT_DEPTH_PX * pixel_size_m, used)

    def change(self, image: np.ndarray, reference: np.ndarray) -> ColorChange:
        """The colour change of ``image`` against ``reference``: at least this sensor's noise counts, and at most
        MAX_CHANGE_FACTOR times that is needed."""
        image = _as_rgb(image, "image")
        if image.shape[:2] != tuple(self.image_size):
            raise TactileError(
                "calibration", f"image is {_wxh(image.shape)}, the calibration is for {_wxh(self.image_size)}"
            )
        cap = MAX_CHANGE_FACTOR * max(MIN_CHANGE, self.change_threshold)
        return color_change(image, reference, min_change=self.change_threshold, max_change=cap)

    def gradients(self, change: ColorChange) -> tuple[np.ndarray, np.ndarray]:
        """Surface gradients (gx, gy) [h, w] of the gel from its colour change."""
        g = _mlp(self.weights, _features(change.change)).reshape(*change.magnitude.shape, 2).astype(np.float64)
        return g[..., 0], g[..., 1]

    def depth(self, image: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Indentation [h, w] float32 metres (>= 0, 0 = no contact) of ``image`` against the no-contact ``reference``."""
        change = self.change(image, reference)
        deformed = _solid_blobs(change.changed)
        if not deformed.any():
            return np.zeros(change.magnitude.shape, np.float32)
        deformed = ndimage.binary_dilation(deformed, iterations=2)
        gx, gy = self.gradients(change)
        gx[~deformed] = 0.0
        gy[~deformed] = 0.0
        depth = np.maximum(poisson_integrate(gx, gy, self.pixel_size_m, contact_region(gx, gy, deformed)), 0.0)
        count, labels = cv2.connectedComponents((depth > 0).astype(np.uint8))
        deepest = ndimage.maximum(depth, labels, np.arange(count))
        return np.where(deepest[labels] >= self.noise_floor_m, depth, 0.0).astype(np.float32)

    def save(self, path: str | Path) -> None:
        """Write the calibration (.npz) atomically (a temporary name, then a rename)."""
        meta = {"format": FORMAT, "version": VERSION, "layers": len(self.weights) // 2, **vars(self)}
        del meta["weights"]  # (the arrays w0, w1, ...)
        weights = {f"w{i}": w for i, w in enumerate(self.weights)}
        atomic_write(path, lambda f: np.savez_compressed(f, meta=json.dumps(meta), **weights))

    @classmethod
    def load(cls, path: str | Path) -> "TactileCalibration":
        path = Path(path)
        try:
            with np.load(path) as data:
                meta = json.loads(str(data["meta"]))
                layers = meta.get("layers", 0) if isinstance(meta, dict) else 0  # (no object: refused below)
                weights = [data[f"w{i}"] for i in range(2 * int(layers))]
        except FileNotFoundError:
            raise TactileError("calibration", f"{path}: file not found") from None
        except _DAMAGED:
            raise TactileError(
                "calibration",
                f"{path}: not a tactile calibration file (an .npz written by `tacsplat calibrate tactile`)",
            ) from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise TactileError("calibration", f"{path} [format]: expected {FORMAT!r}")
        if meta.get("version") != VERSION:
            raise TactileError(
                "calibration",
                f"{path} [version]: {meta.get('version')!r} was written by another "
                f"tacsplat (expected {VERSION}): run `tacsplat calibrate tactile` again",
            )
        try:
            m = _Meta.model_validate(meta)
        except ValidationError as exc:
            raise TactileError("calibration", "{} [{}]: {}".format(path, *field_error(exc, _Meta))) from None
        shapes = [w.shape for w in weights]
        mlp = len(weights) >= 4 and all(
            len(shapes[i]) == 2 and shapes[i + 1] == (shapes[i][1],) and (i == 0 or shapes[i][0] == shapes[i - 2][1])
            for i in range(0, len(shapes), 2)
        )
        mlp = mlp and shapes[0][0] == 5 and shapes[-1] == (2,)  # 5 inputs, 2 outputs
        # real and finite (not strings, integers or complex numbers)
        if not (mlp and all(w.dtype.kind == "f" and np.isfinite(w).all() for w in weights)):
            arrays = ", ".join(f"{w.dtype}{list(w.shape)}" for w in weights)
            raise TactileError("calibration", f"{path} [w0..]: not a finite MLP from 5 inputs to 2 outputs: {arrays}")
        return cls(weights, **(m.model_dump() | {"image_size": tuple(m.image_size)}))


class _Meta(CalibrationFile, extra="ignore"):
    """The metadata of a tactile calibration file (``meta`` of the .npz)."""

    pixel_size_m: Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
    image_size: Annotated[list[Annotated[int, Field(ge=3)]], Field(min_length=2, max_length=2)]  # [height, width]
    ball_radius_m: NonNegative
    change_threshold: NonNegative
    noise_floor_m: NonNegative
    presses: list[dict] = []
    check_summary: dict | None = None


# --- checking a calibration on ball presses ------------------------------------------------------------------------


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Sphere (centre [3], radius) through points [N, 3]: algebraic fit, refined on the geometric distance."""
    A = np.column_stack([2 * points, np.ones(len(points))])
    solution, *_ = np.linalg.lstsq(A, np.sum(points**2, axis=1), rcond=None)
    centre = solution[:3]
    radius = np.sqrt(max(solution[3] + centre @ centre, 1e-18))
    refined = least_squares(lambda p: np.linalg.norm(points - p[:3], axis=1) - p[3], np.append(centre, radius))
    return refined.x[:3], float(abs(refined.x[3]))


def fit_ball(
    calibration: TactileCalibration, reference: np.ndarray, image: np.ndarray, label_radius_px: float | None = None
) -> dict:
    """Check a calibration on one ball press: contact circle, depth, and a sphere fitted to the lifted contact points.

    Returns ``detected`` (a contact circle and a contact in the depth), ``centre_px``, ``contact_radius_px``
    (the circle's), ``fitted_radius_m`` (the sphere through the points of the contact at the circle),
    ``peak_indentation_m``, ``contact_points``, ``other_contact_px`` (contact away from the ball: phantom
    contacts) and ``label_radius_px``.
    """
    circle = find_contact_circle(calibration.change(image, reference))
    depth = calibration.depth(image, reference).astype(np.float64)
    count, labels = cv2.connectedComponents((depth > 0).astype(np.uint8))
    ball = np.zeros(depth.shape, bool)
    if circle is not None and count > 1:
        ys, xs = np.indices(depth.shape)
        inside = np.hypot(xs - circle.cx, ys - circle.cy) < circle.radius
        overlap = np.bincount(labels[inside], minlength=count)[1:]
        ball = labels == 1 + int(np.argmax(overlap)) if overlap.max() > 0 else ball
    result = {
        "detected": bool(ball.sum() >= 10),
        "label_radius_px": label_radius_px,
        "centre_px": None if circle is None else [circle.cx, circle.cy],
        "contact_radius_px": None if circle is None else circle.radius,
        "contact_points": int(ball.sum()),
        "other_contact_px": int((depth > 0).sum() - ball.sum()),
        "peak_indentation_m": float(depth[ball].max()) if ball.any() else 0.0,
        "fitted_radius_m": None,
    }
    if result["detected"]:
        x, y = tactile_pixel_grid(*depth.shape, calibration.pixel_size_m)
        result["fitted_radius_m"] = fit_sphere(np.column_stack([x[ball], y[ball], -depth[ball]]))[1]
    return result


def calibrate_tactile(
    reference: np.ndarray,
    presses: Sequence[np.ndarray],
    names: Sequence[str],
    ball_radius_m: float,
    pixel_size_m: float,
    labels: dict[str, float] | None = None,
    check_every: int = 3,
    steps: int = 1500,
) -> TactileCalibration:
    """Fit on the presses but every ``check_every``-th (the 3rd, 6th, ...), and check the fit on those held out.

    ``labels`` maps a press's name to a hand-labelled contact radius in pixels. The returned calibration's
    ``presses`` hold every press's role and circle (and ball fit for the held-out ones), ``check_summary``
    the median and spread of the fitted radii; :func:`check_problem` says whether to refuse it.
    """
    names = list(names)
    if check_every < 2:
        raise InvalidInputError(f"check_every must be >= 2, got {check_every}")
    held_out = [k for k in range(len(names)) if k % check_every == check_every - 1]
    fitted = [k for k in range(len(names)) if k not in held_out]
    if len(names) >= 3 and not held_out:
        raise TactileError(
            "calibration",
            f"--check-every {check_every} holds out no press of the {len(names)} given: "
            f"give at most {len(names)}, or more presses",
        )
    if len(fitted) < 2 or not held_out:
        raise TactileError(
            "calibration",
            f"{len(names)} ball presses: at least 3 are needed (2 to fit, 1 to check); "
            "10-30 at different places make a good calibration",
        )
    fit_images, fit_names = [presses[k] for k in fitted], [names[k] for k in fitted]
    calib = TactileCalibration.fit(reference, fit_images, ball_radius_m, pixel_size_m, fit_names, steps)
    records = {record["file"]: record for record in calib.presses}
    labels = labels or {}
    for k in held_out:
        result = fit_ball(calib, reference, presses[k], labels.get(names[k]))
        records[names[k]] = {"index": k, "file": names[k], "role": "check", **result}
    for k in fitted:
        records[names[k]].update(index=k, label_radius_px=labels.get(names[k]))
    calib.presses = [records[name] for name in names]
    checks = [records[names[k]] for k in held_out]
    detected = [r for r in checks if r["detected"]]
    radii = [r["fitted_radius_m"] for r in detected]
    calib.check_summary = {"presses": len(checks), "detected": len(radii), "ball_radius_m": ball_radius_m}
    if radii:
        q25, median, q75 = np.percentile(radii, [25, 50, 75])
        spread = {"median": median, "q25": q25, "q75": q75, "min": min(radii), "max": max(radii)}
        calib.check_summary.update({f"{key}_fitted_radius_m": float(value) for key, value in spread.items()})
        calib.check_summary["median_peak_indentation_m"] = float(np.median([r["peak_indentation_m"] for r in detected]))
    ratios = [
        r["contact_radius_px"] / r["label_radius_px"]
        for r in detected
        if r["label_radius_px"] and r["contact_radius_px"]
    ]
    if ratios:
        calib.check_summary["median_contact_radius_over_label"] = float(np.median(ratios))
    return calib


def check_problem(calibration: TactileCalibration, max_radius_error: float = 0.2) -> str | None:
    """Why a calibration from :func:`calibrate_tactile` must not be used (naming what to capture again), or None."""
    summary = calibration.check_summary or {}
    ball_mm = calibration.ball_radius_m * 1e3
    checks = [p for p in calibration.presses if p.get("role") == "check"]
    capture = (
        f"capture them again (the same ball of radius {ball_mm:g} mm, pressed about 0.5-1.5 mm deep, wholly "
        "inside the image, with the reference image of the untouched gel taken just before), "
        "or check --ball-radius-mm and --pixel-size-mm"
    )
    if missed := [p["file"] for p in checks if not p["detected"]]:
        return f"no ball press detected in the held-out {', '.join(missed)}: {capture}"
    median = summary.get("median_fitted_radius_m")
    error = abs(median / calibration.ball_radius_m - 1.0)
    if error > max_radius_error:
        off = [
            f"{p['file']} {p['fitted_radius_m'] * 1e3:.2f} mm"
            for p in checks
            if abs(p["fitted_radius_m"] / calibration.ball_radius_m - 1.0) > max_radius_error
        ]
        return (
            f"on the held-out presses the fitted ball radius is {median * 1e3:.2f} mm (median), {error:.0%} off "
            f"the ball's {ball_mm:g} mm (at most {max_radius_error:.0%} allowed): {'; '.join(off)}; the calibration "
            f"does not generalise to these presses: {capture}"
        )
    # A wrong --pixel-size-mm or --ball-radius-mm passes the radius check (the presses' gradients and the sphere fit
    # share the wrong scale) and shows only in the depth: refused, since every depth the file gave would be off.
    low, high = READ_DEPTH_M
    peak = summary.get("median_peak_indentation_m")
    if peak is not None and not low <= peak <= high:
        return (
            f"on the held-out presses the median peak indentation is {peak * 1e3:.3f} mm, outside the "
            f"{low * 1e3:g}-{high * 1e3:g} mm that presses {_documented_depth()} read: check --pixel-size-mm and "
            f"--ball-radius-mm (a wrong scale passes the radius check, which shares it), or press the ball "
            f"{_documented_depth()}"
        )
    return None


def depth_warning(calibration: TactileCalibration) -> str | None:
    """What to check when the held-out presses read shallower than presses made as documented usually do (below
    ``SHALLOW_DEPTH_M``; :func:`check_problem` refuses below ``READ_DEPTH_M``), or None."""
    peak = (calibration.check_summary or {}).get("median_peak_indentation_m")
    if peak is None or not READ_DEPTH_M[0] <= peak < SHALLOW_DEPTH_M:
        return None
    return (
        f"the held-out presses' median peak indentation is {peak * 1e3:.3f} mm, shallower than presses "
        f"{_documented_depth()} usually read ({SHALLOW_DEPTH_M * 1e3:g} mm or more): check --pixel-size-mm and "
        "--ball-radius-mm, or press deeper"
    )


def _documented_depth() -> str:
    return f"{PRESS_DEPTH_M[0] * 1e3:g}-{PRESS_DEPTH_M[1] * 1e3:g} mm deep"


class OpticalTactileSensor:
    """A fingertip tactile camera implementing the ``TactileSensor`` Protocol; a context manager.

    ``T_hand_sensor`` is the sensor pose in the hand frame: a fixed [4, 4] or a
    callable returning it (e.g. ``lambda: hand.fingertip_poses()["index"]``).
    ``width`` and ``height`` default to the calibration's image size (asked of the camera, verified on open).
    On open, the mean of ``reference_frames`` frames becomes the no-contact
    reference: the gel must be untouched then.
    """

    def __init__(
        self,
        name: str,
        source: int | str,
        calibration: TactileCalibration | str | Path,
        T_hand_sensor: np.ndarray | Callable[[], np.ndarray] = np.eye(4),
        *,
        width: int | None = None,
        height: int | None = None,
        fps: float | None = None,
        timeout_s: float = 2.0,
        reference_frames: int = 5,
        capture_factory=cv2.VideoCapture,
    ):
        self.name = name
        self.calibration = (
            calibration if isinstance(calibration, TactileCalibration) else TactileCalibration.load(calibration)
        )
        self._pose = T_hand_sensor if callable(T_hand_sensor) else (lambda T=as_pose(T_hand_sensor, "T_hand_sensor"): T)
        self.reference_frames = int(reference_frames)
        rows, cols = (int(n) for n in self.calibration.image_size)  # the size to ask for unless told another
        width, height = cols if width is None else width, rows if height is None else height
        video = dict(width=width, height=height, fps=fps, timeout_s=timeout_s, capture_factory=capture_factory)
        self._video = VideoReader(source, name=f"tactile sensor {name!r}", **video)
        self.reference: np.ndarray | None = None  # [h, w, 3] float64 RGB

    def __enter__(self) -> "OpticalTactileSensor":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        """Open the camera and take the no-contact reference; on any failure the camera is closed again."""
        try:
            size = (self._video.open().height, self._video.width)
            if size != tuple(self.calibration.image_size):
                delivers = f"camera delivers {_wxh(size)}, the calibration is for {_wxh(self.calibration.image_size)}"
                raise TactileError(self.name, delivers)
            self.capture_reference()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        self._video.close()

    def capture_reference(self) -> None:
        """Average ``reference_frames`` frames of the untouched gel into the no-contact reference."""
        frames = [self._read_rgb()[0].astype(np.float64) for _ in range(self.reference_frames)]
        self.reference = np.mean(frames, axis=0)

    def _read_rgb(self):
        frame = self._video.read()
        return cv2.cvtColor(frame.image, cv2.COLOR_BGR2RGB), frame

    def read(self) -> TactileReading:
        """A reading with depth from the newest frame (:meth:`TactileCalibration.depth`), its pose in the hand frame."""
        if self.reference is None:
            raise TactileError(self.name, "not open (no reference frame)")
        rgb, frame = self._read_rgb()
        depth = self.calibration.depth(rgb, self.reference)
        return TactileReading(
            depth=depth,
            pixel_size_m=self.calibration.pixel_size_m,
            T_ref_sensor=self._pose(),
            frame="hand",
            timestamp=frame.timestamp,
            meta={"sensor": self.name, "frame_index": frame.index},
        )
