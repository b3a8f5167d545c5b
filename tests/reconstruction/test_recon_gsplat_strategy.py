"""rasterization()'s meta carries the keys gsplat's densification strategies read (gsplat runs on the CPU here)."""

import pytest
import torch

from tacsplat.apps.bench_rasterizer import random_scene
from tacsplat.reconstruction.raster import rasterization

DefaultStrategy = pytest.importorskip("gsplat.strategy").DefaultStrategy


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_gsplats_default_strategy_densifies_on_our_meta(backend):
    scene = random_scene(600, 48, 40, sh_degree=None, seed=1)
    raw = {
        "means": scene["means"],
        "quats": scene["quats"],
        "scales": scene["scales"].log(),
        "opacities": torch.logit(scene["opacities"].clamp(1e-4, 1 - 1e-4)),
        "colors": scene["colors"],
    }
    params = {k: torch.nn.Parameter(v.clone()) for k, v in raw.items()}
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    strategy = DefaultStrategy(refine_start_iter=1, refine_every=2, grow_grad2d=1e-12, prune_opa=1e-6)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=3.0)
    counts = [len(params["means"])]
    for step in range(5):
        image, _, meta = rasterization(
            params["means"],
            params["quats"],
            params["scales"].exp(),
            params["opacities"].sigmoid(),
            params["colors"],
            scene["viewmats"],
            scene["Ks"],
            48,
            40,
            backend=backend,
        )
        strategy.step_pre_backward(params, optimizers, state, step, meta)
        image.sum().backward()
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad()
        strategy.step_post_backward(params, optimizers, state, step, meta, packed=False)
        counts.append(len(params["means"]))
    assert counts[-1] > counts[0]  # it grew, from our gradients and radii
    assert all(len(p) == counts[-1] for p in params.values())
    assert state["count"].shape == (counts[-1],)
