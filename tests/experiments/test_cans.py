"""experiments.cans: the can model's field choice answers each distinct evidence once,
with the bits of the answer row by row."""

import dataclasses

import numpy as np
import pytest
import torch
from effect_networks.experiments import cans
from effect_networks.experiments.can_tossing.run import start_evidence, table_one_cases
from effect_networks.experiments.can_tossing.settings import PROTOCOLS, RULES


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("protocol", PROTOCOLS)
def test_choose_answers_each_distinct_evidence_once_and_as_row_by_row(
    tiny_data_dir, protocol, rule
):
    data = cans.can_dataset(tiny_data_dir, "tiny", progress=False)
    model = cans.fit_can_network(data, 0)
    start, desired = table_one_cases(data, protocol)
    # every case twice, interleaved: rows of equal evidence on purpose
    start, desired = np.repeat(start, 2)[::-1].copy(), np.repeat(desired, 2)[::-1].copy()
    evidence = start_evidence(model, start) | {"end.count": torch.as_tensor(desired)}
    row_by_row = np.array(
        [
            cans._choose(model, {k: v[i : i + 1] for k, v in evidence.items()}, rule)[0]
            for i in range(len(start))
        ]
    )
    asked = []

    class Counting:
        def infer_action(self, ev, **kwargs):
            asked.append(model.net.encode(ev).n_rows)
            return model.compiled.infer_action(ev, **kwargs)

    chosen = cans.choose(dataclasses.replace(model, compiled=Counting()), evidence, rule)
    assert np.array_equal(chosen, row_by_row)
    assert asked == [len({(s, d) for s, d in zip(start.tolist(), desired.tolist(), strict=True)})]


def test_choose_of_no_rows_is_empty(tiny_data_dir):
    data = cans.can_dataset(tiny_data_dir, "tiny", progress=False)
    model = cans.fit_can_network(data, 0)
    none = np.zeros(0, dtype=np.int64)
    evidence = start_evidence(model, none) | {"end.count": torch.as_tensor(none)}
    assert cans.choose(model, evidence, "aim").shape == (0,)


def test_fit_on_replays_is_the_fit_on_the_same_throws_as_a_data_set():
    from effect_networks.sim2d import field_throws, geometry
    from effect_networks.sim2d.can_dataset import CanDataset

    rng = np.random.default_rng(3)
    configs, repeats = (7, 63), 3
    shape = (geometry.N_FIELDS, repeats)
    # each start's ends keep no can it lacked
    ends = np.stack([rng.choice([1, 3, 7], size=shape), rng.choice([1, 3, 7, 15, 63], size=shape)])
    sims = cans.Replays(configs, ends, np.vectorize(lambda m: bin(m).count("1"))(ends))
    throwable = np.array([field_throws.is_throwable(f, 0) for f in range(geometry.N_FIELDS)])
    grid = np.meshgrid(np.arange(len(configs)), np.arange(geometry.N_FIELDS), np.arange(repeats))
    c, f, r = (g.ravel() for g in grid)
    keep = throwable[f]
    n = int(keep.sum())
    zeros = np.zeros(n, np.int64)
    data = CanDataset(
        start_config=np.asarray(configs)[c[keep]],
        field=f[keep],
        angle=zeros,
        repeat=r[keep],
        seed=zeros,
        end_config=ends[c[keep], f[keep], r[keep]],
        thrown_off=zeros,
        count_before=zeros,
        count_after=zeros,
        hit_any_can=np.zeros(n, bool),
        touched=zeros,
        throwable=np.ones(n, bool),
        timed_out=np.zeros(n, bool),
        sim_time=np.zeros(n),
    )
    ours, direct = cans.fit_on_replays(sims), cans.fit_can_network(data, 0)
    assert ours.states == direct.states
    assert torch.equal(ours.throwable, direct.throwable)
    for start in configs:
        torch.testing.assert_close(ours.end_config_probs(start), direct.end_config_probs(start))
    # a replay of an unthrowable field is its start, not a training throw
    assert not throwable.all()
