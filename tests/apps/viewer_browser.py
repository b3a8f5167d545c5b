"""Headless Chromium looking at `tacsplat view` (Debian's chromium, driven over its DevTools protocol).

Used by test_viewer_browser.py, and a script that measures how long a splat takes to appear once the page is
opened (the viewer already serving):

    python tests/apps/viewer_browser.py --gaussians 300000 [--screenshot shot.png]
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import io
import json
import math
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

VIEWPORT = (1280, 720)  # px; the side panel floats over the right of the canvas
PANEL_PX = 470  # the side panel's width with its margins: pixels right of width - PANEL_PX are not the scene's
TOAST = (340, 170)  # top-left box of viser's "software WebGL" notice
WHITE_DISTANCE = 40  # max |RGB - white| of a background pixel
VISER_FOV = math.radians(75.0)  # viser's initial vertical field of view
DEVTOOLS_LINE = re.compile(r"DevTools listening on (ws://127\.0\.0\.1:(\d+)/\S+)")


def browser_missing() -> str | None:
    """Why no headless browser test can run here, or None."""
    if chromium() is None:
        return "no chromium on PATH (make test-browser installs Debian's chromium)"
    return None


def chromium() -> str | None:
    return next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)


class PageSwapped(RuntimeError):
    """The tab is between two renderer processes (a navigation to another origin); a command may be sent again."""


class Page:
    """One browser tab, driven by DevTools protocol commands over its websocket."""

    def __init__(self, ws):
        self.ws, self.next_id = ws, 0

    def call(self, method: str, timeout: float = 120.0, **params) -> dict:
        """Send ``method`` and return its result (events that arrive meanwhile are dropped)."""
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            reply = json.loads(self.ws.recv(timeout=max(0.0, deadline - time.monotonic())))
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    error = reply["error"].get("message", "")
                    raise (PageSwapped if "Not attached" in error else RuntimeError)(f"{method}: {error}")
                return reply["result"]

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def screenshot(self) -> np.ndarray:
        """The page as RGB uint8 [H, W, 3]."""
        from PIL import Image

        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


@contextlib.contextmanager
def headless_chromium(timeout: float = 60.0):
    """A :class:`Page` of a fresh headless Chromium, VIEWPORT-sized at device pixel ratio 1, WebGL in software
    (SwiftShader) where there is no GPU."""
    from websockets.sync.client import connect

    with tempfile.TemporaryDirectory() as profile:
        process = subprocess.Popen(
            [
                chromium(),
                "--headless=new",
                "--no-sandbox",
                "--disable-dev-shm-usage",
                "--enable-unsafe-swiftshader",
                "--use-angle=swiftshader",
                "--no-first-run",
                "--remote-debugging-port=0",
                f"--user-data-dir={profile}",
                f"--window-size={VIEWPORT[0]},{VIEWPORT[1]}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            port = None
            for line in process.stderr:  # Chromium says where its DevTools listen, then keeps logging
                if match := DEVTOOLS_LINE.search(line):
                    port = match.group(2)
                    break
            if port is None:
                raise RuntimeError(f"chromium exited {process.wait()} without opening its DevTools port")
            threading.Thread(target=process.stderr.read, daemon=True).start()  # so that its logs never block it
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=timeout) as response:
                tab = next(t for t in json.load(response) if t["type"] == "page")
            with connect(tab["webSocketDebuggerUrl"], max_size=None, open_timeout=timeout) as ws:
                page = Page(ws)
                page.call(
                    "Emulation.setDeviceMetricsOverride",
                    width=VIEWPORT[0],
                    height=VIEWPORT[1],
                    deviceScaleFactor=1,
                    mobile=False,
                )
                yield page
        finally:
            process.terminate()
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def sphere_splat(n: int, radius: float = 0.08):
    """``n`` opaque flat Gaussians tiling a sphere at the origin (an object of real size), each coloured by its
    normal (0.5 + 0.5 n), so that the colours tell from where the sphere is seen; a cap of them is "touch"."""
    import torch
    from scipy.spatial.transform import Rotation

    from tacsplat.reconstruction.gaussians import Gaussians, rgb_to_sh0

    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    normals = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], axis=1)
    axis = np.cross([0.0, 0.0, 1.0], normals)
    norm = np.linalg.norm(axis, axis=1, keepdims=True)
    rotvec = np.where(norm > 1e-12, axis / np.maximum(norm, 1e-12), 0.0) * np.arccos(np.clip(z, -1, 1))[:, None]
    quats = Rotation.from_rotvec(rotvec).as_quat(scalar_first=True)  # each takes z to its Gaussian's normal
    spacing = math.sqrt(4 * math.pi * radius**2 / n)
    scales = np.tile([0.9 * spacing, 0.9 * spacing, 0.1 * spacing], (n, 1))
    t = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    params = {
        "means": t(radius * normals),
        "quats": t(quats),
        "scales": t(np.log(scales)),
        "opacities": t(np.full(n, 4.0)),
        "sh0": rgb_to_sh0(t(0.5 + 0.5 * normals))[:, None],
        "shN": torch.zeros(n, 0, 3),
    }
    return Gaussians(params, torch.from_numpy(z > 0.8), 0)


def write_splat_run(folder: Path, n: int) -> Path:
    """A run folder holding only the ``splat.ply`` of :func:`sphere_splat` (``n`` Gaussians)."""
    from tacsplat.reconstruction.ply import save_ply

    save_ply(sphere_splat(n), Path(folder) / "splat.ply")
    return Path(folder)


def expected_view(run: Path) -> tuple[np.ndarray, np.ndarray]:
    """(RGB [H, W, 3] uint8 over white, object mask [H, W]: alpha > 0.5) of tacsplat's render of ``run``'s splat
    from the viewer's first viewpoint, the page being VIEWPORT."""
    from tacsplat.apps import viewer
    from tacsplat.apps.viewer_splat import render_viewpoint
    from tacsplat.geometry import focal_from_fov, intrinsics_matrix, look_at

    data = viewer.read_run(run, run.name)
    position, target = viewer.initial_viewpoint(*viewer.object_sphere(data))
    width, height = VIEWPORT
    focal = focal_from_fov(VISER_FOV, height)
    K = intrinsics_matrix(focal, focal, width / 2, height / 2)
    rgb, _, alpha = render_viewpoint(data.gaussians, look_at(position, target), K, width, height)
    return (rgb * 255).round().astype(np.uint8), alpha > 0.5


