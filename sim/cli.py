"""`tacsplat` subcommands of tacsplat.sim: simulate-touches, bench sim (see tacsplat.cli; sim-capture is in
tacsplat.acquisition, which runs it through the same logger as real captures)."""

from __future__ import annotations


def register(cli) -> None:
    """Add this package's commands to the tree."""
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
