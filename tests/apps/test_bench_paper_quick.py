"""The quick preset of `tacsplat bench paper` end to end (slow: run by `make bench-quick`)."""

from __future__ import annotations

import pytest


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_bench_paper_quick_full_beats_vanilla_3dgs(tmp_path):
    from tacsplat.apps.paper_bench import PaperBench, PaperBenchConfig

    config = PaperBenchConfig.quick()
    rows = PaperBench(tmp_path, config).run(progress=False)
    assert len(rows) == len(config.objects) * len(config.methods)
    cd = {(r["object"], r["method"]): r["cd"] for r in rows if r["setting"] == "minimal"}
    for obj in config.objects:
        assert cd[obj, "paper"] < cd[obj, "3dgs"], (
            f"{obj}: paper CD {cd[obj, 'paper']:.4f} >= 3DGS {cd[obj, '3dgs']:.4f}"
        )
    assert "| Paper (T + S) |" in (tmp_path / "report.md").read_text()
