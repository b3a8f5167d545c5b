"""CaptureLogger: views and grasps from a Hand, TactileSensors and a Camera into a scene directory.

The real rig and the MuJoCo twin run this same code; they differ only in the
devices, the clock (``time.sleep`` or the twin's simulated time) and the pose
source (board PnP with its reprojection error, or the twin's ground truth).
Everything is written through :class:`~tacsplat.datasets.SceneWriter`, so a
capture killed at any moment resumes losing at most the record in flight; a
grasp is a group of touches (one per sensor) that resume and undo treat as one
record: a grasp cut short is removed whole and redone.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Protocol, Sequence

import numpy as np

from tacsplat.acquisition.config import BoardConfig, GraspControl
from tacsplat.datasets import HandMotion, SceneWriter
from tacsplat.datasets.reader import STRICT, load_hand_motion
from tacsplat.datasets.records import MOTION_PHASES
from tacsplat.drivers.protocols import Camera, Hand, TactileSensor
from tacsplat.drivers.wrist_camera import opencv_K_from_tacsplat
from tacsplat.errors import CameraError, InvalidInputError, TacsplatError
from tacsplat.geometry import check_rigid, invert_pose
from tacsplat.types import TactileReading

log = logging.getLogger(__name__)


class CaptureRejected(TacsplatError):
    """A view or grasp was not recorded (board not seen, reprojection error over the threshold); nothing failed."""


class Clock(Protocol):
    """A rig's clock: :class:`WallClock`, or the twin itself (sleeping advances its physics)."""

    def sleep(self, seconds: float) -> None: ...

    @property
    def time(self) -> float: ...


class WallClock:
    """A real rig's clock."""

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    @property
    def time(self) -> float:
        return time.monotonic()


@dataclass(frozen=True)
class PoseEstimate:
    """A pose with its quality: the board PnP's RMS reprojection error and the standard deviation of the camera
    position it implies (None for ground truth)."""

    T: np.ndarray  # [4, 4]
    reprojection_px: float | None = None
    corners: int | None = None
    position_std_m: float | None = None


class PoseSource(Protocol):
    def camera_pose(self, image: np.ndarray) -> PoseEstimate:
        """``T_world_cam`` of the camera that took ``image``; raises CaptureRejected when it cannot be known."""

    def hand_pose(self, image: np.ndarray) -> PoseEstimate:
        """``T_world_hand`` at the time ``image`` was taken."""

    def ground_truth_depth(self) -> np.ndarray | None:
        """[H, W] float32 depth of the last view (the twin only; evaluation only)."""


class BoardPoseSource:
    """A real rig's poses: ChArUco board PnP on undistorted frames; the hand from the hand-eye transform."""

    def __init__(self, camera: Camera, board: BoardConfig, T_hand_cam: np.ndarray):
        self.board = board
        self.spec = board.spec()
        self.K_opencv = opencv_K_from_tacsplat(camera.K)
        self.T_cam_hand = invert_pose(check_rigid(T_hand_cam, "T_hand_cam"))

    def measure(self, image: np.ndarray) -> PoseEstimate:
        """The board pose without the threshold (for the live status line); CameraError when not seen."""
        from tacsplat.drivers.wrist_camera import board_pose

        pose = board_pose(image, self.spec, self.K_opencv, None, self.board.min_corners)
        return PoseEstimate(pose.T_world_cam, pose.rms_px, pose.corners, pose.position_std_m)

    def camera_pose(self, image: np.ndarray) -> PoseEstimate:
        try:
            est = self.measure(image)
        except CameraError as exc:
            raise CaptureRejected(f"board not seen ({exc}); move the camera so the board is in view") from None
        if est.reprojection_px > self.board.max_reprojection_px:
            raise CaptureRejected(
                f"board reprojection error {est.reprojection_px:.2f} px is over the threshold "
                f"{self.board.max_reprojection_px:g} px (blur or a bent board?); hold still and retry"
            )
        return est

    def hand_pose(self, image: np.ndarray) -> PoseEstimate:
        est = self.camera_pose(image)
        return replace(est, T=est.T @ self.T_cam_hand)

    def ground_truth_depth(self) -> None:
        return None


class TwinPoseSource:
    """The twin's poses: ground truth for the view camera; the hand base as the rig computes it, from the wrist
    camera's true pose (what board PnP measures) through the rig's ``T_hand_cam`` (off by a hidden hand-eye
    error, as on a real rig)."""

    def __init__(self, twin):
        self.twin = twin

    def camera_pose(self, image: np.ndarray) -> PoseEstimate:
        return PoseEstimate(self.twin.camera_pose())

    def hand_pose(self, image: np.ndarray) -> PoseEstimate:
        return PoseEstimate(self.twin.hand_pose_from_wrist_camera())

    def ground_truth_depth(self) -> np.ndarray:
        return self.twin.view_camera.read_depth()


