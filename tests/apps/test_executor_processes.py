"""The processes executor: jobs side by side in spawned worker processes of this machine, started in order once
their needs have finished and while CPUs are free; failures listed while the others finish, a dead worker failing
only the job it ran (the jobs beside it stopped once, saving what they did, and run again), the workers' log records
reaching this process, and Ctrl-C interrupting the running jobs (which keep what they finished) while the queued
ones never start."""

from __future__ import annotations

import csv
import logging
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from tacsplat.apps import executors
from tacsplat.apps.executors import FAILURES_CSV, default_workers, resolve_executor, run_jobs, side_by_side, usable_cpus

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders; spawned
# workers get this process's sys.path

from batch_test_jobs import DyingWarmJob, FileJob, ImportingJob, SlowWarmJob, wait_until  # noqa: E402


def read_rows(path: Path) -> list[dict]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def test_jobs_run_side_by_side_in_workers_and_failures_are_listed(tmp_path):
    # "second" finishes only once "first" has started, and "first" only once "second" has: both must run at once
    first = FileJob("first", tmp_path / "first", wait_for=tmp_path / "second" / "attempts")
    second = FileJob("second", tmp_path / "second", wait_for=tmp_path / "first" / "attempts")
    jobs = [
        first,
        second,
        FileJob("flaky", tmp_path / "flaky", "raise-while-broken"),
        FileJob("after-flaky", tmp_path / "after-flaky", needs=("flaky",)),
        FileJob("bad-input", tmp_path / "bad-input", "config-error"),
        FileJob("after-first", tmp_path / "after-first", needs=("first",)),
    ]
    (tmp_path / "flaky").mkdir()
    (tmp_path / "flaky" / "broken").touch()
    finished = []
    outcome = run_jobs(
        jobs,
        tmp_path,
        executor="processes",
        workers=2,
        progress=False,
        on_done=lambda job, summary: finished.append(job.name),
    )

    assert sorted(outcome.done) == ["after-first", "first", "second"] and sorted(finished) == sorted(outcome.done)
    assert finished.index("first") < finished.index("after-first")
    pids = {job.name: job.attempts() for job in jobs}
    assert os.getpid() not in pids["first"] + pids["second"] and pids["after-flaky"] == []
    failures = {r["job"]: r for r in read_rows(tmp_path / FAILURES_CSV)}
    assert set(failures) == {"flaky", "after-flaky", "bad-input"}
    assert failures["flaky"]["error"].startswith("RuntimeError: ") and "broken is there" in failures["flaky"]["error"]
    assert failures["after-flaky"]["error"] == "not run: needs flaky, which failed"
    assert outcome.not_run == ["after-flaky"]
    assert failures["bad-input"]["error"] == "threshold: must be > 0, got -1"

    (tmp_path / "flaky" / "broken").unlink()
    rerun = run_jobs(jobs[:4], tmp_path, executor="processes", workers=2, progress=False)
    assert rerun.skipped == ["first", "second"] and rerun.done == ["flaky", "after-flaky"] and not rerun.failed
    assert not (tmp_path / FAILURES_CSV).exists()


@dataclass(frozen=True)
class SlowJob(FileJob):
    def __call__(self) -> dict:
        time.sleep(0.5)
        return super().__call__()


def test_a_job_wanting_every_cpu_runs_alone(tmp_path):
    big = SlowJob("big", tmp_path / "big", cpus=2.0)
    small = FileJob("small", tmp_path / "small")
    outcome = run_jobs([big, small], tmp_path, executor="processes", workers=2, progress=False)
    assert outcome.done == ["big", "small"]
    # side by side, "small" would have started (and logged its attempt) while "big" slept
    assert (small.folder / "attempts").stat().st_mtime_ns >= (big.folder / "done").stat().st_mtime_ns


