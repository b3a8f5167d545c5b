"""Batch files and the local executor, without Ray: one clear error per mistake in a batch file (naming the
file, the job and the field), needs inferred from paths, failures listed while the other jobs go on, the
rerun running only what failed, an evaluate job evaluating with its settings, and SIGTERM or SIGHUP stopping a
batch as Ctrl-C does."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import socket
import subprocess
import sys
from dataclasses import replace
from pathlib import Path, PurePath

import pytest

from tacsplat.apps.batch import CaptureJob, EvaluateJob, ReconstructJob, load_batch
from tacsplat.apps.executors import FAILURES_CSV, RETRIES, BatchError, ExecutorOptions, check_ray_address, run_jobs
from tacsplat.cli import main
from tacsplat.errors import ConfigError
from tacsplat.reconstruction.methods import method_of

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders

from batch_test_jobs import FileJob, wait_until  # noqa: E402


def read_failures(folder: Path) -> dict[str, dict]:
    with (folder / FAILURES_CSV).open() as fh:
        return {row["job"]: row for row in csv.DictReader(fh)}


def test_local_runs_in_order_here_lists_failures_and_reruns_only_them(tmp_path, capsys):
    jobs = [
        FileJob("first", tmp_path / "first"),
        FileJob("flaky", tmp_path / "flaky", "raise-while-broken"),
        FileJob("after-flaky", tmp_path / "after-flaky", needs=("flaky",)),
        FileJob("bad-input", tmp_path / "bad-input", "config-error"),
        FileJob("last", tmp_path / "last"),
    ]
    (tmp_path / "flaky").mkdir()
    (tmp_path / "flaky" / "broken").touch()
    finished = []
    outcome = run_jobs(jobs, tmp_path, on_done=lambda job, summary: finished.append(job.name), desc="tiny")
    last = capsys.readouterr().err.splitlines()[-1]  # of the bar (plain lines: stderr is no terminal)
    assert re.fullmatch(r"tiny: 5/5 jobs in \d+ s \(done 2, running 0, failed 3\)", last), last

    assert finished == outcome.done == ["first", "last"]  # in order, the jobs after a failure included
    assert [j.attempts() for j in jobs] == [[os.getpid()], [os.getpid()], [], [os.getpid()], [os.getpid()]]
    failures = read_failures(tmp_path)
    assert list(failures) == ["flaky", "after-flaky", "bad-input"]
    assert failures["flaky"]["error"].startswith("RuntimeError: ") and failures["flaky"]["attempts"] == "1"
    assert failures["after-flaky"] == {
        "job": "after-flaky",
        "attempts": "0",
        "error": "not run: needs flaky, which failed",
    }
    assert failures["bad-input"]["error"] == "threshold: must be > 0, got -1"
    assert outcome.not_run == ["after-flaky"]
    with pytest.raises(
        BatchError,
        match=r"^2 of 5 jobs failed and 1 not run \(a job they need failed\) \(first: "
        r"flaky: RuntimeError: .*failures.csv",
    ):
        outcome.raise_if_failed(tmp_path)

    (tmp_path / "flaky" / "broken").unlink()
    rerun = run_jobs(jobs[:3], tmp_path, progress=False)
    assert rerun.skipped == ["first"] and rerun.done == ["flaky", "after-flaky"] and not rerun.failed
    assert [len(j.attempts()) for j in jobs[:3]] == [1, 2, 1]
    assert not (tmp_path / FAILURES_CSV).exists()  # nothing failed this time: the old list is gone


@pytest.mark.parametrize("count, unit", [(1, "job"), (2, "jobs")])
def test_each_progress_line_counts_the_jobs_it_says_ended(tmp_path, capsys, monkeypatch, count, unit):
    """Before: "1/1 job in 0 s (done 0, running 1 (a), failed 0)": the count went up before the text did."""
    monkeypatch.setattr("tacsplat.progress.PLAIN_INTERVAL_S", 0.0)  # a line at each update
    jobs = [FileJob(name, tmp_path / name) for name in ("a", "b")[:count]]
    run_jobs(jobs, tmp_path, desc="tiny")
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("tiny: ")]
    pattern = rf"tiny: (\d)/{count} {unit} in \d+ s \(done (\d), running (\d).*, failed 0\)"
    counts = [re.fullmatch(pattern, line).groups() for line in lines]
    assert counts and all(int(n) == int(done) and running == "0" for n, done, running in counts), lines


def test_local_ctrl_c_stops_at_once_and_keeps_finished_jobs(tmp_path):
    jobs = [FileJob(name, tmp_path / name) for name in ("a", "b", "c")]

    def interrupt(job, summary):
        if job.name == "b":
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_jobs(jobs, tmp_path, on_done=interrupt, progress=False)
    assert [j.complete() for j in jobs] == [True, True, False]
    assert run_jobs(jobs, tmp_path, progress=False).done == ["c"]


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


GOOD = """\
jobs:
  - {kind: capture, out: scenes/teapot, object: teapot, resolution: 48, seed: 3}
  - {kind: reconstruct, out: runs/teapot-default, scene: scenes/teapot, iterations: 20, seed: 3}
  - {kind: reconstruct, out: runs/old, scene: %(existing)s, method: 3dgs, preset: paper, name: old scene}
  - {kind: evaluate, run: runs/teapot-default}
  - {kind: evaluate, run: %(existing)s, gt_mesh: mesh.obj, cpus: 2}
