"""Rows drawn from a fitted effect network: the model generating data from itself.

:func:`simulate` draws rows in :func:`inference.fit`'s own format (state labels, the
parameter NaN where the action does not use it, each parameter's cluster as drawn), so
``fit(net, simulate(net, params, n))`` recovers ``params`` within sampling error: the
rows come from the model's one generative model (:mod:`models.model`), the cluster
first, then the value from its cluster's Gaussian. Given evidence, the rows come from the
model's exact conditional:

1. the discrete sites the evidence depends on are drawn jointly from their posterior,
   computed by enumeration (unknown parameters integrated out);
2. an unknown parameter is drawn from its Gaussian posterior given its cluster and the
   observed affected feature (a closed-form identity), or from its cluster's Gaussian
   when that feature is not observed;
3. every remaining site is drawn forward by the model itself; the unobserved dimensions
   of a partly observed feature from its Gaussian conditioned on the observed ones.

Evidence on roots only (initial states, the action) skips step 1: they are independent,
so conditioning on them is clamping them.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from effect_networks.inference.exact.enumeration import enumerate_model
from effect_networks.models.cpds import ParameterMixture
from effect_networks.models.declaration import ACTION, DTYPE, EffectNetwork
from effect_networks.models.evidence import Evidence, is_partial
from effect_networks.models.frames import to_frame
from effect_networks.models.gaussian import condition_on_observed
from effect_networks.models.model import effect_model
from effect_networks.models.params import NetworkParams, check_params, check_seed
from pyro import poutine


def simulate(
    net: EffectNetwork,
    params: NetworkParams,
    n: int,
    evidence: Mapping[str, object] | None = None,
    *,
    seed: int = 0,
    as_frame: bool = False,
) -> dict[str, object]:
    """Draw ``n`` rows from the model, given ``evidence`` if any.

    Parameters
    ----------
    n
        Rows to draw.
    evidence
        Values of some sites (labels, as everywhere; or a pandas ``DataFrame``, see
        :mod:`models.frames`), one row (shared by all ``n``) or ``n`` rows (one per
        draw). ``None``: draws from the model's joint.
    seed
        Seeds the draws; the global random state is left as it was.
    as_frame
        Return the rows as a pandas ``DataFrame``
        (:func:`models.frames.to_frame`: a column per site, ``site[i]`` per dimension
        of a vector) instead of a dict.

    Returns
    -------
    dict
        Every site: discrete sites a list of ``n`` state labels, continuous ones an
        ``(n, d)`` float64 tensor; ``param.p`` is NaN in rows whose action does not use
        ``p``. ``cluster.p`` is the cluster each value was drawn from (0 where the action
        does not use ``p``); the value, drawn from that cluster's Gaussian, may lie outside
        the cluster's cell, and :func:`inference.fit` files the row under the cluster
        given. With ``as_frame``, the same rows as a ``DataFrame``.
    """
    check_params(net, params)
    if not isinstance(n, int | np.integer) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    n, seed = int(n), check_seed(seed)
    enc = net.encode(evidence if evidence is not None else {})
    if len(enc) and enc.n_rows not in (1, n):
        raise ValueError(f"evidence has {enc.n_rows} rows; give one row or n = {n} rows")
    if len(enc) and enc.n_rows == 1 and n > 1:
        enc = enc.repeat(n)
    rows = draw(net, params, enc if len(enc) else Evidence(net, {}, n), seed=seed)
    if as_frame:
        return to_frame(net, Evidence(net, rows, n))
    return {
        site: net.decode(site, value) if net.site(site).discrete else value
        for site, value in rows.items()
    }


def draw(
    net: EffectNetwork, params: NetworkParams, evidence: Evidence, *, seed: int
) -> dict[str, torch.Tensor]:
    """Encoded draws of every site, one per evidence row (see the module's steps)."""
    n = evidence.n_rows
    data = dict(evidence)
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        if any(net.site(s).role not in ("initial", ACTION) for s in evidence):
            unknown = [
                s.name
                for s in net.sites
                if s.role == "initial" and not s.discrete and s.name not in evidence
            ]
            if unknown:  # drawn from its prior, it would ignore the evidence on the rest
                raise ValueError(
                    "simulate given evidence beyond the roots needs the initial state of "
                    f"continuous features; missing {unknown}"
                )
            try:
                e = enumerate_model(net, params, evidence)
            except ValueError as exc:
                raise ValueError(f"simulate given evidence beyond the roots: {exc}") from None
            data |= _posterior_draw(e)
            for m in net.mixtures:
                data[m.value.site] = _parameter_draw(net, params, m, data)
        trace = poutine.trace(effect_model).get_trace(net, params, Evidence(net, data, n))
    out = {s.name: trace.nodes[s.name]["value"] for s in net.sites}
    for site, value in evidence.items():  # partial evidence: the rest of the feature
        if value.is_floating_point() and is_partial(value):
            out[site] = _unobserved_draw(trace.nodes[site]["fn"], value)
    for m in net.mixtures:  # the parameter of an action that does not use it: absent
        uses = m.in_use(out[m.action])
        site = m.value.site
        out[site] = torch.where(uses[:, None], out[site], torch.nan)
    return out


def _unobserved_draw(fn, y: torch.Tensor) -> torch.Tensor:
    """``y`` ``(n, d)`` with its NaN dimensions drawn given the observed ones.

    Drawn from ``fn`` (the feature's Gaussian given its parents) conditioned on the observed ones.
    """
    mean, cov = condition_on_observed(y, fn.loc, fn.covariance_matrix)
    seen = ~torch.isnan(y)
    cov = cov + torch.diag_embed(seen.to(DTYPE))  # observed dims: variance 0, kept as given
    eps = torch.randn(*mean.shape, dtype=DTYPE)
    drawn = mean + (torch.linalg.cholesky(cov) @ eps[..., None]).squeeze(-1)
    return torch.where(seen, y, drawn)


def _posterior_draw(e) -> dict[str, torch.Tensor]:
    """One joint draw per row of the enumerated sites, from their exact posterior."""
    if e.contracted:
        return e.sample()
    post = e.posterior()  # (E..., n)
    n = post.shape[-1]
    flat = post.reshape(-1, n).T.clamp_min(0)  # (n, M)
    pick = torch.multinomial(flat, 1).squeeze(-1)
    shape = post.shape[:-1]
    out = {}
    for site, dim in e.dims.items():
        axis = len(shape) + 1 + dim  # position of the site's dim within ``shape``
        size = shape[axis]
        if size > 1:
            stride = int(torch.tensor(shape[axis + 1 :]).prod()) if axis + 1 < len(shape) else 1
            out[site] = (pick // stride) % size
    return out


def _parameter_draw(
    net: EffectNetwork, params: NetworkParams, m: ParameterMixture, data
) -> torch.Tensor:
    """``param.p`` in every row: given, else drawn given its cluster (and ``end.g``)."""
    p, (c_site, p_site) = m.parameter, m.sites
    action = data[m.action]
    n = action.shape[0]
    theta = data.get(p_site, torch.full((n, p.dim), torch.nan, dtype=DTYPE)).clone()
    todo = torch.isnan(theta).any(-1) & m.in_use(action)
    if not todo.any():
        return theta
    cluster = data[c_site]
    prior = params[p_site]
    mean, cov = prior.bias[cluster], prior.covariance[cluster]
    children = [net.cpd(s) for s in m.continuous if s in data]
    if children:
        acting = net.acting_on(m.child) if m.child is not None else (m,)
        mean, cov = m.posterior(params, children, data, cluster, (mean, cov), acting)
    eps = torch.randn(n, p.dim, dtype=DTYPE)
    drawn = mean + (torch.linalg.cholesky(cov) @ eps[..., None]).squeeze(-1)
    return torch.where(todo[:, None], drawn, theta)
