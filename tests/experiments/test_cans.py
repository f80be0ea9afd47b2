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
