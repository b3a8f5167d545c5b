"""The run directory of a reconstruction: its files, checkpoint, progress log and plot.

``tacsplat reconstruct`` writes, in one folder: ``config.json`` (the
:class:`~tacsplat.reconstruction.config.TrainConfig`), ``checkpoint.pt`` (the
last checkpoint: resumable), ``splat.ply`` (the final Gaussians, a shaded
appearance baked into their SH: :mod:`.baking`), ``progress.csv`` (``PROGRESS_COLUMNS``: iteration,
seconds of run time excluding evaluation, each loss term averaged since the
previous row, Gaussian count, held-out PSNR, CD and the paper's CD), ``error_vs_time.png``,
``metrics.json`` and ``renders/``. Anything else in the folder is someone
else's and is never deleted.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import os
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tacsplat.errors import ConfigError, InvalidInputError, SceneFormatError
from tacsplat.files import atomic_write, default_temp
from tacsplat.reconstruction.config import TrainConfig
from tacsplat.reconstruction.gaussians import Gaussians
from tacsplat.reconstruction.shading import DiffuseLight, Look

log = logging.getLogger(__name__)

# A run directory's own files, each with the temporary name it is written to first (tacsplat.files); anything else
# in it is someone else's and is never deleted.
_OUTPUTS = (
    "config.json",
    "checkpoint.pt",
    "splat.ply",
    "splat.touch.npy",
    "progress.csv",
    "error_vs_time.png",
    "metrics.json",
    "light.png",
)
RUN_FILES = _OUTPUTS + tuple(default_temp(Path(name)).name for name in _OUTPUTS)
RENDERS = "renders"
MESH_FILES = {"mesh": "mesh.ply", "mesh_untouched": "mesh-untouched.ply"}  # `export mesh`'s: metrics prefix -> file
RENDER_FILE = re.compile(r"view_\d{4,}\.png(\.tmp)?")

# the loss terms of a training step, each averaged over the steps since the previous row of progress.csv
LOSS_TERMS = ("loss", "photometric", "transmittance", "smoothness", "backdrop", "normals", "albedo_smoothness")
# progress.csv's columns: a column added later goes last: older files read and resume by name (see cut_progress)
PROGRESS_COLUMNS = (
    "iteration",
    "seconds",
    "loss",
    "photometric",
    "transmittance",
    "smoothness",
    "backdrop",
    "normals",
    "num_gaussians",
    "psnr",
    "cd",
    "cd_paper",
    "albedo_smoothness",
)


@dataclass
class LoadedRun:
    scene_path: Path
    config: TrainConfig
    gaussians: Gaussians
    step: int
    train_seconds: float
    look: Look  # the appearance (with its light where it has one)
    scene_record: dict | None = None  # config.json's record of the scene (scene_record), None where it has none
    touch_points: np.ndarray | None = None  # [P, 3] the touch points it trained with (None: a checkpoint without)


def is_run_folder(path: Path) -> bool:
    """Whether a folder holds a reconstruction run (its config or checkpoint)."""
    return (path / "config.json").is_file() or (path / "checkpoint.pt").is_file()


def run_checkpoint(run_dir: str | Path) -> Path:
    """The checkpoint file of a run directory; a SceneFormatError if there is none (for a run's folder, its
    config.json without a checkpoint, one saying that the run stopped before its first and how to run it again:
    there is nothing to resume, and a run that failed would fail again with its own settings, which --resume keeps)."""
    path = Path(run_dir) / "checkpoint.pt"
    if not Path(run_dir).is_dir():
        missing = "is a file" if Path(run_dir).exists() else "does not exist"
        raise SceneFormatError(run_dir, None, f"{missing}: not a reconstruction run directory")
    if not path.is_file():
        if (writer := run_writer(Path(run_dir))) is not None:
            raise SceneFormatError(
                path,
                None,
                f"no checkpoint yet: the run is still being trained by {writer}; try again after its first checkpoint",
            )
        if (scene := _recorded_run_scene(Path(run_dir))) is not None:
            again = shlex.join(["tacsplat", "reconstruct", scene, "--out", str(run_dir), "--overwrite"])
            raise SceneFormatError(
                path,
                None,
                "no checkpoint: the run stopped or failed before its first checkpoint was written, so there is "
                f"nothing to resume; run the reconstruction again (with the options it needs): {again}",
            )
        raise SceneFormatError(path, None, "no checkpoint: not a reconstruction run directory")
    return path


def run_writer(run_dir: Path) -> str | None:
    """The live process holding the run's lock (training or writing it), as :func:`other_writer` names it; None when
    no process holds it (a run that stopped, or a folder never locked)."""
    import fcntl

    from tacsplat.datasets.outputs import LOCK_NAME, other_writer

    try:
        with open(run_dir / LOCK_NAME, "rb") as lock:  # (read-only: a probe creates nothing)
            try:
                fcntl.flock(lock.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = (run_dir / LOCK_NAME).read_text().split()
                if holder and holder[0] == str(os.getpid()):  # this process's own (evaluate holds it while reading)
                    return None
                return other_writer(run_dir)
            fcntl.flock(lock.fileno(), fcntl.LOCK_UN)
    except OSError:  # no lock file, or one that cannot be opened: nobody to name
        return None
    return None


def _recorded_run_scene(run_dir: Path) -> str | None:
    """The scene a run's config.json records (``SCENE`` for a run's config.json from before scenes were recorded),
    None where the folder has no run's config.json."""
    if (record := recorded_scene(run_dir)) is not None:
        return record["path"]
    try:
        TrainConfig.from_json(read_json(run_dir / "config.json"))
    except ConfigError:
        return None
    return "SCENE"


