"""The ray executor on the embedded local Ray that ``--executor ray`` starts without an address (shared by this
module's tests): a task that raises or whose worker dies is retried, then listed in failures.csv while the others
finish, and the rerun runs only what failed; Ctrl-C, or SIGTERM, cancels the outstanding tasks, and stops a batch
whose Ray is still starting once it has. (The tiny suite, local and on Ray value for value: test_batch_cluster.py.)"""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import ray

from tacsplat.apps.executors import FAILURES_CSV, connect, run_jobs
from tacsplat.interrupts import SignalInterrupt

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders

import batch_test_jobs  # noqa: E402
from batch_test_jobs import FileJob, wait_until  # noqa: E402


@pytest.fixture(scope="module")
def embedded_ray():
    """The embedded Ray of ``--executor ray`` with no address; the jobs run in its workers, which cannot import
    the test folder. Its processes start with SIGINT ignored, as those of a batch started in a script's background
    job do (Python then leaves Ctrl-C ignored, and ray.cancel's interruption with it)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.delenv("RAY_ADDRESS", raising=False)
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            assert connect(None)  # started here
        finally:
            signal.signal(signal.SIGINT, previous)
        ray.cloudpickle.register_pickle_by_value(batch_test_jobs)
        try:
            assert not connect(None)  # run_jobs uses it, and leaves it running
            yield
        finally:
            ray.shutdown()


def read_rows(path: Path) -> list[dict]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def test_failures_are_retried_listed_and_the_rerun_runs_only_them(tmp_path, embedded_ray):
    jobs = [
        FileJob("ok", tmp_path / "ok"),
        FileJob("dies-once", tmp_path / "dies-once", "die-once"),
        FileJob("flaky", tmp_path / "flaky", "raise-while-broken"),
        FileJob("after-flaky", tmp_path / "after-flaky", needs=("flaky",)),
        FileJob("bad-input", tmp_path / "bad-input", "config-error"),
        FileJob("ok-too", tmp_path / "ok-too"),
    ]
    (tmp_path / "flaky").mkdir()
    (tmp_path / "flaky" / "broken").touch()
    finished = []
    outcome = run_jobs(
        jobs,
        tmp_path,
        executor="ray",
        retries=1,
        progress=False,
        on_done=lambda job, summary: finished.append((job.name, summary)),
    )

    assert sorted(outcome.done) == ["dies-once", "ok", "ok-too"]
    assert sorted(finished) == [("dies-once", {"attempts": 2}), ("ok", {"attempts": 1}), ("ok-too", {"attempts": 1})]
    assert os.getpid() not in jobs[0].attempts()  # a Ray worker ran it
    assert len(set(jobs[1].attempts())) == 2  # its worker died; the retry ran in another one
    assert len(jobs[2].attempts()) == 2  # raised: retried once, then given up
    assert len(jobs[4].attempts()) == 1  # a TacsplatError (bad input) is not retried
    assert jobs[3].attempts() == []
    failures = {r["job"]: r for r in read_rows(tmp_path / FAILURES_CSV)}
    assert set(failures) == {"flaky", "after-flaky", "bad-input"}
    assert failures["flaky"]["attempts"] == "2" and failures["flaky"]["error"].startswith("RuntimeError: ")
    assert "broken is there" in failures["flaky"]["error"]
    assert failures["after-flaky"] == {
        "job": "after-flaky",
        "attempts": "0",
        "error": "not run: needs flaky, which failed",
    }
    assert outcome.not_run == ["after-flaky"]
    assert failures["bad-input"]["error"] == "threshold: must be > 0, got -1"

    (tmp_path / "flaky" / "broken").unlink()
    rerun = run_jobs(jobs[:5], tmp_path, executor="ray", retries=1, progress=False)
    assert rerun.skipped == ["ok", "dies-once"] and rerun.done == ["flaky", "after-flaky"]
    assert list(rerun.failed) == ["bad-input"]
    assert len(jobs[0].attempts()) == 1 and len(jobs[1].attempts()) == 2  # the finished jobs were not run again
    assert [r["job"] for r in read_rows(tmp_path / FAILURES_CSV)] == ["bad-input"]


def test_ctrl_c_cancels_outstanding_tasks_and_keeps_finished_ones(tmp_path, embedded_ray):
    hangs = FileJob("hangs", tmp_path / "hangs", "block")
    first = FileJob("first", tmp_path / "first", wait_for=hangs.folder / "started")
    # every CPU of the node: cannot start while another task holds one
    queued = FileJob("queued", tmp_path / "queued", cpus=ray.cluster_resources()["CPU"])

    def interrupt(job, summary):
        raise KeyboardInterrupt  # Ctrl-C as the first job finishes

    with pytest.raises(KeyboardInterrupt):
        run_jobs([hangs, first, queued], tmp_path, executor="ray", on_done=interrupt, progress=False)
    assert first.complete()
    try:  # the running task got the cancellation
        wait_until((hangs.folder / "interrupted").exists, timeout_s=10)
    except TimeoutError:
        raise AssertionError(
            f"no KeyboardInterrupt in the running task: {hangs.folder} holds "
            f"{sorted(p.name for p in hangs.folder.iterdir())}, attempts {hangs.attempts()}"
        ) from None
    assert not hangs.complete() and queued.attempts() == []
    assert ray.is_initialized()  # the batch did not own this Ray: it is left running


def test_sigterm_cancels_outstanding_tasks_as_ctrl_c_does(tmp_path, embedded_ray):
    # not Ray's handler (which aborts the process with a crash dump, cancelling nothing): a SignalInterrupt
    hangs = FileJob("hangs", tmp_path / "hangs", "block")
    first = FileJob("first", tmp_path / "first", wait_for=hangs.folder / "started")

    def terminate(job, summary):
        os.kill(os.getpid(), signal.SIGTERM)  # `kill` as the first job finishes

    with pytest.raises(SignalInterrupt) as info:
        run_jobs([hangs, first], tmp_path, executor="ray", on_done=terminate, progress=False)
    assert info.value.signum == signal.SIGTERM and first.complete()
    wait_until((hangs.folder / "interrupted").exists, timeout_s=10)  # the running task got the cancellation
    assert not hangs.complete()


def session_processes(sid: int) -> dict[int, str]:
    """The live processes of the session ``sid`` (pid -> name; zombies aside)."""
    found = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:  # (ended meanwhile)
            continue
        state, _, _, session = text[text.rindex(")") + 2 :].split()[:4]
        if int(session) == sid and state != "Z":
            found[int(stat.parent.name)] = text[text.index("(") + 1 : text.rindex(")")]
    return found


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigterm_while_ray_starts_stops_the_batch_once_it_has(tmp_path):
    # not ray.init's handlers (exit 15, or 1, cut short: the agents of its raylet outlive it by a minute) nor its
    # core worker's (abort): the batch stops as at any other time, and ends Ray
    path = tmp_path / "b.yaml"
    path.write_text("jobs:\n  - {kind: capture, out: scenes/t, views: 1, test_views: 1, grasps: 1, resolution: 32}\n")
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    out = str(tmp_path / "out")
    command = [sys.executable, "-m", "tacsplat", "batch", str(path), "--out", out, "--executor", "ray"]
    batch = subprocess.Popen(command, env=env, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        wait_until(lambda: "gcs_server" in session_processes(batch.pid).values())  # Ray's first process: starting
        batch.send_signal(signal.SIGTERM)
        _, err = batch.communicate(timeout=120)
    finally:
        batch.kill()
    assert batch.returncode == 128 + signal.SIGTERM, err
    assert "interrupted" in err.splitlines() and "Traceback" not in err and "SIGTERM received" not in err, err
    wait_until(lambda: not session_processes(batch.pid), timeout_s=20)  # Ray's processes ended with the batch
    assert not (tmp_path / "out" / "scenes").exists()  # no job started
