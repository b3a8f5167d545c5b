"""The scene a capture writes: ``--out`` checked, the run's settings recorded, a resume allowed only for the
same capture.

:func:`open_scene` opens the rig and the scene writer of ``tacsplat capture``
and ``sim-capture``. Every setting that changes the data is written into
``scene.json`` when the capture starts (``source``, ``object`` and
``capture_plan`` as always, the rest under ``extra.capture_settings``), and
:func:`check_resume` refuses, before any device opens, a resume that asks for
another value of any of them, naming each and both values. It compares:

* every rig: the rig kind, the scene's object name and the plan (view and grasp
  counts, modes, view radius, grasp seed, and the touch model with its
  parameters: a scene of an older version, which recorded none, was grasped
  with the gel model);
* the twin (``rig: sim``): the library object or the mesh file (resolved path
  and the sha256 of its content), the object radius, the resolution, the seed,
  and the twin's own settings (physics, hand, tactile pad, collision
  decomposition, grasp sampling and control, view placement), which come with
  the tacsplat version rather than from an option (a scene captured with the
  slide, since removed, cannot be continued);
* a real rig: ``--mock`` (and the emulated devices' settings, with the servo
  errors of ``sim.true_errors``), the board that defines the world frame, the
  hand-eye transform, the servo ids, the tactile sensor model and mounting
  transforms, and the sha256 of each calibration file,
  the hand-eye and mounts files included (a recalibration starts a new scene;
  a scene of an older version, which recorded no hand-eye or mounts file,
  resumes on what it recorded). Ports, baud rates, device indices,
  timeouts and the grasp controller's speeds and thresholds may change between
  runs: they change how records are taken, not what they mean.
"""

from __future__ import annotations

import hashlib
import json
import math
from contextlib import ExitStack, contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Any, Iterator

from tacsplat.acquisition.config import SLIDE_KEYS, SLIDE_WHY, RigConfig
from tacsplat.acquisition.devices import TWIN_CONTROL, Rig, open_rig, twin_config
from tacsplat.datasets import SceneMeta, SceneWriter
from tacsplat.datasets.outputs import ensure_output_dir
from tacsplat.datasets.reader import STRICT, load_hand_motion
from tacsplat.datasets.writer import JOURNAL, being_written, has_content, journal_locked, journaled_state
from tacsplat.errors import ConfigError, InvalidInputError, SceneFormatError
from tacsplat.sim.hand import JOINT_NAMES

SETTINGS_KEY = "capture_settings"  # in scene.json's "extra"
_IN_META = ("rig", "object", "plan")  # recorded as SceneMeta's source, object and capture_plan
_SIM_OBJECT = ("sim.object", "sim.mesh", "sim.mesh_sha256")  # the twin's object; its name follows from them
# What scenes of older versions recorded beyond _IN_META, as (extra key, setting); see recorded_settings.
_OLDER_EXTRAS = (
    ("mock", "mock"),
    ("object_bounding_radius_m", "sim.object_radius"),
    ("timestep_s", "twin.timestep"),
    ("contact_timeconst_s", "twin.contact_timeconst"),
    ("gel_compliance_m", "twin.hand_geometry.gel_compliance"),
)
# The slide's settings, which twin captures recorded under the grasp control until the slide was removed: without it
# (slide_m 0) they changed nothing; a scene captured with it (slide_m > 0) cannot be continued (check_resume).
_SLIDE = tuple(f"twin.grasp_control.{key}" for key in SLIDE_KEYS)
_MISSING = object()