def test_a_free_cpu_starts_a_worker_that_imports_what_waiting_jobs_import(tmp_path, monkeypatch):
    # "capture" finishes only once another worker has run the warm-up of "train" (which waits for it)
    warm = tmp_path / "warm"
    warm.mkdir()
    monkeypatch.setenv("TACSPLAT_TEST_WARM_DIR", str(warm))
    capture = FileJob("capture", tmp_path / "capture", wait_for=warm / "imported")
    train = ImportingJob("train", tmp_path / "train", needs=("capture",))
    outcome = run_jobs([capture, train], tmp_path, executor="processes", workers=2, progress=False)
    assert outcome.done == ["capture", "train"]
    importer = int((warm / "imported").read_text())
    assert importer not in capture.attempts() + [os.getpid()]  # a second worker, started while capture ran


def test_the_first_job_waits_for_the_worker_still_warming_up(tmp_path):
    # "capture" ends while the other worker still warms up for the trainings (until "second" has started): the
    # capture's idle, cold worker takes the second training, and the first (the longest, as bench paper orders
    # them) the warm worker
    capture = FileJob("capture", tmp_path / "capture")
    first = SlowWarmJob("first", tmp_path / "first", needs=("capture",), wait_for=tmp_path / "second" / "attempts")
    second = FileJob("second", tmp_path / "second", needs=("capture",), wait_for=tmp_path / "warmed")  # (long)
    outcome = run_jobs([capture, first, second], tmp_path, executor="processes", workers=2, progress=False)
    assert sorted(outcome.done) == ["capture", "first", "second"]
    warm = int((tmp_path / "warmed").read_text())
    assert first.attempts() == [warm] and second.attempts() == capture.attempts()


def test_a_dead_worker_fails_its_job_and_the_rest_go_on(tmp_path):
    jobs = [FileJob("dies", tmp_path / "dies", "die-once"), FileJob("later", tmp_path / "later")]
    outcome = run_jobs(jobs, tmp_path, executor="processes", workers=1, progress=False)
    assert outcome.done == ["later"]
    assert read_rows(tmp_path / FAILURES_CSV) == [
        {"job": "dies", "attempts": "1", "error": "its worker process died (out of memory, or killed)"}
    ]
    assert jobs[0].attempts()[0] != jobs[1].attempts()[0]  # the rest ran in a new worker


def test_a_dead_worker_fails_only_its_job_and_the_jobs_beside_it_save_and_run_again(tmp_path):
    # "dies" kills its worker while "beside" runs in the other: "beside" gets one SIGINT (a second would cut its
    # saving short), saves, and runs again in a new worker, as "queued" runs there; "after-dies" is not run
    beside = FileJob("beside", tmp_path / "beside", "block-once")
    dies = FileJob("dies", tmp_path / "dies", "die-once", wait_for=beside.folder / "started")
    queued = FileJob("queued", tmp_path / "queued")
    after = FileJob("after-dies", tmp_path / "after-dies", needs=("dies",))
    outcome = run_jobs([beside, dies, queued, after], tmp_path, executor="processes", workers=2, progress=False)

    assert sorted(outcome.done) == ["beside", "queued"] and list(outcome.failed) == ["dies", "after-dies"]
    assert read_rows(tmp_path / FAILURES_CSV) == [
        {"job": "dies", "attempts": "1", "error": "its worker process died (out of memory, or killed)"},
        {"job": "after-dies", "attempts": "0", "error": "not run: needs dies, which failed"},
    ]
    assert (beside.folder / "interrupted").read_text() == "KeyboardInterrupt" and (beside.folder / "saved").exists()
    first, second = beside.attempts()  # run again, in a new worker
    assert first != second and dies.attempts() != [first] and len(queued.attempts()) == 1


def test_a_worker_that_dies_warming_up_fails_no_job(tmp_path):
    # the worker warming up for "train" dies while "capture" runs: "capture" saves and runs again, on a pool
    # that no longer warms up, and so does "train"
    capture = FileJob("capture", tmp_path / "capture", "block-once")
    train = DyingWarmJob("train", tmp_path / "train", needs=("capture",), wait_for=capture.folder / "started")
    outcome = run_jobs([capture, train], tmp_path, executor="processes", workers=2, progress=False)
    assert outcome.done == ["capture", "train"] and not outcome.failed
    assert (capture.folder / "saved").exists() and len(capture.attempts()) == 2