def read_checkpoint(path: Path) -> dict:
    """A checkpoint's contents; a SceneFormatError naming the file if it is cut short or not one."""
    try:
        ckpt = torch.load(path, weights_only=False, map_location="cpu")  # moved to the run's device by the caller
    except Exception as exc:  # torch.load raises whatever its zip reader or unpickler meets
        first_line = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise SceneFormatError(path, None, f"corrupt or truncated checkpoint ({first_line})") from None
    keys = ("scene_path", "config", "step", "train_seconds", "gaussians")
    missing = [k for k in keys if k not in ckpt] if isinstance(ckpt, dict) else list(keys)
    if missing:
        raise SceneFormatError(path, None, f"corrupt checkpoint: it has no {', '.join(missing)}")
    return ckpt


def load_checkpoint(path: Path) -> LoadedRun:
    """A checkpoint file of a run (``checkpoint.pt`` or a kept ``checkpoint_*.pt``): its Gaussians, config and
    appearance (with its light where it has one), and its scene: the absolute path the run's config.json records
    (an older checkpoint holds the path as it was typed, relative to a folder no longer known), else the
    checkpoint's."""
    ckpt = read_checkpoint(path)
    config = TrainConfig.from_json(ckpt["config"], path)
    look = Look(config.appearance)
    if config.appearance == "sh-lit":
        look.light = DiffuseLight()
        look.light.load_state_dict(ckpt["light"])
    record = recorded_scene(path.parent)
    return LoadedRun(
        Path(record["path"] if record else ckpt["scene_path"]),
        config,
        checkpoint_gaussians(ckpt, path),
        int(ckpt["step"]),
        float(ckpt["train_seconds"]),
        look,
        record,
        None if ckpt.get("touch_points") is None else np.asarray(ckpt["touch_points"]),
    )


def recorded_scene(run_dir: Path) -> dict | None:
    """The :func:`scene_record` a run's config.json holds, None where it has none (a run from before scenes were
    recorded, or an unreadable config.json: the checkpoint's own record stands)."""
    try:
        scene = read_json(run_dir / "config.json").get("scene")
    except ConfigError:
        return None
    return scene if isinstance(scene, dict) and isinstance(scene.get("path"), str) else None


def run_scene(run: LoadedRun):
    """The scene ``run`` was trained on (a ``Scene``); a ConfigError naming it if its content has changed since
    (another capture in its folder): evaluating or meshing the run on it would score another scene."""
    from tacsplat.datasets import Scene

    scene = Scene.load(run.scene_path)
    if run.scene_record is not None and (what := scene_change(run.scene_record, scene)) is not None:
        raise ConfigError("scene", f"the run cannot be measured on it: {what}; restore it, or train on it anew")
    return scene


def checkpoint_gaussians(ckpt: dict, path: Path) -> Gaussians:
    """The Gaussians of a checkpoint read from ``path``; a SceneFormatError naming it if they are invalid (NaN)."""
    try:
        return Gaussians.from_state_dict(ckpt["gaussians"])
    except InvalidInputError as exc:
        raise SceneFormatError(path, "gaussians", str(exc)) from None