def check_out(out: Path, resume: bool) -> None:
    """Before any device is opened: ``--out`` must be a writable folder that holds a scene to resume, or (created
    if need be) nothing, for a new one."""
    file_in_the_way = any(p.exists() and not p.is_dir() for p in (out, *out.parents))
    if resume and not file_in_the_way and not (out / JOURNAL).is_file():
        raise ConfigError("--resume", f"{out} holds no scene to resume (no {JOURNAL}); drop --resume to start one")
    ensure_output_dir(out, "--out")
    if resume:
        if journal_locked(out / JOURNAL):  # (before its settings are read: a scene being written is not compared)
            raise InvalidInputError(being_written(out))
        return
    # Content first, then the journal: a creation renames its journal into place before it writes anything else,
    # so a folder another capture is creating at this moment is named as that capture's, never as other files.
    content = has_content(out)
    if (out / JOURNAL).exists():
        if journal_locked(out / JOURNAL):
            raise ConfigError(
                "--out", being_written(out, ", then continue the scene with --resume, or choose a new folder")
            )
        raise ConfigError("--out", f"{out} already holds a scene: add --resume to continue it, or choose a new folder")
    if content:
        raise ConfigError("--out", f"{out} holds other files and no scene; choose an empty or new folder")


@contextmanager
def open_scene(config: RigConfig, out: Path, resume: bool, on_hand=None) -> Iterator[tuple[Rig, SceneWriter]]:
    """The open rig and scene writer of a capture: a new scene recording this run's settings, or the scene in
    ``out`` resumed. ``--out`` is checked, and on ``--resume`` the scene's recorded settings are compared with this
    run's (:func:`check_resume`) and its record files checked (:func:`check_record_files`), before any device
    opens or anything in the scene changes. A folder made here for a capture that never started (it
    holds nothing) is removed again. ``on_hand``: see :func:`~tacsplat.acquisition.devices.open_rig`."""
    made = not out.exists()
    try:
        check_out(out, resume)
        settings = capture_settings(config)
        with ExitStack() as stack:
            if resume:
                recorded = journaled_state(out)  # read-only: a refused resume leaves the scene as it was
                check_resume(recorded, settings, config.source)
                check_record_files(recorded)
                writer = stack.enter_context(SceneWriter.resume(out))
                rig = stack.enter_context(open_rig(config, on_hand))
            else:
                rig = stack.enter_context(open_rig(config, on_hand))
                writer = stack.enter_context(
                    SceneWriter.create(out, rig.intrinsics, scene_meta(settings, rig.extra), rig.sensor_model)
                )
            if rig.twin is not None and writer.gt_mesh is None:  # new, or its first run stopped first (a full disk)
                writer.set_gt_mesh(rig.twin.object_mesh)
            yield rig, writer
    finally:
        if made and out.is_dir() and not any(out.iterdir()):
            out.rmdir()


def capture_settings(config: RigConfig) -> dict:
    """The settings of a run that change its data, as plain JSON (see the module docstring)."""
    settings = {"rig": config.rig, "object": config.scene_object, "plan": config.plan.to_json()}
    settings.update(_sim_settings(config) if config.rig == "sim" else _real_settings(config))
    return json.loads(json.dumps(settings))  # tuples as lists, as scene.json gives them back


def scene_meta(settings: dict, extra: dict) -> SceneMeta:
    """The SceneMeta of a new capture: its settings, plus the rig's provenance ``extra``."""
    rest = {k: v for k, v in settings.items() if k not in _IN_META}
    return SceneMeta(settings["rig"], settings["object"], settings["plan"], {**extra, SETTINGS_KEY: rest})


def recorded_settings(writer: SceneWriter) -> dict:
    """The settings a scene was captured with, flat (``"plan.views.train": 20``)."""
    meta = writer.meta
    recorded = {
        "plan.touches.model": "gel",
        **flatten_settings({"rig": meta.source, "object": meta.object, "plan": meta.capture_plan}),
    }
    if meta.source == "sim":
        recorded["sim.texture"] = "none"  # what every twin capture was before the texture became a setting
    if SETTINGS_KEY in meta.extra:
        settings = flatten_settings(meta.extra[SETTINGS_KEY])
        slide = {_SLIDE[0]: settings[_SLIDE[0]]} if settings.get(_SLIDE[0]) else {}
        return {**recorded, **{k: v for k, v in settings.items() if k not in _SLIDE}, **slide}
    # A scene of an older version records no capture_settings; it resumes when what it does record agrees: the rig
    # kind, object and plan; a twin's resolution (its image width); and the extras of _OLDER_EXTRAS it holds.
    if meta.source == "sim":
        recorded["sim.resolution"] = writer.intrinsics.width
    recorded.update({setting: meta.extra[key] for key, setting in _OLDER_EXTRAS if key in meta.extra})
    return recorded