def _grow(mask: np.ndarray, px: int) -> np.ndarray:
    import cv2

    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * px + 1, 2 * px + 1), np.uint8)) > 0


def compare(picture: np.ndarray, expected: np.ndarray, mask: np.ndarray) -> tuple[float, float, float]:
    """Left of the side panel and away from the notice box: (fraction of the object's pixels that are not
    background, fraction of a ring around it that is, mean |RGB difference| / 255 to tacsplat's render on the
    object's pixels)."""
    height, width = mask.shape
    scene_area = np.zeros_like(mask)
    scene_area[:, : width - PANEL_PX] = True
    scene_area[: TOAST[1], : TOAST[0]] = False
    inside = ~_grow(~mask, 6) & scene_area
    ring = _grow(mask, 60) & ~_grow(mask, 15) & scene_area
    picture = picture[..., :3].astype(int)
    background = np.abs(picture - 255).max(axis=-1) <= WHITE_DISTANCE
    error = np.abs(picture[inside] - expected[inside].astype(int)).mean() / 255
    return float((~background[inside]).mean()), float(background[ring].mean()), float(error)


def wait_for_object(
    page: Page,
    url: str,
    expected: np.ndarray,
    mask: np.ndarray,
    timeout: float = 180.0,
    shown: float = 0.9,
    max_error: float = 0.1,
) -> tuple[float | None, np.ndarray | None]:
    """Open ``url`` and take screenshots until the object covers ``shown`` of its pixels with the colours of
    tacsplat's render (mean error at most ``max_error``) over a background: (seconds from opening the page to
    that screenshot, or None at ``timeout``; the last picture)."""
    started = time.perf_counter()
    page.open(url)
    picture = None
    while time.perf_counter() - started < timeout:
        try:
            picture = page.screenshot()
        except PageSwapped:  # a file:// page gets a renderer of its own: ask that one
            continue
        if picture.shape[:2] == mask.shape:
            inside, around, error = compare(picture, expected, mask)
            if inside >= shown and around >= shown and error <= max_error:
                return time.perf_counter() - started, picture
        time.sleep(0.1)
    return None, picture


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Seconds from opening `tacsplat view`'s page to its splat shown.")
    parser.add_argument("--gaussians", type=int, default=300_000)
    parser.add_argument("--timeout", type=float, default=300.0)
    parser.add_argument("--screenshot", type=Path, default=None, help="save the page once the splat is shown")
    args = parser.parse_args(argv)
    if browser_missing():
        print(f"skipped: {browser_missing()}")
        return 1
    sys.path.insert(0, str(Path(__file__).parent))
    from viewer_client import served

    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        run = write_splat_run(Path(folder) / "run", args.gaussians)
        expected, mask = expected_view(run)
        print(f"wrote a {args.gaussians}-Gaussian splat.ply in {time.perf_counter() - started:.1f} s")
        started = time.perf_counter()
        with served(run) as url:
            print(f"tacsplat view served it after {time.perf_counter() - started:.1f} s")
            with headless_chromium() as page:
                seconds, picture = wait_for_object(page, url, expected, mask, args.timeout)
    if args.screenshot is not None and picture is not None:
        from PIL import Image

        Image.fromarray(picture).save(args.screenshot)
    if seconds is None:
        print(f"{args.gaussians} Gaussians: not shown within {args.timeout:.0f} s of opening the page")
        return 1
    print(f"{args.gaussians} Gaussians shown {seconds:.1f} s after opening the page")
    return 0


if __name__ == "__main__":
    sys.exit(main())