def render_backend(config: TrainConfig, run_dir: Path) -> str:
    """The backend a loaded run renders with here: the one it trained with, or ``auto`` (said in one info line) where
    that is gsplat and this machine cannot run it: a run trained on CUDA evaluates and exports on a CPU machine."""
    from tacsplat.reconstruction.raster.rendering import gsplat_available

    if config.backend != "gsplat" or gsplat_available():
        return config.backend
    log.info("%s: trained with gsplat on CUDA; rendering with the CPU rasterizer here", run_dir)
    return "auto"


def load_run(run_dir: Path) -> LoadedRun:
    """The last checkpoint of a run directory (for evaluation)."""
    return load_checkpoint(run_checkpoint(run_dir))


def write_progress(path: Path, rows: list[dict]) -> None:
    """Write ``progress.csv`` (``PROGRESS_COLUMNS``, one row per dict; a column a row lacks stays empty), replacing
    the old file whole: a full disk leaves the old one (a StorageError naming it)."""
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, PROGRESS_COLUMNS, restval="", extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(path, text.getvalue().encode())


def cut_progress(path: Path, step: int) -> list[dict]:
    """Keep the rows of ``progress.csv`` up to ``step`` (a resumed checkpoint's): later ones are redone. The file
    is rewritten with today's columns, each kept row's values under their own names (a column an older version
    did not write stays empty; such a version summed the albedo smoothness into ``smoothness``); returns the rows
    kept."""
    rows = []
    if path.is_file():
        with path.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
    kept = [r for r in rows if (r.get("iteration") or "").isdigit() and int(r["iteration"]) <= step]
    write_progress(path, kept)
    return kept


def read_progress(path: Path) -> dict[str, np.ndarray]:
    """The columns of a ``progress.csv`` as float arrays (a column an older run lacks is NaN)."""
    with Path(path).open() as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r.get(k) or "nan") for r in rows]) for k in PROGRESS_COLUMNS}


def draw_error_vs_time(ax_cd, ax_psnr, curves: dict[str, dict[str, np.ndarray]]) -> None:
    """Held-out CD and PSNR against run time (seconds excluding evaluation) on two matplotlib axes, one line per
    ``curves[label]`` (a :func:`read_progress` result)."""
    for ax, key, ylabel in ((ax_cd, "cd", "Chamfer distance [x GT radius]"), (ax_psnr, "psnr", "held-out PSNR [dB]")):
        for label, data in curves.items():
            ax.plot(data["seconds"], data[key], "o-", ms=3, label=label)
        ax.set_ylabel(ylabel)
        ax.set_xlabel("run time [s] (evaluation excluded)")
        ax.grid(alpha=0.3)


