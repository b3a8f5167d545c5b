"""`tacsplat bench sim`: the simulator's error against its run time.

1. Tactile depth against exact analytic surfaces (a sphere of radius 10 mm and
   a plane, each pressed 1 mm into the gel) as the ray grid over the same
   24 x 19.2 mm pad gets finer: the largest per-pixel depth error, the error of
   the indentation volume and of the contact area (what the depth map
   represents of the continuous surface), and the time per map.
2. Contact penetration of the hand's collision geometry (the error of MuJoCo's
   soft contacts, ideally 0) in the same grasps as the timestep changes, with
   the wall time per simulated second.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tacsplat.apps.report import md_table, pyplot, save_figure
from tacsplat.geometry import look_at, tactile_pixel_grid

SPHERE_RADIUS_M = 0.01
PRESS_M = 0.001
PAD_W_M, PAD_H_M = 0.024, 0.0192


def _analytic_sphere(x, y, r=SPHERE_RADIUS_M, d=PRESS_M):
    rho2 = x**2 + y**2
    inside = rho2 < r**2
    return np.where(inside, np.clip(np.sqrt(np.where(inside, r**2 - rho2, 0.0)) - (r - d), 0.0, None), 0.0)


def bench_tactile_resolution(widths=(40, 80, 160, 320, 640), repeats: int = 3) -> list[dict]:
    """Depth-map error and time per map against the number of ray columns (rows keep the pad's aspect)."""
    import trimesh

    from tacsplat.sim.tactile import TactileConfig, TactileDepthRenderer

    T = look_at([0.0, 0.0, SPHERE_RADIUS_M - PRESS_M], [0.0, 0.0, 1.0])  # gel normal +z, sphere centre in front
    T_plane = look_at([0.0, 0.0, -PRESS_M], [0.0, 0.0, 1.0])
    sphere_world = trimesh.creation.icosphere(subdivisions=7, radius=SPHERE_RADIUS_M)
    sphere_world.apply_translation([0.0, 0.0, SPHERE_RADIUS_M - PRESS_M])  # in the sensor's frame, then the world's
    sphere_world.apply_transform(T)
    plane = trimesh.creation.box([0.1, 0.1, 0.05])
    plane.apply_translation([0.0, 0.0, 0.025 - PRESS_M])
    plane.apply_transform(T_plane)
    cap_volume = np.pi * PRESS_M**2 * (3 * SPHERE_RADIUS_M - PRESS_M) / 3
    cap_area = np.pi * (2 * SPHERE_RADIUS_M * PRESS_M - PRESS_M**2)
    rows = []
    for w in widths:
        pixel = PAD_W_M / w
        h = int(round(PAD_H_M / pixel))
        cfg = TactileConfig(height_px=h, width_px=w, pixel_size_m=pixel)
        for surface, mesh, pose in (("sphere", sphere_world, T), ("plane", plane, T_plane)):
            renderer = TactileDepthRenderer(mesh, cfg)
            renderer.render(pose)  # warm-up (BVH build)
            t0 = time.perf_counter()
            for _ in range(repeats):
                depth = renderer.render(pose).astype(np.float64)
            seconds = (time.perf_counter() - t0) / repeats
            x, y = tactile_pixel_grid(h, w, pixel)
            if surface == "sphere":
                truth, volume, area = _analytic_sphere(x, y), cap_volume, cap_area
            else:
                truth, volume, area = np.full_like(depth, PRESS_M), PRESS_M * PAD_W_M * PAD_H_M, PAD_W_M * PAD_H_M
            rows.append(
                {
                    "surface": surface,
                    "grid": f"{h}x{w}",
                    "pixel_mm": pixel * 1e3,
                    "max_depth_error_um": float(np.abs(depth - truth).max() * 1e6),
                    "volume_error_pct": float(abs(depth.sum() * pixel**2 - volume) / volume * 100),
                    "area_error_pct": float(abs((depth > 0).sum() * pixel**2 - area) / area * 100),
                    "ms_per_map": seconds * 1e3,
                }
            )
    return rows


def bench_timestep(timesteps=(0.0005, 0.001, 0.002, 0.004), grasps: int = 3, obj: str = "teapot") -> list[dict]:
    """Collision penetration in the same grasps (sim-capture's: the logger's controller, placed by the twin
    planner) against the physics timestep, with run time. The touches go to a scratch scene."""
    import tempfile

    from tacsplat.acquisition.devices import twin_rig
    from tacsplat.acquisition.logger import CaptureLogger
    from tacsplat.acquisition.twin_planner import TwinPlanner
    from tacsplat.datasets import SceneMeta, SceneWriter
    from tacsplat.sim.twin import SimTwin, TwinConfig

    rows = []
    for dt in timesteps:
        twin_cfg = TwinConfig(object=obj, timestep=dt, contact_timeconst=max(0.005, 2.5 * dt))
        with SimTwin(twin_cfg) as twin, tempfile.TemporaryDirectory() as scratch:
            rig = twin_rig(twin)
            with SceneWriter.create(
                Path(scratch) / "scene", rig.intrinsics, SceneMeta("sim", obj), rig.sensor_model
            ) as writer:
                logger = CaptureLogger(writer, rig.hand, rig.sensors, rig.camera, rig.clock, rig.poses, rig.control)
                planner = TwinPlanner(twin, grasp_seed=0)
                penetrations, touching, wall = [], 0, 0.0
                for g in range(grasps):
                    t0 = time.perf_counter()
                    outcome = planner.grasp(logger, g)
                    wall += time.perf_counter() - t0
                    if outcome is not None:
                        penetrations.append(twin.peak_penetration_m)  # of the approach kept (each one resets it)
                        touching += len(outcome.fingers_in_contact)
        rows.append(
            {
                "timestep_ms": dt * 1e3,
                "contact_timeconst_ms": twin_cfg.contact_timeconst * 1e3,
                "max_penetration_mm": float(max(penetrations) * 1e3) if penetrations else float("nan"),
                "mean_penetration_mm": float(np.mean(penetrations) * 1e3) if penetrations else float("nan"),
                "pads_in_contact": touching,
                "grasps": grasps,
                "wall_s_per_grasp": wall / grasps,
            }
        )
    return rows


def _markdown(rows: list[dict]) -> str:
    cells = [[f"{v:.4g}" if isinstance(v, float) else str(v) for v in r.values()] for r in rows]
    return "\n".join(md_table(list(rows[0]), cells, "l" * len(rows[0])))


def _plot(tactile: list[dict], physics: list[dict], path: Path) -> None:
    fig, (ax, ax_physics) = pyplot().subplots(1, 2, figsize=(12, 4.5))
    for surface, style in (("sphere", "o-"), ("plane", "s--")):
        rows = [r for r in tactile if r["surface"] == surface]
        ms = [r["ms_per_map"] for r in rows]
        volume = [max(r["volume_error_pct"], 1e-6) for r in rows]
        ax.plot(ms, volume, style, label=f"{surface}: indentation volume error")
        if surface == "sphere":
            ax.plot(ms, [max(r["area_error_pct"], 1e-6) for r in rows], "^:", label="sphere: contact area error")
            for r, x, y in zip(rows, ms, volume):
                ax.annotate(r["grid"], (x, y), fontsize=7)
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="time per tactile map (ms)",
        ylabel="error (%)",
        title="tactile depth vs ray grid (sphere r=10 mm, plane; 1 mm press)",
    )
    ax.legend(fontsize=8)
    wall = [r["wall_s_per_grasp"] for r in physics]
    ax_physics.plot(wall, [r["max_penetration_mm"] for r in physics], "o-", label="max")
    ax_physics.plot(wall, [r["mean_penetration_mm"] for r in physics], "s--", label="mean of grasp maxima")
    for r in physics:
        ax_physics.annotate(f"dt={r['timestep_ms']:g} ms", (r["wall_s_per_grasp"], r["max_penetration_mm"]), fontsize=7)
    ax_physics.set(
        xlabel="wall time per grasp (s)", ylabel="contact penetration (mm)", title="collision penetration vs timestep"
    )
    ax_physics.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)


