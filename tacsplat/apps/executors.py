"""Run a batch of jobs in this process (``local``), in worker processes here (``processes``) or as Ray tasks
(``ray``), with the same results.

A job (:class:`Job`) is a pure function of its fields that writes one output
folder: ``complete()`` says whether that folder already holds its finished
output (the job is then skipped), calling it does the work (resuming what an
interruption left) and returns a small summary. ``needs`` names the jobs whose
outputs it reads: they run first, and a job whose need failed is not run.
Jobs hand each other paths on a filesystem every worker sees, never arrays.

- ``local``: one job after another in this process, in the order given.
- ``processes``: jobs side by side, each in a worker process of this machine, started in the order given once
  its needs have finished, filling ``workers`` CPUs (default: this machine's cores, as far as its memory holds
  2 GB for each; a job takes ``cpus`` of them). A CPU training spends most of a step in single-threaded torch
  code, so on 2 cores two trainings side by side finish sooner than one after the other on both (two of the
  demo's: 1.6x the throughput). A CPU that would idle while the pending jobs wait for another's output starts
  a worker that runs their ``warm_up`` (a training's imports: 3 s), so the first of them starts at once.
  The workers' log records reach this process's handlers, at the levels its loggers have. A worker that dies
  (killed, out of memory) fails its job; the rest go on: the jobs running beside it are stopped as by Ctrl-C (one
  SIGINT: a training saves its checkpoint) and run again, with the jobs not started yet, in new workers (a
  training resumes).
- ``auto``: ``processes`` on a machine with at least 2 cores and no CUDA device, else ``local``.
- ``ray``: every job a Ray task declaring its CPUs (and a GPU where it trains on
  CUDA); a task waits for its needs' tasks (their object refs are its
  arguments). A task that raises, or whose worker dies, is retried ``retries``
  times, except on a :class:`TacsplatError` (a mistake in its input, which a
  retry would repeat). A job that no node of the cluster has the CPUs and GPUs
  for (as its nodes are when the batch starts) fails at once: Ray would queue
  it for ever. Without an address (``--ray-address`` or ``RAY_ADDRESS``),
  or with ``local``, an embedded local Ray is started for the batch and stopped
  after it. An address Ray cannot take (:func:`check_ray_address`), one where
  nothing answers, or one whose ``ray.init`` fails is one error naming it.

Whichever the executor, a job that fails for good is listed in ``OUT/failures.csv`` with
its error while the jobs that do not need it go on; rerunning the same command
runs only what failed or never ran. Ctrl-C, SIGTERM (``kill``) or SIGHUP (a closed terminal) cancels the
outstanding tasks (a training in progress checkpoints; further signals are ignored meanwhile) and leaves every
finished job intact; the command then exits with 128 + the signal's number. While Ray starts (or connects), the
signal waits until it has.
One progress bar counts the jobs done, running and failed.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import logging
import logging.handlers
import multiprocessing
import multiprocessing.queues
import os
import re
import signal
import socket
import threading
import time
from collections import Counter
from concurrent import futures
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Callable, Literal, Protocol, Sequence, get_args

import tyro

from tacsplat.errors import ConfigError, TacsplatError, UsageError
from tacsplat.interrupts import END_SIGNALS, SignalInterrupt, ctrl_c_interrupts, signals_held, signals_interrupt
from tacsplat.progress import progress_bar

log = logging.getLogger(__name__)

Executor = Literal["auto", "local", "processes", "ray"]
EXECUTORS = get_args(Executor)
FAILURES_CSV = "failures.csv"
FAILURE_COLUMNS = ("job", "attempts", "error")
RETRIES = 2  # extra attempts of a Ray task that raised or whose worker died (--retries: with --executor ray only)
EMBEDDED_OBJECT_STORE_BYTES = 256 * 1024**2  # jobs pass paths and small summaries, never arrays
POLL_S = 1.0  # progress refresh while waiting for Ray tasks or worker processes
PROBE_S = 5.0  # for an answer at --ray-address
CANCEL_GRACE_S = 10.0  # after Ctrl-C: time for cancelled tasks to stop (a training saves its checkpoint)
WORKER_MEMORY_BYTES = 2 * 1024**3  # memory a processes-executor worker may need (default_workers)


class BatchError(TacsplatError):
    """Jobs of a batch failed (each listed with its error in the batch's failures.csv); the others finished."""


class Job(Protocol):
    """What the executors run; see the module docstring."""

    name: str  # unique in its batch; shown in the progress, the log and failures.csv
    needs: tuple[str, ...]  # names of the jobs whose outputs this one reads
    cpus: float  # CPUs it uses (Ray reserves them; its numba threads are limited to them)
    # optional: ``warm_up()``, which imports what its call will (:func:`_warm_up` runs it ahead)

    def gpus(self, cluster_has_gpus: bool) -> float: ...

    def complete(self) -> bool: ...

    def __call__(self) -> dict: ...


@dataclass
class BatchOutcome:
    """What one invocation did: names of the jobs run, skipped (already complete) and failed (-> error); those of
    the failed that were not run, since a job they need failed, are also in ``not_run``."""

    done: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    not_run: list[str] = field(default_factory=list)

    def raise_if_failed(self, out: Path) -> None:
        """A :class:`BatchError` naming the first failure and ``failures.csv`` when any job failed."""
        if self.failed:
            name, error = next(iter(self.failed.items()))
            ran = len(self.failed) - len(self.not_run)
            not_run = f" and {len(self.not_run)} not run (a job they need failed)" if self.not_run else ""
            raise BatchError(
                f"{ran} of {len(self.done) + len(self.failed)} jobs failed{not_run} (first: {name}: "
                f"{error}); each is listed in {Path(out) / FAILURES_CSV}; rerun the same command to "
                "retry only those"
            )


@dataclass
class ExecutorOptions:
    """``--executor``, ``--workers``, ``--ray-address`` and ``--retries``: the options of every command that runs a
    batch (its options' field ``executors: Executors = field(default_factory=ExecutorOptions)``)."""

    executor: Executor = "auto"
    """local: one job after another in this process; processes: jobs side by side in worker processes of this
    machine (--workers); ray: each job a Ray task; auto: processes on a machine with 2 or more cores and no CUDA
    device, else local"""
    workers: Annotated[
        int | None,
        tyro.conf.arg(
            metavar="INT", help_behavior_hint="(default: this machine's cores, at most one per 2 GB of memory)"
        ),
    ] = None
    """--executor processes: CPUs to fill with jobs"""
    ray_address: Annotated[
        str | None,
        tyro.conf.arg(
            metavar="STR", help_behavior_hint="(default: RAY_ADDRESS, else an embedded local Ray for this batch)"
        ),
    ] = None
    """--executor ray: the Ray cluster to run on (host:port of `ray start --head`, ray://host:port of its Ray
    Client server, or auto)"""
    # None: not given, Ray's default RETRIES; any value given needs --executor ray
    retries: Annotated[int | None, tyro.conf.arg(metavar="INT", help_behavior_hint=f"(default: {RETRIES})")] = None
    """--executor ray: extra attempts of a Ray task that raised or whose worker died"""

    def run_jobs_args(self) -> dict:
        """The keyword arguments of :func:`run_jobs`; a UsageError naming an option whose value it refuses."""
        if self.retries is not None and self.retries < 0:
            raise UsageError("--retries", f"must be >= 0, got {self.retries}")
        if self.retries is not None and self.executor != "ray":  # (the others never retry: a rerun does)
            raise UsageError("--retries", "sets the attempts of a Ray task: add --executor ray")
        if self.ray_address and self.executor != "ray":
            raise UsageError("--ray-address", "runs jobs on a Ray cluster: add --executor ray")
        if self.ray_address:
            check_ray_address(self.ray_address, "--ray-address", UsageError)
        if self.workers is not None and self.workers < 1:
            raise UsageError("--workers", f"must be >= 1, got {self.workers}")
        if self.workers is not None and self.executor not in ("processes", "auto"):
            raise UsageError("--workers", "sets the jobs run side by side by --executor processes")
        return asdict(self) | {"retries": RETRIES if self.retries is None else self.retries}


Executors = Annotated[ExecutorOptions, tyro.conf.arg(name="")]  # a field `executors: Executors` of a command's options


def usable_cpus() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def default_workers() -> int:
    """The processes executor's CPUs to fill: :func:`usable_cpus`, but no more workers than the memory holds at
    :data:`WORKER_MEMORY_BYTES` each (a worker training the demo holds about 0.8 GB)."""
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # no sysconf (Windows): cores only
        return usable_cpus()
    return max(1, min(usable_cpus(), memory // WORKER_MEMORY_BYTES))


def resolve_executor(executor: str) -> str:
    """``auto`` made concrete (see the module docstring); the others unchanged."""
    if executor != "auto":
        return executor
    import torch

    return "processes" if usable_cpus() >= 2 and not torch.cuda.is_available() else "local"


def side_by_side(executor: str, workers: int | None = None) -> str | None:
    """How a resolved executor runs jobs at once ("up to 2 worker processes", "Ray tasks"); None for ``local``
    (reports say so: a run's train seconds then include the time it shared the cores)."""
    return {"local": None, "ray": "Ray tasks", "processes": f"up to {workers or default_workers()} worker processes"}[
        executor
    ]


def run_jobs(
    jobs: Sequence[Job],
    out: str | Path,
    executor: str = "local",
    ray_address: str | None = None,
    retries: int = RETRIES,
    on_done: Callable[[Job, dict], str | None] | None = None,
    desc: str = "batch",
    progress: bool = True,
    workers: int | None = None,
) -> BatchOutcome:
    """Run every job of ``jobs`` (needs listed before the jobs that read them) that is not complete yet.

    ``on_done(job, summary)`` runs in this process as each job finishes (to write a report so far); the line it
    returns, if any, is printed. Failures are written to ``out/failures.csv``. ``workers``: the CPUs the
    ``processes`` executor fills (default :func:`default_workers`).
    """
    if executor not in EXECUTORS:
        raise ConfigError("executor", f"unknown executor {executor!r}; choose from {', '.join(EXECUTORS)}")
    executor = resolve_executor(executor)
    check_order(jobs)
    batch = _Batch(Path(out), on_done)
    complete = [job.complete() for job in jobs]
    batch.outcome.skipped = [job.name for job, done in zip(jobs, complete) if done]
    todo = [job for job, done in zip(jobs, complete) if not done]
    if batch.outcome.skipped:
        log.info("%d of %d jobs already complete in %s: skipped", len(batch.outcome.skipped), len(jobs), out)
    owned = False
    with _end_signals_interrupt():
        try:
            if executor == "ray" and todo:
                with _signals_held():
                    owned = connect(ray_address)
            unit = "job" if len(todo) == 1 else "jobs"  # ("1/1 job", "0/2 jobs")
            batch.bar = progress_bar(total=len(todo), desc=desc, unit=unit, enabled=progress)
            if executor == "local":
                _run_local(todo, batch)
            elif executor == "processes":  # a dead worker fails its job; a new set of workers runs the rest
                warm = True
                while todo:
                    todo, warm = _run_pool(todo, batch, workers or default_workers(), warm)
            else:
                _run_ray(todo, batch, retries)
        finally:
            if batch.bar is not None:
                batch.bar.close()
            if owned:
                import ray

                ray.shutdown()
    batch.finish()
    return batch.outcome


@contextlib.contextmanager
def _end_signals_interrupt():
    """SIGTERM, SIGHUP (and SIGQUIT) stop the jobs as Ctrl-C does: :func:`signals_interrupt` raises a
    SignalInterrupt, a KeyboardInterrupt, and once one has, further signals are ignored until that is done (a
    training's checkpoint). Where Ray's wait or get turned the SignalInterrupt into a plain KeyboardInterrupt (its
    signal lost: exit 130 for a SIGTERM), it is raised again as that signal's."""
    received: list[int] = []
    with signals_interrupt(once=True):
        if threading.current_thread() is threading.main_thread():  # (elsewhere signals_interrupt changes nothing)
            for signum in END_SIGNALS:
                handler = signal.getsignal(signum)
                if callable(handler):  # (signals_interrupt's; not a signal ignored on entry: nohup's SIGHUP)
                    signal.signal(signum, functools.partial(_noted, handler, received))
        try:
            yield
        except KeyboardInterrupt as exc:
            if received and not isinstance(exc, SignalInterrupt):
                raise SignalInterrupt(received[0]) from None
            raise


def _noted(handler, received: list[int], signum: int, frame) -> None:
    received.append(signum)
    handler(signum, frame)


@contextlib.contextmanager
def _signals_held():
    """While Ray starts (connect()): an ending signal is held until it has, then raised to the handler in force
    before (:func:`~tacsplat.interrupts.signals_held`; a start cut short leaves Ray's processes behind, the agents
    of its raylet for a minute, and may crash this process at its exit). ray.init's own SIGTERM handlers (which exit
    with code 15, or 1) are left out meanwhile, and the handlers are put back after it (its core worker replaces
    SIGTERM's with one that aborts this process with a crash dump, cancelling nothing)."""
    if threading.current_thread() is not threading.main_thread():  # (where ray.init sets no handler either)
        yield
        return
    import ray

    utils = ray._private.utils  # (its set_sigterm_handler: how ray.init installs its handlers)

    with signals_held():
        set_sigterm_handler, utils.set_sigterm_handler = utils.set_sigterm_handler, lambda handler: None
        try:
            yield
        finally:
            utils.set_sigterm_handler = set_sigterm_handler


def check_order(jobs: Sequence[Job]) -> None:
    """Names are unique and every need names an earlier job (a programming error otherwise)."""
    seen: set[str] = set()
    for job in jobs:
        if job.name in seen:
            raise ValueError(f"two jobs are named {job.name!r}")
        if missing := [n for n in job.needs if n not in seen]:
            raise ValueError(f"job {job.name!r} needs {missing}, which is not listed before it")
        seen.add(job.name)


class _Batch:
    """The bookkeeping both executors share: outcome, progress bar, failures.csv, the on_done callback."""

    def __init__(self, out: Path, on_done):
        self.out, self.on_done = out, on_done
        self.outcome = BatchOutcome()
        self.attempts: dict[str, int] = {}
        self.bar = None
        self.running: set[str] = set()

    def show(self) -> None:
        """The bar counts the jobs finished either way; its text says how many are done, running and failed."""
        running = sorted(self.running)
        what = f" ({running[0]})" if len(running) == 1 else ""
        self.bar.set_postfix_str(
            f"done {len(self.outcome.done)}, running {len(running)}{what}, failed {len(self.outcome.failed)}"
        )

    def started(self, names) -> None:
        self.running = set(names)
        self.show()

    def ended(self, job: Job, status: str, value, attempts: int = 1) -> None:
        """An attempt's result: ``("done", summary)`` or ``("failed", error)``."""
        self.running.discard(job.name)
        if status == "done":
            self.outcome.done.append(job.name)
            if line := (self.on_done(job, value) if self.on_done else None):
                self.bar.write(line)
        else:
            self.outcome.failed[job.name] = value
            self.attempts[job.name] = attempts
            log.error("%s failed: %s", job.name, value)
            self._write_failures()
        self.show()  # (first: the line the count's update may write says this job is no longer running)
        self.bar.update(1)

    def blocked_by(self, job: Job) -> str | None:
        return next((n for n in job.needs if n in self.outcome.failed), None)

    def not_run(self, job: Job, need: str) -> None:
        """``job`` is not run: it needs ``need``, which failed (listed in failures.csv, so a rerun runs it)."""
        self.outcome.not_run.append(job.name)
        self.ended(job, "failed", f"not run: needs {need}, which failed", attempts=0)

    def _write_failures(self) -> None:
        from tacsplat.apps.report import write_csv

        failed = [(name, self.attempts[name], error) for name, error in self.outcome.failed.items()]
        write_csv([dict(zip(FAILURE_COLUMNS, row)) for row in failed], self.out / FAILURES_CSV, FAILURE_COLUMNS)

    def finish(self) -> None:
        """A failures.csv of an earlier invocation is removed once nothing failed."""
        if not self.outcome.failed:
            (self.out / FAILURES_CSV).unlink(missing_ok=True)


def _describe(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, TacsplatError) else f"{type(exc).__name__}: {exc}"


# ---------------------------------------------------------------------- local


def _run_local(todo: list[Job], batch: _Batch) -> None:
    """One job after another in this process; KeyboardInterrupt stops at once (finished jobs stay)."""
    for job in todo:
        if need := batch.blocked_by(job):
            batch.not_run(job, need)
            continue
        batch.started([job.name])
        batch.ended(job, *_call(job))


def _call(job: Job) -> tuple[str, object]:
    """``("done", summary)`` or ``("failed", error)`` of one attempt of ``job`` (an error as text: not every
    exception survives pickling); a failure is recorded in failures.csv and the jobs that do not need it go on."""
    try:
        return "done", job()
    except Exception as exc:  # noqa: BLE001 - the batch records it
        if not isinstance(exc, TacsplatError):
            log.debug("%s raised", job.name, exc_info=True)
        return "failed", _describe(exc)


# ---------------------------------------------------------------------- processes

_job_running = False  # in a worker: a job is running (SIGINT interrupts it; an idle worker ignores SIGINT)
_batch_pid = 0  # in a worker: the batch's process (the worker's parent until that dies)
_stopping = None  # in a worker: its pool's flag (shared), set once the batch stops the pool's workers
_events = None  # in a worker: where it says what becomes of each job it takes (_PoolEvents)
PR_SET_PDEATHSIG = 1  # Linux prctl option: a signal for this process when its parent dies
STOPPED_EXIT = 130  # a worker's exit status once it has stopped (its job as after Ctrl-C) for a stopping pool
DIED = "its worker process died (out of memory, or killed)"


def _orphaned() -> bool:
    return os.getppid() != _batch_pid


def _on_interrupt(signum, frame) -> None:
    """A worker's SIGINT: KeyboardInterrupt in its job (a training stops after its step and checkpoints), once;
    while idle, nothing, unless its pool is stopping or the batch's process is gone (then the worker exits)."""
    global _job_running
    if _job_running:
        _job_running = False
        raise KeyboardInterrupt
    if _stopping is not None and _stopping.value:
        os._exit(STOPPED_EXIT)
    if _orphaned():
        os._exit(1)


class _LogPipe(multiprocessing.queues.SimpleQueue):
    """The log pipe from the workers to the batch's process, for the stock QueueHandler and QueueListener: a
    worker's record is written into it by the logging call itself (``put_nowait`` is ``put``), not later by a
    multiprocessing.Queue's feeder thread, so every record a job logs is in the pipe before the job's result, and
    the batch's process, stopping its listener after the last result, reads them all, in the order written (a
    feeder thread slowed by a loaded machine lost them)."""

    def put_nowait(self, item) -> None:
        self.put(item)

    def get(self, block: bool = True):
        return super().get()


class _Worker(multiprocessing.context.SpawnProcess):
    """A worker process of a pool (this object lives in the batch's process). Its ``terminate()``, which
    ProcessPoolExecutor calls on every worker once one of them has died, is :meth:`interrupt`, not SIGTERM: a
    training would take that as a second signal after the batch's own, and stop at once, saving nothing."""

    stopping = None  # the pool's shared flag (kept out of the pickle the worker is spawned from)
    interrupted = False  # it has had its SIGINT
    killed = False  # by the batch, after the grace period

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "stopping"}

    def terminate(self) -> None:
        self.interrupt()

    def interrupt(self) -> None:
        """Stop the pool (its flag: no job starts on any of its workers from now on) and send this worker one
        SIGINT, never a second: its job stops as after Ctrl-C (a training saves its checkpoint), then it exits;
        an idle worker exits at once."""
        with _SIGNALLING:  # (the pool's manager thread calls terminate() as this thread interrupts)
            self.stopping.value = True
            if self.interrupted or self._popen is None or self._popen.poll() is not None:
                return
            self.interrupted = True
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGINT)

    def end(self, kill: bool = False) -> None:
        """SIGTERM (an idle worker, which would leave by itself in a second or two), or SIGKILL, if alive."""
        with _SIGNALLING:
            if self._popen is not None and self.is_alive():
                self.killed = kill
                (super().kill if kill else super().terminate)()


_SIGNALLING = threading.Lock()


class _PoolContext(multiprocessing.context.SpawnContext):
    """The spawn context of one pool: its workers are :class:`_Worker` (listed in ``workers``), sharing the flag
    ``stopping``."""

    def __init__(self):
        self.workers: list[_Worker] = []
        self.stopping = self.RawValue(ctypes.c_bool, False)

    def Process(self, *args, **kwargs) -> _Worker:  # noqa: N802 - the name ProcessPoolExecutor calls
        worker = _Worker(*args, **kwargs)
        worker.stopping = self.stopping
        self.workers.append(worker)
        return worker

    def lost_worker(self) -> bool:
        """Whether a worker has exited (none does unless stopped, or killed). Also what ProcessPoolExecutor can
        miss: a worker started as it began waiting for its workers (submit wakes it before starting one) is not
        watched until something else wakes it, so a pool whose worker died could wait for its other jobs."""
        return any(worker._popen is not None and worker.exitcode is not None for worker in self.workers)


class _PoolEvents:
    """What the workers of a pool say of the jobs they take, in a pipe (read as the pool runs, so that it never
    fills): ``(name, "started", pid)`` before a job starts, ``(name, "ended")`` after it has returned, ``(name,
    "stopped")`` after it stopped as after Ctrl-C (or was not started, its pool stopping)."""

    def __init__(self, context):
        self.pipe = _LogPipe(ctx=context)
        self.worker: dict[str, int] = {}  # job name -> pid of the worker that started it
        self.settled: set[str] = set()  # jobs that ended or stopped

    def read(self) -> None:
        while not self.pipe.empty():
            name, what, *pid = self.pipe.get()
            if what == "started":
                self.worker[name] = pid[0]
            else:
                self.settled.add(name)


def _logger_levels() -> dict[str, int]:
    """The levels set on this process's loggers, the root's included (the CLI's: -v, -q, --log-level, and OpenGL's
    INFO hidden), for a worker to set alike: its records reach this process's handlers without passing these
    loggers, so a logger a worker left at its default would show what it hides here."""
    loggers = logging.Logger.manager.loggerDict.items()
    levels = {name: logger.level for name, logger in loggers if isinstance(logger, logging.Logger) and logger.level}
    return levels | {"root": logging.getLogger().level}


def _start_worker(log_queue, levels: dict[str, int], batch_pid: int, events, stopping) -> None:
    """A worker's set-up: its log records go to the batch's process, its loggers' levels those of the batch's
    (:func:`_logger_levels`); it leaves the terminal's process group
    (a Ctrl-C reaches the batch's process alone, which passes one SIGINT on to each worker: a training stops
    at the second); on Linux it gets SIGINT when the batch's process dies (killed), so that its job stops as
    after Ctrl-C and the worker exits instead of running on unseen."""
    global _batch_pid, _events, _stopping
    _batch_pid, _events, _stopping = batch_pid, events, stopping
    root = logging.getLogger()
    root.handlers[:] = [logging.handlers.QueueHandler(log_queue)]
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)
    signal.signal(signal.SIGINT, _on_interrupt)
    if hasattr(os, "setpgid"):  # (POSIX)
        os.setpgid(0, 0)
    with contextlib.suppress(OSError, AttributeError):  # not Linux: an orphaned worker finishes its job first
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGINT)
    if _orphaned():  # the batch's process died before prctl took effect
        os._exit(1)


