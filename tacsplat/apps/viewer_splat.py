"""Gaussians in the browser (viser's splat buffers) and a browser viewpoint rendered with tacsplat's rasterizer.

viser draws each Gaussian from its centre, its 3D covariance (sent as float16),
its RGB and opacity: the view-independent colour of the DC band, so a splat with
higher SH bands looks flatter in the browser than in our renders. float16
covariances underflow at the sizes of a real object's Gaussians (a 0.1 mm
Gaussian has a covariance of 1e-8 m^2), so a splat is sent in its own length
unit, the median size of its Gaussians (kept within a range of the scene's
extent), and scaled back to metres by its scene node; a Gaussian too large for
float16 in that unit (a foreign splat.ply's log-scale of +80) is drawn clamped,
and one whose centre lies absurdly far from the rest (1e30 m) is left out.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch

from tacsplat.reconstruction.gaussians import Gaussians, quats_to_rotmats, sh0_to_rgb

SPLAT_SETS = {"camera": False, "touch": True}  # node name -> the from_touch flag of its Gaussians (G_c, G_t)
GAUSSIAN_SETS = {"all": None, "touch only (G_t)": ("touch",), "camera only (G_c)": ("camera",)}  # None: every set
# the largest scale drawn, in units: its covariance (units squared) stays finite in viser's float16 (max 65504),
# with a factor of 4 to spare for rounding
MAX_SCALE_UNITS = math.sqrt(float(np.finfo(np.float16).max)) / 2
UNIT_RANGE = (1e-4, 1.0)  # the unit's bounds, times the scene's extent: centres stay within ~1e4 units
# centres farther than this many extents from their set's median are left out: viser sorts by depth in 65536 bins
# from nearest to farthest, so a far one leaves the object unsorted (and one at 3e38 m overflows float32)
MAX_CENTRE_EXTENTS = 1e3

log = logging.getLogger(__name__)


@dataclass
class SplatBuffers:
    """What viser's ``add_gaussian_splats`` takes, in the splat's own length unit ``unit`` (metres)."""

    centers: np.ndarray  # [N, 3] float32, in units of ``unit``
    covariances: np.ndarray  # [N, 3, 3] float32, in units of ``unit`` squared
    rgbs: np.ndarray  # [N, 3] float32 in [0, 1]
    opacities: np.ndarray  # [N, 1] float32 in [0, 1]
    unit: float
    clamped: int = 0  # how many Gaussians were drawn smaller than they are (over MAX_SCALE_UNITS)
    left_out: int = 0  # how many Gaussians were left out (centre over MAX_CENTRE_EXTENTS extents away)


def median_and_extent(means: torch.Tensor) -> tuple[torch.Tensor, float]:
    """(median [3], extent) of the centres ``means`` [N > 0, 3]: their median, and the median distance of the
    centres from it (1 m when that is 0)."""
    median = means.median(dim=0).values
    spread = float((means - median).norm(dim=1).median())
    return median, spread if spread > 0 else 1.0


def far_centres(means: torch.Tensor) -> torch.Tensor:
    """[N] bool: which of the centres ``means`` [N, 3] lie over ``MAX_CENTRE_EXTENTS`` times their extent from
    their median: those a view leaves out."""
    if not len(means):
        return torch.zeros(0, dtype=torch.bool)
    return _far_from(means, *median_and_extent(means))


def _far_from(means: torch.Tensor, median: torch.Tensor, extent: float) -> torch.Tensor:
    """[N] bool: which of ``means`` lie over ``MAX_CENTRE_EXTENTS`` times ``extent`` from ``median``."""
    return (means - median).norm(dim=1) > MAX_CENTRE_EXTENTS * extent


def log_unit_of(log_scales: torch.Tensor, extent: float) -> float:
    """The log of a splat's own length unit (metres): the median size of its Gaussians (``log_scales`` [N > 0, 3]),
    kept within ``UNIT_RANGE`` of its extent ``extent`` (see :func:`median_and_extent`)."""
    low, high = (math.log(extent * bound) for bound in UNIT_RANGE)
    return min(max(float(log_scales.max(dim=1).values.median()), low), high)


@torch.no_grad()
def splat_buffers(gaussians: Gaussians, mask: torch.Tensor | None = None) -> SplatBuffers:
    """The browser's view of ``gaussians`` (those where ``mask`` is True, default all: at least one), less those
    whose centres are far from the rest (as :func:`far_centres` says)."""
    selected = torch.ones(len(gaussians), dtype=torch.bool) if mask is None else mask.cpu()
    centres = gaussians.means.detach().cpu()[selected].double()
    median, extent = median_and_extent(centres)  # (once: two medians over every centre)
    far = torch.zeros_like(selected)
    far[selected] = _far_from(centres, median, extent)
    keep = selected & ~far
    means = gaussians.means.detach().cpu()[keep].double()
    log_scales = gaussians.params["scales"].detach().cpu()[keep].double()  # (in logs: exp of a huge one is inf)
    log_unit = log_unit_of(log_scales, extent)
    log_largest = log_unit + math.log(MAX_SCALE_UNITS)
    scales = (log_scales.clamp(max=log_largest) - log_unit).exp()  # in units
    rotations = quats_to_rotmats(gaussians.quats.detach().cpu()[keep].double())
    covariances = rotations @ torch.diag_embed(scales.square()) @ rotations.transpose(-1, -2)
    rgbs = sh0_to_rgb(gaussians.params["sh0"].detach().cpu()[keep][:, 0]).clamp(0, 1)
    return SplatBuffers(
        centers=(means / math.exp(log_unit)).float().numpy(),
        covariances=covariances.float().numpy(),
        rgbs=rgbs.float().numpy(),
        opacities=gaussians.opacities.detach().cpu()[keep][:, None].float().numpy(),
        unit=math.exp(log_unit),
        clamped=int((log_scales > log_largest).any(dim=1).sum()),
        left_out=int(far.sum()),
    )


def add_splat(
    scene_api, name: str, gaussians: Gaussians, source: object = None, warned: set | None = None
) -> dict[str, object]:
    """Add ``gaussians`` under ``name`` as two splat nodes, ``name/camera`` (G_c) and ``name/touch`` (G_t), so that
    either can be hidden; a set with no Gaussians gets no node. Returns the nodes by set name. Gaussians drawn
    clamped or left out get one warning naming ``source``, the file they came from, unless it is in ``warned``
    (the files already warned about, which it joins: a file shown again is not warned about again)."""
    nodes, clamped, left_out = {}, 0, 0
    for set_name, from_touch in SPLAT_SETS.items():
        mask = gaussians.from_touch.cpu() == from_touch
        if not bool(mask.any()):
            continue
        b = splat_buffers(gaussians, mask)
        clamped += b.clamped
        left_out += b.left_out
        nodes[set_name] = scene_api.add_gaussian_splats(
            f"{name}/{set_name}", b.centers, b.covariances, b.rgbs, b.opacities, scale=b.unit
        )
    n, problems = len(gaussians), []
    if clamped:
        problems.append(
            f"{clamped} of {n} Gaussians are too large to draw (over {MAX_SCALE_UNITS:.0f} times their set's "
            "typical size); drawn at that size"
        )
    if left_out:
        problems.append(
            f"{left_out} of {n} Gaussians lie too far from the rest to draw (over {MAX_CENTRE_EXTENTS:.0f} times "
            "their set's extent); left out"
        )
    warned = set() if warned is None else warned
    if problems and str(source) not in warned:
        warned.add(str(source))
        log.warning("%s: %s", source, "; ".join(problems))
    return nodes


def camera_matrices(wxyz, position, fov_y: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(T_world_cam [4, 4], K [3, 3]) of a browser camera: viser's pose (OpenCV axes, camera-to-world rotation
    ``wxyz`` and ``position``) and vertical field of view, seen at ``width`` x ``height`` pixels."""
    import viser.transforms as vtf

    from tacsplat.geometry import focal_from_fov, intrinsics_matrix, make_pose

    focal = focal_from_fov(fov_y, height)
    return (
        make_pose(vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix(), position),
        intrinsics_matrix(focal, focal, 0.5 * width, 0.5 * height),
    )