class ResumeMismatch(ConfigError):
    """``--resume`` asked for settings other than those the scene was captured with."""

    def __init__(self, differences: list[tuple[str, str]], source=None):
        """``differences``: (setting, what differs), in order; the first one names the error."""
        self.differences = differences
        (key, first), *rest = differences
        told = "; ".join([first, *(f"{k}: {text}" for k, text in rest)])
        super().__init__(key, f"{told}; drop --resume to start a new scene", source)

    def renamed(self, names: dict[str, str]) -> "ResumeMismatch":
        """The same refusal naming a command's options (``names``: setting -> option); each option told once."""
        told: dict[str, str] = {}
        for key, text in self.differences:
            told.setdefault(names.get(key, key), text)
        return ResumeMismatch(list(told.items()), self.source)


def check_resume(writer: SceneWriter, settings: dict, source=None) -> None:
    """Refuse (:class:`ResumeMismatch`) to continue ``writer``'s scene with ``settings`` that differ from its own."""
    requested = flatten_settings(settings)
    differences = [
        (key, old, requested.get(key, _MISSING))
        for key, old in recorded_settings(writer).items()
        if not same_setting(old, requested.get(key, _MISSING))
    ]
    if any(key in _SIM_OBJECT for key, _, _ in differences):
        differences = [d for d in differences if d[0] != "object"]
    differences.sort(key=lambda d: d[0] not in ("object", *_SIM_OBJECT))  # the object first, then in file order
    if differences:
        raise ResumeMismatch([(key, _describe(key, writer.path, old, new)) for key, old, new in differences], source)


def check_record_files(scene: SceneWriter) -> None:
    """Refuse (:class:`SceneFormatError`) to resume ``scene`` (its journaled state) when a file its records refer
    to is missing (a partial copy: the resume would count the record as taken), or when the last record is a touch
    and its grasp's hand motion, which the resume then reads to redo a grasp cut short, is damaged
    (:meth:`~tacsplat.acquisition.logger.CaptureLogger.drop_partial_grasp`)."""
    if missing := sorted(rel for rel in scene.record_files() if not (scene.path / rel).is_file()):
        shown = ", ".join(missing[:3]) + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
        raise SceneFormatError(
            scene.path / JOURNAL,
            None,
            f"records {len(missing)} file(s) that are missing ({shown}): restore them (from the copy the scene "
            "came from), or drop --resume and capture a new scene in another --out",
        )
    last = scene.last_record
    if last is not None and last[0] == "touch" and (hand_file := scene.touches[-1].hand_file):
        load_hand_motion(scene.path / hand_file, STRICT, f"touch {scene.touches[-1].id} hand_file")


# --- the settings of each rig ----------------------------------------------------------------------


def _sim_settings(config: RigConfig) -> dict:
    from tacsplat.sim.grasps import GraspConfig
    from tacsplat.sim.views import ViewConfig

    s = config.sim
    mesh = config.path(s.mesh).resolve() if s.mesh else None
    in_sim = ("object", "mesh_path", "object_radius", "seed", "camera_width", "camera_height", "texture")
    twin = {k: v for k, v in asdict(twin_config(config)).items() if k not in in_sim}
    return {
        "sim": {
            "object": None if mesh else s.object,
            "mesh": str(mesh) if mesh else None,
            "mesh_sha256": _sha256(mesh, "sim.mesh", config.source) if mesh else None,
            "object_radius": s.object_radius,
            "resolution": s.resolution,
            "seed": s.seed,
            "texture": s.texture,
        },
        "twin": {
            **twin,
            "grasp_control": asdict(TWIN_CONTROL),
            "grasping": asdict(GraspConfig()),
            "views": asdict(ViewConfig()),
        },
    }


