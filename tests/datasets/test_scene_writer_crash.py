"""kill -9 a SceneWriter mid-stream, again and again: the scene stays readable and resumes without gaps."""

from __future__ import annotations

import signal
import subprocess
import sys

import numpy as np
import pytest

from tacsplat.datasets import Scene, SceneWriter, check_scene
from tacsplat.errors import SceneFormatError

# The writer process: creates or resumes the scene, then appends frames and touches alternately,
# printing each record once add_* has returned. With CRASH_AT_FSYNC = k > 0 it SIGKILLs itself
# inside its k-th fsync (so at a chosen step: temp file written, rename, journal line, index).
CHILD = r"""
import os, sys, numpy as np
from tacsplat.datasets import SceneMeta, SceneWriter, SensorModel
from tacsplat.geometry import look_at
from tacsplat.types import CameraIntrinsics

path, crash_at, limit = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
if crash_at > 0:
    real_fsync, calls = os.fsync, [0]
    def fsync(fd):
        calls[0] += 1
        if calls[0] == crash_at:
            os.kill(os.getpid(), 9)
        real_fsync(fd)
    os.fsync = fsync

if os.path.exists(os.path.join(path, "journal.jsonl")):
    w = SceneWriter.resume(path)
else:
    K = np.array([[10.0, 0, 4], [0, 10.0, 3], [0, 0, 1]])
    w = SceneWriter.create(path, CameraIntrinsics(K, 8, 6), SceneMeta("sim", "crash"), SensorModel("gel", 5, 4, 1e-3, 2e-3))
print("ready", w.num_frames, w.num_touches, flush=True)
for _ in range(limit):
    if w.num_frames <= w.num_touches:
        i = w.num_frames
        image = np.full((6, 8, 3), i % 251, np.uint8)
        f = w.add_frame(image, look_at([np.cos(i), np.sin(i), 0.5], [0, 0, 0]), split="test" if i % 4 == 3 else "train")
        print("frame", f.id, flush=True)
    else:
        i = w.num_touches
        depth = np.zeros((4, 5), np.float32)
        depth[1, 2] = 1e-4 * (i + 1)
        t = w.add_touch(depth, look_at([0, 0.1, 0.1 + 0.01 * i], [0, 0, 0]), grasp=i // 4, finger="f%d" % (i % 4))
        print("touch", t.id, flush=True)
w.close()
print("done", flush=True)
"""


