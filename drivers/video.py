"""A threaded ``cv2.VideoCapture`` reader that never hangs and never hands out a stale frame unknowingly.

A background thread reads the device as fast as it delivers; :meth:`VideoReader.read`
returns the newest frame that the caller has not seen yet, with its timestamp
and sequence number, so a slow consumer never stalls the device, and a stalled
device (unplugged, driver hang, end of a file) raises :class:`CameraError`
within ``timeout_s`` even when ``VideoCapture.read`` itself blocks forever.
Files are read in order instead, every frame once.
Resolution and fps are verified after they are set. A failure while opening
(the first frame late included) releases the device and stops the reader.
A closed reader can be opened again: it starts afresh (frame indices from 0).
Timestamps are ``time.monotonic()`` seconds: compare them with that clock, which
a wall-clock step (NTP) does not move.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from tacsplat.errors import CameraError

FPS_TOLERANCE = 0.05  # the fps a device reports may be off the one asked for by this fraction


def _is_url(source: int | str | Path) -> bool:
    """A stream URL (``rtsp://``, ``http://``, ...), not a device index or a file path."""
    return isinstance(source, str) and "://" in source


@dataclass(frozen=True)
class Frame:
    image: np.ndarray  # [H, W, 3] uint8, BGR as OpenCV delivers it
    timestamp: float  # time.monotonic() when the frame was received (not wall-clock time: never stepped)
    index: int  # 0, 1, 2, ... in arrival order


class VideoReader:
    """Background reader of a device index, file path or stream URL; a context manager.

    ``width``, ``height``, ``fps`` are requested and then verified (a mismatch
    raises :class:`CameraError`); ``fourcc`` (e.g. ``"MJPG"``) is requested
    before them, as USB cameras need it for full resolution at full rate.
    ``capture_factory(source)`` builds the capture (``cv2.VideoCapture`` by default, which is given open and read
    timeouts of ``timeout_s`` for a stream URL).
    """

    def __init__(
        self,
        source: int | str,
        *,
        width: int | None = None,
        height: int | None = None,
        fps: float | None = None,
        fourcc: str | None = None,
        timeout_s: float = 2.0,
        name: str | None = None,
        capture_factory: Callable[[int | str], object] = cv2.VideoCapture,
    ):
        self.source = source
        self.name = name or f"camera {source}"
        self.timeout_s = float(timeout_s)
        self.sequential = isinstance(source, (str, Path)) and Path(source).is_file()  # a file: every frame, in order
        self._requested = (width, height, fps, fourcc)
        self._factory = capture_factory
        self._cap: list = [None]  # the capture, in a box of its own per opening: whoever releases it empties it
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._release_lock = threading.Lock()
        self._cond = threading.Condition()
        self._frames: deque[Frame] = deque(maxlen=None if self.sequential else 1)
        self._count = 0
        self._last_index = -1
        self._ended: str | None = None  # why the reader thread stopped
        self.width = self.height = 0
        self.fps = 0.0

    # -- lifecycle ---------------------------------------------------------
    def open(self) -> "VideoReader":
        """Open the device, verify its settings and its first frame; on any failure (an exception of the capture's
        too), the device is released and the reader thread stopped before the error is raised. An open reader is
        closed first (its capture released, its thread stopped)."""
        self.close()
        source = str(self.source) if isinstance(self.source, Path) else self.source
        # afresh (opened and closed before?); the reader thread of an earlier opening, if still blocked in its driver,
        # keeps its own stop event and capture
        self._stop = threading.Event()
        with self._cond:
            self._frames.clear()
            self._count, self._last_index, self._ended = 0, -1, None
        self._cap = [self._capture(source)]
        try:
            self._open()
        except BaseException:
            self.close()
            raise
        return self

    def _capture(self, source: int | str):
        """The capture of ``source``; OpenCV's own for a stream URL waits ``timeout_s`` to open and to read, where it
        would wait 30 s (a device index or file opens at once, or not at all)."""
        if self._factory is not cv2.VideoCapture or not _is_url(source):
            return self._factory(source)
        ms = max(1, round(1000 * self.timeout_s))
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms]
        return cv2.VideoCapture(source, cv2.CAP_ANY, params)

    def _open(self) -> None:
        cap = self._cap[0]
        if not cap.isOpened():
            raise CameraError(self.name, f"cannot open {self.source!r}: {self._why_not_open()}")
        width, height, fps, fourcc = self._requested
        code = fourcc and cv2.VideoWriter_fourcc(*fourcc)
        for prop, value in zip(
            (cv2.CAP_PROP_FOURCC, cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT, cv2.CAP_PROP_FPS),
            (code, width, height, fps),
        ):
            if value:  # (the fourcc first: USB cameras need it for full resolution at full rate)
                cap.set(prop, value)
        self.width = int(round(cap.get(cv2.CAP_PROP_FRAME_WIDTH)))
        self.height = int(round(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        self.fps = float(cap.get(cv2.CAP_PROP_FPS))
        if (width and self.width != width) or (height and self.height != height):
            raise CameraError(self.name, f"asked for {width}x{height}, the device delivers {self.width}x{self.height}")
        if fps and abs(self.fps - fps) > FPS_TOLERANCE * fps:
            raise CameraError(self.name, f"asked for {fps:g} fps, the device reports {self.fps:g} fps")
        args = (cap, self._cap, self._stop)
        self._thread = threading.Thread(target=self._run, args=args, name=f"video-{self.name}", daemon=True)
        self._thread.start()
        # the first frame proves the device delivers, at the size it reported
        first = self.read()
        with self._cond:  # hand the first frame out again on the first read()
            self._last_index = first.index - 1
        h, w = first.image.shape[:2]
        if (self.width and w != self.width) or (self.height and h != self.height):
            raise CameraError(self.name, f"reports {self.width}x{self.height} but delivers {w}x{h} frames")
        self.height, self.width = h, w

    def _why_not_open(self) -> str:
        """What likely keeps the source from opening, by its kind: a device, a stream URL or a file."""
        source = self.source
        if isinstance(source, int):
            return f"unplugged, busy, or no permission on /dev/video{source}?"
        if _is_url(source):
            return f"no stream within timeout_s = {self.timeout_s:g} s (is the server up, and the URL right?)"
        if str(source).startswith("/dev/"):
            return "unplugged, busy, or no permission?"
        if not Path(source).exists():
            return "no such file"
        return "not a video OpenCV can read (its format or codec?)"

    def close(self) -> None:
        """Stop the reader and release the device (idempotent). A reader blocked inside the driver is a daemon, not
        waited for: it releases the device itself when the driver returns."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=0.5)
            if self._thread.is_alive():
                self._thread = None
                return
        self._thread = None
        self._release(self._cap)

    def _release(self, box: list) -> None:
        """Release the capture in ``box`` once, whoever (close, or a reader thread that outlived it) comes first."""
        with self._release_lock:
            cap, box[0] = box[0], None
        if cap is not None:
            cap.release()

    def __enter__(self) -> "VideoReader":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- reading -----------------------------------------------------------
    def _run(self, cap, box: list, stop: threading.Event) -> None:
        try:
            while not stop.is_set():
                try:
                    ok, image = cap.read()
                except cv2.error as exc:
                    ok, image = False, exc
                now = time.monotonic()
                if stop.is_set():  # closed meanwhile: no frame after close
                    return
                with self._cond:
                    if not ok or image is None or getattr(image, "size", 0) == 0:
                        self._ended = "end of stream" if self.sequential else "the device returned no frame"
                        self._cond.notify_all()
                        return
                    if self.sequential:  # keep every frame: wait for the consumer instead of dropping
                        while len(self._fresh()) >= 8 and not stop.is_set():
                            self._cond.wait(0.1)
                        if stop.is_set():
                            return
                    self._frames.append(Frame(image, now, self._count))
                    self._count += 1
                    self._cond.notify_all()
        finally:
            if stop.is_set():  # closed while this thread was in the driver: close left the release to it
                self._release(box)

    def read(self, timeout_s: float | None = None) -> Frame:
        """The next frame not yet returned (the newest one for live devices); CameraError after the timeout."""
        if self._thread is None and not self._frames:
            raise CameraError(self.name, "not open")
        timeout = self.timeout_s if timeout_s is None else timeout_s
        with self._cond:
            self._cond.wait_for(lambda: self._fresh() or self._ended, timeout)
            fresh = self._fresh()
            if not fresh:
                why = self._ended or f"no new frame within {timeout:g} s (unplugged or stalled?)"
                raise CameraError(self.name, f"{why} after {self._count} frames")
            frame = fresh[0] if self.sequential else fresh[-1]
            self._last_index = frame.index
            while self._frames[0].index < frame.index:
                self._frames.popleft()
            self._cond.notify_all()
            return frame

    def _fresh(self) -> list[Frame]:
        """The frames not yet returned, oldest first."""
        return [f for f in self._frames if f.index > self._last_index]

    @property
    def frames_received(self) -> int:
        return self._count
