"""`tacsplat calibrate camera`, `tacsplat calibrate tactile` and `tacsplat tactile depth` (see tacsplat.cli); their
options are the dataclasses below (tacsplat.options)."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from tacsplat.errors import CameraError, ConfigError, InvalidInputError, TactileError, UsageError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
MAX_RMS_PX = 1.0  # a camera calibration's RMS reprojection error above this is warned about (expect well under 1 px)


@dataclass
class CalibrateCamera:
    """intrinsic calibration of the wrist camera from photos of a ChArUco board or a chessboard

    Finds the board's corners (sub-pixel) in every photo, runs cv2.calibrateCameraExtended, prints the RMS
    reprojection error, the intrinsics and their standard deviations. Refuses, naming the photos and what to add, a
    set that cannot determine the intrinsics (fewer than 3 distinct board poses, a repeated photo counting once, or
    the board in fewer than 3 orientations 10 degrees apart: a board facing the camera, or boards parallel to each
    other, leave the focal length unobservable) and a result that is no camera (a field of view outside 2-170
    degrees, a standard deviation of zero, distortion that folds the image where corners were seen). Warns, naming
    what to add, when the focal length is poorly constrained (standard deviation above 1%), parts of the image saw
    no corner, the lens model fails in the image corners beyond the corners seen, photos repeat a pose (one that
    repeats another pixel for pixel is left out of the solve) or the RMS error is over 1 px. Writes
    the calibration (OpenCV K with pixel centres at integers, distortion, K_std_px, warnings) as JSON, a picture of
    the detected and reprojected corners (.png) and one of the corner coverage (_coverage.png) next to it."""

    photos: Annotated[
        tyro.conf.Positional[tuple[Path, ...]], tyro.conf.arg(metavar="PHOTOS", help_behavior_hint="(required)")
    ]
    """board photos (png, jpg, ...) or folders of them"""
    out: Path
    """calibration file to write (.json)"""
    board: Literal["charuco", "chessboard"] = "charuco"
    """the printed board"""
    inner_corners: Annotated[str | None, tyro.conf.arg(metavar="XxY")] = None
    """chessboard: inner corners (where four squares meet) along x and y, e.g. 9x6"""
    square_mm: Annotated[
        float | None,
        tyro.conf.arg(metavar="FLOAT", help_behavior_hint="(default: 30 for a ChArUco board; needed for a chessboard)"),
    ] = None
    """square side in millimetres"""
    squares_x: Annotated[int | None, tyro.conf.arg(metavar="INT", help_behavior_hint="(default: 7)")] = None
    """ChArUco: squares along x"""
    squares_y: Annotated[int | None, tyro.conf.arg(metavar="INT", help_behavior_hint="(default: 5)")] = None
    """ChArUco: squares along y"""
    marker_mm: Annotated[float | None, tyro.conf.arg(metavar="FLOAT", help_behavior_hint="(default: 22)")] = None
    """ChArUco: ArUco marker side, millimetres"""
    dictionary: Annotated[str | None, tyro.conf.arg(metavar="STR", help_behavior_hint="(default: DICT_5X5_100)")] = None
    """ChArUco: cv2.aruco predefined dictionary"""
    legacy_pattern: bool = False
    """ChArUco: board printed by OpenCV < 4.6"""
    distortion: Literal["opencv5", "opencv4", "rational8"] = "opencv5"  # wrist_camera.DISTORTION_MODELS
    """distortion model: opencv5 = k1 k2 p1 p2 k3 (all free), opencv4 = k3 held at zero, rational8 = k1..k6 p1 p2
    (wide-angle lenses)"""


@dataclass
class CalibrateTactile:
    """GelSight-style calibration of an optical tactile sensor from ball presses

    FOLDER holds one image of the untouched gel named reference.* and images of presses of a ball of known radius
    (any other names), taken in name order. Fits colour change -> surface gradient (a small MLP on colour change and
    pixel position) on two thirds of the presses, checks it on every third press (a sphere fitted to the depth of
    each held-out press, against the ball), prints the median and spread of the fitted radii, and refuses to write a
    calibration whose fitted radii are far off, or whose presses come out far shallower or deeper than the 0.5-1.5
    mm they are pressed (a wrong --pixel-size-mm or --ball-radius-mm). The images must be the sensor's colour
    images. Writes the calibration (.npz) and a picture of the detected contact circles over each press (.png) next
    to it."""

    folder: tyro.conf.Positional[Path]
    """folder with reference.* and ball-press images"""
    out: Path
    """calibration file to write (.npz)"""
    ball_radius_mm: float
    """radius of the pressed ball, mm"""
    pixel_size_mm: float
    """gel size of one image pixel, mm"""
    labels: Path | None = None
    """JSON of hand labels: {"presses": [{"file": ..., "contact_radius_px": ..., "center_xy_px": [x, y]}, ...]},
    reported beside the fits; its "pixel_size_mm" and "ball_radius_mm", when given, must be the options'"""
    check_every: int = 3
    """hold out every n-th press to check the fit"""
    max_radius_error: float = 0.2
    """refuse when the held-out presses' median fitted radius is off the ball's by more than this fraction"""