@dataclass(frozen=True)
class LoggingJob(FileJob):
    def __call__(self) -> dict:
        logging.getLogger("tacsplat.test_worker").warning("hello from %s", self.name)
        return super().__call__()


class SlowToSend:
    """A log record's attribute whose pickling, as the record leaves its worker, takes a second: the delay a loaded
    machine can put between a worker logging a record and the record reaching the batch's process."""

    def __reduce__(self):
        time.sleep(1.0)
        return str, ("sent",)


@dataclass(frozen=True)
class SlowLoggingJob(FileJob):
    def __call__(self) -> dict:
        logging.getLogger("tacsplat.test_worker").warning("hello from %s", self.name, extra={"slow": SlowToSend()})
        return super().__call__()


@pytest.mark.parametrize("job", [LoggingJob, SlowLoggingJob])
def test_worker_log_records_reach_this_process(tmp_path, caplog, job):
    # a record logged just before the job returns is handled here before run_jobs returns, however slow to send
    with caplog.at_level(logging.INFO):
        run_jobs([job("talks", tmp_path / "talks")], tmp_path, executor="processes", progress=False)
    assert [(r.name, r.getMessage()) for r in caplog.records if r.name == "tacsplat.test_worker"] == [
        ("tacsplat.test_worker", "hello from talks")
    ]


def test_ctrl_c_interrupts_running_jobs_and_keeps_finished_ones(tmp_path):
    hangs = FileJob("hangs", tmp_path / "hangs", "block")
    first = FileJob("first", tmp_path / "first", wait_for=hangs.folder / "started")
    queued = FileJob("queued", tmp_path / "queued")

    def interrupt(job, summary):
        raise KeyboardInterrupt  # Ctrl-C as the first job finishes

    with pytest.raises(KeyboardInterrupt):
        run_jobs([hangs, first, queued], tmp_path, executor="processes", workers=2, on_done=interrupt, progress=False)
    assert first.complete()
    assert (hangs.folder / "interrupted").exists()  # the running job got KeyboardInterrupt (and could save)
    assert not hangs.complete() and queued.attempts() == []


def test_default_workers_are_the_cores_the_memory_can_hold(monkeypatch):
    monkeypatch.setattr(executors, "usable_cpus", lambda: 16)
    pages = {"SC_PAGE_SIZE": 4096, "SC_PHYS_PAGES": 8 * 1024**3 // 4096}  # 8 GB: 4 workers of 2 GB
    monkeypatch.setattr(os, "sysconf", pages.__getitem__)
    assert default_workers() == 4
    pages["SC_PHYS_PAGES"] = 1024**3 // 4096  # 1 GB: still one
    assert default_workers() == 1
    pages["SC_PHYS_PAGES"] = 128 * 1024**3 // 4096
    assert default_workers() == 16


def test_auto_is_processes_on_a_cpu_machine_with_cores_to_share(monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_executor("auto") == ("processes" if usable_cpus() >= 2 else "local")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_executor("auto") == "local"
    assert resolve_executor("ray") == "ray"
    assert side_by_side("local") is None and side_by_side("processes", 3) == "up to 3 worker processes"


def test_workers_stop_their_jobs_and_exit_when_the_batch_process_is_killed(tmp_path):
    hangs = FileJob("hangs", tmp_path / "hangs", "block")
    script = (
        "import sys; from pathlib import Path; from batch_test_jobs import FileJob; "
        "from tacsplat.apps.executors import run_jobs; "
        f"run_jobs([FileJob('hangs', Path({str(hangs.folder)!r}), 'block')], Path({str(tmp_path)!r}), "
        "executor='processes', progress=False)"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")])}
    batch = subprocess.Popen([sys.executable, "-c", script], env=env)
    try:
        wait_until((hangs.folder / "started").exists)
        batch.kill()  # SIGKILL: no chance to clean up
        batch.wait()
        wait_until((hangs.folder / "interrupted").exists, timeout_s=10)  # the job got KeyboardInterrupt
        worker = hangs.attempts()[0]
        wait_until(lambda: not _alive(worker), timeout_s=10)  # and its worker exited
    finally:
        batch.kill()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").is_file() and Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