def _warm_up(jobs: list[Job]) -> None:
    """A warm-up task: a CPU that would idle while every pending job waits for another's output starts a worker
    that imports what those jobs will (``warm_up``; seconds each: torch alone takes 1.5), so the first of them to
    start there starts at once. A failure is left to the job itself to report."""
    for job in jobs:
        job.warm_up()


def _run_in_worker(job: Job) -> tuple[str, object]:
    """The body of a job in a worker, with twice its CPUs as numba threads: :func:`_call`'s result.

    Twice: a job that runs alone at the end of a batch then uses the cores the others left, and side by side
    the threads cost nothing measurable (two demo trainings on 2 cores: 43.2 s at 2 threads each, 42.5 s at 1).

    Interrupted (SIGINT: Ctrl-C, or its pool stopping as one of its workers died), or taken from a stopping pool,
    the job stops and the worker exits (taking no other job).
    """
    global _job_running
    try:
        _job_running = True  # (before the flag is read: a SIGINT after it interrupts the job)
        if _stopping is not None and _stopping.value:
            raise KeyboardInterrupt
        _events.put((job.name, "started", os.getpid()))
        _limit_threads(2 * job.cpus)
        result = _call(job)
        _events.put((job.name, "ended"))
        return result
    except KeyboardInterrupt:
        _job_running = False
        with contextlib.suppress(Exception):  # (a second signal here ends the worker all the same)
            _events.put((job.name, "stopped"))
        os._exit(STOPPED_EXIT)
    finally:
        _job_running = False
        if _orphaned():  # the job has stopped (a training saved its checkpoint); nobody waits for its result
            os._exit(1)