@dataclass
class TactileDepth:
    """depth maps of tactile images with a calibration (checks a calibration on new presses)

    For each IMAGE, writes OUT/<image stem>.npz with a float32 `depth` array (indentation in metres, 0 = no
    contact, the image's size) and a picture of it, OUT/<image stem>.png. The sensor driver computes depth the same
    way."""

    images: Annotated[
        tyro.conf.Positional[tuple[Path, ...]], tyro.conf.arg(metavar="IMAGE", help_behavior_hint="(required)")
    ]
    """tactile images"""
    calibration: Path
    """tactile calibration (.npz)"""
    reference: Path
    """image of the untouched gel"""
    out: Path
    """folder to write into"""
    overwrite: bool = False
    """replace results already in OUT"""


def register(cli) -> None:
    """Add this package's commands to the tree."""
    cli.typed("calibrate camera", CalibrateCamera, _calibrate_camera)
    cli.typed("calibrate tactile", CalibrateTactile, _calibrate_tactile)
    cli.typed("tactile depth", TactileDepth, _tactile_depth)


def _corner_counts(text: str) -> tuple[int, int]:
    try:
        x, y = (int(n) for n in text.lower().split("x"))
    except ValueError:
        raise UsageError("--inner-corners", f"expected XxY (e.g. 9x6), got {text!r}") from None
    return x, y


def _images(paths) -> list[Path]:
    """Image files: each path an image, or a folder whose images are taken in name order."""

    found = []
    for path in paths:
        if path.is_dir():
            if not (inside := sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)):
                raise InvalidInputError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)})")
            found += inside
        elif path.is_file():
            found.append(path)
        else:
            raise InvalidInputError(f"{path}: no such image or folder")
    return found


def _photo_names(paths: list[Path]) -> list[str]:
    """A name per photo that tells it from the others (in the report and the pictures): its path from the folder
    common to all, so ``s1/img01.jpg`` and ``s2/img01.jpg``, or its file name when they share one folder."""
    absolute = [Path(os.path.abspath(p)) for p in paths]
    for i, path in enumerate(absolute):
        if path in absolute[:i]:
            raise InvalidInputError(f"{paths[i]}: given twice")
    common = Path(os.path.commonpath([p.parent for p in absolute]))
    return [p.relative_to(common).as_posix() for p in absolute]


