"""The one crash-safe writer of scene directories.

Every file is written to a hidden temporary name in its final folder, flushed
to disk (fsync) and renamed over its final name (``os.replace``), so a reader
never sees a partial file. Records are appended one line each to
``journal.jsonl`` (fsync'ed); the index files ``transforms.json``,
``touches.json`` and ``scene.json`` are re-materialised atomically from the
in-memory state after each record (by a job, an import or a copy, once, when
it finishes). Besides frames, touches and the ground truth, a record can be a
capture annotation (:meth:`SceneWriter.annotate`: plain JSON under a key of
scene.json's ``annotations``, the latest value of a key wins), e.g. the
decisions of a next-best capture. After ``kill -9`` at any point:

* the index files are a consistent snapshot, at most one record behind the
  journal (readers refuse such a scene, naming the journal, until it is resumed);
  a job's scene (:meth:`SceneWriter.create`'s ``job``) is complete only with its
  last record, 'finish': readers refuse one without it, saying to run the job again;
  a creation writes its journal first, so one killed before the index files
  leaves a scene resume completes, and one killed before that a folder create takes;
* :meth:`SceneWriter.resume` replays the journal, drops a torn last line,
  deletes leftover temporary files, rewrites the index and continues numbering
  where the journal stopped: only the record in flight can be lost.

A full disk or a read-only file system is one :class:`~tacsplat.errors.StorageError` naming the file
(:mod:`tacsplat.files`): no temporary file is left, a journal line cut short is cut from the journal again, and
the scene resumes once there is space. One writer holds a scene at a time (a lock on its journal); a second one
is refused naming the process that holds it (its PID, in the folder's lock file, ``datasets.outputs``).

Ids are dense per kind (frames 0..N-1, touches 0..M-1): ``remove_last`` (the
operator's undo) is itself a journal record and the next record reuses the
freed id, so a scene never has gaps.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import io
import json
import logging
import os
import re
import shutil
import signal
import time
from contextlib import AbstractContextManager, contextmanager
from dataclasses import asdict
from pathlib import Path

import numpy as np

import tacsplat
from tacsplat.errors import InvalidInputError, SceneFormatError
from tacsplat.files import atomic_write, fsync_dir, storage_error
from tacsplat.interrupts import signals_interrupt
from tacsplat.types import CameraIntrinsics, TactileReading

from .outputs import LOCK_NAME, claim_output_dir, other_writer, record_writer
from .records import (
    FORMAT_NAME,
    FORMAT_VERSION,
    GT_DEPTH_LIMIT,
    SPARSE_POINTS,
    SPLITS,
    Frame,
    HandMotion,
    SceneMeta,
    SensorModel,
    Touch,
    check_pose,
    depth_problem,
    frame_from_json,
    frame_to_json,
    frame_to_nerfstudio,
    intrinsics_equal,
    intrinsics_from_json,
    intrinsics_to_json,
    normal_map_problem,
    sensor_to_json,
    sparse_points_problem,
    touch_depth_limit,
    touch_to_json,
)

log = logging.getLogger(__name__)

JOURNAL = "journal.jsonl"
TEMP_SUFFIX = ".tmp"
JOBS = ("import", "copy")  # what writes a whole scene at once (SceneWriter.create's job); a rerun starts again
_RECORD_FILE = re.compile(r"\d{6}\.(png|npz)")


def temp_name(path: Path) -> Path:
    """The hidden temporary sibling a file is written to before its rename."""
    return path.with_name(f".{path.name}.{os.getpid()}{TEMP_SUFFIX}")


def is_temp_file(path: Path) -> bool:
    return path.name.startswith(".") and path.name.endswith(TEMP_SUFFIX)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that ``path`` is always either the old or the new file (through its hidden
    temporary name, which a resume deletes after a crash); a full or read-only disk is a StorageError."""
    atomic_write(path, data, temp=temp_name(Path(path)))