def _run_pool(pending: list[Job], batch: _Batch, workers: int, warm: bool = True) -> tuple[list[Job], bool]:
    """Run ``pending`` on one pool of workers (``warm``: with warm-up tasks). When a worker died, the jobs to run
    on a new pool (those not started, and those stopped beside the dead worker's job, in the order given) and
    whether that pool may warm up (:func:`_after_death`); else ``([], True)``."""
    order = {job.name: i for i, job in enumerate(pending)}
    context = _PoolContext()  # spawned: never fork a process that holds OpenMP thread pools
    log_queue = _LogPipe(ctx=context)
    events = _PoolEvents(context)
    listener = logging.handlers.QueueListener(log_queue, *logging.getLogger().handlers, respect_handler_level=True)
    listener.start()
    running: dict[futures.Future, Job] = {}
    size = min(workers, len(pending))
    pool = futures.ProcessPoolExecutor(
        max_workers=size,
        mp_context=context,
        initializer=_start_worker,
        initargs=(log_queue, _logger_levels(), os.getpid(), events.pipe, context.stopping),
    )
    warm_ups: list[futures.Future] = []  # workers started ahead of the jobs that wait for another's output
    starting: list[Job] = []
    try:
        while pending or running:
            starting = []
            for job in list(pending):  # in order: a job waits for its needs, and for CPUs behind earlier jobs
                if need := batch.blocked_by(job):
                    pending.remove(job)
                    batch.not_run(job, need)
                    continue
                unfinished = {j.name for j in (*pending, *starting, *running.values())}
                if any(n in unfinished for n in job.needs):
                    continue
                busy = [*running.values(), *starting]
                if busy and sum(j.cpus for j in busy) + job.cpus > workers:
                    break
                pending.remove(job)
                starting.append(job)
            if any(not w.done() for w in warm_ups):  # the idle workers are cold: they take the later jobs, and
                starting.reverse()  # the first waits for the worker still warming up (the queue is first come)
            while starting:  # (a pool that broke refuses them: they wait for the next)
                future = pool.submit(_run_in_worker, starting[0])
                running[future] = starting.pop(0)
            batch.started(j.name for j in running.values())
            free = workers - sum(j.cpus for j in running.values())
            kinds = list({type(job): job for job in pending if hasattr(job, "warm_up")}.values())  # one per class
            while warm and kinds and free >= 1 and len(running) + len(warm_ups) < size:  # (the pool starts a
                warm_ups.append(pool.submit(_warm_up, kinds))  # worker per task submitted while none is idle)
                free -= 1
            events.read()
            if not running:
                continue
            done, _ = futures.wait(running, timeout=POLL_S, return_when=futures.FIRST_COMPLETED)
            batch.show()  # (the bar's clock moves while long jobs run)
            for future in sorted(done, key=lambda f: order[running[f].name]):
                if not _broken(future):
                    batch.ended(running.pop(future), *future.result())
            if any(_broken(future) for future in running) or context.lost_worker():
                raise futures.process.BrokenProcessPool
    except futures.process.BrokenProcessPool:  # a worker died (killed, out of memory)
        pending += starting
        again, warm = _after_death(context, events, running, batch, warm)
        return sorted(pending + again, key=lambda job: order[job.name]), warm
    except KeyboardInterrupt:
        if running:
            log.warning("interrupted: stopping %d running jobs", len(running))
        _stop_workers(context)  # (in their own process group: a Ctrl-C at the terminal reached this process only)
        raise
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
        for worker in context.workers:  # idle workers (leaving by themselves takes a second or two)
            worker.end()
        listener.stop()
    return [], True