def _read_rgb(path: Path):
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InvalidInputError(f"{path}: cannot read the image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _check_output_file(path: Path, suffix: str, picture: Path) -> None:
    """``--out`` must name a file, not a folder, nor the ``picture`` written beside it (checked before any work)."""

    if path.is_dir():
        raise ConfigError("--out", f"{path} is a folder; give a {suffix} file")
    if str(path).casefold() == str(picture).casefold():  # (the same file where names ignore case, too)
        raise UsageError("--out", f"{path} would be overwritten by the picture written beside it; give a {suffix} file")


def _output_file(path: Path) -> Path:
    """``--out`` ready to be written: its folder made (when missing) and writable."""
    from tacsplat.datasets.outputs import ensure_output_dir

    ensure_output_dir(path.parent, "--out")
    return path


def _write_image(path: Path, bgr) -> Path:
    """Write a picture atomically (a temporary name, then a rename; a full disk is one error naming it)."""
    import cv2

    from tacsplat.files import atomic_write

    ok, encoded = cv2.imencode(path.suffix or ".png", bgr)
    if not ok:
        raise InvalidInputError(f"{path}: OpenCV cannot encode a {path.suffix or '.png'} picture")
    return atomic_write(path, encoded.tobytes())


_BOARD_OPTIONS = {  # board spec field -> the option that sets it
    "inner_corners_x": "--inner-corners",
    "inner_corners_y": "--inner-corners",
    "square_length_m": "--square-mm",
    "squares_x": "--squares-x",
    "squares_y": "--squares-y",
    "marker_length_m": "--marker-mm",
    "dictionary": "--dictionary",
    "legacy_pattern": "--legacy-pattern",
}


def _board_spec(args: CalibrateCamera):
    from tacsplat.drivers.wrist_camera import MAX_SQUARE_LENGTH_M, CharucoBoardSpec, ChessboardSpec

    mm = {"square_length_m": args.square_mm, "marker_length_m": args.marker_mm}
    charuco = {"squares_x": args.squares_x, "squares_y": args.squares_y, "dictionary": args.dictionary}
    charuco |= {"marker_length_m": args.marker_mm, "legacy_pattern": args.legacy_pattern or None}
    if args.board == "chessboard":
        if given := [_BOARD_OPTIONS[name] for name, value in charuco.items() if value is not None]:
            raise UsageError(given[0], "is a ChArUco option; a chessboard takes --inner-corners and --square-mm")
        if args.inner_corners is None:
            raise UsageError(
                "--inner-corners",
                "needed with --board chessboard: the inner corners (where four squares meet) along x and y, e.g. 9x6",
            )
        if args.square_mm is None:
            raise UsageError("--square-mm", "needed with --board chessboard: the printed square side, mm")
        spec = ChessboardSpec(*_corner_counts(args.inner_corners), args.square_mm / 1000.0)
    else:
        if args.inner_corners is not None:
            raise UsageError("--inner-corners", "is a chessboard option; a ChArUco board takes --squares-x/-y")
        given = {**charuco, **{name: value / 1000.0 for name, value in mm.items() if value is not None}}
        spec = dataclasses.replace(CharucoBoardSpec(), **{k: v for k, v in given.items() if v is not None})
    for name in (name for name in mm if hasattr(spec, name)):
        if not 0 < getattr(spec, name) <= MAX_SQUARE_LENGTH_M:
            raise UsageError(
                _BOARD_OPTIONS[name],
                f"must be in (0, {MAX_SQUARE_LENGTH_M * 1000:g}] mm, got {getattr(spec, name) * 1000:g}",
            )
    if isinstance(spec, CharucoBoardSpec) and not spec.marker_length_m < spec.square_length_m:
        square, marker = spec.square_length_m * 1000, spec.marker_length_m * 1000
        raise UsageError("--marker-mm", f"must be smaller than the square ({square:g} mm), got {marker:g}")
    if problem := spec.problem():
        raise UsageError(_BOARD_OPTIONS[problem[0]], problem[1])
    return spec


def _calibrate_camera(args: CalibrateCamera) -> int:
    import numpy as np

    from tacsplat.drivers.wrist_camera import (
        ChessboardSpec,
        calibrate_views,
        detect_board_views,
        distinct_views,
        tacsplat_K_from_opencv,
        view_set_problem,
    )

    if not args.photos:
        raise UsageError("PHOTOS", "required (board photos or folders of them)")
    spec = _board_spec(args)
    _check_output_file(args.out, ".json", args.out.with_suffix(".png"))
    paths = _images(args.photos)
    names = _photo_names(paths)
    images = [_read_rgb(p) for p in paths]
    views, size = detect_board_views(images, spec, names)
    if len(views) < 3:
        option = "--inner-corners" if isinstance(spec, ChessboardSpec) else "--squares-x, --squares-y, --dictionary"
        seen = f" ({', '.join(v.name for v in views)})" if views else ""
        advice = (
            "take more photos (15-30, from varied distances, the board tilted 30-45 degrees towards each side)"
            if len(views) == len(paths)  # the board was found in every photo: there are too few of them
            else f"check {option} against the printed board and that the whole board is in view and sharp"
        )
        raise CameraError(
            "calibration",
            f"the {spec.describe()} was found in {len(views)} of {len(paths)} images{seen}; at least 3 are needed: "
            f"{advice}",
        )
    copies = _copies(images, names, views)
    if copies:  # the set's refusal (too few poses or orientations) names every photo, copies included
        if problem := view_set_problem(views, *distinct_views(views, size), size):
            raise CameraError("calibration", problem)
    # a copy adds the same equations again, making K_std_px too optimistic: left out of the solve
    calib = calibrate_views([v for v in views if v.name not in copies], size, spec, args.distortion)
    calib.warnings += [
        f"{', '.join(repeats)} show{'s' * (len(repeats) == 1)} the board where {first} does (the same photo, pixel "
        f"for pixel: left out of the calibration, {first} kept), adding nothing: take each photo from a new pose"
        for first, repeats in _grouped(copies).items()
    ]
    if calib.rms_px > MAX_RMS_PX:
        calib.warnings.append(
            f"the RMS reprojection error is {calib.rms_px:.2f} px, over {MAX_RMS_PX:g} px (expect well under 1 px): "
            "the corners were found poorly or the photos disagree (a blurred or moving board, a board not flat, "
            "photos of other cameras or sizes, too simple a --distortion model): see the error of each photo"
        )
    out = _output_file(args.out)
    calib.save(out)
    picture = _corner_sheet(images, names, views, calib, out.with_suffix(".png"))
    coverage = _coverage_picture(images[0], views, calib, out.with_name(out.stem + "_coverage.png"))
    K = tacsplat_K_from_opencv(calib.K_opencv)
    std = calib.K_std_px
    used = len(views) - len(copies)
    print(f"{used} of {len(paths)} images used, {calib.width}x{calib.height}, distortion {args.distortion}")
    print(f"RMS reprojection error: {calib.rms_px:.3f} px")
    print(
        f"fx {K[0, 0]:.2f} +- {std['fx']:.2f}  fy {K[1, 1]:.2f} +- {std['fy']:.2f}  cx {K[0, 2]:.2f} +- "
        f"{std['cx']:.2f}  cy {K[1, 2]:.2f} +- {std['cy']:.2f} px (pixel centres at +0.5; {out.name} stores "
        "OpenCV's K, centres at integers)"
    )
    print(f"distortion: {np.array2string(calib.dist, precision=5)}")
    for name, err in calib.per_image_rms_px.items():
        print(f"  {name}: {err:.3f} px")
    for warning in calib.warnings:
        print(f"warning: {warning}")
    print(
        f"wrote {out}; detected corners (green) and their reprojections (red) in {picture}, "
        f"corner coverage in {coverage}"
    )
    return 0


def _copies(images, names, views) -> dict[str, str]:
    """The photos among ``views`` whose pixels repeat an earlier one's: name -> the first photo's name."""
    import hashlib

    first, copies = {}, {}
    used = {view.name for view in views}
    for image, name in zip(images, names):
        if name in used:
            key = (image.shape, hashlib.sha256(image.tobytes()).digest())
            if key in first:
                copies[name] = first[key]
            else:
                first[key] = name
    return copies


def _grouped(copies: dict[str, str]) -> dict[str, list[str]]:
    """``{copy: first}`` as ``{first: [copies]}``."""
    groups = {}
    for name, first in copies.items():
        groups.setdefault(first, []).append(name)
    return groups


def _contact_sheet(tiles, columns: int = 4):
    import numpy as np

    columns = min(columns, len(tiles))
    tiles = tiles + [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    return np.vstack([np.hstack(tiles[i : i + columns]) for i in range(0, len(tiles), columns)])


def _corner_sheet(images, names, views, calib, path: Path) -> Path:
    """A picture of every board image with its detected corners and their reprojection by the calibration."""
    import cv2

    found = {view.name: view for view in views}
    tiles = []
    for image, name in zip(images, names):
        half = (image.shape[1] // 2, image.shape[0] // 2)
        tile = cv2.resize(cv2.cvtColor(image, cv2.COLOR_RGB2BGR), half, interpolation=cv2.INTER_AREA)
        view = found.get(name)
        if view is not None:
            ok, rvec, tvec = cv2.solvePnP(view.object_points, view.image_points, calib.K_opencv, calib.dist)
            proj = view.image_points
            if ok:
                proj = cv2.projectPoints(view.object_points, rvec, tvec, calib.K_opencv, calib.dist)[0].reshape(-1, 2)
            for (u, v), (pu, pv) in zip(view.image_points, proj):  # OpenCV pixel coordinates, drawn at half size
                cv2.circle(tile, (int(round(u / 2)), int(round(v / 2))), 4, (0, 200, 0), 1, cv2.LINE_AA)
                cv2.drawMarker(tile, (int(round(pu / 2)), int(round(pv / 2))), (0, 0, 255), cv2.MARKER_CROSS, 5, 1)
        rms = calib.per_image_rms_px.get(name)
        label = f"{name}: " + (f"{rms:.2f} px" if rms is not None else "not used")
        cv2.putText(tile, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    return _write_image(path, _contact_sheet(tiles))


def _coverage_picture(first_image, views, calib, path: Path) -> Path:
    """Where corners were seen: every view's corners (and the board outline) over the first photo, dimmed; the
    parts of a 3x3 grid with no corner tinted red."""
    import colorsys

    import cv2
    import numpy as np

    from tacsplat.drivers.wrist_camera import CELL_NAMES, empty_image_cells

    h, w = first_image.shape[:2]
    canvas = (cv2.cvtColor(first_image, cv2.COLOR_RGB2BGR) * 0.35).astype(np.uint8)
    empty = set(empty_image_cells(views, (w, h)))
    for r, c in np.ndindex(3, 3):  # the 3x3 grid's parts, row by row
        name = CELL_NAMES[r][c]
        x0, y0, x1, y1 = c * w // 3, r * h // 3, (c + 1) * w // 3, (r + 1) * h // 3
        if name in empty:
            canvas[y0:y1, x0:x1, 2] = np.maximum(canvas[y0:y1, x0:x1, 2], 120)
            cv2.putText(
                canvas, "no corners", (x0 + 8, y0 + 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA
            )
        cv2.rectangle(canvas, (x0, y0), (x1 - 1, y1 - 1), (128, 128, 128), 1)
    for i, view in enumerate(views):
        color = tuple(int(255 * x) for x in colorsys.hsv_to_rgb(i / max(len(views), 1), 0.9, 1.0))[::-1]
        hull = cv2.convexHull(np.round(view.image_points).astype(np.int32))
        cv2.polylines(canvas, [hull], True, color, 1, cv2.LINE_AA)
        for u, v in view.image_points:
            cv2.circle(canvas, (int(round(u)), int(round(v))), 2, color, -1, cv2.LINE_AA)
    text = f"{len(views)} views, {sum(len(v.image_points) for v in views)} corners; " + (
        "well spread" if not empty else f"no corners: {', '.join(sorted(empty))}"
    )
    cv2.putText(canvas, text, (8, h - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return _write_image(path, canvas)


def _read_labels(path: Path) -> tuple[dict[str, dict], dict[str, float]]:
    """Hand labels of ball presses: file name -> {"radius": px, "centre": (x, y) or None}, and the sizes the file
    gives (its ``pixel_size_mm`` and ``ball_radius_mm``, when given); errors name the field."""

    from pydantic import Field

    from tacsplat.drivers.calibration import read_calibration
    from tacsplat.drivers.calibration_files import CalibrationFile

    class Label(CalibrationFile, extra="ignore"):
        file: str
        contact_radius_px: Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
        center_xy_px: (
            Annotated[list[Annotated[float, Field(allow_inf_nan=False)]], Field(min_length=2, max_length=2)] | None
        ) = None

    class Labels(CalibrationFile, extra="ignore"):
        presses: list[Label]
        pixel_size_mm: Annotated[float, Field(gt=0.0, allow_inf_nan=False)] | None = None
        ball_radius_mm: Annotated[float, Field(gt=0.0, allow_inf_nan=False)] | None = None

    labels = read_calibration(path, Labels, key="--labels")
    presses = {
        p.file: {"radius": p.contact_radius_px, "centre": p.center_xy_px and tuple(p.center_xy_px)}
        for p in labels.presses
    }
    sizes = {"pixel_size_mm": labels.pixel_size_mm, "ball_radius_mm": labels.ball_radius_mm}
    return presses, {key: value for key, value in sizes.items() if value is not None}


def _check_label_sizes(args: CalibrateTactile, sizes: dict[str, float]) -> None:
    """The sizes the labels file gives must be the options' (beyond rounding, 1 %): the labels and the ball fit
    would share a wrong one, which the held-out check cannot see."""
    differ = []
    for key, option, value in (
        ("pixel_size_mm", "--pixel-size-mm", args.pixel_size_mm),
        ("ball_radius_mm", "--ball-radius-mm", args.ball_radius_mm),
    ):
        if key in sizes and abs(value / sizes[key] - 1) > 0.01:
            differ.append((option, f"{option} {value:g} mm, but {args.labels} gives {key} {sizes[key]:g} mm"))
    if differ:
        what = "; ".join(text for _, text in differ)
        raise UsageError(differ[0][0], f"{what}: give the sensor's pixel size and the pressed ball's radius in both")


def _press_sheet(images, names, calib, labels, path: Path) -> Path:
    """Each press with its detected contact circle (red), the hand label (white) and its role and ball fit."""
    import cv2

    scale = max(1, round(320 / images[0].shape[1]))
    records = {p["file"]: p for p in calib.presses}
    tiles = []
    for image, name in zip(images, names):
        tile = cv2.resize(
            cv2.cvtColor(image, cv2.COLOR_RGB2BGR), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST
        )
        record = records.get(name, {})

        def circle(centre, radius, color):
            at = (int(round((centre[0] + 0.5) * scale - 0.5)), int(round((centre[1] + 0.5) * scale - 0.5)))
            cv2.circle(tile, at, int(round(radius * scale)), color, 1, cv2.LINE_AA)

        label = labels.get(name)
        if label and label["centre"] is not None:
            circle(label["centre"], label["radius"], (255, 255, 255))
        if record.get("centre_px") is not None:
            circle(record["centre_px"], record["contact_radius_px"], (0, 0, 255))
        if record.get("role") == "check":
            status = f"check: R {record['fitted_radius_m'] * 1e3:.2f} mm" if record["detected"] else "check: NOT FOUND"
        else:
            status = "fit" if "skipped" not in record else "fit: skipped"
        for row, text in enumerate((name, status)):
            cv2.putText(tile, text, (4, 14 + 16 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    return _write_image(path, _contact_sheet(tiles))


def _calibrate_tactile(args: CalibrateTactile) -> int:
    from tacsplat.drivers.optical_tactile import calibrate_tactile, check_problem, depth_warning, image_problem

    for option, value in (("--ball-radius-mm", args.ball_radius_mm), ("--pixel-size-mm", args.pixel_size_mm)):
        if not 0 < value < 1000:
            raise UsageError(option, f"must be in (0, 1000) mm, got {value}")
    if not 0 < args.max_radius_error < 1:
        raise UsageError("--max-radius-error", f"must be in (0, 1), got {args.max_radius_error}")
    if args.check_every < 2:
        raise UsageError("--check-every", f"must be >= 2, got {args.check_every}")
    _check_output_file(args.out, ".npz", args.out.with_suffix(".png"))
    if not args.folder.is_dir():
        raise InvalidInputError(f"{args.folder}: not a folder")
    paths = _images([args.folder])
    references = [p for p in paths if p.stem.lower() == "reference"]
    if len(references) != 1:
        raise InvalidInputError(f"{args.folder}: expected exactly one image named reference.*, found {len(references)}")
    labels, label_sizes = _read_labels(args.labels) if args.labels else ({}, {})
    _check_label_sizes(args, label_sizes)
    presses = [p for p in paths if p not in references]
    reference = _read_rgb(references[0])
    if problem := image_problem(reference):
        raise InvalidInputError(f"{references[0]}: the reference image of the untouched gel is {problem}")
    images = [_read_rgb(p) for p in presses]
    for path, image in zip(presses, images):
        if image.shape != reference.shape:
            raise InvalidInputError(
                f"{path}: {image.shape[1]}x{image.shape[0]}, the reference {reference.shape[1]}x{reference.shape[0]}"
            )
        if problem := image_problem(image, reference=False):
            raise InvalidInputError(f"{path}: {problem}")
    names = [p.name for p in presses]
    if unmatched := [name for name in labels if name not in names]:
        print(f"warning: {args.labels}: the labels of {', '.join(unmatched)} match no press in {args.folder}: unused")
    sizes_m = args.ball_radius_mm / 1000.0, args.pixel_size_mm / 1000.0
    label_radii = {name: label["radius"] for name, label in labels.items()}
    calib = calibrate_tactile(reference, images, names, *sizes_m, labels=label_radii, check_every=args.check_every)
    problem = check_problem(calib, args.max_radius_error)
    out = _output_file(args.out)
    picture = out.with_suffix(".png") if problem is None else out.with_name(out.stem + ".rejected.png")
    _press_sheet(images, names, calib, labels, picture)
    fitted = [p for p in calib.presses if p["role"] == "fit"]
    print(
        f"{sum('skipped' not in p for p in fitted)} of {len(fitted)} presses fitted, "
        f"{len(calib.presses) - len(fitted)} held out (1 in {args.check_every}) to check the fit; contact circles "
        f"drawn in {picture}"
    )
    for p in calib.presses:
        label = f", hand label {p['label_radius_px']:g} px" if p.get("label_radius_px") else ""
        if p["role"] == "fit":
            detail = p.get("skipped") or (
                f"contact circle ({p['centre_px'][0]:.1f}, {p['centre_px'][1]:.1f}) px, "
                f"radius {p['contact_radius_px']:.1f} px{label}"
            )
            print(f"  fit    {p['file']}: {detail}")
        elif p["detected"]:
            phantom = f"; {p['other_contact_px']} px of contact away from the ball" if p["other_contact_px"] else ""
            print(
                f"  check  {p['file']}: fitted ball radius {p['fitted_radius_m'] * 1e3:.3f} mm, peak indentation "
                f"{p['peak_indentation_m'] * 1e3:.3f} mm, contact radius {p['contact_radius_px']:.1f} px{label}"
                f"{phantom}"
            )
        else:
            print(f"  check  {p['file']}: no contact detected")
    summary = calib.check_summary
    if summary.get("detected"):
        print(
            f"held-out presses: {summary['detected']} of {summary['presses']} detected; fitted ball radius median "
            f"{summary['median_fitted_radius_m'] * 1e3:.3f} mm (ball {args.ball_radius_mm:g} mm), quartiles "
            f"{summary['q25_fitted_radius_m'] * 1e3:.3f}-{summary['q75_fitted_radius_m'] * 1e3:.3f} mm, range "
            f"{summary['min_fitted_radius_m'] * 1e3:.3f}-{summary['max_fitted_radius_m'] * 1e3:.3f} mm; median "
            f"peak indentation {summary['median_peak_indentation_m'] * 1e3:.3f} mm"
        )
        if "median_contact_radius_over_label" in summary:
            print(
                f"contact radius / hand label: median {summary['median_contact_radius_over_label']:.2f} (the circle "
                "is the steepest slope, the rim of the ball's print)"
            )
    if problem:
        raise TactileError("calibration", f"not written: {problem} (the contact circles are drawn in {picture})")
    if warning := depth_warning(calib):
        print(f"warning: {warning}")
    calib.save(out)
    print(f"wrote {out}")
    return 0


def _tactile_depth(args: TactileDepth) -> int:
    import cv2
    import numpy as np

    from tacsplat.datasets.outputs import claim_output_dir
    from tacsplat.drivers.optical_tactile import TactileCalibration, image_problem
    from tacsplat.files import atomic_write

    if not args.images:
        raise UsageError("IMAGE", "required (tactile images)")
    calib = TactileCalibration.load(args.calibration)
    height, width = calib.image_size
    reference = _read_rgb(args.reference)
    if problem := image_problem(reference):
        raise InvalidInputError(f"--reference {args.reference}: the image of the untouched gel is {problem}")
    inputs = [(args.reference, reference)] + [(path, _read_rgb(path)) for path in args.images]
    for path, image in inputs:
        if image.shape[:2] != (height, width):
            raise InvalidInputError(
                f"{path}: {image.shape[1]}x{image.shape[0]}, but {args.calibration.name} is for {width}x{height} images"
            )
    stems = {}
    for path in args.images:
        if path.stem in stems and stems[path.stem] != path:
            raise InvalidInputError(f"{path} and {stems[path.stem]} would both be written as {path.stem}.npz")
        stems[path.stem] = path
    with claim_output_dir(args.out):
        targets = [(args.out / f"{stem}.npz", args.out / f"{stem}.png") for stem in stems]
        existing = [t for pair in targets for t in pair if t.exists()]
        if existing and not args.overwrite:
            raise ConfigError("--out", f"{existing[0]} already exists; pass --overwrite to replace it")
        images = dict(inputs)
        for (stem, path), (npz, png) in zip(stems.items(), targets):
            depth = calib.depth(images[path], reference)
            atomic_write(npz, lambda f: np.savez_compressed(f, depth=depth))
            peak = float(depth.max())
            scaled = np.clip(depth / max(peak, 1e-12) * 255, 0, 255).astype(np.uint8)  # (depth >= 0)
            picture = cv2.applyColorMap(scaled, cv2.COLORMAP_VIRIDIS)
            picture[depth <= 0] = 0
            _write_image(png, picture)
            print(
                f"{path.name}: peak indentation {peak * 1e3:.3f} mm, {int((depth > 0).sum())} contact pixels -> {npz}"
            )
    return 0