def atomic_write_json(path: Path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=1) + "\n").encode())


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an RGB uint8 image [H, W, 3] or a greyscale one [H, W]."""
    import cv2  # here, not at import: reading a scene loads no OpenCV

    ok, buf = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image)
    if not ok:
        raise InvalidInputError("image: OpenCV could not encode it as PNG")
    return buf.tobytes()


def encode_npz(**arrays) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def has_content(path: Path) -> bool:
    """Whether a folder holds anything besides the lock file of the command writing it (``datasets.outputs``) and
    temporary files."""
    return any(p.name != LOCK_NAME and not is_temp_file(p) for p in Path(path).iterdir())


def check_new_scene_dir(path: Path, job: str | None = None) -> None:
    """Refuse (InvalidInputError) a folder that holds anything: a scene starts in a new or empty one. A ``job``
    (an import, a copy) cannot continue a scene: its messages say to remove it, not to --resume."""
    path = Path(path)
    content = path.is_dir() and has_content(path)  # before the journal, which a creation writes first
    if (path / JOURNAL).exists():
        if journal_locked(path / JOURNAL):
            then = "," if job else " and continue the scene with --resume, or"
            raise InvalidInputError(being_written(path, f"{then} choose a new folder"))
        if job:
            raise InvalidInputError(f"{path} already holds a scene: remove it to {job} again, or choose another --out")
        raise InvalidInputError(f"{path} already holds a scene: continue it with --resume, or choose a new folder")
    if content:
        raise InvalidInputError(f"{path} exists and is not an empty folder; choose a new output folder")


@contextmanager
def removed_on_failure(out: Path):
    """Delete a new output folder again when an import into it fails, so that a rerun can use it; SIGTERM and
    SIGHUP (``timeout``, a batch scheduler, a closed ssh session) fail it too, as SignalInterrupt."""
    out = Path(out)
    had_content = out.is_dir() and has_content(out)
    with signals_interrupt((signal.SIGTERM, signal.SIGHUP), once=True):
        try:
            yield
        except BaseException:
            if not had_content:
                shutil.rmtree(out, ignore_errors=True)
            raise


@contextmanager
def new_import(out: Path, intrinsics: CameraIntrinsics, importer: str, source: Path, name: str | None, **extra):
    """The writer of an importer's scene ``out``: a new or empty folder, claimed as the ``--out`` of a writing
    command (``datasets.outputs``), removed again when the import fails, and marked finished when the block ends
    (readers refuse an import that never finished). Its provenance: the object ``name`` (default: the ``source``
    path's last part), ``importer``, ``source``'s absolute path, then ``extra``."""
    check_new_scene_dir(out, "import")  # before the claim, which would put its lock file among someone's files
    source = Path(source).resolve()
    meta = SceneMeta("import", name or source.name, extra={"importer": importer, "source_path": str(source), **extra})
    with (
        claim_output_dir(out),
        removed_on_failure(out),
        SceneWriter.create(out, intrinsics, meta, job="import") as writer,
    ):
        yield writer
        writer.finish()


def _check_intrinsics(intr) -> CameraIntrinsics:
    """``intr`` if it is a camera the scene format holds (zero-skew pinhole, see ``records.camera_problem``)."""
    if not isinstance(intr, CameraIntrinsics):
        raise InvalidInputError(f"intrinsics: expected CameraIntrinsics, got {type(intr).__name__}")
    intrinsics_to_json(intr)  # rejects skew and impossible cameras
    return intr


def _check_depth(depth, shape: tuple[int, int], name: str, limit: tuple[float, str]) -> np.ndarray:
    """``depth`` as float32 if it is a depth map the reader accepts (see ``records.depth_problem``)."""
    depth = np.asarray(depth)
    if depth.shape != shape:
        raise InvalidInputError(f"{name}: expected shape {shape}, got {depth.shape}")
    if np.issubdtype(depth.dtype, np.floating):
        depth = depth.astype(np.float32)
    if problem := depth_problem(depth, *limit):
        raise InvalidInputError(f"{name}: {problem}")
    return depth


class SceneWriter(AbstractContextManager):
    """Appends frames and touches to a scene directory, crash-safely (see the module docstring).

    Use :meth:`create` for a new scene and :meth:`resume` to continue one; both
    return a writer that holds an exclusive lock on the scene until :meth:`close`
    (also a context manager).
    """

    def __init__(self, path: Path, header: dict):
        """The writer of scene ``path`` whose journal starts with ``header`` (its 'create' record), before any
        record is applied."""
        self.path = Path(path)
        self.intrinsics = intrinsics_from_json(header["intrinsics"])
        self.meta = SceneMeta(**header["meta"])
        self.sensor = None if header["sensor"] is None else SensorModel(**header["sensor"])
        self._created = header["created"]
        self._version = header.get("tacsplat_version", tacsplat.__version__)
        self.job = header.get("job")  # "import" | "copy": the scene is complete once finished; None: a capture
        if self.job is not None and self.job not in JOBS:
            raise ValueError(f"job: expected one of {JOBS}, got {self.job!r}")
        self.finished = False  # whether the job's 'finish' record is written
        self._stale: set[str] = set()  # index files behind the records: a job writes them when it finishes
        self.frames: list[Frame] = []
        self.touches: list[Touch] = []
        self.gt_depth_files: dict[int, str] = {}  # frame id -> the path in the scene of its ground-truth depth
        self.gt_mesh: str | None = None  # the ground-truth mesh's path in the scene (gt/mesh.ply), once set
        self.gt_points: str | None = None  # the ground-truth point cloud's path in the scene (gt/points.ply), once set
        self.sparse_points: str | None = None  # the sparse points' path in the scene (SPARSE_POINTS), once set
        self.annotations: dict = {}  # key -> plain JSON value, the latest recorded; read it, change it by annotate
        self._order: list[tuple[str, int]] = []  # live records, oldest first, for remove_last
        self._journal = None

    # --- opening ------------------------------------------------------------------------------

    @classmethod
    def create(
        cls,
        path,
        intrinsics: CameraIntrinsics,
        meta: SceneMeta,
        sensor: SensorModel | None = None,
        *,
        job: str | None = None,
    ) -> "SceneWriter":
        """Start a new scene in ``path`` (which must not exist or be an empty folder).

        ``job`` ("import" or "copy", one of :data:`JOBS`): the scene is written at once and is complete only after
        :meth:`finish`, which also writes the index files (once, not after every record); readers refuse it before
        that. A capture, which resumes, passes none."""
        path = Path(path)
        _check_intrinsics(intrinsics)
        if job is not None and job not in JOBS:
            raise InvalidInputError(f"job: expected one of {JOBS} or None, got {job!r}")
        if not isinstance(meta, SceneMeta):
            raise InvalidInputError(f"meta: expected SceneMeta, got {type(meta).__name__}")
        if sensor is not None and not isinstance(sensor, SensorModel):
            raise InvalidInputError(f"sensor: expected SensorModel or None, got {type(sensor).__name__}")
        try:
            json.dumps(asdict(meta), allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"meta: capture_plan and extra must be plain JSON data: {exc}") from exc
        if path.exists() and not path.is_dir():
            raise InvalidInputError(f"{path} exists and is not a folder; choose a new output folder")
        _make_folders(path, "")
        # The journal is written under a name every creator of this folder opens, and locked before the folder is
        # checked, so of two processes creating one scene at once the second is refused, naming the first.
        creating = path / f".{JOURNAL}.new{TEMP_SUFFIX}"
        header = {
            "op": "create",
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "tacsplat_version": tacsplat.__version__,
            "intrinsics": intrinsics_to_json(intrinsics),
            "sensor": sensor_to_json(sensor),
            "meta": asdict(meta),
            **({"job": job} if job else {}),
        }
        journal = _lock_journal(creating, path)
        try:
            try:
                check_new_scene_dir(path, job)
            except BaseException:
                creating.unlink(missing_ok=True)
                raise
            record_writer(path)
            renamed = False
            # The journal first, then the folders and index files: its header is what makes the folder resumable,
            # so a creation killed at any point leaves a folder that create (no journal, nothing but temporary
            # files) or resume (a journal: it makes the folders and writes the index) takes.
            try:
                writer = cls(path, header)
                journal.truncate(0)  # (the file of a creation that crashed before its rename)
                writer._journal = journal
                writer._append(header)
                os.rename(creating, path / JOURNAL)
                renamed = True
                fsync_dir(path)
                _make_folders(path, "images", "touches", "gt", "gt/depth")
                writer._materialise("transforms", "touches", "scene")
            except BaseException as exc:
                # a scene whose creation failed holds nothing yet (it was checked empty, under the lock): what it
                # wrote goes, so a rerun can start again
                (path / JOURNAL if renamed else creating).unlink(missing_ok=True)
                _remove_index(path)
                if isinstance(exc, OSError):
                    raise storage_error(exc, path / JOURNAL) from None
                raise
        except BaseException:
            journal.close()
            raise
        return writer

    @classmethod
    def resume(cls, path) -> "SceneWriter":
        """Continue a scene after a clean close or a crash: replay the journal, rewrite the index."""
        path = Path(path)
        journal_path = path / JOURNAL
        if not journal_path.is_file():
            raise SceneFormatError(
                journal_path,
                None,
                "missing: this folder was not written by SceneWriter (or its creation never finished)",
            )
        journal = _lock_journal(journal_path, path)
        try:
            writer = cls._replay(path, _read_journal(journal_path))
        except BaseException:
            journal.close()
            raise
        writer._journal = journal
        record_writer(path)
        _make_folders(path, "images", "touches", "gt", "gt/depth")
        removed = writer._remove_leftovers()
        writer._materialise("transforms", "touches", "scene")
        log.info(
            "resumed %s: %d frames, %d touches (%d leftover files removed)",
            path,
            writer.num_frames,
            writer.num_touches,
            removed,
        )
        return writer

    @classmethod
    def _replay(cls, path: Path, entries: list[dict]) -> "SceneWriter":
        writer = None
        for lineno, entry in enumerate(entries, start=1):
            try:
                if writer is not None:
                    writer._apply(entry)
                elif entry.get("op") != "create":
                    raise ValueError("the journal must start with the 'create' header")
                else:
                    writer = cls(path, entry)
            except (KeyError, TypeError, ValueError, OverflowError, InvalidInputError) as exc:
                error = SceneFormatError(path / JOURNAL, f"line {lineno}", f"invalid {entry.get('op')!r} record: {exc}")
                raise error from exc
        return writer

    def record_files(self) -> set[str]:
        """The paths in the scene of the files the records refer to (images, masks, depth maps, hand motions,
        ground truth)."""
        files = {path for f in self.frames for path in (f.file_path, f.mask_path)} | set(self.gt_depth_files.values())
        files |= {path for t in self.touches for path in (t.depth_file, t.hand_file)}
        return files.union([self.gt_mesh, self.gt_points, self.sparse_points]) - {None}

    def _remove_leftovers(self) -> int:
        """Delete temporary files and record files no journal record refers to (a crash's in-flight record,
        an undo cut short); returns how many."""
        live = self.record_files()
        record_folders = ("images", "masks", "touches", "grasps", "gt/depth")  # where NNNNNN.png/.npz are records
        count = 0
        for sub in ("", "gt", *record_folders):
            if not (self.path / sub).is_dir():
                continue
            for p in (self.path / sub).iterdir():
                rel = p.relative_to(self.path).as_posix()
                orphan = sub in record_folders and _RECORD_FILE.fullmatch(p.name) and rel not in live
                if p.is_file() and (is_temp_file(p) or orphan):
                    p.unlink()
                    count += 1
        return count

    # --- state --------------------------------------------------------------------------------

    @property
    def num_frames(self) -> int:
        return len(self.frames)

    @property
    def num_touches(self) -> int:
        return len(self.touches)

    @property
    def last_record(self) -> tuple[str, int] | None:
        """``(kind, id)`` of the newest live record ("frame" | "touch"): what :meth:`remove_last` would undo."""
        return self._order[-1] if self._order else None

    def _apply(self, entry: dict) -> None:
        """Apply one journal record to the in-memory state (used live and on replay)."""
        op = entry["op"]
        if op in ("frame", "touch"):
            record = frame_from_json(entry["frame"]) if op == "frame" else Touch(**entry["touch"])
            records = self.frames if op == "frame" else self.touches
            if record.id != len(records):
                raise ValueError(f"{op} id {record.id} breaks the numbering (expected {len(records)})")
            records.append(record)
            if entry.get("gt_depth"):
                self.gt_depth_files[record.id] = entry["gt_depth"]
            self._order.append((op, record.id))
        elif op == "remove":
            kind, rid = entry["kind"], int(entry["id"])
            if not self._order or self._order[-1] != (kind, rid):
                raise ValueError(f"removal of {kind} {rid}, which is not the last record")
            self._order.pop()
            (self.frames if kind == "frame" else self.touches).pop()
            if kind == "frame":
                self.gt_depth_files.pop(rid, None)
        elif op in ("gt_mesh", "gt_points", "sparse_points"):
            setattr(self, op, entry["path"])
        elif op == "annotation":
            key = entry["key"]
            if not isinstance(key, str) or not key:
                raise ValueError(f"annotation key: expected a non-empty string, got {key!r}")
            self.annotations[key] = entry["value"]
        elif op == "finish":
            self.finished = True
        else:
            raise ValueError(f"unknown op {op!r}")

    def _record(self, entry: dict) -> None:
        """Journal ``entry`` durably, apply it, then rewrite the index files it changes: that of its kind of record
        (scene.json for the ground truth and annotations), and scene.json when it adds or removes a frame's
        ground-truth depth. A job that has not finished leaves them to :meth:`finish` (rewriting the whole index
        after each record made an import of N frames take N^2 time)."""
        if self._journal is None:
            raise InvalidInputError(f"SceneWriter for {self.path} is closed")
        kind = entry.get("kind", entry["op"])
        gt = entry.get("gt_depth") or (kind == "frame" and entry.get("id") in self.gt_depth_files)
        entry = {**entry, "t": time.time()}
        self._append(entry)
        self._apply(entry)
        if kind != "finish":
            self._stale.update(
                [{"frame": "transforms", "touch": "touches"}.get(kind, "scene"), *(["scene"] if gt else [])]
            )
        if self.job is None or self.finished:
            stale, self._stale = self._stale, set()
            self._materialise(*stale)

    def _append(self, entry: dict) -> None:
        """Append ``entry`` to the journal as one line, durably (fsync). When the write fails (a full disk) the
        journal is cut back to where it was, so that no record ever follows a torn line; if even that fails, the
        writer closes (a resume drops the torn line)."""
        fd = self._journal.fileno()
        end = os.lseek(fd, 0, os.SEEK_END)
        try:
            line = memoryview((json.dumps(entry) + "\n").encode())
            while line:
                line = line[os.write(fd, line) :]
            os.fsync(fd)
        except OSError as exc:
            try:
                os.ftruncate(fd, end)
            except OSError:
                self.close()
            raise storage_error(exc, self.path / JOURNAL) from None

    def _materialise(self, *which: str) -> None:
        """Rewrite the index files ``which`` ("transforms", "touches", "scene": ``<name>.json``)."""
        builders = {"transforms": self._transforms_json, "touches": self._touches_json, "scene": self._scene_json}
        for name, build in builders.items():  # in this order, whatever the order of ``which``
            if name in which:
                atomic_write_json(self.path / f"{name}.json", build())

    def _transforms_json(self) -> dict:
        shared = all(intrinsics_equal(f.intrinsics, self.intrinsics) for f in self.frames)
        out = {"camera_model": "OPENCV"}
        if shared:  # nerfstudio reads per-frame intrinsics only when the top-level keys are absent
            out.update(intrinsics_to_json(self.intrinsics))
        out.update({"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0})
        out["frames"] = [frame_to_nerfstudio(f, with_intrinsics=not shared) for f in self.frames]
        out["train_filenames"] = [f.file_path for f in self.frames if f.split == "train"]
        # nerfstudio asks for "val" when evaluating during training: the test views serve both.
        out["val_filenames"] = out["test_filenames"] = [f.file_path for f in self.frames if f.split == "test"]
        return out

    def _touches_json(self) -> dict:
        return {"sensor": sensor_to_json(self.sensor), "touches": [touch_to_json(t) for t in self.touches]}

    def _scene_json(self) -> dict:
        return {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            **asdict(self.meta),
            "units": "m",
            "tacsplat_version": self._version,
            "created": self._created,
            "gt": {
                "mesh": self.gt_mesh,
                "points": self.gt_points,
                "depth": {str(k): v for k, v in sorted(self.gt_depth_files.items())},
            },
            "annotations": self.annotations,
            # (only in a scene that has them: the scene.json of every other scene stays as it was)
            **({"sparse_points": self.sparse_points} if self.sparse_points else {}),
        }

    # --- records ------------------------------------------------------------------------------

    def add_frame(
        self,
        image: np.ndarray,
        T_world_cam: np.ndarray,
        split: str = "train",
        gt_depth: np.ndarray | None = None,
        intrinsics: CameraIntrinsics | None = None,
        mask: np.ndarray | None = None,
        gt_normal: np.ndarray | None = None,
    ) -> Frame:
        """Append a view: ``image`` [H, W, 3] uint8 RGB, ``T_world_cam`` [4, 4] OpenCV camera-to-world.

        ``gt_depth`` [H, W] float32 metres (0 = no surface) goes to ``gt/`` for
        evaluation only, with ``gt_normal`` [H, W, 3], the surface's unit
        world-frame normals (0 where no surface), where a dataset has them. ``intrinsics`` defaults to the scene's. ``mask`` [H, W]
        bool (True = use the pixel) goes to ``masks/``; a scene has a mask on
        every frame or on none (as nerfstudio reads them).
        """
        intr = _check_intrinsics(self.intrinsics if intrinsics is None else intrinsics)
        h, w, image = intr.height, intr.width, np.asarray(image)
        if image.dtype != np.uint8 or image.shape != (h, w, 3):
            raise InvalidInputError(
                f"image: expected uint8 RGB {(h, w, 3)} (the intrinsics'), got {image.dtype} {image.shape}"
            )
        pose = check_pose(T_world_cam, "T_world_cam")
        if split not in SPLITS:
            raise InvalidInputError(f"split: expected one of {SPLITS}, got {split!r}")
        if gt_depth is not None:
            gt_depth = _check_depth(gt_depth, (h, w), "gt_depth", GT_DEPTH_LIMIT)
        if gt_normal is not None:
            if gt_depth is None:
                raise InvalidInputError("gt_normal: needs gt_depth (both are the ground truth of one view)")
            gt_normal = np.asarray(gt_normal, dtype=np.float32)
            if problem := normal_map_problem(gt_normal, (h, w)):
                raise InvalidInputError(f"gt_normal: {problem}")
        if mask is not None:
            mask = np.asarray(mask)
            if mask.dtype != np.bool_ or mask.shape != (h, w):
                raise InvalidInputError(
                    f"mask: expected bool {(h, w)} (the intrinsics'), got {mask.dtype} {mask.shape}"
                )
        if self.frames and (self.frames[0].mask_path is None) != (mask is None):
            raise InvalidInputError(
                f"mask: the scene has masks on every frame or on none; frame 0 has "
                f"{'none' if self.frames[0].mask_path is None else 'one'}"
            )
        fid = self.num_frames
        mask_path = None if mask is None else f"masks/{fid:06d}.png"
        frame = Frame(fid, f"images/{fid:06d}.png", pose, split, intr, mask_path)
        atomic_write_bytes(self.path / frame.file_path, encode_png(image))
        if mask_path is not None:
            (self.path / "masks").mkdir(exist_ok=True)
            atomic_write_bytes(self.path / mask_path, encode_png(np.where(mask, 255, 0).astype(np.uint8)))
        gt_file = None if gt_depth is None else f"gt/depth/{fid:06d}.npz"
        if gt_file is not None:
            normal = {} if gt_normal is None else {"normal": gt_normal}
            atomic_write_bytes(self.path / gt_file, encode_npz(depth=gt_depth, **normal))
        self._record({"op": "frame", "frame": frame_to_json(frame), "gt_depth": gt_file})
        return frame

    def add_hand_motion(self, motion: HandMotion) -> str:
        """Write a grasp's :class:`HandMotion` as ``grasps/<grasp>.npz`` and return that path, for the grasp's
        touches to refer to (``add_touch(..., hand_file=)``): it becomes part of the scene with the first of them
        (a resume deletes it when no touch refers to it)."""
        if not isinstance(motion, HandMotion):
            raise InvalidInputError(f"motion: expected a HandMotion, got {type(motion).__name__}")
        rel = f"grasps/{motion.grasp:06d}.npz"
        (self.path / "grasps").mkdir(exist_ok=True)
        atomic_write_bytes(self.path / rel, encode_npz(**motion.to_arrays()))
        return rel

    def add_touch(
        self, depth: np.ndarray, T_world_sensor: np.ndarray, grasp: int, finger: str, hand_file: str | None = None
    ) -> Touch:
        """Append a tactile reading: ``depth`` [h, w] float32 metres of indentation (0 = no contact); ``hand_file``:
        its grasp's hand motion (:meth:`add_hand_motion`)."""
        if self.sensor is None:
            raise InvalidInputError(
                f"{self.path}: the scene was created without a sensor model; it cannot hold touches"
            )
        shape = (self.sensor.height_px, self.sensor.width_px)
        depth = _check_depth(depth, shape, "depth", touch_depth_limit(self.sensor))
        pose = check_pose(T_world_sensor, "T_world_sensor")
        if isinstance(grasp, bool) or not isinstance(grasp, (int, np.integer)) or grasp < 0:
            raise InvalidInputError(f"grasp: expected a non-negative integer, got {grasp!r}")
        if not isinstance(finger, str) or not finger:
            raise InvalidInputError(f"finger: expected a non-empty name, got {finger!r}")
        tid = self.num_touches
        touch = Touch(tid, int(grasp), finger, f"touches/{tid:06d}.npz", pose, bool((depth > 0).any()), hand_file)
        if hand_file is not None and not (self.path / hand_file).is_file():
            raise InvalidInputError(f"hand_file: {self.path / hand_file} does not exist (write it by add_hand_motion)")
        atomic_write_bytes(self.path / touch.depth_file, encode_npz(depth=depth))
        self._record({"op": "touch", "touch": touch_to_json(touch)})
        return touch

    def add_reading(self, reading: TactileReading, grasp: int, finger: str, hand_file: str | None = None) -> Touch:
        """Append a world-frame :class:`TactileReading` (its pixel size must match the sensor model)."""
        if reading.frame != "world":
            raise InvalidInputError(f"reading: its pose is in the '{reading.frame}' frame; call to_world() first")
        if self.sensor is not None and not np.isclose(reading.pixel_size_m, self.sensor.pixel_size_m, rtol=1e-6):
            raise InvalidInputError(
                f"reading.pixel_size_m {reading.pixel_size_m} differs from the sensor model's "
                f"{self.sensor.pixel_size_m}"
            )
        return self.add_touch(reading.depth, reading.T_world_sensor, grasp, finger, hand_file)

    def set_gt_mesh(self, mesh) -> Path:
        """Store the ground-truth mesh (a path to any mesh trimesh reads, or a ``trimesh.Trimesh``) as ``gt/mesh.ply``."""
        import trimesh

        if isinstance(mesh, (str, os.PathLike)):
            src = Path(mesh)
            if not src.is_file():
                raise InvalidInputError(f"mesh: {src} does not exist")
            ply = src.suffix.lower() == ".ply"
            data = src.read_bytes() if ply else trimesh.load(src, force="mesh").export(file_type="ply")
        elif isinstance(mesh, trimesh.Trimesh):
            data = mesh.export(file_type="ply")
        else:
            raise InvalidInputError(f"mesh: expected a path or trimesh.Trimesh, got {type(mesh).__name__}")
        return self._set_gt("mesh", data)

    def set_gt_points(self, points: np.ndarray) -> Path:
        """Store a ground-truth point cloud [N, 3] (metres, world frame) as ``gt/points.ply``: the object's surface
        where a dataset ships points, not a mesh (NeRO's ``eval_pts.ply``)."""
        import trimesh

        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or not len(points):
            raise InvalidInputError(f"points: expected a non-empty [N, 3] array, got shape {points.shape}")
        if not np.isfinite(points).all():
            raise InvalidInputError("points: contain NaN or infinite values")
        return self._set_gt("points", trimesh.PointCloud(points).export(file_type="ply"))

    def set_sparse_points(self, points: np.ndarray, colors: np.ndarray) -> Path:
        """Store the scene's sparse points [N, 3] (metres, world frame) and their colours [N, 3] uint8 RGB as
        :data:`SPARSE_POINTS`, a binary PLY (float64 x y z, uchar red green blue): an import's SfM points, which
        the initialisation starts from instead of triangulating its own."""
        from plyfile import PlyData, PlyElement

        points, colors = np.asarray(points, dtype=np.float64), np.asarray(colors)
        if problem := sparse_points_problem(points, colors):
            raise InvalidInputError(f"sparse points: {problem}")
        vertex = np.empty(len(points), [(a, "<f8") for a in "xyz"] + [(c, "u1") for c in ("red", "green", "blue")])
        for k, axis in enumerate("xyz"):
            vertex[axis] = points[:, k]
        for k, channel in enumerate(("red", "green", "blue")):
            vertex[channel] = colors[:, k]
        buf = io.BytesIO()
        PlyData([PlyElement.describe(vertex, "vertex")]).write(buf)
        atomic_write_bytes(self.path / SPARSE_POINTS, buf.getvalue())
        self._record({"op": "sparse_points", "path": SPARSE_POINTS})
        return self.path / SPARSE_POINTS

    def _set_gt(self, kind: str, ply: bytes) -> Path:
        """Store the ground truth ``kind`` ("mesh" or "points") as ``gt/<kind>.ply`` and record it."""
        rel = f"gt/{kind}.ply"
        atomic_write_bytes(self.path / rel, ply)
        self._record({"op": f"gt_{kind}", "path": rel})
        return self.path / rel

    def annotate(self, key: str, value) -> None:
        """Record ``value`` (plain JSON: dicts with string keys, lists, strings, finite numbers, booleans, None)
        as scene.json's ``annotations[key]``, replacing an earlier value of ``key``; journaled like every record,
        so a resumed writer holds it in :attr:`annotations`."""
        if not isinstance(key, str) or not key:
            raise InvalidInputError(f"annotation key: expected a non-empty string, got {key!r}")
        try:
            plain = json.loads(json.dumps(value, allow_nan=False))
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"annotation {key!r}: expected plain JSON data: {exc}") from exc
        if plain != value:
            raise InvalidInputError(
                f"annotation {key!r}: expected plain JSON data; it would read back changed "
                "(a tuple, or a dict key that is not a string?)"
            )
        self._record({"op": "annotation", "key": key, "value": plain})

    def remove_last(self) -> Frame | Touch:
        """Undo the most recent frame or touch (the operator's undo); its id is reused next."""
        if not self._order:
            raise InvalidInputError(f"{self.path}: nothing to remove")
        kind, rid = self._order[-1]
        record = self.frames[-1] if kind == "frame" else self.touches[-1]
        gt_file = self.gt_depth_files.get(rid) if kind == "frame" else None
        self._record({"op": "remove", "kind": kind, "id": rid})
        files = [record.file_path, record.mask_path, gt_file] if kind == "frame" else [record.depth_file]
        if kind == "touch" and record.hand_file and all(t.hand_file != record.hand_file for t in self.touches):
            files.append(record.hand_file)  # its grasp's last touch
        for rel in filter(None, files):
            (self.path / rel).unlink(missing_ok=True)
        return record

    def finish(self) -> None:
        """Mark the job's scene complete (its last record) and write the index files it left until now."""
        if self.job is None or self.finished:
            raise InvalidInputError(
                f"{self.path}: nothing to finish (the writer of a job, an import or a copy, finishes once)"
            )
        self._record({"op": "finish"})

    # --- closing ------------------------------------------------------------------------------

    def close(self) -> None:
        """Release the scene (the index is up to date after every record, and after a job's :meth:`finish`)."""
        if self._journal is not None:
            self._journal.close()
            self._journal = None

    def __exit__(self, *exc) -> None:
        self.close()