def _broken(future: futures.Future) -> bool:
    """The future of a task that its pool failed, as one of its workers died."""
    return future.done() and isinstance(future.exception(), futures.process.BrokenProcessPool)


def _stop_workers(context: _PoolContext) -> None:
    """Stop every worker of a pool as after Ctrl-C (:meth:`_Worker.interrupt`: one SIGINT each) and wait up to
    CANCEL_GRACE_S for them to exit (a training saves its checkpoint); those still running then are killed."""
    for worker in context.workers:
        worker.interrupt()
    deadline = time.monotonic() + CANCEL_GRACE_S
    for worker in context.workers:
        if worker._popen is not None:  # (started)
            worker.join(max(0.0, deadline - time.monotonic()))
        worker.end(kill=True)


def _after_death(context: _PoolContext, events: _PoolEvents, running: dict, batch: _Batch, warm: bool):
    """A worker of the pool died, and ProcessPoolExecutor failed every job the pool had: the job that worker ran
    fails (:data:`DIED`); the others are stopped as after Ctrl-C (a training checkpoints) and returned, to run
    again on a new pool, with whether that pool may warm up. A death no job explains (a worker that died idle, or
    warming up) runs them again on a pool without warm-ups (``warm`` False), and there fails them all (a worker
    that cannot start: this ends)."""
    _stop_workers(context)
    events.read()
    killed = {worker.pid for worker in context.workers if worker.killed}
    again, died = [], []
    for future, job in running.items():
        if future.done() and future.exception() is None:  # (ended before the pool broke)
            batch.ended(job, *future.result())
        elif job.name in events.worker and job.name not in events.settled and events.worker[job.name] not in killed:
            died.append(job)
        else:
            again.append(job)
    if not died and not warm:
        died, again = again, []
    for job in died:
        batch.ended(job, "failed", DIED)
    if again:
        log.warning(
            "a worker process died: %s stopped and run again in new workers (a training resumes from its checkpoint)",
            ", ".join(job.name for job in again),
        )
    return again, bool(died)


