"""explain's log-likelihood and posteriors against Pyro's own enumeration.

The demonstration's hidden Markov model written directly in Pyro from the switch world's
tables (each time's hidden features and each step's action enumerated under
``pyro.markov``), its evidence summed by ``TraceEnum_ELBO``: it shares no code with
explain's step tables, states or sums.
"""

from __future__ import annotations

import numpy as np
import pyro
import pyro.distributions as dist
import pytest
import torch
from effect_networks.experiments.switch_worlds import switch_world
from effect_networks.inference import explain
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from pyro.infer import TraceEnum_ELBO
from pyro.ops.indexing import Vindex


def pyro_log_evidence(world, demo, times: int) -> float:
    """``log p(what the first ``times`` states show)`` by Pyro's enumeration."""
    net, params = world.net, world.params
    names = [f.name for f in net.features]

    def observed(t, f):
        v = demo[t][f]
        return None if v is None else torch.tensor(net.feature(f).states.index(v))

    def model():
        prev = {}
        for f in names:
            prev[f] = pyro.sample(
                f"x0_{f}",
                dist.Categorical(params[f"initial.{f}"].probs),
                obs=observed(0, f),
                infer={"enumerate": "parallel"},
            )
        for t in pyro.markov(range(times - 1)):
            a = pyro.sample(
                f"a{t}", dist.Categorical(params["action"].probs), infer={"enumerate": "parallel"}
            )
            new = {}
            for f in names:
                parents = net.cpd(f"end.{f}").parents
                index = [a if q == "action" else prev[q.removeprefix("initial.")] for q in parents]
                probs = Vindex(params[f"end.{f}"].probs)[tuple(index)]
                new[f] = pyro.sample(
                    f"x{t + 1}_{f}",
                    dist.Categorical(probs),
                    obs=observed(t + 1, f),
                    infer={"enumerate": "parallel"},
                )
            prev = new

    elbo = TraceEnum_ELBO(max_plate_nesting=0)
    return -float(elbo.loss(model, lambda: None))


@pytest.mark.parametrize(
    "k, hidden, seed", [(4, 0.0, 0), (5, 0.2, 1), (6, 0.2, 2), (10, 0.2, 3), (12, 0.2, 4)]
)
def test_explain_s_log_likelihood_is_pyro_s(k, hidden, seed):
    world = switch_world(k, "sparse")
    states, _ = simulate_demonstrations(world.net, world.params, 3, 4, seed=seed)
    rng = np.random.default_rng(seed)
    names = [f.name for f in world.net.features]
    for i in range(3):
        demo = [
            {f: (None if t and rng.random() < hidden else states[f][i, t]) for f in names}
            for t in range(5)
        ]
        got = float(explain(world.net, world.params, demo).log_likelihood[0])
        want = pyro_log_evidence(world, demo, 5) - pyro_log_evidence(world, demo, 1)
        assert got == pytest.approx(want, abs=1e-10)
