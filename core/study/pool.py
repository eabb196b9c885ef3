"""The study's trials on a process pool: same rows, in the same order, as one process.

Every trial is seeded from (root seed, condition, index) alone, so where it runs does not
change its rows; :func:`run_tasks` returns them in task order. Workers ignore Ctrl-C (the
terminal sends it to the whole process group): the parent gets it, terminates and joins
its workers and re-raises, so no worker outlives the run (ADR 0021).

This module knows nothing of what a task is: the caller (:mod:`cellcal.core.study.trials`)
gives the module-level functions that set a worker up and run one task, so the dependency
points one way (trials → pool).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

if TYPE_CHECKING:
    from multiprocessing.pool import Pool

__all__ = ["default_jobs", "run_calls", "run_tasks"]

#: One task (for the study: a condition and the trial's index within it).
Task = TypeVar("Task")
Rows = list[dict[str, Any]]


def default_jobs() -> int:
    """The cores this process may run on (its CPU affinity where the OS has one)."""
    with contextlib.suppress(AttributeError, OSError):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def _init_worker(initializer: Callable[..., None], initargs: tuple[Any, ...]) -> None:
    """Worker start: ignore Ctrl-C (the parent handles it), then the caller's ``initializer``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    initializer(*initargs)


@contextlib.contextmanager
def _sigint_blocked() -> Iterator[None]:
    """Hold Ctrl-C back while workers start, so none of them ever runs the parent's handler.

    A press in that window is delivered when the block ends, in the parent.
    """
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def _pool(jobs: int, initializer: Callable[..., None], initargs: tuple[Any, ...]) -> Iterator[Pool]:
    """A pool of ``jobs`` workers for one batch: started with Ctrl-C held back, closed and joined
    after the batch, terminated and joined at once on Ctrl-C or an error (which is re-raised)."""
    with _sigint_blocked():
        pool = multiprocessing.get_context().Pool(jobs, initializer, initargs)
    try:
        yield pool
    except BaseException:
        pool.terminate()  # Ctrl-C or an error: stop the workers now
        pool.join()
        raise
    pool.close()
    pool.join()


def _ignore_sigint() -> None:
    """Worker start for :func:`run_calls`: Ctrl-C is the parent's."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _call(function: Callable[..., Any], args: tuple[Any, ...]) -> Any:
    return function(*args)


def run_calls(calls: Sequence[tuple[Callable[..., Any], tuple[Any, ...]]], jobs: int) -> list[Any]:
    """Independent calls on up to ``jobs`` worker processes; their results in call order.

    Each call is a module-level function and its (picklable) arguments. With ``jobs`` 1 or
    a single call they run in this process. Ctrl-C as in :func:`run_tasks`.
    """
    if jobs <= 1 or len(calls) <= 1:
        return [function(*args) for function, args in calls]
    with _pool(min(jobs, len(calls)), _ignore_sigint, ()) as pool:
        return pool.starmap(_call, calls)


def run_tasks(tasks: Sequence[Task], jobs: int, run: Callable[[Task], Rows],
              on_done: Callable[[int, Rows], None], local: tuple[int, Callable[[Task], Rows]] | None = None,
              *, initializer: Callable[..., None], initargs: tuple[Any, ...] = ()) -> list[Rows]:
    """Run ``tasks`` on ``jobs`` worker processes; the rows of each task, in task order.

    Args:
        tasks: The trials to run (picklable).
        jobs: Worker processes (at least 1).
        run: Runs one task in a worker (a module-level function: it is sent by name).
        on_done: Called in the parent with (task index, rows) as tasks finish, in order.
        local: (index, run) of one task the parent runs itself with ``run`` while the
            workers run the others (the study's example trial, whose frame the parent
            keeps); None: the workers run every task.
        initializer: Called once in each worker with ``initargs`` (a module-level function),
            after the worker has been set to ignore Ctrl-C.
        initargs: Its (picklable) arguments, sent to each worker once.

    Raises:
        KeyboardInterrupt: After the workers are terminated and joined.
    """
    out: list[Rows | None] = [None] * len(tasks)
    remote = [task for i, task in enumerate(tasks) if local is None or i != local[0]]
    with _pool(max(1, min(jobs, len(remote))), _init_worker, (initializer, initargs)) as pool:
        results = pool.imap(run, remote)
        if local is not None:
            out[local[0]] = local[1](tasks[local[0]])
        for i in range(len(tasks)):
            rows = out[i]
            if rows is None:
                rows = out[i] = next(results)  # the workers' results come in task order
            on_done(i, rows)
    return [rows for rows in out if rows is not None]