# ---------------------------------------------------------------------- ray


def _execute(job: Job, starts, *needs: tuple) -> tuple[str, str, object]:
    """The body of a job's Ray task: ``(status, job name, summary or error)``; ``needs`` are its needs' results."""
    import ray

    started = starts.started.remote(job.name)
    try:
        if failed := next((name for status, name, _ in needs if status != "done"), None):
            return "blocked", job.name, failed
        _limit_threads(job.cpus)
        try:
            with ctrl_c_interrupts():  # ray.cancel interrupts the job (a training checkpoints)
                return "done", job.name, job()
        except TacsplatError as exc:  # a mistake in its input: a retry would repeat it
            return "failed", job.name, str(exc)
    finally:  # counted before the attempt's result or error reaches the driver, which reads the counts then;
        # awaited at the end, not the start: a task blocked in ray.get lends its CPUs to the next queued task
        ray.get(started)


def _limit_threads(cpus: float) -> None:
    """numba's kernels use ``cpus`` threads (at most the node's cores), not every core of the node (a Ray task
    its CPUs: Ray sets OMP_NUM_THREADS the same way)."""
    import numba

    numba.set_num_threads(max(1, int(min(numba.config.NUMBA_NUM_THREADS, cpus))))  # (an infinite or NaN cpus: all)


