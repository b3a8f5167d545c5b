"""Applications built on every layer below: the benchmarks, the demo and their report writer.

``paper_bench`` (the paper's tables), ``touch_bench`` (CD against the number of
touches), ``bench_rasterizer``, ``bench_sim``, ``demo`` (the README's main job),
``report`` (tables and figures), ``options`` (shared option values).
"""
