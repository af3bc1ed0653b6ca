"""Lockstep runs side by side: ``mfvs experiment --jobs N`` and ``mfvs demo``.

Each run is :func:`services.servo.run` with a whole stack of its own (composed in the process that runs it, or its
router on a port it picks and its processes; its run directory, its renderer), so runs share nothing but the host.
In lockstep a run's numbers do not depend on how fast the host is (the robot waits for every answer; messages block
rather than drop), so a run gives the same trajectory log whether it ran alone or beside others; the results come
back in the order the runs were given, whatever order they finish in.

``jobs`` 1 runs them one after another in this process, as before. More run in that many worker processes, forked
from the warm server of :mod:`services.stack.warm_start` (never from this process, whose zenoh sessions and threads a
fork would copy; and processes, not threads: pyplot, which draws a run's figures, is not thread-safe), with this
process's environment. Per-iteration progress comes back through a queue and is handed to ``on_iteration`` on a
thread of this process.

Each worker, and the whole stack of every run it makes, is pinned to one core of this process's (worker ``k`` to
the ``k``-th, round the cores when there are more workers than cores). A lockstep run is a chain: each process waits
for the one before it, so it needs one core at a time. Unpinned, two runs on two cores kept waking each other's
processes on the core the other run was busy on, and every hand-off of a chain (a dozen an iteration) waited for a
time slice: measured on this 2-core machine, Table 3's p-joint run took 6.6 s alone, 9.5 s beside a second run
unpinned and 7.1-7.4 s pinned (two runs in 7.4 s, against 9.5 s unpinned and 13.1 s one after the other). What a
run computes does not depend on it (lockstep), only how soon.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional

if TYPE_CHECKING:  # the CLI's parser reads default_jobs(): no numpy, MuJoCo or zenoh for that
    from services.servo.result import ServoResult
    from services.servo.scenario import Scenario


@dataclass
class RunTask:
    """One run: ``label`` names it in progress lines, ``out_dir`` receives its log (and figures with ``plots``)."""

    label: str
    scenario: Scenario
    out_dir: Path
    profile: str = "sim"
    plots: bool = False
    #: every service a process of its own, as deployed, rather than composed (:func:`services.servo.run`)
    processes: bool = False
    #: a run of another kind than one servo task: ``module:function`` taking (task, each) and returning what the
    #: experiment makes of it (the markerless experiment's teach, servo and tag runs of one start), with its ``args``
    runner: Optional[str] = None
    args: Optional[dict] = None


def default_jobs() -> int:
    """The cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def check_jobs(jobs: int) -> int:
    if jobs < 1:
        raise ValueError(f"--jobs must be at least 1, not {jobs}")
    return jobs


OnIteration = Callable[[RunTask, object], None]
OnDone = Callable[[RunTask, "ServoResult"], None]


def run_tasks(tasks: list[RunTask], jobs: int, on_iteration: Optional[OnIteration] = None,
              on_done: Optional[OnDone] = None) -> list[ServoResult]:
    """Every task's result, in the tasks' order. ``on_iteration(task, record)`` during a run, ``on_done(task,
    result)`` as each run ends (in the order they end)."""
    check_jobs(jobs)
    if jobs == 1 or len(tasks) <= 1:
        return [_run_here(task, on_iteration, on_done) for task in tasks]
    return _run_in_workers(tasks, min(jobs, len(tasks)), on_iteration, on_done)


def _run(task: RunTask, each: Optional[Callable[[object], None]]) -> ServoResult:
    if task.runner is not None:
        import importlib

        module, function = task.runner.split(":")
        return getattr(importlib.import_module(module), function)(task, each)
    from services.servo.run import run

    return run(task.scenario, task.out_dir, each, profile=task.profile, plots=task.plots, processes=task.processes)


def _run_here(task: RunTask, on_iteration: Optional[OnIteration], on_done: Optional[OnDone]) -> ServoResult:
    result = _run(task, None if on_iteration is None else (lambda record: on_iteration(task, record)))
    if on_done is not None:
        on_done(task, result)
    return result


# ------------------------------------------------------------------------------------------------ workers
_progress_queue = None


def worker_cores(cores: set[int] | list[int], worker: int) -> set[int]:
    """The core worker number ``worker`` (from 0) runs on, of ``cores``: one each, round the cores."""
    ordered = sorted(cores)
    return {ordered[worker % len(ordered)]}


def pin_process(cores: set[int]) -> None:
    """This process and every thread it has (the main one among them) to ``cores``; threads and processes it starts
    later inherit them."""
    for task in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(task), cores)
        except (ProcessLookupError, PermissionError):  # a thread that ended meanwhile
            pass


def _init_worker(progress_queue, environment: dict, workers_started, cores: list[int], server: str) -> None:
    global _progress_queue
    from services.stack.warm_start import fork_from_server_at

    fork_from_server_at(server)  # the stacks' services come from the server this worker came from
    _progress_queue = progress_queue
    # a fork of the warm server has the server's environment: the caller's is what a run must see
    os.environ.clear()
    os.environ.update(environment)
    with workers_started.get_lock():
        worker = workers_started.value
        workers_started.value += 1
    pin_process(worker_cores(cores, worker))


def _run_in_worker(index: int, task: RunTask) -> ServoResult:
    sink = _progress_queue
    return _run(task, None if sink is None else (lambda record: sink.put((index, record))))


def _run_in_workers(tasks: list[RunTask], jobs: int, on_iteration: Optional[OnIteration],
                    on_done: Optional[OnDone]) -> list[ServoResult]:
    from services.stack.warm_start import WarmContext, server_address

    context = WarmContext()
    progress = context.Queue() if on_iteration is not None else None
    workers_started = context.Value("i", 0)
    cores = sorted(os.sched_getaffinity(0))
    relay: Optional[threading.Thread] = None
    if progress is not None:
        def forward() -> None:
            while True:
                item = progress.get()
                if item is None:
                    return
                index, record = item
                on_iteration(tasks[index], record)

        relay = threading.Thread(target=forward, name="run-pool-progress", daemon=True)
        relay.start()
    results: list[Optional[ServoResult]] = [None] * len(tasks)
    try:
        with ProcessPoolExecutor(max_workers=jobs, mp_context=context, initializer=_init_worker,
                                 initargs=(progress, dict(os.environ), workers_started, cores,
                                           server_address())) as pool:
            pending = {pool.submit(_run_in_worker, i, task): i for i, task in enumerate(tasks)}
            try:
                while pending:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    for future in done:
                        index = pending.pop(future)
                        results[index] = future.result()  # a run that raised raises here, as it would alone
                        if on_done is not None:
                            on_done(tasks[index], results[index])
            except BaseException:
                for future in pending:
                    future.cancel()
                raise
    finally:
        if progress is not None:
            progress.put(None)
            relay.join(timeout=5.0)
            progress.close()
    return results  # type: ignore[return-value]