class _Starts:
    """A Ray actor counting the attempts each task started (what is running, and how often it was tried)."""

    def __init__(self):
        self.counts: Counter = Counter()

    def started(self, name: str) -> None:
        self.counts[name] += 1

    def get(self) -> dict[str, int]:
        return dict(self.counts)


@functools.cache
def _remote():
    """The Ray task and actor classes, made once (ray is imported only when the ray executor runs)."""
    import ray

    return ray.remote(_execute), ray.remote(num_cpus=0)(_Starts)


def connect(address: str | None) -> bool:
    """Connect to the Ray cluster at ``address`` (else ``RAY_ADDRESS``), or start an embedded local Ray; True
    when this call started or joined Ray (and so should shut it down), False when Ray was already initialised."""
    import ray

    if ray.is_initialized():
        return False
    option = "--ray-address" if address else "RAY_ADDRESS"
    address = address or os.environ.get("RAY_ADDRESS")
    if address and address != "local":
        host_port = check_ray_address(address, option)
        try:  # (Ray itself would retry for minutes)
            if host_port is not None:  # (auto names none)
                socket.create_connection(host_port, timeout=PROBE_S).close()
        except OSError as exc:
            raise ConfigError(
                option,
                f"nothing answers at {address} ({exc.strerror or type(exc).__name__}): give the host:port of the "
                "cluster's head (`ray start --head --port=PORT` prints it)",
            ) from None
        log.info("connecting to the Ray cluster at %s", address)
        try:
            ray.init(address=address, log_to_driver=True)
        except Exception as exc:  # noqa: BLE001 - whatever Ray raises (ConnectionError, ValueError, its own
            # RayErrors, ...) is one line naming the option
            log.debug("ray.init(address=%r) raised", address, exc_info=True)
            ray.shutdown()  # (whatever of it had started)
            raise ConfigError(
                option,
                f"cannot connect to a Ray cluster at {address}: "
                f"{_describe(exc).strip().splitlines()[0]} (check the address, and that this machine "
                "has the cluster's token: RAY_AUTH_MODE=token and RAY_AUTH_TOKEN or "
                "~/.ray/auth_token)",
            ) from None
    else:
        ray.init(
            address="local",
            include_dashboard=False,
            object_store_memory=EMBEDDED_OBJECT_STORE_BYTES,
            log_to_driver=True,
        )
    return True


