"""Jobs asking for more than there is: on Ray, a job no node has the CPUs for fails at once, naming what it asked
for (Ray would queue it forever) while the others run; any executor takes an unbounded ``cpus`` without
crashing."""

from __future__ import annotations

import csv
import math
import signal
import sys
from pathlib import Path

import pytest

from tacsplat.apps import executors
from tacsplat.apps.executors import FAILURES_CSV, run_jobs

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders

import batch_test_jobs  # noqa: E402
from batch_test_jobs import FileJob  # noqa: E402

HANG_S = 120  # a batch still running after this long waits for something that never comes


class Hung(Exception):
    pass


def test_a_ray_job_no_node_can_hold_fails_at_once_and_the_others_run(tmp_path, monkeypatch):
    ray = pytest.importorskip("ray")
    monkeypatch.delenv("RAY_ADDRESS", raising=False)  # run_jobs starts an embedded local Ray, and stops it
    ray.cloudpickle.register_pickle_by_value(batch_test_jobs)  # (its workers cannot import the test folder)
    jobs = [
        FileJob("huge", tmp_path / "huge", cpus=1000),  # more than any one machine this runs on
        FileJob("after-huge", tmp_path / "after-huge", needs=("huge",)),
        FileJob("ok", tmp_path / "ok"),
    ]

    def hung(signum, frame):
        raise Hung(f"the batch still runs after {HANG_S} s")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(HANG_S)
    try:
        outcome = run_jobs(jobs, tmp_path, executor="ray", progress=False)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)

    assert outcome.done == ["ok"] and outcome.not_run == ["after-huge"]
    assert not ray.is_initialized()
    with (tmp_path / FAILURES_CSV).open() as fh:
        failures = {row["job"]: row for row in csv.DictReader(fh)}
    assert set(failures) == {"huge", "after-huge"} and failures["huge"]["attempts"] == "0"
    error = failures["huge"]["error"]
    assert error.startswith("needs 1000 CPUs and 0 GPUs on one node;") and " CPUs" in error.partition(";")[2], error
    assert jobs[0].attempts() == [] and jobs[1].attempts() == []


@pytest.mark.parametrize("cpus", [math.inf, math.nan, 0.0, 1e300])
def test_any_cpus_limits_the_threads_to_the_cores(cpus):
    numba = pytest.importorskip("numba")
    before = numba.get_num_threads()
    try:
        executors._limit_threads(cpus)
        assert 1 <= numba.get_num_threads() <= numba.config.NUMBA_NUM_THREADS
    finally:
        numba.set_num_threads(before)
