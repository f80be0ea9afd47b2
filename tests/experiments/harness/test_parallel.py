"""experiments.harness.parallel: tasks forked onto several cores give what they give in turn, in order."""

import os

import numpy as np
import pytest
import torch
from effect_networks.experiments.adaptive_throw.run import run_adaptive_throw
from effect_networks.experiments.adaptive_throw.settings import AdaptiveThrowConfig
from effect_networks.experiments.harness.compare import compare_values
from effect_networks.experiments.harness.parallel import forks, resolve_workers, run_tasks
from effect_networks.sim2d.executors import available_cores

from tests.helpers import ADAPTIVE_THROW_TINY as TINY


def _square(x):
    return lambda: (x * x, os.getpid())


def test_run_tasks_returns_every_result_in_order_from_worker_processes():
    results = run_tasks([_square(x) for x in range(7)], workers=2)
    assert [value for value, _ in results] == [x * x for x in range(7)]
    assert os.getpid() not in {pid for _, pid in results}  # forked, not run here
    alone = run_tasks([_square(x) for x in range(7)], workers=1)
    assert [value for value, _ in alone] == [x * x for x in range(7)]
    assert {pid for _, pid in alone} == {os.getpid()}
    assert run_tasks([], workers=2) == []


def test_a_task_sees_what_its_caller_computed_and_runs_on_one_thread():
    data = torch.randn(50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    tasks = [lambda: (data.sum(0), torch.get_num_threads()), lambda: (data @ data.T, 1)]
    (total, threads), (gram, _) = run_tasks(tasks, workers=2)
    assert torch.equal(total, data.sum(0)) and torch.equal(gram, data @ data.T)
    assert threads == 1


def _fails():
    raise RuntimeError("task 1 failed")


def test_a_failing_task_raises_in_the_caller():
    with pytest.raises(RuntimeError, match="task 1 failed"):
        run_tasks([lambda: 0, _fails, lambda: 2], workers=2)


@pytest.mark.parametrize("workers", [-1, 1.5, True, "2"])
def test_bad_worker_counts_are_refused(workers):
    with pytest.raises(ValueError, match="workers"):
        resolve_workers(workers)


def test_zero_workers_is_one_per_core():
    assert resolve_workers(0) == available_cores() >= 1
    assert resolve_workers(3) == 3


def test_adaptive_throw_gives_the_same_results_on_one_and_on_two_workers():
    """Bit for bit: every figure but the fit times (measured inside the tasks)."""
    one = run_adaptive_throw(AdaptiveThrowConfig(**TINY | {"workers": 1}, seed=1)).to_dict()
    two = run_adaptive_throw(AdaptiveThrowConfig(**TINY | {"workers": 2}, seed=1)).to_dict()
    assert compare_values(one, two, "adaptive_throw") == []
    assert np.isfinite(two["floor"]["rms_y_m"])


def _inner(x):
    return lambda: sum(run_tasks([lambda: x, lambda: 10 * x], workers=1))


def test_a_task_may_run_tasks_of_its_own():
    """A worker that runs an inner call still finds the outer call's next tasks."""
    assert run_tasks([_inner(x) for x in range(5)], workers=2) == [11 * x for x in range(5)]


def test_forks_says_where_the_tasks_run():
    assert forks(2, 3) and forks(0, 5) == (available_cores() > 1)
    assert not forks(1, 3) and not forks(2, 1) and not forks(2, 0)