_HOST = re.compile(r"\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+")  # [IPv6], IPv4 or a host name
_PORT = re.compile(r"[0-9]{1,5}")


def check_ray_address(address: str, option: str, error: type[ConfigError] = ConfigError) -> tuple[str, int] | None:
    """The host and port of a Ray address in a form ray.init takes (None for ``auto`` and ``local``, which name
    none): ``HOST:PORT`` of a head node (``[IPv6]:PORT``) or ``ray://HOST:PORT`` of its Ray Client server. Any
    other value is an ``error`` naming ``option`` (Ray's own comes as a traceback from deep in ray.init)."""
    if address in ("auto", "local"):
        return None
    scheme, sep, rest = address.rpartition("://")
    host, colon, port = rest.rpartition(":")
    if sep and scheme != "ray":
        why = f"{scheme}:// is not a Ray address (ray:// is)"
    elif not colon:
        why = "no port"
    elif not _HOST.fullmatch(host):
        why = f"{host!r} is not a host name or IP address"
    elif not _PORT.fullmatch(port) or not 1 <= int(port) <= 65535:
        why = f"the port must be an integer in 1..65535, got {port!r}"
    else:
        return host.strip("[]"), int(port)
    raise error(
        option,
        f"expected HOST:PORT (of the cluster's head: `ray start --head --port=PORT` prints it), "
        f"ray://HOST:PORT or auto, got {address!r}: {why}",
    )