"""


def test_batch_file_resolves_paths_and_infers_needs(tmp_path):
    existing = tmp_path / "elsewhere"
    existing.mkdir()
    (tmp_path / "mesh.obj").write_text("v 0 0 0\n")
    out = tmp_path / "out"
    capture, train, old, evaluate, evaluate_old = load_batch(
        write(tmp_path / "b.yaml", GOOD % {"existing": existing}), out
    )
    assert capture == CaptureJob(
        out=out / "scenes/teapot", object="teapot", resolution=48, seed=3, name="capture scenes/teapot"
    )
    assert train == ReconstructJob(
        out=out / "runs/teapot-default",
        scene=out / "scenes/teapot",
        iterations=20,
        seed=3,
        name="reconstruct runs/teapot-default",
        needs=("capture scenes/teapot",),
    )
    assert (old.scene, old.needs, old.name, method_of(old.config())) == (existing, (), "old scene", "3dgs")
    assert evaluate == EvaluateJob(
        run=out / "runs/teapot-default", name="evaluate runs/teapot-default", needs=("reconstruct runs/teapot-default",)
    )
    assert evaluate_old.gt_mesh == str(tmp_path / "mesh.obj") and evaluate_old.cpus == 2 and not evaluate_old.needs
    assert train.gpus(cluster_has_gpus=False) == 0 and train.gpus(cluster_has_gpus=True) == 1
    assert capture.gpus(cluster_has_gpus=True) == 0


def test_needs_in_a_batch_file_run_each_job_after_what_it_needs(tmp_path):
    text = """\
jobs:
  - {kind: capture, out: scenes/z}
  - {kind: capture, out: scenes/a, needs: [last capture]}
  - {kind: reconstruct, out: runs/r, scene: scenes/a, needs: [copy, capture scenes/a]}
  - {kind: capture, out: scenes/b, name: copy}
  - {kind: evaluate, run: runs/r, name: judge}
  - {kind: capture, out: scenes/c, name: last capture, needs: [copy, copy]}
