"""Property: `tacsplat inspect` and `tacsplat reconstruct` agree on every scene, however it is damaged.

A valid tiny scene (16x16 renders of a sphere, touches, ground truth) is built
once; each example damages a copy (files deleted, truncated or overwritten;
numbers in the JSON and NPZ files replaced by NaN, infinities, negatives, huge
or wrongly typed values; index entries dropped; images swapped for other
sizes or modes) and runs both commands in-process. Either both accept the
scene (exit 0, reconstruct trains 2 steps and evaluates) or both refuse it
(exit 1), reconstruct with exactly one stderr line, the same first problem
inspect lists, and neither with a traceback.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

from tacsplat.cli import main

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from recon_synthetic import build_sphere_scene  # noqa: E402

RECONSTRUCT = ["--iterations", "2", "--sh-degree", "0", "--lambda-s", "0", "--backend", "cpu", "--quiet"]
SPECIAL_NUMBERS = [math.nan, math.inf, -math.inf, 0, 0.0, -1, -1e-3, 1e-300, 1e300, -1e300, 10**400, 2**63, 1]
OTHER_TYPES = [None, "0.5", [], {}, [1.0, 2.0], True, False]


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    return build_sphere_scene(tmp_path_factory.mktemp("fuzz") / "scene", size=16, train_views=3, test_views=1)


def _files(scene: Path, suffix: str = "") -> list[Path]:
    return sorted(p for p in scene.rglob(f"*{suffix}") if p.is_file())


def _json_leaves(data, path=()):
    """Paths (tuples of keys and indices) of every value in a JSON document, in document order."""
    if isinstance(data, dict):
        items = data.items()
    elif isinstance(data, list):
        items = enumerate(data)
    else:
        return [path]
    leaves = [path] if path else []
    for key, value in items:
        leaves += _json_leaves(value, path + (key,))
    return leaves


def _get(data, path):
    for key in path:
        data = data[key]
    return data


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _is_rotation_entry(path) -> bool:
    return any(k in ("transform_matrix", "T_world_sensor") for k in path) and not (path[-1] == 3 and path[-2] < 3)


def _set(data, path, value):
    for key in path[:-1]:
        data = data[key]
    if value is _DROP:
        del data[path[-1]]
    else:
        data[path[-1]] = value


_DROP = object()
numbers = st.one_of(st.sampled_from(SPECIAL_NUMBERS), st.floats(), st.integers(-(10**6), 10**6))
new_values = st.one_of(numbers, st.sampled_from(OTHER_TYPES), st.just(_DROP))


@st.composite
def damage(draw):
    """One way to damage a scene: (kind, which file (an index into the sorted candidates), details)."""
    kind = draw(
        st.sampled_from(["delete", "truncate", "overwrite", "json", "json", "nudge", "nudge", "npz", "npz", "image"])
    )
    which = draw(st.integers(0, 10**6))
    if kind == "truncate":
        return kind, which, draw(st.floats(0, 1))
    if kind == "overwrite":
        return kind, which, (draw(st.floats(0, 1)), draw(st.binary(min_size=1, max_size=8)))
    if kind == "json":
        return kind, which, (draw(st.integers(0, 10**6)), draw(new_values))
    if kind == "nudge":  # a plausible number changed by a plausible factor: the scene often stays valid
        return kind, which, (draw(st.integers(0, 10**6)), draw(st.floats(0.5, 2.0)))
    if kind == "npz":
        change = draw(st.sampled_from(["value", "value", "all", "dtype", "shape", "key"]))
        return kind, which, (change, draw(st.integers(0, 10**6)), draw(numbers))
    if kind == "image":
        return kind, which, draw(st.sampled_from(["smaller", "larger", "grey", "rgba", "16-bit"]))
    return kind, which, None


def _apply(scene: Path, kind: str, which: int, details) -> None:
    files = _files(scene, {"json": ".json", "nudge": ".json", "npz": ".npz", "image": ".png"}.get(kind, ""))
    if not files:
        return
    target = files[which % len(files)]
    if kind in ("delete", "truncate", "overwrite"):
        if kind == "delete":
            target.unlink()
        elif kind == "truncate":
            data = target.read_bytes()
            target.write_bytes(data[: int(len(data) * details)])
        else:
            at, payload = details
            data = bytearray(target.read_bytes())
            start = int(len(data) * at)
            data[start : start + len(payload)] = payload
            target.write_bytes(bytes(data))
    elif kind in ("json", "nudge"):
        try:
            data = json.loads(target.read_text())
        except ValueError:
            return  # already damaged beyond JSON
        leaves = _json_leaves(data)
        if kind == "nudge":  # numbers, and of a pose only its translation (a rotation scaled is no rotation)
            leaves = [p for p in leaves if _is_number(_get(data, p)) and not _is_rotation_entry(p)]
        if leaves:
            leaf, value = details
            path = leaves[leaf % len(leaves)]
            _set(data, path, _get(data, path) * value if kind == "nudge" else value)
            target.write_text(json.dumps(data))
    elif kind == "npz":
        try:
            with np.load(target) as npz:
                depth = npz["depth"]
        except Exception:
            return  # already damaged beyond NPZ
        change, index, value = details
        value = float(value) if abs(value) < 1e308 else (math.inf if value > 0 else -math.inf)
        if change in ("value", "all") and depth.size:
            with np.errstate(over="ignore"):  # (a float32 map holds a huge value as inf)
                depth.reshape(-1)[index % depth.size if change == "value" else slice(None)] = value
        elif change == "dtype":
            depth = depth.astype([np.float64, np.float16, np.int32, np.uint8][index % 4])
        elif change == "shape":
            depth = depth[: max(depth.shape[0] - 1 - index % 3, 0)]
        buf = io.BytesIO()
        np.savez(buf, **({"other": depth} if change == "key" else {"depth": depth}))
        target.write_bytes(buf.getvalue())
    elif kind == "image":
        bgr = cv2.imread(str(target), cv2.IMREAD_COLOR)
        if bgr is None:
            return
        replacement = {
            "smaller": lambda: bgr[:-1],
            "larger": lambda: np.pad(bgr, ((0, 1), (0, 0), (0, 0))),
            "grey": lambda: cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY),
            "rgba": lambda: cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA),
            "16-bit": lambda: bgr.astype(np.uint16) * 257,
        }[details]()
        cv2.imwrite(str(target), replacement)


def _run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


@settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(damages=st.lists(damage(), min_size=0, max_size=3))
@example(damages=[])  # the undamaged scene: both accept it
@example(damages=[("npz", 3, ("all", 0, 0.0))])  # a test view whose ground truth misses the object
@example(damages=[("delete", 14, None)])  # touches.json
def test_inspect_and_reconstruct_agree_on_every_damaged_scene(template, damages):
    work = Path(tempfile.mkdtemp(prefix="fuzz-"))
    try:
        scene = Path(shutil.copytree(template, work / "scene"))
        for kind, which, details in damages:
            _apply(scene, kind, which, details)
        inspect_code, inspect_out, inspect_err = _run(["inspect", str(scene), "--json"])
        code, _, err = _run(["reconstruct", str(scene), "--out", str(work / "run"), *RECONSTRUCT])
        assert "Traceback" not in inspect_err + err
        problems = json.loads(inspect_out)["problems"]
        event("refused" if problems else "accepted")
        assert (inspect_code, code) in ((0, 0), (1, 1)), (problems, err)
        if code == 1:
            messages = [line for line in err.splitlines() if not line.startswith(("INFO ", "WARNING ", "DEBUG "))]
            assert messages == [f"error: {problems[0]}"], (messages, problems)
        else:
            assert problems == [] and (work / "run" / "metrics.json").is_file()
    finally:
        shutil.rmtree(work, ignore_errors=True)