def _remove_index(scene: Path) -> None:
    """Remove what a failed :meth:`SceneWriter.create` wrote besides the journal (index files, empty record
    folders, the lock file's PID), as far as possible."""
    try:
        for name in ("transforms.json", "touches.json", "scene.json", LOCK_NAME):
            (scene / name).unlink(missing_ok=True)
        for sub in ("gt/depth", "gt", "touches", "images"):
            (scene / sub).rmdir()
    except OSError:
        pass  # (a read-only disk, or a folder that holds something: a later create names what is in the way)


def _make_folders(scene: Path, *subs: str) -> None:
    for sub in subs:
        try:
            (scene / sub).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise storage_error(exc, scene / sub) from None


def _lock_journal(path: Path, scene: Path):
    """Open the journal ``path`` of ``scene`` for appending (unbuffered: :meth:`SceneWriter._append` writes whole
    lines), holding an exclusive lock (released by close or by the process dying). The holder records its PID in
    the scene's lock file (``record_writer``), for the message that refuses another writer."""
    try:
        journal = open(path, "ab", buffering=0)
    except OSError as exc:
        raise storage_error(exc, scene / JOURNAL) from None
    try:
        fcntl.flock(journal.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        journal.close()
        raise InvalidInputError(being_written(scene)) from None
    return journal


def being_written(scene: Path, then: str = ", then continue the scene with --resume") -> str:
    """What refuses ``scene`` while another process writes it: wait for that to end, ``then`` what."""
    return f"{scene} is being written by {other_writer(scene)}: wait for it to end{then}"


def journal_locked(path: Path) -> bool:
    """Whether a writer (of any process) holds the journal ``path``."""
    with open(path, "rb") as f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
    return False


def journaled_state(path) -> SceneWriter:
    """What a scene's journal records, read-only: a closed writer (for the reader: the index files are behind the
    journal only when a writer died between the two; resuming rewrites them)."""
    path = Path(path)
    return SceneWriter._replay(path, _read_journal(path / JOURNAL, truncate=False))


def _read_journal(path: Path, truncate: bool = True) -> list[dict]:
    """Parse the journal; a torn or unparseable *last* line (a write cut by a crash) is dropped (and, with
    ``truncate``, cut from the file). A last line that is a whole JSON object but lacks its newline (a journal
    saved by an editor or a script) is a record: kept, and with ``truncate`` its newline is added. The file changes
    only once all of it parsed (a journal refused is left as it was)."""
    data = path.read_bytes()
    *complete, tail = data.split(b"\n")  # tail is b"" when the file ends with a newline
    if tail and _is_json_object(tail):
        complete, tail = [*complete, tail], b""
    entries, good_bytes = [], 0
    for i, raw in enumerate(complete):
        try:
            entry = json.loads(raw)
            if not isinstance(entry, dict):
                raise ValueError("not a JSON object")
        except ValueError as exc:
            if i == len(complete) - 1 and not tail:
                log.warning("%s: dropping the unparseable last line %d (a write cut by a crash)", path, i + 1)
                break
            raise SceneFormatError(path, f"line {i + 1}", f"not a valid JSON record: {exc}") from exc
        entries.append(entry)
        good_bytes += len(raw) + 1
    if tail:
        log.warning("%s: dropping a torn last line of %d bytes (a write cut by a crash)", path, len(tail))
    if truncate and good_bytes != len(data):
        with open(path, "r+b") as f:
            if good_bytes < len(data):  # what was dropped
                f.truncate(good_bytes)
            else:  # the last record's missing newline
                f.seek(0, os.SEEK_END)
                f.write(b"\n")
            os.fsync(f.fileno())
    if not entries:
        raise SceneFormatError(path, "line 1", "the journal is empty")
    return entries


def _is_json_object(raw: bytes) -> bool:
    """Whether ``raw`` is a whole JSON object (a torn line never is: it lacks the closing brace)."""
    try:
        return isinstance(json.loads(raw), dict)
    except ValueError:
        return False