"""
    jobs = load_batch(write(tmp_path / "b.yaml", text), tmp_path / "out")
    # the file's order where the needs allow it; a need given and implied (by the scene) counted once
    assert [(job.name, job.needs) for job in jobs] == [
        ("capture scenes/z", ()),
        ("copy", ()),
        ("last capture", ("copy",)),
        ("capture scenes/a", ("last capture",)),
        ("reconstruct runs/r", ("copy", "capture scenes/a")),
        ("judge", ("reconstruct runs/r",)),
    ]


def test_a_job_whose_need_failed_is_not_run_and_a_cycle_runs_nothing(tmp_path, capsys):
    (tmp_path / "out" / "no-run").mkdir(parents=True)  # a folder without a run: its evaluation fails
    path = write(
        tmp_path / "b.yaml",
        "jobs:\n  - {kind: capture, out: a, needs: [judge]}\n  - {kind: evaluate, run: no-run, name: judge}\n",
    )
    assert main(["batch", str(path), "--out", str(tmp_path / "out"), "--executor", "local"]) == 1
    assert read_failures(tmp_path / "out")["capture a"]["error"] == "not run: needs judge, which failed"
    assert not (tmp_path / "out" / "a").exists()
    assert (
        capsys.readouterr()
        .err.splitlines()[-1]
        .startswith("error: 1 of 2 jobs failed and 1 not run (a job they need failed) (first: judge: ")
    )

    path = write(
        tmp_path / "cycle.yaml",
        "jobs:\n  - {kind: capture, out: a, needs: [capture b]}\n  - {kind: capture, out: b, needs: [capture a]}\n",
    )
    assert main(["batch", str(path), "--out", str(tmp_path / "cycle"), "--executor", "local"]) == 1
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"error: {path}: jobs: the needs form a cycle, so none of its jobs can run: 'capture a' (jobs[0]) needs "
        "'capture b' (jobs[1]), which needs 'capture a' (jobs[0])"
    )
    assert not (tmp_path / "cycle").exists()


def test_a_reconstruct_job_without_a_method_trains_what_reconstruct_trains(tmp_path):
    from tacsplat.reconstruction.command import parse

    given = parse([str(tmp_path), "--out", str(tmp_path / "r"), "--iterations", "20", "--seed", "3"]).train
    assert ReconstructJob(out=tmp_path / "r", scene=tmp_path, iterations=20, seed=3).config() == given


def test_nested_overrides_are_the_dotted_ones(tmp_path):
    """Before: ``init: {num_random_points: 500}`` was refused as a pydantic union error naming ``.bool``."""
    (tmp_path / "s").mkdir()
    job = "jobs:\n  - {kind: reconstruct, out: r, scene: s, overrides: %s}"
    nested = load_batch(write(tmp_path / "n.yaml", job % "{init: {num_random_points: 500}, lambda_s: 0}"), tmp_path)
    dotted = load_batch(write(tmp_path / "d.yaml", job % "{init.num_random_points: 500, lambda_s: 0}"), tmp_path)
    assert nested == dotted and nested[0].config().init.num_random_points == 500


def test_a_run_folder_names_the_settings_that_changed_since(tmp_path):
    from tacsplat.reconstruction.methods import DEFAULT_METHOD

    paper = ReconstructJob(out=tmp_path / "r", scene=tmp_path, method="paper", iterations=20, seed=3)
    default = ReconstructJob(out=paper.out, scene=tmp_path, iterations=20, seed=3)
    recorded = paper.config().to_json() | {"depth_normal_start_iter": 123}  # unused by full: not a change for it
    paper.out.mkdir()
    (paper.out / "config.json").write_text(json.dumps(recorded))
    assert default.changed_settings() == []  # neither finished nor interrupted: nothing to reuse or resume
    (paper.out / "checkpoint.pt").write_bytes(b"")  # interrupted: a rerun would resume it as recorded
    changes = default.changed_settings()
    assert changes[0] == f"method paper -> {DEFAULT_METHOD}"
    assert {
        "lambda_depth_normal 0.0 -> 0.05",
        "appearance 'sh' -> 'sh-lit'",
        "depth_normal_start_iter 123 -> 700",
    } <= set(changes)
    assert paper.changed_settings() == []
    with pytest.raises(ConfigError, match=r"--out: .*r was trained with other settings \(method paper -> .*delete"):
        default.refuse_changed_settings()
    paper.refuse_changed_settings()

    (paper.out / "metrics.json").write_text(json.dumps({"settings": recorded}))  # finished ...
    (paper.out / "config.json").unlink()  # ... and recorded in metrics.json only (evaluated here)
    assert default.changed_settings()[0] == f"method paper -> {DEFAULT_METHOD}" and paper.changed_settings() == []
    (paper.out / "config.json").write_text("[1, 2]")
    assert default.changed_settings() == paper.changed_settings() != []
    assert paper.changed_settings()[0].startswith("config.json unreadable (")


def test_a_run_folder_that_trained_with_a_removed_loss_names_it_as_a_change(tmp_path):
    """A run of the default from before the tactile-normal loss was removed reads as today's default, but neither
    its numbers nor its checkpoint are this job's: the loss is named (finished, or interrupted)."""
    job = ReconstructJob(out=tmp_path / "r", scene=tmp_path, iterations=20, seed=3)
    job.out.mkdir()
    (job.out / "config.json").write_text(json.dumps(job.config().to_json() | {"lambda_touch_normal": 0.1}))
    (job.out / "checkpoint.pt").write_bytes(b"")
    assert job.changed_settings() == ["lambda_touch_normal 0.1 -> removed"]
    with pytest.raises(ConfigError, match=r"--out: .*r was trained with other settings \(lambda_touch_normal 0.1 -> "):
        job.refuse_changed_settings()
    (job.out / "config.json").write_text(json.dumps(job.config().to_json() | {"lambda_touch_normal": 0.0}))
    assert job.changed_settings() == []