@dataclass
class GraspOutcome:
    """One recorded grasp."""

    index: int  # the grasp number in the scene
    touches: list  # the Touch records, one per sensor
    stopped_by: dict[str, str]  # finger -> "reached" | "stalled" | "timeout"
    settled: bool
    close_seconds: float  # on the rig's clock
    T_world_hand: np.ndarray
    hand_reprojection_px: float | None = None
    motion: HandMotion | None = None  # the hand's trajectory through the grasp, as recorded

    @property
    def fingers_in_contact(self) -> list[str]:
        return [t.finger for t in self.touches if t.in_contact]


@dataclass
class ViewOutcome:
    frame: object  # the Frame record
    reprojection_px: float | None = None

    @property
    def board_note(self) -> str:
        """``", board reprojection 0.42 px"``, or nothing (ground truth): how the log and the session tell it."""
        return "" if self.reprojection_px is None else f", board reprojection {self.reprojection_px:.2f} px"


@dataclass
class Counts:
    train: int = 0
    test: int = 0
    grasps: int = 0
    touches: int = 0
    contacts: int = 0  # touches in contact


def finger_joints(joint_names: Sequence[str]) -> dict[str, list[int]]:
    """Each finger's joint indices, by the joints' names (``index_0`` ... ``index_3``: finger ``index``)."""
    fingers: dict[str, list[int]] = {}
    for i, joint in enumerate(joint_names):
        fingers.setdefault(joint.rsplit("_", 1)[0], []).append(i)
    return fingers


