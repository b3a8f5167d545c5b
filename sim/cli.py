"""`tacsplat simulate-touches` (see tacsplat.cli; sim-capture is in tacsplat.acquisition, which runs it through
the same logger as real captures)."""

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


def _simulate_touches(args) -> int:
    from tacsplat.sim.capture import simulate_touches

    target = simulate_touches(args.mesh, args.scene, args.grasps, args.out, args.object_radius, args.seed)
    print(f"touches written to {target}")
    return 0
