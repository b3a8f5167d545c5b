"""`tacsplat calibrate camera` and `tacsplat calibrate tactile` (see tacsplat.cli)."""

from __future__ import annotations

from pathlib import Path

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def register(cli) -> None:
    """Add this package's commands to the tree."""
    camera = cli.command(
        "calibrate camera",
        help="intrinsic calibration of the wrist camera from ChArUco board images",
        description="Detects the ChArUco board in every image of FOLDER, runs cv2.calibrateCamera, prints the "
        "RMS reprojection error and writes the calibration (OpenCV K, distortion) as JSON, and a picture of the "
        "detected and reprojected corners next to it (.png).",
    )
    camera.add_argument("folder", type=Path, help="folder of board images (png, jpg, ...)")
    camera.add_argument("--out", type=Path, required=True, help="calibration file to write (.json)")
    camera.add_argument("--squares-x", type=int, default=7, help="board squares along x")
    camera.add_argument("--squares-y", type=int, default=5, help="board squares along y")
    camera.add_argument("--square-mm", type=float, default=30.0, help="chessboard square side, millimetres")
    camera.add_argument("--marker-mm", type=float, default=22.0, help="ArUco marker side, millimetres")
    camera.add_argument("--dictionary", default="DICT_5X5_100", help="cv2.aruco predefined dictionary")
    camera.add_argument("--legacy-pattern", action="store_true", help="board printed by OpenCV < 4.6")
    camera.set_defaults(func=_calibrate_camera)

    tactile = cli.command(
        "calibrate tactile",
        help="GelSight-style calibration of an optical tactile sensor from ball presses",
        description="FOLDER holds one image of the untouched gel named reference.* and images of presses of a "
        "ball of known radius (any other names). Fits the lookup table colour change -> surface gradient, writes "
        "it (.npz) and a picture of the detected contact circles next to it (.png).",
    )
    tactile.add_argument("folder", type=Path, help="folder with reference.* and ball-press images")
    tactile.add_argument("--out", type=Path, required=True, help="calibration file to write (.npz)")
    tactile.add_argument("--ball-radius-mm", type=float, required=True, help="radius of the pressed ball, mm")
    tactile.add_argument("--pixel-size-mm", type=float, required=True, help="gel size of one image pixel, mm")
    tactile.add_argument("--bin-size", type=float, default=4.0, help="grey levels per lookup-table bin")
    tactile.set_defaults(func=_calibrate_tactile)


def _images(folder: Path):
    from tacsplat.errors import InvalidInputError

    if not folder.is_dir():
        raise InvalidInputError(f"{folder}: not a folder")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise InvalidInputError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    return paths


def _read_rgb(path: Path):
    import cv2

    from tacsplat.errors import InvalidInputError

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InvalidInputError(f"{path}: cannot read the image")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _calibrate_camera(args) -> int:
    import numpy as np

    from tacsplat.drivers.wrist_camera import CharucoBoardSpec, calibrate_intrinsics, tacsplat_K_from_opencv

    spec = CharucoBoardSpec(args.squares_x, args.squares_y, args.square_mm / 1000.0, args.marker_mm / 1000.0,
                            args.dictionary, args.legacy_pattern)
    paths = _images(args.folder)
    images = [_read_rgb(p) for p in paths]
    calib = calibrate_intrinsics(images, spec, names=[p.name for p in paths])
    calib.save(args.out)
    picture = _corner_sheet(images, [p.name for p in paths], calib, spec, args.out.with_suffix(".png"))
    K = tacsplat_K_from_opencv(calib.K_opencv)
    print(f"{len(calib.per_image_rms_px)} of {len(paths)} images used, {calib.width}x{calib.height}")
    print(f"RMS reprojection error: {calib.rms_px:.3f} px")
    print(f"fx {K[0, 0]:.2f}  fy {K[1, 1]:.2f}  cx {K[0, 2]:.2f}  cy {K[1, 2]:.2f} (pixel centres at +0.5)")
    print(f"distortion k1 k2 p1 p2 k3: {np.array2string(calib.dist, precision=5)}")
    for name, err in calib.per_image_rms_px.items():
        print(f"  {name}: {err:.3f} px")
    print(f"wrote {args.out}; detected corners (green) and their reprojections (red) in {picture}")
    return 0


def _contact_sheet(tiles, columns: int = 4):
    import numpy as np

    columns = min(columns, len(tiles))
    tiles = tiles + [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    return np.vstack([np.hstack(tiles[i : i + columns]) for i in range(0, len(tiles), columns)])


def _corner_sheet(images, names, calib, spec, path: Path) -> Path:
    """A picture of every board image with its detected corners and their reprojection by the calibration."""
    import cv2
    import numpy as np

    from tacsplat.drivers.wrist_camera import detect_charuco

    board = spec.board()
    tiles = []
    for image, name in zip(images, names):
        half = (image.shape[1] // 2, image.shape[0] // 2)
        tile = cv2.resize(cv2.cvtColor(image, cv2.COLOR_RGB2BGR), half, interpolation=cv2.INTER_AREA)
        obj, img = detect_charuco(image, board)
        if len(obj) >= 6:
            ok, rvec, tvec = cv2.solvePnP(obj, img, calib.K_opencv, calib.dist)
            proj = cv2.projectPoints(obj, rvec, tvec, calib.K_opencv, calib.dist)[0].reshape(-1, 2) if ok else img
            for (u, v), (pu, pv) in zip(img, proj):  # OpenCV pixel coordinates, drawn at half size
                cv2.circle(tile, (int(round(u / 2)), int(round(v / 2))), 4, (0, 200, 0), 1, cv2.LINE_AA)
                cv2.drawMarker(tile, (int(round(pu / 2)), int(round(pv / 2))), (0, 0, 255), cv2.MARKER_CROSS, 5, 1)
        rms = calib.per_image_rms_px.get(name)
        label = f"{name}: " + (f"{rms:.2f} px" if rms is not None else "not used")
        cv2.putText(tile, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    cv2.imwrite(str(path), _contact_sheet(tiles))
    return path


def _calibrate_tactile(args) -> int:
    import cv2

    from tacsplat.drivers.optical_tactile import TactileCalibration
    from tacsplat.errors import InvalidInputError

    paths = _images(args.folder)
    references = [p for p in paths if p.stem.lower() == "reference"]
    if len(references) != 1:
        raise InvalidInputError(f"{args.folder}: expected exactly one image named reference.*, found {len(references)}")
    presses = [p for p in paths if p not in references]
    images = [_read_rgb(p) for p in presses]
    calib = TactileCalibration.fit(_read_rgb(references[0]), images, args.ball_radius_mm / 1000.0,
                                   args.pixel_size_mm / 1000.0, bin_size=args.bin_size)
    calib.save(args.out)
    tiles = []
    for k, image in enumerate(images):
        tile = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        for press in calib.presses:
            if press["index"] == k:
                (cx, cy), r = press["centre_px"], press["contact_radius_px"]
                cv2.circle(tile, (int(round(cx)), int(round(cy))), int(round(r)), (0, 0, 255), 1, cv2.LINE_AA)
        cv2.putText(tile, presses[k].name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    picture = args.out.with_suffix(".png")
    cv2.imwrite(str(picture), _contact_sheet(tiles))
    print(f"{len(calib.presses)} of {len(presses)} presses used; contact circles drawn in {picture}")
    for press in calib.presses:
        cx, cy = press["centre_px"]
        print(f"  {presses[press['index']].name}: centre ({cx:.1f}, {cy:.1f}) px, radius {press['contact_radius_px']:.1f} px")
    print(f"wrote {args.out}")
    return 0
