"""Run independent tasks on one core, on this machine's cores, or on a Dask cluster.

Each task is a picklable function and its (small) arguments; results come back in task
order whatever order they finished in, so the caller's output does not depend on the
backend or on scheduling (the corpus replay's summary is the same on one core, on a
process pool and on a cluster).

Why a ``multiprocessing`` (fork) pool here and Dask only for ``--scheduler``: Dask stays
an optional extra (``attitude-bridge[cluster]``) that a single machine never needs; a
forked worker starts in milliseconds and inherits the estimators' compiled kernels
already loaded by the parent (:func:`run`'s ``warm``), where a ``LocalCluster`` spends
seconds starting, and each of its workers loads the kernels again; and ``tune`` already
works this way. The task function is the same for both, so the numbers are too.

The pool is a ``ProcessPoolExecutor`` rather than ``multiprocessing.Pool``: when a
worker dies (killed, out of memory) the executor says so, where ``Pool`` would wait for
the lost task forever. The tasks that were in flight then are run again one at a time,
each in a fresh single-process pool, so only the task that kills its worker is reported
(``on_crash``) and the rest of the batch goes on.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

#: How many tasks wait in the pool's queue per worker: enough to keep every worker busy,
#: few enough that a crash leaves only a handful of suspects to re-run alone.
QUEUED_PER_WORKER = 2
WORKER_DIED = "worker process died while running it (killed, or out of memory)"

Task = tuple[Any, ...]
OnDone = Callable[[int, Any], None]
OnCrash = Callable[[Task, str], Any]


@dataclass
class Outcome:
    """Per task its result (None where not done), and whether Ctrl-C stopped the run."""

    results: list[Any]
    interrupted: bool = False

    @property
    def done(self) -> int:
        return sum(r is not None for r in self.results)


def cores() -> int:
    """Cores this process may run on (the affinity mask, e.g. a container's cpuset)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def workers_for(jobs: int | None, tasks: int) -> int:
    """``--jobs`` (default: every core), never more than there are tasks."""
    if jobs is not None and jobs < 1:
        raise ValueError(f"--jobs {jobs}: expected a number of processes >= 1")
    return max(1, min(jobs or cores(), tasks))


def run(fn: Callable[..., Any], tasks: Sequence[Task], *, on_crash: OnCrash,
        jobs: int | None = None, scheduler: str | None = None,
        on_done: OnDone | None = None, warm: Callable[[], None] | None = None,
        order: Sequence[int] | None = None,
        weights: Sequence[float] | None = None) -> Outcome:
    """``fn(*task)`` for every task; ``on_done(index, result)`` as each one finishes.

    ``scheduler``: a Dask scheduler's address (``replay.cluster``); else ``jobs``
    processes here (1: in this process). ``warm`` runs once in the parent before the
    pool forks (load compiled kernels once, shared by every worker). ``order``: the
    order to start the tasks in (indices; default as given): the longest first keeps a
    long task from starting last while the other workers have nothing left to do.
    ``weights``: each task's expected work (e.g. a log's size), by which a cluster's
    batches are cut (``replay.cluster``); a local pool takes one task at a time and
    needs none. Results stay in task order. Ctrl-C stops the run: the result then has
    ``interrupted`` set and the finished tasks' results.
    """
    notify = on_done or (lambda i, r: None)
    order = list(range(len(tasks)) if order is None else order)
    if sorted(order) != list(range(len(tasks))):
        raise ValueError("order must name every task once")
    if scheduler is not None:
        from .cluster import run_on_cluster

        return run_on_cluster(fn, tasks, scheduler, on_crash, notify, order, weights)
    out = Outcome([None] * len(tasks))
    try:
        if workers_for(jobs, len(tasks)) == 1:
            for i in order:
                out.results[i] = fn(*tasks[i])
                notify(i, out.results[i])
        else:
            if warm is not None:
                warm()
            _run_pool(fn, tasks, order, workers_for(jobs, len(tasks)), on_crash, notify,
                      out.results)
    except KeyboardInterrupt:
        out.interrupted = True
    return out


def _ignore_sigint() -> None:
    """Workers leave Ctrl-C to the parent, which stops the run and keeps the results."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _executor(workers: int) -> ProcessPoolExecutor:
    return ProcessPoolExecutor(workers, mp_context=mp.get_context("fork"),
                               initializer=_ignore_sigint)


def _run_pool(fn: Callable[..., Any], tasks: Sequence[Task], order: list[int], workers: int,
              on_crash: OnCrash, notify: OnDone, results: list[Any]) -> None:
    pending = deque(order)
    while pending:
        suspects = _pool_round(fn, tasks, workers, pending, notify, results)
        for i in suspects:  # each alone: only the one that kills its worker is lost
            with _executor(1) as ex:
                try:
                    results[i] = ex.submit(fn, *tasks[i]).result()
                except BrokenProcessPool:
                    results[i] = on_crash(tasks[i], WORKER_DIED)
            notify(i, results[i])


def _pool_round(fn: Callable[..., Any], tasks: Sequence[Task], workers: int,
                pending: deque[int], notify: OnDone, results: list[Any]) -> list[int]:
    """Run ``pending`` on one pool until done or the pool breaks; the tasks in flight
    when it broke (to re-run alone)."""
    ex = _executor(workers)
    inflight: dict[Future, int] = {}
    try:
        while pending or inflight:
            while pending and len(inflight) < QUEUED_PER_WORKER * workers:
                i = pending.popleft()
                inflight[ex.submit(fn, *tasks[i])] = i
            done, _ = wait(inflight, return_when=FIRST_COMPLETED)
            if any(isinstance(f.exception(), BrokenProcessPool) for f in done):
                suspects = []
                for f, i in inflight.items():
                    if f.done() and f.exception() is None:
                        results[i] = f.result()
                        notify(i, results[i])
                    else:
                        suspects.append(i)
                return sorted(suspects)
            for f in done:
                i = inflight.pop(f)
                results[i] = f.result()  # fn catches its own errors; anything else is a bug
                notify(i, results[i])
        return []
    finally:
        ex.shutdown(wait=True, cancel_futures=True)