def _real_settings(c: RigConfig) -> dict:
    def sha(key: str, name: str | None) -> str | None:  # the mock generates the camera's and sensors' calibrations
        generated = c.mock and (key == "camera.calibration" or key.startswith("tactile.sensors["))
        return None if generated or name is None else _sha256(c.path(name), key, c.source)

    b, t = c.board, c.tactile
    settings = {
        "mock": c.mock,
        "board": asdict(b.spec()),
        "hand": {"ids": c.hand.ids, "calibration_sha256": sha("hand.calibration", c.hand.calibration)},
        "camera": {
            "T_hand_cam": c.camera.T_hand_cam,
            "calibration_sha256": sha("camera.calibration", c.camera.calibration),
            "hand_eye_sha256": sha("camera.hand_eye", c.camera.hand_eye),
        },
        "tactile": {
            "sensor_name": t.sensor_name,
            "gel_thickness_m": t.gel_thickness_m,
            "sensors": [
                {
                    "finger": s.finger,
                    "T_fingertip_sensor": s.T_fingertip_sensor,
                    "calibration_sha256": sha(f"tactile.sensors[{i}].calibration", s.calibration),
                }
                for i, s in enumerate(t.sensors)
            ],
            "mounts_sha256": sha("tactile.mounts", t.mounts),
        },
    }
    if c.mock:
        settings["mock_devices"] = {
            k: v for k, v in asdict(c.mock_devices).items() if k not in ("servo_timeout_s", "servo_port")
        }  # the servo link, not the scene
        # the emulated servos' readings, so the joint angles the scene records: as the file's keys, over every joint
        # (a joint the file leaves out at its default), so that a difference names its joint
        e = c.sim.true_errors
        settings["sim"] = {
            "true_errors": {
                "joint_offsets_rad": dict(zip(JOINT_NAMES, e.servo_offsets())),
                "joint_signs": dict(zip(JOINT_NAMES, e.servo_signs())),
            }
        }
    return settings


# --- helpers ------------------------------------------------------------------------------------


def _sha256(path: Path, key: str, source) -> str:
    try:
        with open(path, "rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except OSError as exc:
        raise ConfigError(key, f"cannot read {path}: {exc.strerror}", source) from None


def flatten_settings(data: dict, prefix: str = "") -> dict:
    """``{"a": {"b": 1}, "s": [{"c": 2}]}`` -> ``{"a.b": 1, "s[0].c": 2}`` (other lists are values)."""
    flat = {}
    for name, value in data.items():
        key = f"{prefix}{name}"
        if isinstance(value, dict) and value:
            flat.update(flatten_settings(value, key + "."))
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for i, item in enumerate(value):
                flat.update(flatten_settings(item, f"{key}[{i}]."))
        else:
            flat[key] = value
    return flat


def same_setting(a: Any, b: Any) -> bool:
    """Equal JSON values; numbers to 1e-9 relative (older scenes recorded some as computed, e.g. 0.08000000000000002)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(map(same_setting, a, b))
    return a == b


def _show(value: Any) -> str:
    if value is _MISSING:
        return "(not set)"
    return format(value, ".10g") if isinstance(value, float) else repr(value)


def _describe(key: str, scene: Path, old: Any, new: Any) -> str:
    if key == _SLIDE[0]:
        return f"{scene} was captured with the slide (slide_m {_show(old)}) and {SLIDE_WHY}"
    if key.endswith("_sha256") and isinstance(old, str) and isinstance(new, str):
        return f"{scene} was captured with a file of sha256 {old[:12]}, this run's file has sha256 {new[:12]}"
    return f"{scene} was captured with {_show(old)}, this run asks for {_show(new)}"