def run_bench(out: str | Path, quick: bool = False) -> str:
    """Run both benchmarks; write sim.json, sim.md and sim.png into ``out``; return the markdown report."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    tactile = bench_tactile_resolution(widths=(40, 160, 640) if quick else (40, 80, 160, 320, 640))
    physics = bench_timestep(
        timesteps=(0.001, 0.004) if quick else (0.0005, 0.001, 0.002, 0.004), grasps=2 if quick else 4
    )
    (out / "sim.json").write_text(json.dumps({"tactile": tactile, "physics": physics}, indent=2))
    report = (
        f"## Tactile depth vs ray grid\n\n{_markdown(tactile)}\n\n## Penetration vs timestep\n\n{_markdown(physics)}\n"
    )
    (out / "sim.md").write_text(report)
    _plot(tactile, physics, out / "sim.png")
    return report


@dataclass
class BenchSim:
    """simulator error against run time: tactile depth vs ray-grid resolution, penetration vs timestep"""

    out: Path = Path("bench-output/sim")
    """folder for sim.json, sim.md and sim.png"""
    quick: bool = False
    """fewer resolutions and timesteps"""


def register(cli) -> None:
    """Add ``tacsplat bench sim`` to the command tree."""
    cli.typed("bench sim", BenchSim, lambda args: print(run_bench(args.out, quick=args.quick)))