@pytest.mark.parametrize(
    "jobs, key, message",
    [
        ("- {kind: train, out: a}", "jobs[0].kind", "expected one of capture, reconstruct, evaluate, got 'train'"),
        ("- {out: a}", "jobs[0].kind", "expected one of capture, reconstruct, evaluate, got None"),
        ("- {kind: capture}", "jobs[0].out", "missing (a required key)"),
        ("- {kind: capture, out: a, steps: 3}", "jobs[0].steps", "unknown key (a capture job takes cpus, grasps, "),
        ("- {kind: capture, out: a, views: '5'}", "jobs[0].views", "Input should be a valid integer, got '5'"),
        (
            "- {kind: capture, out: a}\n- {kind: reconstruct, out: r, scene: a, iterations: 2.5}",
            "jobs[1].iterations",
            "Input should be a valid integer",
        ),
        (
            "- {kind: capture, out: a, object: sphere}",
            "jobs[0] (capture a)",
            "object: unknown library object 'sphere' (one of ['teapot', ",
        ),
        ("- {kind: capture, out: a, views: 0}", "jobs[0] (capture a)", "views: must be >= 1, got 0"),
        ("- {kind: capture, out: a, seed: -1}", "jobs[0] (capture a)", "seed: must be >= 0, got -1"),
        ("- {kind: capture, out: a, cpus: 0}", "jobs[0] (capture a)", "cpus: must be a finite number > 0, got 0.0"),
        ("- {kind: capture, out: a, cpus: .inf}", "jobs[0] (capture a)", "cpus: must be a finite number > 0, got inf"),
        (
            "- {kind: capture, out: a}\n- {kind: reconstruct, out: r, scene: a, overrides: {seed: 3}}",
            "jobs[1] (reconstruct r)",
            "overrides.seed: a field of the job: set `seed:` beside `overrides:`, not in them",
        ),
        (
            "- {kind: capture, out: a}\n- {kind: reconstruct, out: r, scene: a, overrides: {lambda_s: 0, device: cpu}}",
            "jobs[1] (reconstruct r)",
            "overrides.device: a field of the job",
        ),
        (
            "- {kind: capture, out: a}\n- {kind: reconstruct, out: r, scene: a, iterations: 50, overrides: "
            "{iterations: 7}}",
            "jobs[1] (reconstruct r)",
            "overrides.iterations: a field of the job",
        ),
        ("- {kind: capture, out: ''}", "jobs[0].out", "is --out itself; give a folder in it"),
        ("- {kind: capture, out: x/..}", "jobs[0].out", "is --out itself; give a folder in it"),
        ("- {kind: capture, out: ..}", "jobs[0].out", "out/.. holds --out ("),
        (
            "- {kind: capture, out: runs/a}\n- {kind: capture, out: runs/a/b, seed: 1}",
            "jobs[1].out",
            "out/runs/a/b is inside ",
        ),
        (
            "- {kind: capture, out: runs/a/b}\n- {kind: capture, out: c}\n- {kind: reconstruct, out: runs/a, scene: c}",
            "jobs[2].out",
            "out/runs/a/b, the out of capture runs/a/b (jobs[0]): give each job a folder outside the others'",
        ),
        (
            "- {kind: capture, out: runs/a/x}\n- {kind: capture, out: runs/a/y, seed: 1}\n"
            "- {kind: capture, out: runs, seed: 2}",
            "jobs[2].out",
            "out/runs/a/x, the out of capture runs/a/x (jobs[0]): give each job a folder outside the others'",
        ),  # (the first of the outs it holds)
        ("- {kind: capture, out: a}\n- {kind: capture, out: a/b/c, seed: 1}", "jobs[1].out", "out/a/b/c is inside "),
        (
            "- {kind: capture, out: a}\n- {kind: capture, out: x/../a, seed: 1}",
            "jobs[1].out",
            "is also the out of capture a",
        ),
        (
            "- {kind: capture, out: a}\n- {kind: reconstruct, out: r, scene: a, method: ours}",
            "jobs[1] (reconstruct r)",
            "unknown method 'ours'",
        ),
        (
            "- {kind: capture, out: a}\n- {kind: reconstruct, out: r, scene: a, iterations: 0}",
            "jobs[1] (reconstruct r)",
            "iterations",
        ),
        (
            "- {kind: reconstruct, out: r, scene: a}\n- {kind: capture, out: a}",
            "jobs[0].scene",
            "is not a folder, nor the out of a capture job listed before this one",
        ),
        ("- {kind: evaluate, run: nowhere}", "jobs[0].run", "is not a folder, nor the out of a reconstruct job"),
        (
            "- {kind: capture, out: a}\n- {kind: capture, out: a, seed: 1}",
            "jobs[1].out",
            "is also the out of capture a",
        ),
        (
            "- {kind: capture, out: a, name: x}\n- {kind: capture, out: b, name: x}",
            "jobs[1].name",
            "two jobs are named 'x'",
        ),
        ("- 3", "jobs[0]", "expected a mapping with a kind"),
        (
            "- {kind: capture, out: a, needs: [capture b]}",
            "jobs[0].needs",
            "'capture a' needs 'capture b', which is no job of this file (a job's name is its `name:`, else ",
        ),
        (
            "- {kind: capture, out: a, name: x, needs: [x]}",
            "jobs",
            "the needs form a cycle, so none of its jobs can run: 'x' (jobs[0]) needs 'x' (jobs[0])",
        ),
        (
            "- {kind: capture, out: c, needs: [capture b]}\n- {kind: capture, out: a, needs: [capture c]}\n"
            "- {kind: capture, out: b, needs: [capture a]}",
            "jobs",
            "the needs form a cycle, so none of its jobs can run: "
            "'capture c' (jobs[0]) needs 'capture b' (jobs[2]), which needs 'capture a' (jobs[1]), which needs 'capture c' "
            "(jobs[0])",
        ),
        (
            "- {kind: capture, out: a, needs: [reconstruct r]}\n- {kind: reconstruct, out: r, scene: a}",
            "jobs",
            "'capture a' (jobs[0]) needs 'reconstruct r' (jobs[1]), which needs 'capture a' (jobs[0])",
        ),  # (r's scene)
        (
            "- {kind: capture, out: a}\n- {kind: reconstruct, out: r, scene: a}\n- {kind: evaluate, run: r}\n"
            "- {kind: evaluate, run: ./r, name: again}",
            "jobs[3].run",
            "r is also evaluated by evaluate r",
        ),
    ],
)
def test_batch_file_mistakes_name_the_job_and_field(tmp_path, jobs, key, message):
    path = write(tmp_path / "b.yaml", "jobs:\n" + "\n".join("  " + line for line in jobs.splitlines()) + "\n")
    with pytest.raises(ConfigError) as info:
        load_batch(path, tmp_path / "out")
    assert str(info.value).startswith(f"{path}: {key}: ") and message in str(info.value), str(info.value)


