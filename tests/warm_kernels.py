"""Compile the reconstruction's numba kernels into numba's on-disk cache, in a process of its own.

`make test` starts this beside pytest: on a fresh clone the kernels otherwise compile inside the first tests that
reconstruct (about a minute on 2 cores), while the device tests that run first mostly wait on timeouts. The tests
then load the kernels from the cache (a kernel still compiling is compiled by the test that needs it, as without
this script). It checks nothing.
"""

import tempfile
from pathlib import Path

from tacsplat.cli import main

with tempfile.TemporaryDirectory(prefix="tacsplat-warm-") as folder:
    scene, run = Path(folder) / "scene", Path(folder) / "run"
    main(
        ["sim-capture", "--out", str(scene), "--resolution", "32", "--views", "2", "--test-views", "1", "--grasps", "1"]
    )
    for method in ("default", "3dgs"):
        main(["reconstruct", str(scene), "--out", str(run / method), "--method", method, "--iterations", "2"])
