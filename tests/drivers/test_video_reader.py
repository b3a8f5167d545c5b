"""VideoReader: verified settings, newest-frame semantics, and a stalled device raises instead of hanging."""

import contextlib
import socket
import threading
import time

import cv2
import numpy as np
import pytest

from tacsplat.drivers.video import VideoReader
from tacsplat.errors import CameraError

pytestmark = pytest.mark.timeout(30)


class LiveDevice:
    """A stand-in for a USB camera: frames at ``fps`` carrying their number; can be unplugged.

    After ``unplug()``, ``read()`` either blocks forever (a driver hang, the
    worst case) or returns ``(False, None)``, as a real unplugged V4L2 device does.
    """

    def __init__(self, width=64, height=48, fps=100.0, hang_on_unplug=True):
        self.width, self.height, self.fps = width, height, fps
        self.hang_on_unplug = hang_on_unplug
        self.unplugged = threading.Event()
        self.frames_made = 0
        self._forever = threading.Event()

    def isOpened(self):
        return True

    def set(self, prop, value):
        return False  # this device cannot change its mode

    def get(self, prop):
        return {
            cv2.CAP_PROP_FRAME_WIDTH: self.width,
            cv2.CAP_PROP_FRAME_HEIGHT: self.height,
            cv2.CAP_PROP_FPS: self.fps,
        }.get(prop, 0.0)

    def read(self):
        if self.unplugged.is_set():
            if self.hang_on_unplug:
                self._forever.wait()
            return False, None
        time.sleep(1.0 / self.fps)
        self.frames_made += 1
        return True, np.full((self.height, self.width, 3), self.frames_made % 256, np.uint8)

    def release(self):
        self._forever.set()


def test_unplugged_device_that_hangs_raises_within_the_timeout():
    device = LiveDevice(hang_on_unplug=True)
    with VideoReader(0, timeout_s=0.5, capture_factory=lambda s: device) as reader:
        reader.read()
        device.unplugged.set()
        time.sleep(0.05)
        start = time.monotonic()
        with pytest.raises(CameraError, match=r"no new frame within 0.5 s"):
            while True:  # frames already received are handed out once, then the timeout
                reader.read()
        assert time.monotonic() - start < 5.0  # raised, did not hang


def test_unplugged_device_that_fails_reads_raises():
    device = LiveDevice(hang_on_unplug=False)
    with VideoReader(0, timeout_s=5.0, capture_factory=lambda s: device) as reader:
        device.unplugged.set()
        with pytest.raises(CameraError, match="returned no frame"):
            for _ in range(100):
                reader.read()


def test_slow_consumer_gets_the_newest_frame_never_a_repeat():
    device = LiveDevice(fps=200.0)
    with VideoReader(0, timeout_s=1.0, capture_factory=lambda s: device) as reader:
        indices = [-1]
        for _ in range(5):
            # a slow consumer: the device streams at least two frames meanwhile (waited for, not slept: a loaded
            # machine may starve the device's thread for any time)
            deadline = time.monotonic() + 10
            while reader.frames_received < indices[-1] + 4 and time.monotonic() < deadline:
                time.sleep(0.01)
            newest = reader.frames_received - 1  # frame indices count from 0
            frame = reader.read()
            assert frame.index >= newest  # the newest at the time of reading, or one arriving meanwhile
            indices.append(frame.index)
        assert all(b > a + 1 for a, b in zip(indices[1:], indices[2:]))  # newest, stale ones skipped
        assert device.frames_made >= indices[-1] + 1  # the device kept streaming, never stalled by the consumer
        stamps = [reader.read().timestamp for _ in range(3)]
        assert stamps == sorted(stamps) and len(set(stamps)) == 3  # each read is a new frame


def test_resolution_and_fps_are_verified(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (80, 60))
    for i in range(4):
        writer.write(np.full((60, 80, 3), 40 * i, np.uint8))
    writer.release()
    with pytest.raises(CameraError, match="asked for 640x480"):
        VideoReader(str(path), width=640, height=480).open()
    with pytest.raises(CameraError, match="asked for 60 fps"):
        VideoReader(str(path), fps=60.0).open()
    with pytest.raises(CameraError, match="asked for 640x480, the device delivers 64x48"):
        VideoReader(0, width=640, height=480, capture_factory=lambda s: LiveDevice()).open()
    # a file is read in order, every frame once, then it ends with a clear error
    with VideoReader(str(path), width=80, height=60, fps=30.0) as reader:
        values = [int(reader.read().image[0, 0, 0]) for _ in range(4)]
        assert values == [0, 40, 80, 120]
        with pytest.raises(CameraError, match="end of stream after 4 frames"):
            reader.read()


def test_missing_device_is_a_clear_error():
    with pytest.raises(CameraError, match="cannot open"):
        VideoReader("/nonexistent/video.avi").open()


class ClosedDevice(LiveDevice):
    """A capture that did not open."""

    def isOpened(self):
        return False


def test_a_source_that_does_not_open_is_named_by_its_kind(tmp_path):
    not_video = tmp_path / "notes.avi"
    not_video.write_text("not a video")
    with pytest.raises(CameraError, match=r"cannot open 3: unplugged, busy, or no permission on /dev/video3\?$"):
        VideoReader(3, capture_factory=lambda s: ClosedDevice()).open()
    with pytest.raises(CameraError, match=r"cannot open '/nonexistent/video\.avi': no such file$"):
        VideoReader("/nonexistent/video.avi").open()
    with pytest.raises(CameraError, match=r"notes\.avi': not a video OpenCV can read \(its format or codec\?\)$"):
        VideoReader(str(not_video)).open()


