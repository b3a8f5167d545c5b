"""`tacsplat view PATH`: a scene, a reconstruction run or a benchmark report in the browser, on viser.

PATH is one of:

- a scene directory (``transforms.json``): train and test camera frusta with
  their images, the touch points coloured by grasp with each sensor's gel
  frame, the ground-truth mesh when the scene has one and the object's
  bounding sphere, each with a toggle;
- a run directory (``tacsplat reconstruct --out``): its ``splat.ply`` (touch
  Gaussians G_t and camera Gaussians G_c shown or hidden apart), its scene's
  cameras and touches, a slider over its checkpoints when several
  ``checkpoint*.pt`` were kept, the numbers of ``metrics.json``, and a button
  that renders the browser's viewpoint with tacsplat's rasterizer (RGB and
  expected depth) beside the browser's own approximation;
- a benchmark report folder (``tacsplat bench paper --out``): two of its runs
  chosen from drop-downs side by side (default: vanilla 3DGS and the paper's
  method), seen from one viewpoint, with their metrics; the render button
  renders both from that same viewpoint.

The server needs no display; the command prints the URL to open (``--host
0.0.0.0`` serves other machines; otherwise forward the port, e.g. ``ssh -L
8080:localhost:8080``). ``--export FILE.html`` writes the view as one
self-contained HTML page (viser's serialised scene inside its static client)
that opens without Python, and exits; the side panel's controls need the
server and are left out of it.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from tacsplat.errors import ConfigError, TacsplatError, UsageError
from tacsplat.files import atomic_write, check_out_folder
from tacsplat.interrupts import ctrl_c_interrupts

log = logging.getLogger(__name__)

RENDER_WIDTH = 320  # px of a render of the browser's viewpoint (the CPU rasterizer answers in about a second)
SIDE_BY_SIDE_GAP = 0.25  # of the larger object's radius, between the two runs of a report
CAMERA_DISTANCE = 2.5  # initial viewpoint: this many radii from the centre of what is shown


@dataclass
class ViewCommand:
    """look at a scene, a reconstruction run or a benchmark report in the browser (viser)

    Serve PATH to a browser: a scene directory (cameras with their images, touches by grasp with their gel frames,
    ground-truth mesh, bounding sphere), a run directory (its splat, touch or camera Gaussians alone, its scene, its
    kept checkpoints, metrics.json, renders of the browser's viewpoint with tacsplat's rasterizer) or a benchmark
    report folder (two of its runs side by side from one viewpoint). Needs no display: it prints the URL to open
    (use --host 0.0.0.0 or an SSH tunnel from another machine). --export writes the view as one HTML page that opens
    without Python."""

    path: tyro.conf.Positional[Path]
    """a scene directory, a run directory or a benchmark report folder"""
    port: int = 8080
    """port to serve on (the next free one if it is taken)"""
    host: str = "127.0.0.1"
    """address to listen on; 0.0.0.0 lets a browser on another machine connect"""
    export: Annotated[Path | None, tyro.conf.arg(metavar="FILE.html")] = None
    """write a self-contained HTML view that opens without Python (the scene, without the side panel's controls),
    then exit"""
    overwrite: bool = False
    """replace an existing --export file (never one inside PATH or the run's scene)"""


def register(cli) -> None:
    cli.typed("view", ViewCommand, _run)


def _run(args: ViewCommand) -> int:
    import viser  # (first: without the viewer extra nothing else is worth checking)

    if not 0 <= args.port <= 65535:
        raise UsageError("--port", f"must be in [0, 65535], got {args.port}")
    export = args.export
    if export is not None:
        check_export_out(args.path, export, args.overwrite)
        check_out_folder("--export", export)  # a read-only or full folder is refused before the view is built
    else:
        check_host(args.host, args.port)  # (an address this machine lacks: viser would try port after port forever)
    content = load_content(args.path)
    logging.getLogger("websockets").setLevel(logging.WARNING)
    with _viser_quiet():  # viser prints its own banner; ours follows
        server = viser.ViserServer(
            host="127.0.0.1" if export else args.host, port=0 if export else args.port, verbose=False
        )
    try:
        build_view(server, content)
        if export is not None:
            size = write_export(server, export) / 1e6
            print(f"wrote {export} ({size:.1f} MB): open it in a browser, no Python needed")
        else:
            with ctrl_c_interrupts():  # (also where it was started with Ctrl-C ignored)
                port = server.get_port()
                moved = f" (port {args.port} was taken)" if args.port and port != args.port else ""
                print(
                    f"tacsplat view: {content.kind} {args.path} at {server_url(args.host, port)}{moved} "
                    "(Ctrl-C to stop)",
                    flush=True,
                )
                server.sleep_forever()
    except KeyboardInterrupt:  # how a user stops the server
        pass
    finally:
        with _viser_quiet():
            server.stop()
    return 0


def check_export_out(path: Path, export: Path, overwrite: bool = False) -> None:
    """Refuse (a UsageError on ``--export``) a page that is not ``.html``, one inside ``path`` (the scene, run or
    report shown) or inside a run's recorded scene, whatever ``overwrite`` says, and an existing file unless
    ``overwrite``."""
    if export.suffix.lower() != ".html":
        raise UsageError("--export", f"{export} is not an .html file: name the page FILE.html")
    target = export.resolve()
    owners = [path.resolve()]
    from tacsplat.reconstruction.run_dir import recorded_scene

    if record := recorded_scene(path):  # (a run's: its scene's files are refused too)
        owners.append(Path(record["path"]).resolve())
    for owner in owners:
        if target == owner or target.is_relative_to(owner):
            raise UsageError(
                "--export", f"{export} lies in {owner}, whose files are not to be replaced: name a file outside it"
            )
    if target.exists() and not overwrite:
        raise UsageError("--export", f"{export} exists; pass --overwrite to replace it")


def _viser_quiet():
    """Swallow what viser prints on stdout (its banner, 'Server stopped')."""
    import io

    return contextlib.redirect_stdout(io.StringIO())


def server_url(host: str, port: int) -> str:
    """The URL a browser opens (this machine's name when serving every interface; an IPv6 literal bracketed)."""
    import socket

    name = socket.gethostname() if host in ("0.0.0.0", "::", "") else host
    return f"http://{f'[{name}]' if ':' in name else name}:{port}"


def check_host(host: str, port: int) -> None:
    """Refuse (a UsageError on ``--host``) an address that does not resolve or that this machine cannot listen on,
    with the operating system's reason; a port in use is fine (the server takes the next free one)."""
    import errno
    import socket

    try:
        addresses = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        raise UsageError("--host", f"cannot resolve {host!r}: {getattr(exc, 'strerror', None) or exc}") from None
    family, kind, proto, _, address = addresses[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno != errno.EADDRINUSE:
                raise UsageError("--host", f"cannot listen on {host}: {exc.strerror or exc}") from None


# Opened from a file (file://), Chromium gives the page an opaque origin and refuses the workers viser's client
# starts from blob: URLs, among them the one that sorts the splat by depth (unsorted, the back shows through).
# This script, run before the client's, starts such a worker from a data: URL of the same source instead.
FILE_PAGE_WORKERS = """<script>
if (location.protocol === "file:") (function () {
  var NativeBlob = Blob, NativeWorker = Worker, createURL = URL.createObjectURL, parts = new WeakMap(), sources = {};
  window.Blob = function (content, options) {
    var blob = new NativeBlob(content, options);
    parts.set(blob, content);
    return blob;
  };
  window.Blob.prototype = NativeBlob.prototype;
  URL.createObjectURL = function (object) {
    var url = createURL.call(URL, object), content = parts.get(object);
    var text = function (p) {
      return typeof p === "string" ? p : ArrayBuffer.isView(p) ? new TextDecoder().decode(p) : null;
    };
    if (Array.isArray(content) && content.every(function (p) { return text(p) !== null; }))
      sources[url] = content.map(text);
    return url;
  };
  window.Worker = function (url, options) {
    var source = sources[String(url)];
    if (source) url = "data:text/javascript;charset=utf-8," + encodeURIComponent(source.join(""));
    return new NativeWorker(url, options);
  };
})();
</script>"""


def write_export(server, path: Path) -> int:
    """Write the server's scene as a self-contained HTML page (replacing ``path`` atomically, making its folders; a
    full or read-only disk is a StorageError naming it); its size in bytes."""
    html = server.get_scene_serializer().as_html().replace("<head>", "<head>" + FILE_PAGE_WORKERS, 1).encode()
    Path(path).parent.mkdir(parents=True, exist_ok=True)  # (the folders a new path names: made only now, to write)
    atomic_write(path, html)
    return len(html)


# ---------------------------------------------------------------------------------------------- reading PATH


@dataclass
class RunData:
    """A run directory's Gaussians (``splat.ply``, else its last checkpoint), metrics and scene."""

    path: Path
    label: str
    gaussians: object  # tacsplat.reconstruction.gaussians.Gaussians
    metrics: dict
    scene: object | None  # tacsplat.datasets.Scene, or None when the scene is not found
    checkpoints: list[Path] = field(default_factory=list)  # kept checkpoint*.pt, oldest first
    sphere: tuple[np.ndarray, float] | None = None  # (centre, radius) of its object, once computed


@dataclass
class Content:
    kind: str  # "scene", "run" or "report"
    path: Path
    scene: object | None = None  # kind "scene"
    run: RunData | None = None  # kind "run"
    report_runs: dict[str, Path] = field(default_factory=dict)  # kind "report": label -> run directory
    pair: tuple[RunData, RunData | None] | None = None  # kind "report": the two runs shown first


def load_content(path: Path) -> Content:
    """Read what ``path`` holds, a scene, a run or a report (every file the first view shows), raising the first
    problem (a ConfigError naming ``path`` when it is none of them)."""
    from tacsplat.datasets import Scene
    from tacsplat.reconstruction.run_dir import is_run_folder

    if not path.exists():
        raise ConfigError("PATH", f"{path} does not exist")
    if (path / "transforms.json").is_file():  # (False for a file: it holds nothing)
        return Content("scene", path, scene=Scene.load(path))
    if (path / "splat.ply").is_file() or is_run_folder(path):
        return Content("run", path, run=read_run(path, path.name))
    if not (path / "runs").is_dir():
        raise ConfigError(
            "PATH",
            f"{path} is neither a scene directory (with transforms.json), a run directory (with "
            "splat.ply, from tacsplat reconstruct) nor a benchmark report folder (with runs/, from tacsplat "
            "bench paper)",
        )
    if not (runs := report_runs(path)):
        raise ConfigError("PATH", f"{path} has no finished run (no runs/<object>/<setting>/<method>/splat.ply)")
    left, right = default_pair(runs)
    pair = (read_run(runs[left], left, path), read_run(runs[right], right, path) if right else None)
    return Content("report", path, report_runs=runs, pair=pair)


def read_run(path: Path, label: str, report: Path | None = None) -> RunData:
    """A run directory's splat, metrics and scene (searched for in ``report`` too)."""
    from tacsplat.reconstruction.baking import bake_appearance
    from tacsplat.reconstruction.ply import load_ply
    from tacsplat.reconstruction.run_dir import load_run, read_checkpoint, read_json, recorded_scene

    metrics = read_json(path / "metrics.json") if (path / "metrics.json").is_file() else {}
    if (path / "splat.ply").is_file():
        # config.json's absolute path, else metrics.json's (as typed, relative to where the run was made)
        record = recorded_scene(path)
        gaussians, scene_path = load_ply(path / "splat.ply"), record["path"] if record else metrics.get("scene")
    else:  # a run stopped before its splat.ply: its last checkpoint, coloured as its splat.ply will be
        loaded = load_run(path)
        gaussians, scene_path = bake_appearance(loaded.gaussians, loaded.look), loaded.scene_path
    if scene_path is None and (path / "checkpoint.pt").is_file():
        scene_path = read_checkpoint(path / "checkpoint.pt")["scene_path"]
    return RunData(path, label, gaussians, metrics, find_scene(scene_path, path, report), kept_checkpoints(path))


def find_scene(recorded, run: Path, report: Path | None = None):
    """The scene a run was trained on: its recorded path as it is, relative to the run, or (runs of a report)
    its part from ``scenes/`` on inside the report; None (with a warning naming the places tried) when none of
    them is a scene."""
    from tacsplat.datasets import Scene

    if recorded is None:
        return None
    recorded = Path(recorded)
    candidates = [recorded, run / recorded]  # (the same path twice when it is absolute)
    if report is not None and "scenes" in recorded.parts:
        candidates.append(report.joinpath(*recorded.parts[recorded.parts.index("scenes") :]))
    for candidate in candidates:
        if (candidate / "transforms.json").is_file():
            return Scene.load(candidate)
    tried = ", ".join(dict.fromkeys(str(c.absolute()) for c in candidates))
    log.warning("%s: its scene %s is not found (tried %s); showing the splat alone", run, recorded, tried)
    return None


def kept_checkpoints(run: Path) -> list[Path]:
    """The run's ``checkpoint*.pt`` files, oldest first."""
    return sorted(run.glob("checkpoint*.pt"), key=lambda p: (p.stat().st_mtime, p.name))


def report_runs(report: Path) -> dict[str, Path]:
    """A report's finished runs (``runs/<object>/<setting>/<method>-s<seed>`` with a ``splat.ply``), by label."""
    runs = report / "runs"
    return {p.parent.relative_to(runs).as_posix(): p.parent for p in sorted(runs.glob("*/*/*/splat.ply"))}


def default_pair(runs: dict[str, Path]) -> tuple[str, str | None]:
    """The two runs shown first: vanilla 3DGS and the paper's method of one object, setting and seed when the
    report has them, else its first two runs (or its only one)."""
    labels = list(runs)
    for label in labels:
        head, _, name = label.rpartition("/")
        if name.startswith("3dgs-"):
            paper = f"{head}/paper-{name.removeprefix('3dgs-')}"
            if paper in runs:
                return label, paper
    return labels[0], labels[1] if len(labels) > 1 else None


# ---------------------------------------------------------------------------------------------- views


@dataclass
class View:
    """What :func:`build_view` made: the splat slots, the side panel's controls by label, the scene's nodes."""

    slots: list = field(default_factory=list)  # SplatSlot
    controls: dict[str, object] = field(default_factory=dict)
    scene_nodes: object | None = None  # viewer_scene.SceneNodes
    mesh_node: object | None = None  # the run's exported mesh (RUN/mesh.ply), when it has one
    warned: set = field(default_factory=set)  # the splat files warned about (viewer_splat.add_splat): once each


def build_view(server, content: Content) -> View:
    """Draw ``content`` in ``server``'s scene and add its controls to the side panel."""
    server.gui.configure_theme(control_width="large", show_share_button=False)
    view = View()
    {"scene": _scene_view, "run": _run_view, "report": _report_view}[content.kind](server, content, view)
    return view


def initial_viewpoint(
    centre: np.ndarray, extent: float, cameras: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(position, look-at point) of the first view: ``CAMERA_DISTANCE`` x ``extent`` from ``centre``, 27 degrees
    above it (z up), in front (-y) or, given the scene's camera positions ``cameras`` [N, 3], from the azimuth
    farthest from all of them (so that no frustum stands before the object)."""
    azimuths = np.radians(np.arange(-90, 270, 15))  # [A], -90: the -y side
    directions = np.stack([np.cos(azimuths), np.sin(azimuths), np.full_like(azimuths, 0.5)], axis=1) / np.sqrt(1.25)
    best = 0
    if cameras is not None and len(cameras):
        towards = np.asarray(cameras, dtype=np.float64) - centre  # [N, 3]
        towards /= np.maximum(np.linalg.norm(towards, axis=1, keepdims=True), 1e-12)
        best = int(np.argmin((directions @ towards.T).max(axis=1)))  # the largest angle to the nearest camera
    return np.asarray(centre) + CAMERA_DISTANCE * extent * directions[best], np.asarray(centre, dtype=np.float64)


def _look_from(server, centre: np.ndarray, extent: float, scene=None) -> None:
    cameras = None if scene is None else np.array([f.T_world_cam[:3, 3] for f in scene.frames])
    position, look_at = initial_viewpoint(centre, extent, cameras)
    camera = server.initial_camera
    camera.position, camera.look_at, camera.up = tuple(position), tuple(look_at), (0.0, 0.0, 1.0)
    camera.near, camera.far = 0.01 * extent, 1000.0 * extent


def _add_scene(server, view: View, name: str, scene, hidden: tuple[str, ...] = ()) -> None:
    """``scene``'s nodes under ``name``, its summary, and a checkbox per group of its nodes (cameras, touches,
    mesh, sphere); the groups in ``hidden`` are hidden at first."""
    from tacsplat.apps.viewer_scene import add_scene

    nodes = view.scene_nodes = add_scene(server.scene, name, scene, "mesh" not in hidden, "sphere" not in hidden)
    train, test = len(scene.split("train")), len(scene.split("test"))
    server.gui.add_markdown(
        f"**{scene.meta.object}** ({scene.meta.source}): {train} train and {test} test views, "
        f"{len(scene.touches)} touches in {scene.num_grasps} grasps"
    )
    labels = {
        "cameras": "camera frusta",
        "touches": "touches (by grasp) and gel frames",
        "mesh": "ground-truth mesh",
        "sphere": f"bounding sphere ({nodes.sphere.source})",
    }
    for group, members in nodes.groups.items():
        if members:
            _visibility_checkbox(server, view, labels[group], members, group not in hidden)


def _visibility_checkbox(server, view: View, label: str, nodes: list, initial: bool, hint: str | None = None) -> None:
    """A checkbox ``label`` that shows or hides ``nodes``."""
    box = view.controls[label] = server.gui.add_checkbox(label, initial, hint=hint)

    @box.on_update
    def _(event) -> None:
        for node in nodes:
            node.visible = event.target.value


def _scene_view(server, content: Content, view: View) -> None:
    _add_scene(server, view, "/scene", content.scene)
    _look_from(server, view.scene_nodes.sphere.centre, view.scene_nodes.sphere.radius, content.scene)


class SplatSlot:
    """Where one run's splat is shown: a scene node placed so that the run's object centre lands at ``position``;
    its Gaussians can be replaced (another checkpoint, another run) and their sets hidden. A file's Gaussians
    that cannot be drawn as they are get one warning, not one each time it is shown: ``warned``, the files warned
    about, is shared by a view's slots."""

    def __init__(self, server, name: str, position=(0.0, 0.0, 0.0), warned: set | None = None):
        self.server, self.name, self.position = server, name, np.asarray(position, dtype=np.float64)
        self.warned = set() if warned is None else warned
        self.run: RunData | None = None
        self.gaussians = None
        self.offset = np.zeros(3)  # world position of the run's own origin
        self.nodes: dict[str, object] = {}  # viewer_splat.SPLAT_SETS name -> splat node
        self.sets: tuple[str, ...] | None = None  # the shown sets; None: all
        self.lock = threading.Lock()

    def show(self, run: RunData | None, gaussians=None, source: Path | None = None) -> None:
        """Show ``run`` (its ``gaussians`` read from the file ``source``, default the run's own); None empties the
        slot."""
        from tacsplat.apps.viewer_splat import add_splat

        with self.lock:
            for node in self.nodes.values():
                node.remove()
            self.nodes, self.run, self.gaussians = {}, run, None
            if run is None:
                return
            self.gaussians = run.gaussians if gaussians is None else gaussians
            self.offset = self.position - object_sphere(run)[0]
            self.server.scene.add_frame(self.name, show_axes=False, position=self.offset)
            if source is None:  # (a run without its splat.ply is shown from its last checkpoint)
                source = run.path / "splat.ply" if (run.path / "splat.ply").is_file() else run.path
            self.nodes = add_splat(self.server.scene, self.name, self.gaussians, source, self.warned)
            self.show_sets(self.sets)

    def show_sets(self, sets: tuple[str, ...] | None) -> None:
        self.sets = sets
        for name, node in self.nodes.items():
            node.visible = sets is None or name in sets

    def shown_gaussians(self):
        """The Gaussians of the shown sets, or None."""
        import torch

        from tacsplat.apps.viewer_splat import SPLAT_SETS
        from tacsplat.reconstruction.gaussians import Gaussians

        g = self.gaussians
        if g is None or self.sets is None:
            return g
        flags = torch.tensor([SPLAT_SETS[name] for name in self.sets])
        keep = (g.from_touch.cpu()[:, None] == flags).any(dim=1)
        return Gaussians({k: v.detach()[keep] for k, v in g.params.items()}, g.from_touch[keep], g.sh_degree)


def object_sphere(run: RunData) -> tuple[np.ndarray, float]:
    """(centre, radius) of a run's object: its scene's bounding sphere, else the sphere around the central 95 % of
    its Gaussians, less those far from the rest (a unit sphere at the origin when it has none)."""
    from tacsplat.apps.viewer_scene import bounding_sphere, load_mesh
    from tacsplat.apps.viewer_splat import far_centres

    if run.sphere is None:
        if run.scene is not None:
            sphere = bounding_sphere(run.scene, load_mesh(run.scene))
            run.sphere = (sphere.centre, sphere.radius)
        else:
            means = run.gaussians.means.detach().cpu().double()
            means = means[~far_centres(means)].numpy()  # (a foreign splat's centre at 1e30 m would frame nothing)
            centre = np.median(means, axis=0) if len(means) else np.zeros(3)  # (no Gaussians: the origin)
            radius = float(np.percentile(np.linalg.norm(means - centre, axis=1), 95)) if len(means) else 0.0
            run.sphere = (centre, radius if radius > 0 else 1.0)
    return run.sphere


def _gaussian_sets(server, view: View) -> None:
    from tacsplat.apps.viewer_splat import GAUSSIAN_SETS

    choice = view.controls["Gaussians"] = server.gui.add_dropdown(
        "Gaussians",
        tuple(GAUSSIAN_SETS),
        initial_value="all",
        hint="G_t: the Gaussians started on touch points (and their clones and splits); G_c: the others",
    )

    @choice.on_update
    def _(event) -> None:
        for slot in view.slots:
            slot.show_sets(GAUSSIAN_SETS[event.target.value])


def _exported_mesh(server, view: View, run: RunData) -> None:
    """The run's ``mesh.ply`` (``tacsplat export mesh``), with its vertex colours, behind a checkbox; nothing
    without one."""
    path = run.path / "mesh.ply"
    if not path.is_file():
        return
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh")
        if not len(mesh.vertices) or not len(mesh.faces):
            raise ValueError("no vertices or faces")
    except Exception as exc:  # trimesh raises many types for a damaged file: the rest is still shown
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        log.warning("%s: unreadable mesh (%s); showing the run without it (export mesh writes it anew)", path, reason)
        return
    view.mesh_node = server.scene.add_mesh_trimesh("/run/mesh", mesh, visible=False)
    hint = "RUN/mesh.ply, written by tacsplat export mesh"
    _visibility_checkbox(server, view, "exported mesh", [view.mesh_node], False, hint)


def _checkpoint_slider(server, view: View, run: RunData) -> None:
    """A slider over the run's kept checkpoints (only when there are several)."""
    from tacsplat.reconstruction.baking import bake_appearance
    from tacsplat.reconstruction.run_dir import load_checkpoint

    if len(run.checkpoints) < 2:
        return
    names = [p.name for p in run.checkpoints]
    slider = view.controls["checkpoint"] = server.gui.add_slider(
        "checkpoint", 0, len(names) - 1, 1, len(names) - 1, hint="the run's checkpoint*.pt files, oldest first"
    )
    shown = view.controls["checkpoint shown"] = server.gui.add_markdown(f"showing splat.ply (newest: {names[-1]})")
    baked: dict[Path, tuple] = {}  # checkpoint -> (its Gaussians as splat.ply would hold them, its step): bake once

    @slider.on_update
    def _(event) -> None:
        path = run.checkpoints[event.target.value]
        if path not in baked:
            try:
                loaded = load_checkpoint(path)
            except TacsplatError as exc:
                shown.content = f"**cannot show {path.name}**: {exc}"
                return
            baked[path] = bake_appearance(loaded.gaussians, loaded.look), loaded.step
        gaussians, step = baked[path]
        view.slots[0].show(run, gaussians, path)
        shown.content = f"showing {path.name}: step {step}, {len(gaussians)} Gaussians"


def metrics_markdown(columns: dict[str, dict]) -> str:
    """A markdown table of the scalar entries of one or more ``metrics.json`` (one column each)."""
    from tacsplat.apps.report import md_table

    scalar = (int, float, str)
    keys = dict.fromkeys(k for m in columns.values() for k, v in m.items() if isinstance(v, scalar) and k != "scene")
    if not keys:
        return "no metrics.json"

    def cell(value) -> str:
        return f"{value:.4g}" if isinstance(value, float) else "" if value is None else str(value)

    rows = [[k, *(cell(m.get(k)) for m in columns.values())] for k in keys]
    return "\n".join(md_table(["", *columns], rows, "l" * (len(columns) + 1)))


def render_rows(
    slots: list[SplatSlot], wxyz, position, fov_y: float, width: int, height: int, browser: np.ndarray | None = None
) -> np.ndarray | None:
    """One row per shown run of a browser camera's view: the browser's own picture (when given, uint8
    [H, W, 3]), tacsplat's RGB render and its expected depth; None when no run is shown."""
    from tacsplat.apps.viewer_splat import camera_matrices, depth_picture, render_viewpoint

    rows = []
    for slot in slots:
        gaussians = slot.shown_gaussians()
        if gaussians is None:
            continue
        T_world_cam, K = camera_matrices(wxyz, np.asarray(position) - slot.offset, fov_y, width, height)
        rgb, depth, alpha = render_viewpoint(gaussians, T_world_cam, K, width, height)
        panels = [] if browser is None else [browser[..., :3]]
        rows.append(
            np.concatenate([*panels, (rgb * 255).round().astype(np.uint8), depth_picture(depth, alpha)], axis=1)
        )
    return np.concatenate(rows, axis=0) if rows else None


def _render_button(server, view: View) -> None:
    """A button that renders the clicking browser's viewpoint with tacsplat's rasterizer beside the browser's
    own picture of it."""
    button = view.controls["render"] = server.gui.add_button("Render this view with tacsplat's rasterizer")
    status = server.gui.add_markdown("browser | tacsplat RGB | tacsplat expected depth, from the browser's viewpoint")
    picture = server.gui.add_image(np.full((8, 8, 3), 255, np.uint8), label="renders", format="png")

    @button.on_click
    def _(event) -> None:
        camera = event.client.camera
        width, height = RENDER_WIDTH, max(1, round(RENDER_WIDTH / camera.aspect))
        started = time.perf_counter()
        browser = None
        with contextlib.suppress(Exception):  # the browser did not answer (closed, busy): tacsplat's renders alone
            browser = camera.get_render(height, width, timeout=10.0)
        image = render_rows(view.slots, camera.wxyz, camera.position, camera.fov, width, height, browser)
        if image is not None:
            picture.image = image
        shown = "" if browser is not None else " (no picture from the browser)"
        status.content = (
            f"{width}x{height} in {time.perf_counter() - started:.1f} s{shown}: browser | tacsplat RGB "
            "| expected depth (red near, blue far), one row per run"
        )


def _run_view(server, content: Content, view: View) -> None:
    run = content.run
    centre, radius = object_sphere(run)
    view.slots.append(SplatSlot(server, "/run/splat", centre, view.warned))  # in the run's own frame, with its scene
    view.slots[0].show(run)
    _look_from(server, centre, radius, run.scene)
    with server.gui.add_folder("Splat"):
        server.gui.add_markdown(
            f"**{run.label}**: {len(run.gaussians)} Gaussians, {int(run.gaussians.from_touch.sum())} from touch"
        )
        _gaussian_sets(server, view)
        _checkpoint_slider(server, view, run)
        _exported_mesh(server, view, run)
    if run.scene is not None:
        with server.gui.add_folder("Scene"):
            _add_scene(server, view, "/run/scene", run.scene, hidden=("mesh", "sphere"))
    with server.gui.add_folder("Render"):
        _render_button(server, view)
    with server.gui.add_folder("Metrics"):
        view.controls["metrics"] = server.gui.add_markdown(metrics_markdown({"metrics.json": run.metrics}))


def _report_view(server, content: Content, view: View) -> None:
    pair = [r for r in content.pair if r is not None]
    spacing = (1 + SIDE_BY_SIDE_GAP) * max(object_sphere(r)[1] for r in pair)
    view.slots += [
        SplatSlot(server, f"/report/{side}", (x, 0.0, 0.0), view.warned)
        for side, x in (("left", -spacing), ("right", spacing))
    ]
    for slot, run in zip(view.slots, content.pair):
        slot.show(run)
    _look_from(server, np.zeros(3), spacing)
    loaded = {r.label: r for r in pair}
    table = None  # the metrics table, made last (the side panel lists what is made in order)

    def show_metrics() -> None:  # (the runs' names are in the drop-downs above)
        shown = zip(("left", "right"), view.slots)
        table.content = metrics_markdown({side: slot.run.metrics for side, slot in shown if slot.run})

    with server.gui.add_folder("Runs"):
        for side, slot, run in zip(("left", "right"), view.slots, content.pair):
            choice = view.controls[f"{side} run"] = server.gui.add_dropdown(
                f"{side} run", ("(none)", *content.report_runs), initial_value=run.label if run else "(none)"
            )

            @choice.on_update
            def _(event, slot=slot) -> None:
                label = event.target.value
                try:
                    if label != "(none)" and label not in loaded:
                        loaded[label] = read_run(content.report_runs[label], label, content.path)
                except TacsplatError as exc:
                    table.content = f"**cannot show {label}**: {exc}"
                    return
                slot.show(loaded.get(label))
                show_metrics()

        _gaussian_sets(server, view)
    with server.gui.add_folder("Render"):
        _render_button(server, view)
    with server.gui.add_folder("Metrics"):
        table = view.controls["metrics"] = server.gui.add_markdown("")
    show_metrics()
