"""`tacsplat bench next-touch` on a tiny configuration: both strategies at each budget from the same captures, the
first k grasps of a capture kept whole, the CSV, report and pictures written, a rerun redoing nothing, and
`--executor ray` (an embedded local Ray) giving the same scenes and results as the local executor."""

import csv
import json

import pytest

from tacsplat.apps.executors import RETRIES
from tacsplat.apps.next_touch_bench import (
    STRATEGIES,
    NextTouchBench,
    NextTouchBenchCommand,
    NextTouchBenchConfig,
    first_grasps,
)
from tacsplat.cli import main
from tacsplat.datasets import Scene
from tacsplat.errors import ConfigError
from tacsplat.options import parse_options

pytestmark = pytest.mark.timeout(600)

TINY = NextTouchBenchConfig(
    objects=("bell",),
    seeds=(0,),
    grasps=(0, 2),
    views=2,
    test_views=2,
    resolution=32,
    iterations=4,
    candidates=2,
    selection_steps=4,
)


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    bench = NextTouchBench(tmp_path_factory.mktemp("bench") / "R", TINY)
    return bench, bench.run(progress=False)


@pytest.mark.slow  # the bench's captures and runs, however tiny: ~30 s
def test_both_strategies_at_every_budget_with_the_same_views(bench):
    bench, rows = bench
    assert [(r["strategy"], r["grasps"]) for r in rows] == [
        ("random", 0),
        ("random", 2),
        ("next-best", 0),
        ("next-best", 2),
    ]
    random, chosen = (Scene.load(bench.out / "scenes" / f"bell-s0-{s}") for s in ("random", "next-best"))
    assert [f.T_world_cam.tobytes() for f in random.frames] == [f.T_world_cam.tobytes() for f in chosen.frames]
    for strategy, scene in (("random", random), ("next-best", chosen)):
        kept = Scene.load(bench.out / "scenes" / f"bell-s0-{strategy}-g2")
        assert len(kept.frames) == len(scene.frames)
        first_two = sorted({t.grasp for t in scene.touches})[:2]
        assert [(t.grasp, t.finger) for t in kept.touches] == [
            (t.grasp, t.finger) for t in scene.touches if t.grasp in first_two
        ]
        assert Scene.load(bench.out / "scenes" / f"bell-s0-{strategy}-g0").touches == []
    assert all(r["selection_seconds"] == 0 for r in rows if r["strategy"] == "random")
    assert [r["selection_seconds"] > 0 for r in rows if r["strategy"] == "next-best"] == [False, True]
    assert all(r["cd"] > 0 for r in rows)


@pytest.mark.slow  # the bench's captures and runs, however tiny: ~30 s
def test_results_report_and_pictures(bench):
    bench, rows = bench
    with (bench.out / "results.csv").open() as fh:
        table = list(csv.DictReader(fh))
    assert list(table[0]) == [
        "object",
        "strategy",
        "grasps",
        "seed",
        "cd",
        "cd_paper",
        "psnr",
        "seconds",
        "selection_seconds",
        "touches",
    ]
    assert len(table) == 4 and float(table[0]["cd"]) == pytest.approx(rows[0]["cd"])
    report = (bench.out / "report.md").read_text()
    assert "| bell | next-best |" in report and "| 2 |" in report and "Spearman" in report
    assert f"every reconstruction `{TINY.method}`" in report
    assert (bench.out / "cd_vs_grasps.png").stat().st_size > 0 and (
        bench.out / "uncertainty_bell.png"
    ).stat().st_size > 0
    rho = [line for line in report.splitlines() if line.startswith("| bell | ") and "%" not in line][-1]
    assert len(rho.split("|")) == 5  # one correlation per score


@pytest.mark.slow  # the bench's captures and runs, however tiny: ~30 s
def test_a_rerun_redoes_nothing(bench):
    bench, rows = bench
    metrics = sorted((bench.out / "runs").glob("*/metrics.json"))
    stamps = [p.stat().st_mtime_ns for p in metrics]
    again = NextTouchBench(bench.out, TINY).run(progress=False)
    assert [p.stat().st_mtime_ns for p in metrics] == stamps
    assert [r["cd"] for r in again] == [r["cd"] for r in rows]


@pytest.mark.slow  # the bench's captures and runs, however tiny: ~30 s
def test_first_grasps_keeps_whole_grasps_in_number_order(bench, tmp_path):
    bench, _ = bench
    source = bench.out / "scenes" / "bell-s0-random"
    grasps, touches = first_grasps(source, tmp_path / "one", 1)
    kept = Scene.load(tmp_path / "one")
    assert grasps == 1 and {t.grasp for t in kept.touches} == {min(t.grasp for t in Scene.load(source).touches)}
    assert touches == sum(t.in_contact for t in kept.touches)
    assert json.loads((tmp_path / "one" / "scene.json").read_text())["extra"]["first_grasps"]["grasps"] == 1