def _start(path, crash_at=0, limit=10**6):
    return subprocess.Popen(
        [sys.executable, "-c", CHILD, str(path), str(crash_at), str(limit)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


class Acked:
    """What the writer process confirmed (add_* returned) before it died."""

    def __init__(self):
        self.frames = 0
        self.touches = 0

    def read(self, proc, stop_after=None) -> int:
        """Consume the process's output; SIGKILL it after ``stop_after`` confirmed records. Returns its exit code."""
        start = proc.stdout.readline().split()
        if start and start[0] == "ready":  # resumed numbering == what the previous runs confirmed, or one more
            assert (int(start[1]), int(start[2])) in {
                (self.frames, self.touches),
                (self.frames + 1, self.touches),
                (self.frames, self.touches + 1),
            }
            self.frames, self.touches = int(start[1]), int(start[2])
        seen = 0
        for line in proc.stdout:
            kind, *rest = line.split()
            if kind == "done":
                continue
            rid = int(rest[0])
            expected = self.frames if kind == "frame" else self.touches
            assert rid == expected, f"{kind} {rid} after {expected} confirmed: numbering has a gap or a duplicate"
            if kind == "frame":
                self.frames += 1
            else:
                self.touches += 1
            seen += 1
            if stop_after is not None and seen == stop_after:
                proc.send_signal(signal.SIGKILL)
                break
        proc.stdout.close()
        errors = proc.stderr.read()
        proc.stderr.close()
        code = proc.wait()
        assert code in (0, -signal.SIGKILL), f"the writer process failed ({code}):\n{errors}"
        return code


def _check_after_crash(path, acked: Acked):
    """Readable before any resume (every reader refuses an index behind its journal, but nothing else is wrong);
    resume loses nothing confirmed and at most the record in flight."""
    scene, problems = check_scene(path)
    assert all("a writer stopped between the two" in str(p) for p in problems), problems
    assert [f.id for f in scene.frames] == list(range(len(scene.frames)))
    assert [t.id for t in scene.touches] == list(range(len(scene.touches)))
    assert len(scene.frames) >= acked.frames and len(scene.touches) >= acked.touches
    for f in scene.frames:  # each image is the one written for that id, never a half-written or stale file
        assert scene.load_image(f)[0, 0, 0] == np.float32((f.id % 251) / 255)
    for t in scene.touches:
        assert scene.load_touch_depth(t)[1, 2] == np.float32(1e-4 * (t.id + 1))
    with SceneWriter.resume(path) as w:
        assert w.num_frames >= len(scene.frames) and w.num_touches >= len(scene.touches)  # index never ahead of journal
        assert w.num_frames >= acked.frames and w.num_touches >= acked.touches
        assert w.num_frames + w.num_touches <= acked.frames + acked.touches + 1
    leftovers = [p for p in path.rglob("*") if p.name.endswith(".tmp")]
    assert leftovers == [], leftovers
    resumed = Scene.load(path)
    assert len(resumed.frames) == w.num_frames and len(resumed.touches) == w.num_touches
    # no orphan of the record in flight either: every record file belongs to a record
    assert sorted(p.name for p in (path / "images").iterdir()) == [f"{i:06d}.png" for i in range(w.num_frames)]
    assert sorted(p.name for p in (path / "touches").iterdir()) == [f"{i:06d}.npz" for i in range(w.num_touches)]
    with open(path / "journal.jsonl", "rb") as f:
        assert f.read().endswith(b"\n")


def test_kill_9_at_random_points_then_resume(tmp_path):
    path = tmp_path / "scene"
    acked = Acked()
    for stop_after in (5, 1, 8, 3):
        proc = _start(path)
        assert acked.read(proc, stop_after=stop_after) == -signal.SIGKILL
        _check_after_crash(path, acked)
    assert acked.frames + acked.touches >= 17


def test_kill_9_inside_every_step_of_a_record(tmp_path):
    """SIGKILL inside the k-th fsync: temp file written but not renamed, renamed but not journaled, journaled
    but index not rewritten, index temp written but not renamed, ..."""
    path = tmp_path / "scene"
    acked = Acked()
    assert acked.read(_start(path, limit=2)) == 0  # frame 0, touch 0
    for crash_at in range(1, 17):  # a resume (3 index files) then a frame and a touch take 16 fsyncs
        proc = _start(path, crash_at=crash_at, limit=2)
        assert acked.read(proc) == -signal.SIGKILL, f"the process outlived fsync {crash_at}"
        _check_after_crash(path, acked)
    assert acked.read(_start(path, limit=4)) == 0
    scene = Scene.load(path)
    assert len(scene.frames) >= 4 and len(scene.touches) >= 4


def test_kill_9_inside_every_step_of_a_creation_leaves_a_folder_create_or_resume_takes(tmp_path):
    """A creation killed anywhere (the journal's temporary file written or renamed, a folder or an index file
    written or not): the folder is either still new to create or a scene resume continues, never refused by
    both."""
    crash_at = 0
    while True:
        crash_at += 1
        assert crash_at < 30, "create takes more fsyncs than expected"
        path = tmp_path / f"scene{crash_at}"
        code = _start(path, crash_at=crash_at, limit=0).wait()
        if code == 0:
            break  # past the creation's last fsync
        assert code == -signal.SIGKILL
        assert Acked().read(_start(path, limit=1)) == 0  # create (no journal) or resume (a journal), then a frame
        assert len(Scene.load(path).frames) == 1
    assert crash_at > 3, crash_at  # (the kill points include the ones between the journal and the index files)


def test_torn_last_journal_line_is_dropped_and_a_corrupt_middle_line_is_an_error(tmp_path, h):
    path = h.build_scene(tmp_path / "s", n_frames=2, n_touches=1)
    journal = path / "journal.jsonl"
    good = journal.read_bytes()
    journal.write_bytes(good + b'{"op": "frame", "frame": {"id": 2, "file_pa')  # power cut mid-write
    with SceneWriter.resume(path) as w:
        assert (w.num_frames, w.num_touches) == (2, 1)
        assert w.add_frame(h.frame_image(2), h.ring_pose(2)).id == 2
    assert len(Scene.load(path).frames) == 3
    lines = journal.read_bytes().split(b"\n")
    lines[2] = lines[2][:-3]
    journal.write_bytes(b"\n".join(lines))
    with pytest.raises(SceneFormatError) as info:
        SceneWriter.resume(path)
    assert info.value.path == journal and info.value.field == "line 3"


def test_resume_of_a_folder_without_journal_names_it(tmp_path):
    with pytest.raises(SceneFormatError, match="journal.jsonl"):
        SceneWriter.resume(tmp_path)


def test_a_whole_last_record_without_its_newline_is_kept_with_its_files(tmp_path, h):
    path = h.build_scene(tmp_path / "s", n_frames=3, n_touches=0)
    journal = path / "journal.jsonl"
    journal.write_bytes(journal.read_bytes().rstrip(b"\n"))  # saved by an editor without a final newline
    scene, problems = check_scene(path)
    assert (len(scene.frames), problems) == (3, [])
    with SceneWriter.resume(path) as w:
        assert w.num_frames == 3
        assert w.add_frame(h.frame_image(3), h.ring_pose(3)).id == 3
    assert [f.id for f in Scene.load(path).frames] == [0, 1, 2, 3]
    assert (path / "images" / "000002.png").is_file()


def test_a_journal_refused_for_a_corrupt_middle_line_is_left_as_it_was_without_its_final_newline(tmp_path, h):
    path = h.build_scene(tmp_path / "s", n_frames=3, n_touches=0)
    journal = path / "journal.jsonl"
    lines = journal.read_bytes().rstrip(b"\n").split(b"\n")  # saved by an editor without a final newline
    lines[2] = lines[2][:-3]
    journal.write_bytes(b"\n".join(lines))
    before = journal.read_bytes()
    with pytest.raises(SceneFormatError) as info:
        SceneWriter.resume(path)
    assert info.value.field == "line 3"
    assert journal.read_bytes() == before
