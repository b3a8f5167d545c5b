"""``tacsplat inspect``: a summary of a scene directory and every problem found in it."""

from __future__ import annotations

import itertools
import json
from collections import Counter
from pathlib import Path

import numpy as np

from tacsplat.errors import SceneFormatError, UsageError
from tacsplat.files import atomic_write, check_out_folder

from .reader import check_scene, not_a_scene
from .records import MOTION_PHASES, SPARSE_POINTS, SPLITS, sensor_to_json
from .writer import JOURNAL


def summarise(path) -> dict:
    """Frames per split, touches per grasp and finger, bounds, ground truth, annotation keys and every problem
    (those of :func:`check_scene`: what it lists, ``Scene.load`` raises), as one JSON-able dict. A SceneFormatError
    when ``path`` is no scene at all (:func:`not_a_scene`: missing, a file, a reconstruction run, ...)."""
    path = Path(path)
    if why := not_a_scene(path):
        raise SceneFormatError(path, None, why)
    scene, errors = check_scene(path)
    frames, touches = (scene.frames, scene.touches) if scene else ([], [])
    motions = scene.hand_motions() if scene else []
    durations = [float(m.t[-1] - m.t[0]) for m in motions]
    lo, hi = _bounds(scene)
    return {
        "path": str(path),
        "source": scene and scene.meta.source,
        "object": scene and scene.meta.object,
        "frames": {s: sum(f.split == s for f in frames) for s in SPLITS},
        "image_sizes": sorted({f"{f.intrinsics.width}x{f.intrinsics.height}" for f in frames}),
        "touches": len(touches),
        "touches_in_contact": sum(t.in_contact for t in touches),
        "grasps": len({t.grasp for t in touches}),
        "touches_per_grasp": {str(g): n for g, n in sorted(Counter(t.grasp for t in touches).items())},
        "touches_per_finger": dict(sorted(Counter(t.finger for t in touches).items())),
        "hand_motion": {
            "grasps": len(motions),
            "samples": int(sum(len(m.t) for m in motions)),
            "joints": len(motions[0].joint_names),
            "links": len(motions[0].link_names),
            "seconds_per_grasp": {"min": min(durations), "median": float(np.median(durations)), "max": max(durations)},
            "effort_unit": motions[0].effort_unit,
            "peak_effort": float(np.nanmax([np.nanmax(np.abs(m.effort), initial=0.0) for m in motions])),
            # grasps that slid their pads (in scenes captured before the slide was removed)
            "slides": sum(bool((m.phase == MOTION_PHASES.index("slide")).any()) for m in motions),
        }
        if motions
        else None,
        "sensor": sensor_to_json(scene and scene.sensor),
        "bounds": None if lo is None else {"lo": lo.tolist(), "hi": hi.tolist()},
        "gt": {
            "mesh": scene and scene.gt_mesh_file,
            "points": scene and scene.gt_points_file,
            "depth_maps": len(scene.gt_depth_files) if scene else 0,
        },
        "sparse_points": len(scene.sparse_points()[0]) if scene and scene.sparse_points_file else 0,
        "annotations": sorted(scene.annotations) if scene else [],
        "journal": (path / JOURNAL).is_file(),
        "problems": [str(e) for e in errors],
    }


def _bounds(scene) -> tuple[np.ndarray, np.ndarray] | tuple[None, None]:
    """The scene's bounds, or (None, None) where it has none (neither frames nor contact points)."""
    if scene is None:
        return None, None
    try:
        return scene.bounds()
    except SceneFormatError:  # no frames nor contact points (check_scene left out the touches it cannot read)
        return None, None


def format_summary(summary: dict) -> str:
    """The readable text form of :func:`summarise`."""
    lines = [f"scene     {summary['path']}"]
    if summary["source"] is not None:
        lines.append(f"object    {summary['object']} (source: {summary['source']})")
    frames = summary["frames"]
    sizes = ", ".join(summary["image_sizes"]) or "-"
    lines.append(
        f"frames    {sum(frames.values())}: " + ", ".join(f"{n} {s}" for s, n in frames.items()) + f"  [{sizes}]"
    )
    lines.append(
        f"touches   {summary['touches']} ({summary['touches_in_contact']} in contact) in {summary['grasps']} grasps"
    )
    if summary["touches_per_grasp"]:
        lines.append("  per grasp   " + ", ".join(f"{g}: {n}" for g, n in summary["touches_per_grasp"].items()))
        lines.append("  per finger  " + ", ".join(f"{f}: {n}" for f, n in summary["touches_per_finger"].items()))
    motion = summary["hand_motion"]
    if motion is not None:
        d = motion["seconds_per_grasp"]
        lines.append(
            f"hand      {motion['grasps']} grasps recorded ({motion['samples']} samples of {motion['joints']} joints, "
            f"{motion['links']} links): {d['min']:.2f} to {d['max']:.2f} s per grasp (median {d['median']:.2f}), "
            f"peak effort {motion['peak_effort']:.3g} {motion['effort_unit']}"
            + (f"; {motion['slides']} slid their pads along the surface" if motion["slides"] else "")
        )
    if (s := summary["sensor"]) is None:
        lines.append("sensor    none")
    else:
        mm = f"{s['pixel_size_m'] * 1e3:.3g} mm/px, gel {s['gel_thickness_m'] * 1e3:.3g} mm"
        lines.append(f"sensor    {s['name']} {s['width_px']}x{s['height_px']} px, {mm}")
    if summary["bounds"] is not None:
        lo, hi = np.asarray(summary["bounds"]["lo"]), np.asarray(summary["bounds"]["hi"])
        fmt = lambda v: "(" + ", ".join(f"{x:+.3f}" for x in v) + ")"  # noqa: E731
        lines.append(f"bounds    {fmt(lo)} .. {fmt(hi)} m  (size {fmt(hi - lo)})")
    gt = summary["gt"]
    points = f", points: {gt['points']}" if gt["points"] else ""
    lines.append(f"gt        mesh: {gt['mesh'] or 'none'}{points}, depth maps: {gt['depth_maps']}")
    if summary["sparse_points"]:
        lines.append(f"points    {summary['sparse_points']} sparse points ({SPARSE_POINTS}), where training starts")
    if summary["annotations"]:
        lines.append("annotated " + ", ".join(summary["annotations"]))
    problems = summary["problems"]
    lines.append(f"problems  {len(problems) or 'none'}")
    lines.extend(f"  - {p}" for p in problems)
    return "\n".join(lines)