@dataclass(eq=False)
class CaptureLogger:
    """Writes views and grasps through ``writer``; the devices are seen only through their Protocols.

    Each finger's joints are those named after it (:func:`finger_joints`). Opening a logger on a resumed writer
    first removes a grasp cut short (a last grasp with fewer touches than its hand motion's ``touch_t`` lists, or
    than sensors), unless ``redo_partial_grasp`` is False (a scene another tool wrote, whose grasps may hold fewer
    touches).
    """

    writer: SceneWriter
    hand: Hand
    sensors: Sequence[TactileSensor]
    camera: Camera
    clock: Clock
    poses: PoseSource
    control: GraspControl = GraspControl()
    redo_partial_grasp: bool = True

    def __post_init__(self):
        self.sensors = list(self.sensors)
        if not self.sensors:
            raise InvalidInputError("sensors: a capture needs at least one tactile sensor")
        names = [s.name for s in self.sensors]
        if len(set(names)) != len(names):
            raise InvalidInputError(f"sensors: duplicate names {names}")
        self.fingers = {f: np.asarray(j, dtype=int) for f, j in finger_joints(self.hand.joint_names).items()}
        self.hand_state = "open"
        self._samples: list | None = None  # (t, phase, q, target, effort) while a grasp records its motion
        self.dropped_partial_grasp = self.drop_partial_grasp() if self.redo_partial_grasp else 0

    # --- state ------------------------------------------------------------------------------------
    def counts(self) -> Counts:
        w = self.writer
        return Counts(
            train=sum(f.split == "train" for f in w.frames),
            test=sum(f.split == "test" for f in w.frames),
            grasps=len({t.grasp for t in w.touches}),
            touches=w.num_touches,
            contacts=sum(t.in_contact for t in w.touches),
        )

    def next_grasp_index(self) -> int:
        return max((t.grasp for t in self.writer.touches), default=-1) + 1

    def drop_partial_grasp(self) -> int:
        """Remove the touches of a last grasp that has fewer touches than sensors (a capture cut short while
        writing it); returns how many were removed. A missing or damaged hand motion file of that grasp is a
        SceneFormatError naming it."""
        w = self.writer
        if (last := w.last_record) is None or last[0] != "touch":
            return 0
        g = w.touches[-1].grasp
        have = sum(t.grasp == g for t in w.touches)
        touch_t = None
        if (hand_file := w.touches[-1].hand_file) is not None:
            touch_t = load_hand_motion(w.path / hand_file, STRICT, f"touch {w.touches[-1].id} hand_file").touch_t
        # (a grasp of an older scene captured with the slide, since removed, holds more touches than sensors)
        want = len(self.sensors) if touch_t is None else len(touch_t)
        if have >= want:
            return 0
        self._remove_last_grasp()
        log.warning("grasp %d was cut short (%d of %d touches): removed, to be redone whole", g, have, want)
        return have

    # --- views ------------------------------------------------------------------------------------
    def take_view(self, split: str = "train", image: np.ndarray | None = None) -> ViewOutcome:
        """Read the camera (or use ``image``), compute its pose, append the frame.

        Raises :class:`CaptureRejected` (nothing written) when the pose cannot be
        trusted: board not seen, or its reprojection error over the threshold.
        """
        if image is None:
            image, _ = self.camera.read()
        est = self.poses.camera_pose(image)
        gt = self.poses.ground_truth_depth() if split == "test" else None
        outcome = ViewOutcome(self.writer.add_frame(image, est.T, split, gt_depth=gt), est.reprojection_px)
        log.debug("view %d (%s) recorded%s", outcome.frame.id, split, outcome.board_note)
        return outcome

    # --- grasps -----------------------------------------------------------------------------------
    def take_grasp(
        self,
        close_pose: np.ndarray | None = None,
        open_pose: np.ndarray | None = None,
        T_world_hand: np.ndarray | None = None,
        index: int | None = None,
    ) -> GraspOutcome:
        """Close, wait until the fingers settle or stall, read every sensor, append the touches, open.

        ``T_world_hand`` [4, 4] defaults to the pose source's (board PnP through
        the hand-eye transform on a real rig, measured before closing; ground
        truth on the twin). Touches with no contact are recorded as such.
        ``index`` (the grasp number) defaults to one after the last recorded grasp.
        """
        q_close = self._joint_pose(close_pose, "close_pose")  # both checked before anything moves
        q_open = self._joint_pose(open_pose, "open_pose")
        hand_rms = None
        if T_world_hand is None:
            # before the fingers move: CaptureRejected leaves the hand open
            est = self.poses.hand_pose(self.camera.read()[0])
            T_world_hand, hand_rms = est.T, est.reprojection_px
        T_world_hand = check_rigid(T_world_hand, "T_world_hand")
        index = self.next_grasp_index() if index is None else int(index)
        if any(t.grasp == index for t in self.writer.touches):
            raise InvalidInputError(f"grasp {index} is already recorded")
        self.hand_state = "closing"
        t0 = self.clock.time
        self._samples = []
        try:
            stopped_by, settled = self._close(q_close)
            close_s = self.clock.time - t0
            self.hand_state = "closed"
            readings = self._read(t0)
            touch_t = np.array([t for t, _, _ in readings])
            hand_file = self.writer.add_hand_motion(self._motion(index, T_world_hand, t0, touch_t))
            touches = [
                self.writer.add_reading(reading.to_world(T_world_hand), grasp=index, finger=name, hand_file=hand_file)
                for _, name, reading in readings
            ]
            self.open(q_open)
            motion = self._motion(index, T_world_hand, t0, touch_t)  # with the release
            self.writer.add_hand_motion(motion)
        finally:
            self._samples = None
        outcome = GraspOutcome(index, touches, stopped_by, settled, close_s, T_world_hand, hand_rms, motion)
        no_contact = [t.finger for t in touches if not t.in_contact]
        log.debug(
            "grasp %d recorded: %d touches (%s), stopped by %s%s",
            index,
            len(touches),
            f"no contact on {', '.join(no_contact)}" if no_contact else "all in contact",
            stopped_by,
            "" if settled else "; the fingers had not settled",
        )
        return outcome

    def _joint_pose(self, given, name: str) -> np.ndarray:
        """``given``, or the GraspControl's pose ``name`` when None, as one finite position per joint of the hand;
        an InvalidInputError naming the argument (or the ``grasp.`` setting) otherwise."""
        joints = list(self.hand.joint_names)
        n, where = len(joints), name if given is not None else f"grasp.{name}"
        value = getattr(self.control, name) if given is None else given
        try:
            q = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise InvalidInputError(f"{where}: expected {n} joint positions (numbers), got {value!r}") from None
        if q.shape != (n,):
            got = f"{q.size} joint positions" if q.ndim == 1 else f"an array of shape {q.shape}"
            hint = "" if given is not None else f"; give take_grasp a close_pose and an open_pose of {n} for this hand"
            raise InvalidInputError(f"{where}: {got} for a hand of {n} joints ({', '.join(joints)}){hint}")
        if not np.isfinite(q).all():
            raise InvalidInputError(f"{where}: expected finite joint positions, got {q.tolist()}")
        return q

    def open(self, q_open: np.ndarray | None = None) -> None:
        """Command the open pose and wait ``open_s`` (sampling the joints every poll while a grasp records)."""
        target = self._joint_pose(q_open, "open_pose")
        self.hand_state = "opening"
        self.hand.command_joint_positions(target)
        if self._samples is None:
            self.clock.sleep(self.control.open_s)
        else:
            t_end = self.clock.time + self.control.open_s
            while (left := t_end - self.clock.time) > 1e-9:
                self.clock.sleep(min(self.control.poll_s, left))
                self._sample("open", target)
        self.hand_state = "open"

    def _sample(self, phase: str, target: np.ndarray | None) -> np.ndarray:
        """Read the joints (and efforts), keep them as a sample of the grasp's motion; returns the positions."""
        q, effort = self.hand.read_joint_state()
        if self._samples is not None:
            target = q if target is None else target  # (the preshape: at rest where it was put)
            self._samples.append((self.clock.time, MOTION_PHASES.index(phase), q, np.array(target, float), effort))
        return q

    def _read(self, t0: float) -> list[tuple[float, str, TactileReading]]:
        """``(seconds since t0, sensor name, reading in the hand frame)`` of each sensor, read now."""
        rows = []
        for sensor in self.sensors:
            reading = sensor.read()  # (then the time: after the read, as a real sensor's frame arrives)
            if reading.frame != "hand":  # a driver outside the package could place its pad elsewhere
                raise InvalidInputError(
                    f"sensor {sensor.name!r}: expected a reading in the hand frame, got {reading.frame!r}"
                )
            rows.append((self.clock.time - t0, sensor.name, reading))
        return rows

    def _motion(self, index: int, T_world_hand: np.ndarray, t0: float, touch_t: np.ndarray) -> HandMotion:
        """The grasp's :class:`HandMotion` from the samples so far, with the hand's boxes placed at each."""
        t, phase, q, target, effort = (np.array(column) for column in zip(*self._samples))
        boxes = [self.hand.link_boxes(qs) for qs in q]
        return HandMotion(
            grasp=index,
            joint_names=tuple(self.hand.joint_names),
            t=t - t0,
            phase=phase,
            q=q,
            q_target=target,
            effort=effort,
            effort_unit=self.hand.effort_unit,
            T_world_hand=T_world_hand,
            link_names=tuple(self.hand.link_names),
            link_half_extents=boxes[0][1],
            link_poses=np.einsum("ij,sljk->slik", T_world_hand, np.stack([T for T, _ in boxes])),
            touch_t=touch_t,
        )

    def _close(self, q_close: np.ndarray) -> tuple[dict[str, str], bool]:
        """Ramp the targets toward ``q_close`` at ``close_speed_rad_s``; a finger whose joints lag their target by
        ``stall_error_rad`` stops there (stalled on the object); then wait until the joints settle. Returns each
        finger's state and whether they settled."""
        c = self.control
        lo, hi = np.asarray(self.hand.joint_limits, dtype=np.float64).T
        q_close = np.clip(q_close, lo, hi)
        q_start = self._sample("preshape", None)
        target = q_start.copy()
        state = dict.fromkeys(self.fingers, "closing")  # -> "reached" | "stalled"
        step = c.close_speed_rad_s * c.poll_s
        t_end = self.clock.time + c.max_close_s
        still, q_prev = 0, q_start
        while True:
            q = self._sample("close", target)
            for f, j in self.fingers.items():
                if state[f] != "closing":
                    continue
                if np.abs(target[j] - q[j]).max() > c.stall_error_rad:
                    state[f] = "stalled"
                    target[j] = q[j] + np.clip(target[j] - q[j], -c.stall_error_rad, c.stall_error_rad)
                    continue
                target[j] += np.clip(q_close[j] - target[j], -step, step)
                if np.abs(q_close[j] - target[j]).max() < 1e-12:
                    state[f] = "reached"
            moving = np.abs(q - q_prev).max()
            still = still + 1 if moving < c.settle_tol_rad else 0
            if "closing" not in state.values() and still >= c.settle_polls:
                return state, True
            if self.clock.time >= t_end:
                log.warning("the fingers did not settle within %.2f s; reading anyway", c.max_close_s)
                return {f: "timeout" if s == "closing" else s for f, s in state.items()}, False
            self.hand.command_joint_positions(target)
            q_prev = q
            self.clock.sleep(c.poll_s)

    # --- undo -------------------------------------------------------------------------------------
    def undo(self) -> str:
        """Remove the last record: a view, or a whole grasp (all its touches). Returns what was removed."""
        if (last := self.writer.last_record) is None:
            raise CaptureRejected("nothing to undo")
        if last[0] == "frame":
            frame = self.writer.remove_last()
            return f"view {frame.id} ({frame.split})"
        return "grasp {} ({} touches)".format(*self._remove_last_grasp())

    def _remove_last_grasp(self) -> tuple[int, int]:
        """Remove the touches of the last grasp (the last records); returns its number and how many went."""
        w, removed = self.writer, 0
        g = w.touches[-1].grasp
        while w.last_record is not None and w.last_record[0] == "touch" and w.touches[-1].grasp == g:
            w.remove_last()
            removed += 1
        return g, removed