@pytest.fixture
def silent_server():
    """A stream server that accepts connections and never says a word; its URL."""
    server = socket.create_server(("127.0.0.1", 0))
    accepted = []

    def accept():
        with contextlib.suppress(OSError):  # (closed at the end)
            while True:
                accepted.append(server.accept()[0])

    threading.Thread(target=accept, daemon=True).start()
    yield f"http://127.0.0.1:{server.getsockname()[1]}/stream.mjpg"
    server.close()
    for connection in accepted:
        connection.close()


def test_a_stream_url_that_never_answers_is_refused_after_timeout_s(silent_server):
    start = time.monotonic()
    with pytest.raises(
        CameraError, match=r"no stream within timeout_s = 1 s \(is the server up, and the URL right\?\)"
    ):
        VideoReader(silent_server, timeout_s=1.0).open()
    assert time.monotonic() - start < 15.0  # OpenCV's own timeout is 30 s


def test_opening_an_open_reader_closes_the_first_opening():
    """``with reader:`` entered twice: the first capture is released and its thread stopped, not leaked."""
    first, second = StartingDevice(), StartingDevice()
    devices = iter([first, second])
    reader = VideoReader(0, timeout_s=1.0, name="twice", capture_factory=lambda s: next(devices))
    reader.open()
    reader.open()
    assert first.released.wait(5.0) and not second.released.is_set()
    running = lambda: [t.name for t in threading.enumerate()].count("video-twice")  # noqa: E731
    deadline = time.monotonic() + 5.0
    while running() > 1 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert running() == 1, "the first opening's reader thread still runs"
    assert int(reader.read().image[0, 0, 0]) <= 2  # one of the second device's first frames
    reader.close()
    assert second.released.is_set()


class StartingDevice(LiveDevice):
    """Opens and reports its size, but its first frame comes only after ``delay_s`` (a camera still starting up);
    ``fail`` names a call (``"set"`` or ``"get"``) that raises, as a driver's may."""

    def __init__(self, delay_s=0.0, fail=None):
        super().__init__()
        self.delay_s, self.fail, self.released = delay_s, fail, threading.Event()

    def set(self, prop, value):
        if self.fail == "set":
            raise cv2.error("set failed")
        return False

    def get(self, prop):
        if self.fail == "get":
            raise cv2.error("get failed")
        return super().get(prop)

    def read(self):
        if self.delay_s:
            time.sleep(self.delay_s)
            self.delay_s = 0.0
        return super().read()

    def release(self):
        self.released.set()
        super().release()


@pytest.mark.parametrize("fail", ["first frame late", "set", "get"])
def test_a_failed_open_releases_the_device_and_stops_the_reader(fail):
    device = StartingDevice(delay_s=1.0) if fail == "first frame late" else StartingDevice(fail=fail)
    reader = VideoReader(0, width=64, timeout_s=0.2, name=f"starting {fail}", capture_factory=lambda s: device)
    with pytest.raises((CameraError, cv2.error)):
        reader.open()
    assert device.released.wait(3.0), "the device was never released"
    running = lambda: any(t.name == f"video-starting {fail}" for t in threading.enumerate())  # noqa: E731
    deadline = time.monotonic() + 3.0
    while running() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not running(), "the reader thread still runs"
    assert reader.frames_received == 0  # the late frame, delivered after the error, is not taken


def test_frame_timestamps_are_monotonic_seconds_a_wall_clock_step_does_not_move(monkeypatch):
    """NTP steps the wall clock back 5 s between two frames: the later frame is still the later one, on the clock
    the consumers compare it with (time.monotonic(), as the presses' freshness check does)."""
    device = LiveDevice(fps=100.0)
    with VideoReader(0, timeout_s=1.0, capture_factory=lambda s: device) as reader:
        first = reader.read()
        told = time.monotonic()
        wall = time.time
        monkeypatch.setattr(time, "time", lambda: wall() - 5.0)
        later = reader.read()
        assert later.index > first.index and later.timestamp > first.timestamp
        assert later.timestamp >= told - 0.05  # (a frame may have been received just before ``told``)
        assert abs(later.timestamp - time.monotonic()) < 1.0


def test_a_closed_reader_opens_again():
    """Closed, then opened again (a sensor reopened after a fault): it reads the device's new frames."""
    devices = []
    reader = VideoReader(0, timeout_s=1.0, capture_factory=lambda s: devices.append(LiveDevice()) or devices[-1])
    with reader:
        reader.read()
    with reader:
        frame = reader.read()
        assert frame.index == 0 and reader.read().index > 0  # counted afresh
        assert int(frame.image[0, 0, 0]) <= 2  # one of the new device's first frames
    assert len(devices) == 2


def test_a_reader_thread_stuck_in_its_driver_leaves_the_next_opening_alone():
    """Closed while its thread hangs in the driver, then opened again: when that driver call returns at last, the
    old thread releases its own device, not the new one, and adds no frame."""
    old, new = StartingDevice(), StartingDevice()
    devices = iter([old, new])
    reader = VideoReader(0, timeout_s=1.0, capture_factory=lambda s: next(devices))
    reader.open()
    old.unplugged.set()  # its next read blocks
    time.sleep(0.05)
    reader.close()  # the thread stays in the driver: the release is left to it
    with reader:
        old._forever.set()  # the driver returns
        assert old.released.wait(3.0)
        time.sleep(0.1)
        assert not new.released.is_set()
        frames = [reader.read() for _ in range(3)]
        assert all(f.image[0, 0, 0] == (f.index + 1) % 256 for f in frames)  # the new device's n-th frame has index n
        assert [f.index for f in frames] == sorted({f.index for f in frames})
    assert new.released.is_set()
