"""`tacsplat bench compare A.json B.json`: two benchmark results side by side (before / after).

Its options and what it does: :class:`BenchCompare`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import tyro

from tacsplat.errors import InvalidInputError

SKIPPED_KEYS = ("per_step",)  # long per-step series: summarised elsewhere in the same file


def _row_label(row, index: int) -> str:
    if isinstance(row, dict):
        if "label" in row:
            return str(row["label"])
        if {"width", "height", "n_gaussians"} <= row.keys():
            return f"{row['width']}x{row['height']}:{row['n_gaussians']}"
    return str(index)


def flatten(data, prefix: str = "") -> dict[str, float]:
    """``{"sizes.256x256:20000.cpu.forward_ms": 12.3, ...}``: every number (not bool) in nested dicts and lists."""
    if isinstance(data, (int, float)) and not isinstance(data, bool):
        return {prefix: float(data)}
    if isinstance(data, dict):
        items = ((str(k), v) for k, v in data.items() if k not in SKIPPED_KEYS)
    elif isinstance(data, list):
        items = ((_row_label(v, i), v) for i, v in enumerate(data))
    else:
        return {}
    return {k: v for key, value in items for k, v in flatten(value, f"{prefix}.{key}" if prefix else key).items()}


def read_results(path: str | Path) -> dict:
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InvalidInputError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InvalidInputError(f"{path}: not a benchmark JSON file ({exc})") from None


def compare(a: dict, b: dict, match: str | None = None) -> list[tuple[str, float | None, float | None, float | None]]:
    """``(path, A, B, B / A)`` for every number of either result (None where one lacks it), in A's order."""
    flat_a, flat_b = flatten(a), flatten(b)
    rows = [(key, flat_a.get(key), flat_b.get(key)) for key in {**flat_a, **flat_b} if not match or match in key]
    return [(key, va, vb, vb / va if va and vb is not None else None) for key, va, vb in rows]


def format_comparison(rows, name_a: str, name_b: str) -> str:
    def cell(v):
        if v is None:
            return f"{'-':>12}"
        return f"{v:12.4g}" if math.isfinite(v) else f"{v!s:>12}"

    width = max([len("value")] + [len(key) for key, *_ in rows])
    lines = [
        f"{'value':{width}s} {name_a[-12:]:>12} {name_b[-12:]:>12} {'B / A':>8}",
        f"{'':{width}s} {'(A)':>12} {'(B)':>12}",
    ]
    for key, va, vb, ratio in rows:
        lines.append(f"{key:{width}s} {cell(va)} {cell(vb)} " + (f"{ratio:8.3f}" if ratio is not None else f"{'':8s}"))
    return "\n".join(lines)


@dataclass
class BenchCompare:
    """two benchmark JSON files side by side (A before, B after) with ratios

    Reads any JSON that the benchmarks write ('bench rasterizer --json', 'bench step''s 'step.json', ...) and
    prints every number found in either file under the same path, A, B and the ratio B / A. Rows of a list are
    matched by their label ('WxH:N' for the rasterizer's sizes, '128px' for the step profile's resolutions), not
    by their position; per-step records are skipped."""

    a: tyro.conf.Positional[Path]
    """benchmark JSON (before)"""
    b: tyro.conf.Positional[Path]
    """benchmark JSON (after)"""
    match: str | None = None
    """only the values whose path contains this text, e.g. _ms"""


def register(cli) -> None:
    """Add `tacsplat bench compare`."""
    cli.typed("bench compare", BenchCompare, _handler)


def _handler(args: BenchCompare) -> int:
    rows = compare(read_results(args.a), read_results(args.b), args.match)
    print(format_comparison(rows, args.a.name, args.b.name))
    return 0