def _run_ray(todo: list[Job], batch: _Batch, retries: int) -> None:
    """Every job a Ray task on the Ray this process is connected to; see the module docstring."""
    import ray

    execute, starts_actor = _remote()
    outstanding: list = []
    try:
        starts = starts_actor.remote()
        has_gpus = ray.cluster_resources().get("GPU", 0) > 0
        nodes = [node["Resources"] for node in ray.nodes() if node["Alive"]]
        refs: dict[str, object] = {}
        for job in todo:
            if need := batch.blocked_by(job):  # (a need that no node can run)
                batch.not_run(job, need)
                continue
            if too_big := _too_big(job.cpus, job.gpus(has_gpus), nodes):
                batch.ended(job, "failed", too_big, attempts=0)
                continue
            needs = [refs[n] for n in job.needs if n in refs]
            refs[job.name] = execute.options(
                num_cpus=job.cpus,
                num_gpus=job.gpus(has_gpus),
                max_retries=retries,
                retry_exceptions=True,
                name=job.name,
            ).remote(job, starts, *needs)
        order = {ref: i for i, ref in enumerate(refs.values())}
        jobs = {refs[job.name]: job for job in todo if job.name in refs}
        outstanding = list(refs.values())
        while outstanding:
            ready, _ = ray.wait(outstanding, num_returns=1, timeout=POLL_S)
            if ready:
                ready, outstanding = ray.wait(outstanding, num_returns=len(outstanding), timeout=0)
            attempts = ray.get(starts.get.remote())
            for ref in sorted(ready, key=order.get):  # needs before the jobs that read them
                _collect(jobs[ref], ref, batch, attempts.get(jobs[ref].name, 0))
            batch.started(n for n in attempts if n not in batch.outcome.done and n not in batch.outcome.failed)
    except KeyboardInterrupt:
        if outstanding:
            log.warning("interrupted: cancelling %d outstanding jobs", len(outstanding))
            for ref in outstanding:  # a running task gets KeyboardInterrupt (a training checkpoints), a queued one
                ray.cancel(ref)  # never starts
            ray.wait(outstanding, num_returns=len(outstanding), timeout=CANCEL_GRACE_S)
        raise


def _too_big(cpus: float, gpus: float, nodes: list[dict[str, float]]) -> str | None:
    """Why a task of ``cpus`` CPUs and ``gpus`` GPUs can never start on a cluster of ``nodes`` (each node's
    resources), or None when one of them has both."""
    if any(node.get("CPU", 0) >= cpus and node.get("GPU", 0) >= gpus for node in nodes):
        return None
    sizes = sorted({(node.get("CPU", 0), node.get("GPU", 0)) for node in nodes}, reverse=True)
    has = f"its nodes have {', '.join(f'{c:g} CPUs and {g:g} GPUs' for c, g in sizes)}" if sizes else "it has none"
    return f"needs {cpus:g} CPUs and {gpus:g} GPUs on one node; no node of the Ray cluster has that many ({has})"


def _collect(job: Job, ref, batch: _Batch, attempts: int) -> None:
    """Record the result of a finished task."""
    import ray

    try:
        status, _, value = ray.get(ref)
    except ray.exceptions.RayError as exc:  # raised after its retries, or its worker died each time
        if need := batch.blocked_by(job):  # (its need raised: Ray passed that error on instead of running it)
            batch.not_run(job, need)
            return
        cause = exc.cause if isinstance(exc, ray.exceptions.RayTaskError) else exc
        batch.ended(job, "failed", _describe(cause).strip().splitlines()[0], attempts)
        return
    if status == "blocked":
        batch.not_run(job, value)
    else:
        batch.ended(job, status, value, attempts)
