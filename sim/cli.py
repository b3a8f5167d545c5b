"""`tacsplat` subcommands of tacsplat.sim: sim-capture, simulate-touches, bench sim (see tacsplat.cli)."""

from __future__ import annotations

import json


def register(cli) -> None:
    """Add this package's commands to the tree."""
    p = cli.command(
        "sim-capture",
        help="simulated capture: train views, test views with ground truth, and grasps, into a scene directory",
    )
    p.add_argument("--object", default="teapot", help="library object (teapot, toaster, bell, helmet, torus, car)")
    p.add_argument("--mesh", default=None, help="any .obj/.ply/.stl mesh instead of a library object")
    p.add_argument("--object-radius", type=float, default=0.08, help="bounding-sphere radius in metres")
    p.add_argument("--views", type=int, default=5, help="train views")
    p.add_argument("--test-views", type=int, default=24, help="held-out test views (with GT depth in gt/)")
    p.add_argument("--grasps", type=int, default=5, help="grasps of four touches each")
    p.add_argument("--resolution", type=int, default=200, help="image width and height in pixels")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="scene directory to create (or continue with --resume)")
    p.add_argument("--resume", action="store_true", help="continue a capture that was interrupted")
    p.set_defaults(func=_sim_capture)

    p = cli.command(
        "simulate-touches",
        help="add simulated grasps of a mesh to a scene (e.g. an imported Shiny Blender scene)",
    )
    p.add_argument("--mesh", required=True, help="the object's mesh, in the scene's world frame and units")
    p.add_argument("--scene", required=True, help="scene directory")
    p.add_argument("--grasps", type=int, default=5)
    p.add_argument("--out", default=None, help="new scene directory (needed when SCENE has no tactile sensor model)")
    p.add_argument("--object-radius", type=float, default=0.08, help="graspable size the mesh is simulated at (m)")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_simulate_touches)

    p = cli.command(
        "bench sim",
        help="simulator error against run time: tactile depth vs ray-grid resolution, penetration vs timestep",
    )
    p.add_argument("--out", default="bench-output/sim", help="folder for sim.json, sim.md and sim.png")
    p.add_argument("--quick", action="store_true", help="fewer resolutions and timesteps")
    p.set_defaults(func=_bench_sim)


def _sim_capture(args) -> int:
    """Through the acquisition logger, exactly as a real capture (tacsplat.acquisition.sim_capture)."""
    from tacsplat.acquisition.sim_capture import sim_capture, sim_rig_config

    config = sim_rig_config(
        object=args.object,
        mesh=args.mesh,
        object_radius=args.object_radius,
        views=args.views,
        test_views=args.test_views,
        grasps=args.grasps,
        resolution=args.resolution,
        seed=args.seed,
    )
    timings = sim_capture(config, args.out, resume=args.resume)
    print(json.dumps({"scene": args.out, **{k: round(v, 2) for k, v in timings.items()}}))
    return 0


def _simulate_touches(args) -> int:
    from tacsplat.sim.capture import simulate_touches

    target = simulate_touches(args.mesh, args.scene, args.grasps, args.out, args.object_radius, args.seed)
    print(f"touches written to {target}")
    return 0


def _bench_sim(args) -> int:
    from tacsplat.sim.bench import run_bench

    report = run_bench(args.out, quick=args.quick)
    print(report)
    return 0
