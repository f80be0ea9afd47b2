"""Choosing a parameter's next values by information about its clusters' regressions.

For a network with a grid-layout parameter ``p`` acting on one continuous feature ``g``,
each cluster's linear Gaussian ``g = W [x, p, 1] + e`` is a Bayesian linear regression:
with the rows seen so far in its parent configuration, ``A = lambda I + sum z z^T``
(``z = [x, p, 1]``, the sufficient statistic :func:`inference.fit` sums), one more row at
``z`` tells about ``W`` (with its noise known) the expected information gain, in nats,

    EIG(z) = d / 2 * log(1 + z^T A^-1 z)

(the determinant ratio of the posterior precisions; ``d`` the feature's dimension). It is
largest in configurations no row has reached and at the edges of those seen.
:func:`select_by_information` picks a batch greedily: the best candidate, then ``A`` of
its configuration updated in closed form (``A += z z^T``) before the next pick, so a
batch spreads out instead of piling onto one spot. No scene knowledge: the candidates
are rows of the network's sites.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from effect_networks.inference.fitting.rows import training_rows
from effect_networks.inference.fitting.sufficient_statistics import statistics
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.evidence import DTYPE

__all__ = ["regression_information", "select_by_information"]


def _design(net: EffectNetwork, parameter: str, enc):
    """The affected feature's CPD, and per row its flat parent configuration and ``z``."""
    m = net.mixture(parameter)
    if m.parameter.adaptive:
        raise ValueError(
            f"parameter {parameter!r} has adaptive clusters: a candidate's cluster is then "
            "uncertain; choose by information with the grid layout"
        )
    if m.child is None or m.affected != (m.child,):
        raise ValueError(
            f"parameter {parameter!r} must act on exactly one continuous feature, "
            f"it acts on {list(m.affected)}"
        )
    cpd = net.cpd(m.child)
    values = dict(enc)
    values[m.cluster.site] = m.cells(enc[m.value.site], enc[ACTION])
    missing = [s for s in (*cpd.parents, *cpd.inputs) if s not in values]
    if missing:
        raise ValueError(f"candidates must give {missing}")
    group = torch.zeros(enc.n_rows, dtype=torch.long)
    for s, k in zip(cpd.parents, cpd.card, strict=True):
        group = group * k + values[s]
    inputs = [values[s].nan_to_num() for s in cpd.inputs]
    z = torch.cat([*inputs, torch.ones(enc.n_rows, 1, dtype=DTYPE)], -1)
    return cpd, group, z


def regression_information(
    net: EffectNetwork,
    parameter: str,
    data: Mapping[str, object],
    candidates: Mapping[str, object],
    *,
    prior_precision: float = 1e-3,
) -> torch.Tensor:
    """``(m,)`` expected information gain (nats) of one more row at each candidate.

    About the regression of the feature ``parameter`` acts on, given the training rows ``data``
    (every site, as for :func:`inference.fit`). ``candidates``: rows giving the action, the
    parameter and the feature's other parents (no end values).
    """
    return _information(net, parameter, data, candidates, prior_precision)[0]


def _information(net, parameter, data, candidates, prior_precision):
    if not (isinstance(prior_precision, int | float) and prior_precision > 0):
        raise ValueError(f"prior_precision must be a number > 0, got {prior_precision!r}")
    enc = training_rows(net, data)
    cpd = net.cpd(net.mixture(parameter).child)
    zz = statistics(net, enc).sites[cpd.site].zz.clone()  # (G, q, q)
    zz += prior_precision * torch.eye(zz.shape[-1], dtype=DTYPE)
    cand = net.encode(candidates)
    _, group, z = _design(net, parameter, cand)
    d = net.site(cpd.site).size
    gain = _gain(zz, group, z, d)
    return gain, zz, group, z, d


def _gain(zz, group, z, d) -> torch.Tensor:
    solved = torch.linalg.solve(zz[group], z[..., None])[..., 0]
    return 0.5 * d * torch.log1p((z * solved).sum(-1))


def select_by_information(
    net: EffectNetwork,
    parameter: str,
    data: Mapping[str, object],
    candidates: Mapping[str, object],
    k: int,
    *,
    prior_precision: float = 1e-3,
) -> torch.Tensor:
    """Indices ``(k,)`` of ``k`` distinct candidates, chosen greedily.

    Chosen by :func:`regression_information`; each pick's row is added to its configuration's
    statistics before the next (see the module).
    """
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"k must be a positive int, got {k!r}")
    gain, zz, group, z, d = _information(net, parameter, data, candidates, prior_precision)
    if k > len(gain):
        raise ValueError(f"k = {k} exceeds the {len(gain)} candidates")
    chosen = []
    gain = gain.clone()
    for _ in range(k):
        i = int(gain.argmax())
        chosen.append(i)
        g = int(group[i])
        zz[g] += z[i, :, None] * z[i, None, :]
        same = group == g
        gain[same] = _gain(zz, group[same], z[same], d)
        gain[chosen] = -torch.inf
    return torch.tensor(chosen, dtype=torch.long)