def plot_scene(path, png_path) -> Path:
    """A picture of the capture: camera centres and viewing directions per split, contact points, bounds; saved
    (atomically, in the format of its suffix) as ``png_path``, making its folders."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    scene, _ = check_scene(path)
    lo, hi = _bounds(scene)
    if lo is None:  # (touches without contact points alone: nothing to place or frame)
        raise SceneFormatError(path, None, "nothing to plot: no readable frames or contact points")
    fig = Figure(figsize=(7, 6))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    arrow = 0.25 * float(np.max(hi - lo))
    for split, color in zip(SPLITS, ("tab:blue", "tab:orange")):
        if not (frames := scene.split(split)):
            continue
        c = np.array([f.T_world_cam[:3, 3] for f in frames])
        z = np.array([f.T_world_cam[:3, 2] for f in frames])
        ax.scatter(*c.T, color=color, s=12, label=f"{split} cameras ({len(frames)})")
        ax.quiver(*c.T, *(arrow * z).T, color=color, linewidth=0.6)
    if len(points := scene.touch_points()):
        ax.scatter(*points.T, color="tab:red", s=1, label=f"contact points ({len(scene.touches)} touches)")
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    for a, b in itertools.combinations(corners, 2):
        if np.count_nonzero(a != b) == 1:  # an edge of the box
            ax.plot(*np.stack([a, b]).T, color="grey", linewidth=0.5)
    shown = np.array([f.T_world_cam[:3, 3] for f in scene.frames] + [lo, hi])
    centre = (shown.min(axis=0) + shown.max(axis=0)) / 2
    half = max(float(np.max(shown.max(axis=0) - shown.min(axis=0))) / 2, 1e-3) * 1.1
    ax.set(**{f"{axis}lim": (c - half, c + half) for axis, c in zip("xyz", centre)})  # equal axes: the real shape
    ax.set_box_aspect((1, 1, 1))
    ax.set(xlabel="x [m]", ylabel="y [m]", zlabel="z [m]")
    ax.set_title(f"{scene.meta.object} ({scene.meta.source}): cameras, touches and bounds")
    ax.legend(loc="upper left", fontsize="small")
    png_path = Path(png_path)
    png_path.parent.mkdir(parents=True, exist_ok=True)  # (the folders a new path names: made only now, to write)
    atomic_write(png_path, lambda f: fig.savefig(f, format=picture_format(png_path), dpi=100))
    return png_path


def picture_format(path) -> str:
    """The picture format :func:`plot_scene` writes to ``path``: its suffix's (png without one)."""
    return Path(path).suffix.lstrip(".").lower() or "png"


def plot_formats() -> list[str]:
    """The picture formats :func:`plot_scene` can write (matplotlib's)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    return sorted(FigureCanvasAgg(Figure()).get_supported_filetypes())


def check_plot_out(path, plot, overwrite: bool = False) -> None:
    """Refuse (a UsageError on ``--plot``) a picture file without a suffix matplotlib writes, one inside the scene
    ``path`` (its captured data) whatever ``overwrite`` says, and an existing file unless ``overwrite``."""
    plot, formats = Path(plot), plot_formats()
    if not plot.suffix or picture_format(plot) not in formats:
        names = ", ".join("." + f for f in formats)
        raise UsageError("--plot", f"cannot save a picture as {plot.suffix or plot.name}; use one of {names}")
    target, scene = plot.resolve(), Path(path).resolve()
    if target.is_relative_to(scene):  # (the scene folder itself too)
        raise UsageError("--plot", f"{plot} lies in the scene {path}, whose files are not to be replaced")
    if target.exists() and not overwrite:
        raise UsageError("--plot", f"{plot} exists; pass --overwrite to replace it")


def run_inspect(path, as_json: bool = False, plot: str | Path | None = None, overwrite: bool = False) -> int:
    """Print the summary (text or one JSON object), optionally save :func:`plot_scene`; exit code 1 on problems.
    The picture file is refused as :func:`check_plot_out` says, and its folder as :func:`check_out_folder` does,
    before anything is printed."""
    if plot is not None:
        check_plot_out(path, plot, overwrite)
        check_out_folder("--plot", plot)
    summary = summarise(path)
    print(json.dumps(summary, indent=1) if as_json else format_summary(summary))
    if plot is not None:
        plot_scene(path, plot)
    return 1 if summary["problems"] else 0