def test_the_nested_outs_check_does_not_compare_every_pair_of_jobs(tmp_path, monkeypatch):
    """Each out is looked up among the folders of the jobs before it, not compared with each (5,000 jobs: 2 min):
    twice the jobs make twice the path comparisons (==, as `in folder.parents` makes them, and is_relative_to),
    not four times."""
    compared = []
    for name in ("__eq__", "is_relative_to"):
        method = getattr(PurePath, name)
        monkeypatch.setattr(PurePath, name, lambda self, other, m=method: compared.append(1) or m(self, other))

    def comparisons(n: int) -> int:
        compared.clear()
        jobs = "".join(f"  - {{kind: capture, out: c{i}}}\n" for i in range(n))
        assert len(load_batch(write(tmp_path / f"b{n}.yaml", "jobs:\n" + jobs), tmp_path / "out")) == n
        return len(compared)

    assert comparisons(600) < 3 * comparisons(300)


def test_needs_order_places_each_job_once_not_by_scanning_the_file_again(tmp_path):
    """Each job is taken from a heap of the ready ones, not found by scanning the file for each (20,000 jobs: 30 s);
    the first ready job of the file next, even one that got ready after others (jobs[0] after jobs[1] here)."""
    from tacsplat.apps.batch import _in_needs_order

    class Counted(list):  # the jobs, counting each one looked at
        looked_at = 0

        def __iter__(self):
            for job in super().__iter__():
                Counted.looked_at += 1
                yield job

    n = 300  # each even job needs the one after it
    jobs = Counted(
        CaptureJob(out=tmp_path / f"c{i}", name=f"c{i}", needs=(f"c{i + 1}",) if i % 2 == 0 else ()) for i in range(n)
    )
    order = _in_needs_order(jobs, tmp_path / "b.yaml")
    assert [job.name for job in order] == [f"c{i ^ 1}" for i in range(n)]  # c1, c0, c3, c2, ...
    assert Counted.looked_at <= 4 * n


def test_a_batch_file_out_outside_out_is_taken_as_given(tmp_path):
    # as an absolute out is: a rerun resolves it to the same folder, and results.csv names it by that path
    path = write(tmp_path / "b.yaml", "jobs:\n  - {kind: capture, out: ../shared/teapot}\n")
    [capture] = load_batch(path, tmp_path / "out")
    assert capture.out.resolve() == tmp_path / "shared/teapot"


