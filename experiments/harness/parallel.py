"""An experiment's own model work, split into independent tasks, on several cores.

The simulations run on an executor (:mod:`sim2d.executors`); the learning and evaluation
around them run in the experiment's process, on one torch thread. Where that work splits
into tasks that share nothing (one grid size's fits and queries, one learner's curve),
:func:`run_tasks` runs them in worker processes forked from the calling one: each starts
with everything the caller has imported and computed, runs its task on one torch thread
and sends back the task's result. Each task computes what it would compute in the caller,
in the same order, so the results do not depend on the number of workers, bit for bit
(tests/experiments/harness/test_parallel.py); only timings measured inside a task may grow a
little when workers share the memory bus.

The tasks are plain callables, closures included: a forked worker finds them in its copy
of the caller's memory, so only their results cross between processes (they must pickle).
Where processes cannot be forked (not POSIX), or with one worker or one task, the tasks
run in the caller, in turn.

Simulation time spent inside a worker (:func:`sim2d.clock.simulation_seconds`) stays in
the worker's count: a step that simulates inside its tasks reports that time in its rest.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
from collections.abc import Callable, Sequence
from typing import TypeVar

from effect_networks.sim2d.executors import available_cores
from tqdm.auto import tqdm

__all__ = ["forks", "resolve_workers", "run_tasks"]

T = TypeVar("T")

#: The tasks of the :func:`run_tasks` call in progress, read by the forked workers.
_TASKS: Sequence[Callable[[], object]] = ()


def resolve_workers(workers: int) -> int:
    """``workers`` processes, or with 0 one per core this process may use.

    Raises ``ValueError`` for a negative count.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise ValueError(f"workers={workers!r}: expected an int >= 0 (0: one per core)")
    return workers or available_cores()


def forks(workers: int, n_tasks: int) -> bool:
    """Whether :func:`run_tasks` runs ``n_tasks`` tasks on ``workers`` in forked processes.

    Not with one worker or one task, nor where processes cannot be forked: then they run in the
    caller, in turn (and may show progress bars of their own).
    """
    count = min(resolve_workers(workers), n_tasks)
    return count > 1 and "fork" in multiprocessing.get_all_start_methods()


def _one_thread() -> None:
    import torch

    torch.set_num_threads(1)


def _run(index: int):
    return _TASKS[index]()


def run_tasks(
    tasks: Sequence[Callable[[], T]],
    workers: int = 0,
    *,
    desc: str | None = None,
    progress: bool = False,
) -> list[T]:
    """Every task's result, in the order of ``tasks``.

    Parameters
    ----------
    tasks
        Callables taking no argument; the first ones start first, so put the longest first.
    workers
        Processes at most (0: one per core, :func:`resolve_workers`); never more than tasks.
    desc, progress
        A progress bar over the finished tasks, with this description.

    Returns
    -------
    list
        ``[task() for task in tasks]``. A task that raises raises here (the others are
        cancelled or finish first).
    """
    global _TASKS
    tasks, previous = list(tasks), _TASKS  # previous: a task of an outer call runs this one
    bar = tqdm(total=len(tasks), desc=desc, disable=not progress)
    try:
        if not forks(workers, len(tasks)):
            results = []
            for task in tasks:
                results.append(task())
                bar.update()
            return results
        _TASKS = tasks
        context = multiprocessing.get_context("fork")
        with concurrent.futures.ProcessPoolExecutor(
            min(resolve_workers(workers), len(tasks)), mp_context=context, initializer=_one_thread
        ) as pool:
            futures = [pool.submit(_run, i) for i in range(len(tasks))]
            try:
                for future in concurrent.futures.as_completed(futures):
                    future.result()  # the first failure, as soon as it is known
                    bar.update()
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
            return [future.result() for future in futures]
    finally:
        _TASKS = previous
        bar.close()