def plot_error_vs_time(progress_path: Path, png_path: Path) -> None:
    """A run's ``error_vs_time.png``: geometry error (CD) and image error (PSNR) against run time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_cd, ax_psnr) = plt.subplots(1, 2, figsize=(10, 4))
    draw_error_vs_time(ax_cd, ax_psnr, {"this run": read_progress(progress_path)})
    ax_cd.set_title("geometry error")
    ax_psnr.set_title("image error")
    fig.tight_layout()
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=100)
    plt.close(fig)
    atomic_write(png_path, png.getvalue())


def read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError("config", f"unreadable: {exc}", path) from None
    if not isinstance(data, dict):
        raise ConfigError("config", "expected a JSON object", path)
    return data


def scene_record(scene) -> dict:
    """What a run records of its scene in ``config.json``: its absolute ``path`` and ``sha256``, a hash of what
    training reads (``transforms.json`` and ``touches.json`` byte for byte, and the name and size of every image,
    mask and touch file they name): a scene moved elsewhere keeps its hash, another or a changed scene has its
    own."""
    root = Path(scene.path)
    digest = hashlib.sha256()
    for name in ("transforms.json", "touches.json"):
        index = root / name
        digest.update(name.encode() + b"\0" + (index.read_bytes() if index.is_file() else b"") + b"\0")
    names = {f.file_path for f in scene.frames} | {f.mask_path for f in scene.frames if f.mask_path}
    for name in sorted(names | {t.depth_file for t in scene.touches}):
        size = (root / name).stat().st_size if (root / name).is_file() else -1
        digest.update(f"{name}\0{size}\0".encode())
    return {"path": str(root.resolve()), "sha256": digest.hexdigest()}


def write_run_config(out: Path, config: TrainConfig, scene: dict) -> None:
    """Write ``config.json``: the run's settings and its :func:`scene_record` (``scene``); not rewritten when
    unchanged."""
    path = out / "config.json"
    text = json.dumps({**config.to_json(), "scene": scene}, indent=2)
    if not (path.is_file() and path.read_text() == text):
        atomic_write(path, text.encode())


def read_run_config(out: Path) -> tuple[TrainConfig, dict | None]:
    """The settings a resume of a run continues with and its :func:`scene_record` (None for a run from before scenes
    were recorded); a ConfigError for a run that trained with a removed loss (:meth:`TrainConfig.from_json`)."""
    path = out / "config.json"
    data = read_json(path)
    scene = data.get("scene")
    return TrainConfig.from_json(data, path, resuming=True), scene if isinstance(scene, dict) else None


def scene_change(recorded: dict, scene) -> str | None:
    """How ``scene`` differs from the one a run recorded (``recorded``: its :func:`scene_record`), as a phrase for a
    message; None for the same content, wherever it lies now (a scene moved)."""
    now = scene_record(scene)
    then_path, then_content = recorded.get("path"), str(recorded.get("sha256"))
    if then_content == now["sha256"]:
        return None
    if then_path == now["path"]:
        return (
            f"its scene {then_path} has changed since (content {then_content[:12]} then, {now['sha256'][:12]} now: "
            "other frames, poses, images or touches)"
        )
    given = f"{now['path']} (content {now['sha256'][:12]})"
    return f"it was trained on the scene {then_path} (content {then_content[:12]}), not on {given}"


def check_resumed_scene(out: Path, recorded: dict | None, scene) -> None:
    """Refuse to resume the run in ``out`` on another scene than the one it recorded (or on that scene changed):
    a ConfigError on ``--resume`` naming both. The same content at another path (a scene moved) resumes."""
    if recorded is None:
        return  # a run from before scenes were recorded: nothing to compare
    if (what := scene_change(recorded, scene)) is None:
        if recorded.get("path") != str(Path(scene.path).resolve()):
            log.info(
                "%s: its scene moved from %s to %s (same content): resuming", out, recorded.get("path"), scene.path
            )
        return
    raise ConfigError(
        "--resume",
        f"{out} cannot continue on this scene: {what}; resume it with the scene it was "
        "trained on, or train this one into a new --out",
    )


def check_run_folder(out: Path, resume: bool, overwrite: bool, locked: bool) -> None:
    """Refuse an ``--out`` that is neither new, empty, nor (with ``resume``/``overwrite``) an earlier run.

    Before the lock (``locked=False``) only what no other job can change is
    refused (a folder of someone else's files, a resume of no run), so that no
    folder or lock file is made for nothing; the rest is decided under the lock, where a resume of a run without
    a checkpoint (it stopped or failed before its first) is refused as evaluate refuses it (:func:`run_checkpoint`):
    its recorded settings would train it again from step 0, and a run that failed would fail again.
    """
    from tacsplat.datasets.outputs import LOCK_NAME

    entries = sorted(p.name for p in out.iterdir() if p.name != LOCK_NAME) if out.is_dir() else []
    is_run = is_run_folder(out)
    if entries and not is_run:
        shown = ", ".join(entries[:5]) + (f" and {len(entries) - 5} more" if len(entries) > 5 else "")
        raise ConfigError(
            "--out", f"{out} holds files that are not a reconstruction run ({shown}); choose a new or empty folder"
        )
    if resume and not is_run:
        raise ConfigError("--resume", f"{out} holds no run (no config.json or checkpoint.pt): nothing to resume")
    if locked and resume:
        run_checkpoint(out)
    if locked and is_run and not (resume or overwrite):
        advice = "pass --resume to continue it or --overwrite to replace it"
        if not (out / "checkpoint.pt").is_file():  # (it stopped or failed before its first: nothing to resume)
            advice = "it has no checkpoint to resume: pass --overwrite to replace it"
        raise ConfigError("--out", f"{out} already holds a reconstruction run; {advice}")


def remove_meshes(out: Path) -> None:
    """Delete the meshes ``export mesh`` wrote into a run (MESH_FILES, and their temporary files): made of Gaussians
    that are being replaced, evaluate would report their metrics and the viewer show them as the run's."""
    for name in MESH_FILES.values():
        (out / name).unlink(missing_ok=True)
        default_temp(out / name).unlink(missing_ok=True)


def remove_run_files(out: Path) -> None:
    """Delete an earlier run's files (RUN_FILES, its meshes and renders/view_*.png); anything else stays."""
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)
    remove_meshes(out)
    renders = out / RENDERS
    if renders.is_dir():
        for p in renders.iterdir():
            if RENDER_FILE.fullmatch(p.name) and p.is_file():
                p.unlink()
        if not any(renders.iterdir()):
            renders.rmdir()