@pytest.mark.parametrize(
    "text, message",
    [
        ("jobs: []", "jobs: expected a non-empty list of jobs"),
        ("runs: []", "jobs: the file must hold one key, `jobs:`"),
        ("jobs: [", "jobs: not valid YAML"),
    ],
)
def test_batch_file_shape_errors(tmp_path, text, message):
    path = write(tmp_path / "b.yaml", text)
    with pytest.raises(ConfigError, match=message):
        load_batch(path, tmp_path / "out")
    with pytest.raises(ConfigError, match="cannot read the batch file"):
        load_batch(tmp_path / "missing.yaml", tmp_path / "out")


def test_batch_command_refuses_a_bad_file_before_writing_anything(tmp_path, capsys):
    path = write(tmp_path / "b.yaml", "jobs:\n  - {kind: capture, out: a, grasps: many}\n")
    assert main(["batch", str(path), "--out", str(tmp_path / "out")]) == 1
    assert capsys.readouterr().err.startswith(f"error: {path}: jobs[0].grasps: Input should be a valid integer")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "options, message",
    [
        (["--ray-address", "127.0.0.1:6379"], "--ray-address: runs jobs on a Ray cluster: add --executor ray"),
        (["--executor", "ray", "--retries", "-1"], "--retries: must be >= 0, got -1"),
        (["--retries", "3"], "--retries: sets the attempts of a Ray task: add --executor ray"),
        (["--retries", "2"], "--retries: sets the attempts of a Ray task: add --executor ray"),  # (its default)
        (
            ["--executor", "processes", "--retries", "0"],
            "--retries: sets the attempts of a Ray task: add --executor ray",
        ),
        (["--workers", "0"], "--workers: must be >= 1, got 0"),
        (
            ["--executor", "local", "--workers", "2"],
            "--workers: sets the jobs run side by side by --executor processes",
        ),
    ],
)
def test_executor_option_mistakes_are_usage_errors(tmp_path, capsys, options, message):
    path = write(tmp_path / "b.yaml", "jobs:\n  - {kind: capture, out: a}\n")
    assert main(["batch", str(path), "--out", str(tmp_path / "out"), *options]) == 2
    assert message in capsys.readouterr().err
    assert main(["bench", "touches", "--out", str(tmp_path / "t"), *options]) == 2
    assert not (tmp_path / "out").exists() and not (tmp_path / "t").exists()


def test_retries_defaults_to_rays_two_and_help_says_so(capsys):
    assert ExecutorOptions(executor="ray").run_jobs_args()["retries"] == RETRIES == 2
    assert ExecutorOptions(executor="ray", retries=0).run_jobs_args()["retries"] == 0
    with pytest.raises(SystemExit):
        main(["batch", "--help"])
    assert "whose worker died (default: 2)" in " ".join(capsys.readouterr().out.split())


def test_an_address_where_no_cluster_answers_is_one_error(tmp_path, capsys, monkeypatch):
    with socket.socket() as s:  # a port nothing listens on once closed
        s.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{s.getsockname()[1]}"
    path = write(tmp_path / "b.yaml", "jobs:\n  - {kind: capture, out: a}\n")
    assert (
        main(["batch", str(path), "--out", str(tmp_path / "out"), "--executor", "ray", "--ray-address", address]) == 1
    )
    assert capsys.readouterr().err.splitlines()[-1].startswith(f"error: --ray-address: nothing answers at {address} (")
    monkeypatch.setenv("RAY_ADDRESS", address)
    with pytest.raises(ConfigError, match=f"^RAY_ADDRESS: nothing answers at {address} "):
        run_jobs([FileJob("a", tmp_path / "a")], tmp_path, executor="ray", progress=False)


@pytest.mark.parametrize(
    "address, why",
    [
        ("not a host:xx", "'not a host' is not a host name or IP address"),
        ("head:xx", "the port must be an integer in 1..65535, got 'xx'"),
        ("head:0", "the port must be an integer in 1..65535, got '0'"),
        ("head:65536", "the port must be an integer in 1..65535, got '65536'"),
        ("head: 6379", "the port must be an integer in 1..65535, got ' 6379'"),
        ("head", "no port"),
        ("ray://head", "no port"),
        ("http://head:8265", "http:// is not a Ray address (ray:// is)"),
    ],
)
def test_a_malformed_ray_address_is_a_usage_error(tmp_path, capsys, monkeypatch, address, why):
    path = write(tmp_path / "b.yaml", "jobs:\n  - {kind: capture, out: a}\n")
    assert (
        main(["batch", str(path), "--out", str(tmp_path / "out"), "--executor", "ray", "--ray-address", address]) == 2
    )
    err = capsys.readouterr().err
    assert "error: --ray-address: expected HOST:PORT (of the cluster's head: " in err
    assert f"ray://HOST:PORT or auto, got {address!r}: {why} (see " in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()
    monkeypatch.setenv("RAY_ADDRESS", address)  # the same mistake in the environment: an error naming it
    with pytest.raises(ConfigError, match=f"^RAY_ADDRESS: expected HOST:PORT .*: {re.escape(why)}$"):
        run_jobs([FileJob("a", tmp_path / "a")], tmp_path, executor="ray", progress=False)