@torch.no_grad()
def render_viewpoint(
    gaussians: Gaussians, T_world_cam: np.ndarray, K: np.ndarray, width: int, height: int, background=(1.0, 1.0, 1.0)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb [H, W, 3] in [0, 1] over ``background``, expected depth [H, W] in metres, alpha [H, W]) of
    ``gaussians`` seen from a pinhole camera, by :func:`tacsplat.reconstruction.raster.rasterization`."""
    from tacsplat.geometry import invert_pose
    from tacsplat.reconstruction.raster import rasterization

    g = gaussians.to("cpu")
    viewmat = torch.tensor(invert_pose(T_world_cam), dtype=torch.float32)[None]
    Ks = torch.tensor(K, dtype=torch.float32)[None]
    out, alpha, _ = rasterization(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        g.sh_coefficients(),
        viewmat,
        Ks,
        width,
        height,
        sh_degree=g.sh_degree,
        render_mode="RGB+ED",
        backgrounds=torch.tensor([background], dtype=torch.float32),
    )
    return out[0, ..., :3].clamp(0, 1).numpy(), out[0, ..., 3].numpy(), alpha[0, ..., 0].numpy()


def depth_picture(depth: np.ndarray, alpha: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """A uint8 RGB picture [H, W, 3] of an expected-depth map: matplotlib's turbo colour map over the drawn
    pixels' depth range (red near, blue far), white where alpha <= ``threshold``."""
    import matplotlib

    drawn = alpha > threshold
    picture = np.full(depth.shape + (3,), 255, np.uint8)
    if drawn.any():
        near, far = float(depth[drawn].min()), float(depth[drawn].max())
        scaled = 1.0 - (depth[drawn] - near) / max(far - near, 1e-9)
        picture[drawn] = (matplotlib.colormaps["turbo"](scaled)[:, :3] * 255).round().astype(np.uint8)
    return picture