@pytest.mark.parametrize(
    "change, option",
    [
        ({"objects": ("vase",)}, "--objects"),
        ({"grasps": ()}, "--grasps"),
        ({"uncertainty": "entropy"}, "--uncertainty"),
        ({"mesh": "/no/such.obj"}, "--mesh"),
        ({"grasps": (2, 2)}, "--grasps"),
        ({"method": "ours"}, "--method"),
        ({"slide_m": -0.01}, "--slide-m: must be in \\[0, 0.1\\] m"),
    ],
)
def test_bad_settings_name_their_option(change, option, tmp_path):
    from dataclasses import replace

    with pytest.raises(ConfigError, match=option):
        NextTouchBench(tmp_path / "R", replace(TINY, **change))
    assert not (tmp_path / "R").exists()


@pytest.mark.slow  # the bench's captures and runs, however tiny: ~30 s
def test_a_rerun_with_other_settings_in_the_same_folder_is_refused(bench):
    from dataclasses import replace

    bench, _ = bench
    with pytest.raises(ConfigError, match="--out.*another plan"):
        NextTouchBench(bench.out, replace(TINY, uncertainty="fisher")).run(progress=False)
    with pytest.raises(ConfigError, match="--out.*other settings.*iterations 4 -> 5"):
        NextTouchBench(bench.out, replace(TINY, iterations=5)).run(progress=False)
    with pytest.raises(ConfigError, match="--out.*other settings.*appearance 'sh-lit' -> 'sh'"):
        NextTouchBench(bench.out, replace(TINY, method="paper")).run(progress=False)


def test_the_final_runs_train_the_bench_method_by_default_what_reconstruct_trains(tmp_path):
    from dataclasses import replace

    from tacsplat.apps.batch import ReconstructJob
    from tacsplat.reconstruction.config import TrainConfig

    for config, expected in ((TINY, TrainConfig()), (replace(TINY, method="paper"), None)):
        runs = [job for job in NextTouchBench(tmp_path / "R", config).jobs() if isinstance(job, ReconstructJob)]
        assert len(runs) == 4 and {job.method for job in runs} == {config.method}
        if expected is not None:  # the defaults: TrainConfig's, the steps and seed aside
            assert replace(runs[0].config(), iterations=expected.iterations, seed=expected.seed) == expected


def test_a_folder_with_a_run_of_other_settings_is_refused_before_anything_runs(tmp_path):
    from dataclasses import replace

    bench = NextTouchBench(tmp_path / "R", TINY)
    run = next(job for job in bench.jobs() if job.kind == "reconstruct")
    run.out.mkdir(parents=True)
    (run.out / "config.json").write_text(json.dumps(replace(run, method="paper").config().to_json()))
    (run.out / "metrics.json").write_text("{}")
    with pytest.raises(ConfigError, match=f"--out: {run.out} was trained with other settings \\(method paper -> "):
        bench.run(progress=False)
    assert sorted(p.name for p in (tmp_path / "R").iterdir()) == ["runs"]  # no capture, nothing else
    NextTouchBench(tmp_path / "R", replace(TINY, method="paper")).check_out()  # the options it was trained with


def read_rows(path) -> list[dict]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow  # the tiny bench again, its jobs as Ray tasks: ~1 min
def test_executor_ray_gives_the_local_scenes_and_results(bench, tmp_path, monkeypatch):
    local, _ = bench
    monkeypatch.delenv("RAY_ADDRESS", raising=False)  # an embedded Ray for this batch
    on_ray = NextTouchBench(tmp_path / "R", TINY)
    rows = on_ray.run(progress=False, executor="ray", retries=0)
    for strategy in STRATEGIES:
        scenes = [Scene.load(b.out / "scenes" / f"bell-s0-{strategy}") for b in (on_ray, local)]
        assert scenes[0].touches == scenes[1].touches and len(scenes[0].frames) == len(scenes[1].frames)
    timings = ("seconds", "selection_seconds")
    table, expected = read_rows(on_ray.out / "results.csv"), read_rows(local.out / "results.csv")
    assert [{k: v for k, v in r.items() if k not in timings} for r in table] == [
        {k: v for k, v in r.items() if k not in timings} for r in expected
    ]
    assert len(rows) == 4 and all(r["cd"] > 0 for r in rows)
    assert not (on_ray.out / "failures.csv").exists() and (on_ray.out / "report.md").is_file()


def test_the_executor_options_are_on_the_command(tmp_path, capsys):
    def parse(argv):
        return parse_options(NextTouchBenchCommand, argv, "tacsplat bench next-touch").executors

    args = parse(
        [
            "--out",
            str(tmp_path),
            "--executor",
            "ray",
            "--ray-address",
            "head:6379",
            "--retries",
            "1",
        ]
    )
    assert (args.executor, args.ray_address, args.retries) == ("ray", "head:6379", 1)
    args = parse(["--out", str(tmp_path)])
    assert (args.executor, args.ray_address, args.retries, args.workers) == ("auto", None, RETRIES, None)
    assert main(["bench", "next-touch", "--out", str(tmp_path / "R"), "--ray-address", "head:6379"]) == 2
    assert "--ray-address: runs jobs on a Ray cluster: add --executor ray" in capsys.readouterr().err
    assert not (tmp_path / "R").exists()