def test_the_ray_address_forms_ray_takes():
    assert check_ray_address("10.0.0.5:6379", "--ray-address") == ("10.0.0.5", 6379)
    assert check_ray_address("head-node.cluster.local:65535", "--ray-address") == ("head-node.cluster.local", 65535)
    assert check_ray_address("[fe80::1]:6379", "--ray-address") == ("fe80::1", 6379)
    assert check_ray_address("ray://head:10001", "--ray-address") == ("head", 10001)
    assert check_ray_address("auto", "--ray-address") is None and check_ray_address("local", "x") is None


def test_a_ray_error_at_init_is_one_line_naming_the_option(tmp_path, capsys, monkeypatch):
    import ray.client_builder

    # Ray's own error for a ray:// address without its client package (ValueError), whether installed or not
    monkeypatch.setattr(ray.client_builder, "get_ray_client_dependency_error", lambda: ImportError("no grpc"))
    path = write(tmp_path / "b.yaml", "jobs:\n  - {kind: capture, out: a}\n")
    with socket.socket() as server:  # something answers at the address
        server.bind(("127.0.0.1", 0))
        server.listen()
        address = f"ray://127.0.0.1:{server.getsockname()[1]}"
        assert (
            main(["batch", str(path), "--out", str(tmp_path / "out"), "--executor", "ray", "--ray-address", address])
            == 1
        )
    err = capsys.readouterr().err
    assert err.splitlines()[-1].startswith(
        f"error: --ray-address: cannot connect to a Ray cluster at {address}: "
        "ValueError: Ray Client requires pip package `ray[client]`. "
    )
    assert "Traceback" not in err


def test_batch_warns_of_a_run_trained_with_other_settings_and_keeps_it(tmp_path, caplog):
    from tacsplat.apps.batch import run_batch

    job = ReconstructJob(out=tmp_path / "r", scene=tmp_path, iterations=20, seed=3, name="reconstruct r")
    job.out.mkdir()
    recorded = ReconstructJob(out=job.out, scene=tmp_path, method="paper", iterations=20, seed=3).config().to_json()
    (job.out / "config.json").write_text(json.dumps(recorded))
    (job.out / "metrics.json").write_text(json.dumps({"cd": 0.02, "psnr": 20.0, "method": "paper"}))
    with caplog.at_level("WARNING"):
        run_batch([job], tmp_path, progress=False, executor="local")
    assert "reconstruct r:" in caplog.text and "trained with other settings (method paper -> " in caplog.text
    assert json.loads((job.out / "metrics.json").read_text())["method"] == "paper"  # kept


def test_batch_warns_of_a_capture_made_with_other_settings_and_keeps_it(tmp_path, caplog):
    from tacsplat.apps.batch import run_batch
    from tacsplat.datasets import Scene

    job = CaptureJob(out=tmp_path / "s", resolution=32, views=1, test_views=1, grasps=0, name="capture s")
    run_batch([job], tmp_path, progress=False, executor="local")
    with caplog.at_level("WARNING"):
        run_batch([replace(job, resolution=48)], tmp_path, progress=False, executor="local")
    assert "capture s:" in caplog.text and "a capture made with other settings (resolution 32 -> 48)" in caplog.text
    assert Scene.load(job.out).intrinsics.width == 32  # kept


def test_an_evaluate_job_evaluates_a_run_the_batch_trains_with_its_settings(tmp_path, capsys):
    import trimesh

    for name, radius in (("big.ply", 0.5), ("small.ply", 0.05)):
        trimesh.creation.icosphere(radius=radius).export(tmp_path / name)
    batch = """\
jobs:
  - {kind: capture, out: scenes/t, object: teapot, views: 3, test_views: 2, grasps: 1, resolution: 64}
  - {kind: reconstruct, out: runs/e, scene: scenes/t, iterations: 20}
  - {kind: evaluate, run: runs/e, gt_mesh: %s}
"""
    path, out = write(tmp_path / "b.yaml", batch % "big.ply"), tmp_path / "out"
    metrics, record = out / "runs/e/metrics.json", out / "runs/e/evaluated.json"

    def results() -> list[dict]:
        assert main(["batch", str(path), "--out", str(out), "--executor", "local"]) == 0
        with (out / "results.csv").open() as fh:
            return list(csv.DictReader(fh))

    rows = results()  # one row for the run: the evaluation's
    assert [(r["job"], r["run"]) for r in rows] == [("evaluate runs/e", "runs/e")]
    assert json.loads(metrics.read_text())["gt_source"] == f"mesh {tmp_path / 'big.ply'}"
    assert float(rows[0]["cd"]) == json.loads(metrics.read_text())["cd"]

    written = metrics.stat().st_mtime_ns, record.stat().st_mtime_ns
    assert results() == rows  # done: not evaluated again
    assert (metrics.stat().st_mtime_ns, record.stat().st_mtime_ns) == written

    write(path, batch % "small.ply")  # another ground truth: evaluated again with it
    (again,) = results()
    assert json.loads(metrics.read_text())["gt_source"] == f"mesh {tmp_path / 'small.ply'}"
    assert again["job"] == "evaluate runs/e" and again["cd"] != rows[0]["cd"]


def test_results_name_a_scene_alike_for_a_reconstruction_and_an_evaluation(tmp_path, monkeypatch):
    # a relative --out: a reconstruction's metrics.json has its scene relative to the cwd, an evaluation's absolute
    monkeypatch.chdir(tmp_path)
    path = write(
        tmp_path / "b.yaml",
        """\
jobs:
  - {kind: capture, out: scenes/t, object: teapot, views: 2, test_views: 1, grasps: 0, resolution: 32}
  - {kind: reconstruct, out: runs/a, scene: scenes/t, iterations: 5}
  - {kind: reconstruct, out: runs/e, scene: scenes/t, iterations: 5}
  - {kind: evaluate, run: runs/e}
""",
    )
    assert main(["batch", str(path), "--out", "out", "--executor", "local"]) == 0
    with open("out/results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["job"], r["scene"]) for r in rows] == [
        ("reconstruct runs/a", "scenes/t"),
        ("evaluate runs/e", "scenes/t"),
    ]


@pytest.mark.parametrize("executor", ["local", "processes"])
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_stop_a_batch_as_ctrl_c_does(tmp_path, executor, signum):
    # the running job is interrupted once (it saves what it did: a second signal would cut that short), and the
    # batch ends on a SignalInterrupt, which the command turns into exit 128 + the signal's number
    job = FileJob("trains", tmp_path / "trains", "block-once")
    script = (
        "import sys; from pathlib import Path; from batch_test_jobs import FileJob; "
        "from tacsplat.apps.executors import run_jobs; from tacsplat.interrupts import SignalInterrupt\n"
        "try:\n"
        f"    run_jobs([FileJob('trains', Path({str(job.folder)!r}), 'block-once')], Path({str(tmp_path)!r}), "
        f"executor={executor!r}, progress=False)\n"
        "except SignalInterrupt as exc:\n"
        "    sys.exit(128 + exc.signum)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")])}
    batch = subprocess.Popen([sys.executable, "-c", script], env=env)
    try:
        wait_until((job.folder / "started").exists)
        batch.send_signal(signum)
        assert batch.wait(timeout=60) == 128 + signum
    finally:
        batch.kill()
    assert (job.folder / "interrupted").exists() and (job.folder / "saved").exists() and not job.complete()


def test_a_signal_ray_turns_into_a_plain_keyboard_interrupt_keeps_its_number():
    from tacsplat.apps.executors import _end_signals_interrupt
    from tacsplat.interrupts import SignalInterrupt

    with pytest.raises(SignalInterrupt) as info, _end_signals_interrupt():
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            wait_until(lambda: False)  # (until the handler raises)
        except SignalInterrupt:
            raise KeyboardInterrupt from None  # what Ray's wait and get raise instead
    assert info.value.signum == signal.SIGTERM


def test_the_last_progress_line_is_written_once(tmp_path, capsys, monkeypatch):
    """Before: a batch whose last job ended PLAIN_INTERVAL_S or more after the line before wrote its last line
    twice ("batch: 4/4 jobs in 111 s (...)"): by the count's update, then again by close."""
    monkeypatch.setattr("tacsplat.progress.PLAIN_INTERVAL_S", 0.0)  # a line at each update
    run_jobs([FileJob(name, tmp_path / name) for name in ("a", "b")], tmp_path, desc="tiny")
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("tiny: ")]
    assert [line.partition(" in ")[0] for line in lines] == ["tiny: 1/2 jobs", "tiny: 2/2 jobs"], lines
