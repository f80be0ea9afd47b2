"""The effect network as a Pyro model: the one definition fitting and every query run on.

Sites, for features ``f`` and an action parameter ``p`` acting on feature ``g``::

    initial.f  ~ Categorical(table)              | MVN(mean, cov)            (roots)
    action     ~ Categorical(table)                                           (enumerated)
    cluster.p  ~ Categorical(table[action])      one-hot on cell 0 for actions not using p
    param.p    ~ MVN(mean[cluster], cov[cluster])   density left out for actions not using p
    end.f      ~ Categorical(table[initial discrete..., action])                discrete f
               | Categorical(softmax(W[...] @ initial continuous + b[...]))    with cont. parents
               | MVN(W[...] @ [initial continuous, param] + b[...], cov[...])   continuous f

Every discrete site carries ``infer={"enumerate": "parallel"}``; rows live in
``pyro.plate("rows", n, dim=-1)``, so enumeration takes dims -2, -3, ... . The set of
sites never depends on what ``data`` holds: a site missing from ``data`` is latent
(sampled, or enumerated under ``poutine.enum``), and Pyro's handlers
(``pyro.condition``, ``Predictive``, ``infer_discrete``, ``TraceEnum_ELBO``) see the
same model that fitting and the queries use.

Two rules shape the parameter sites:

* **An action that does not use a parameter ignores it**
  (:meth:`EffectNetwork.parameter_in_use`): its value has no effect on the affected
  feature, its density is left out, its cluster sits on cell 0.
* **The cluster is the parameter's equidistant cell.** A factor ``cluster.p.cell`` is
  zero where ``cell(param.p) == cluster.p`` and ``-inf`` elsewhere, so conditioning on
  ``param.p`` (by ``data`` or by ``pyro.condition``) fixes the cluster. Forward sampling
  ignores factors: a sampled parameter may leave its cell's Gaussian's cell.

``collapse=True`` is the form the exact queries run. A parameter given as NaN in a
row, or not given at all, is then *unknown* in that row and is integrated out in closed
form: the affected feature follows the marginal
``MVN(W_x x + W_p mean[c] + b, cov + W_p cov_p[c] W_p^T)`` given the cluster ``c`` (a
linear-Gaussian identity), so no continuous site is latent and every discrete sum is
exact. In the default form a parameter is an ordinary sample site: given, or sampled.

Values that reach the model through Pyro's handlers are the model's own: state indices
for discrete sites (``net.encode`` turns labels into them), numbers for continuous ones
(float32 is accepted and computed in float64).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import pyro
import pyro.distributions as dist
import torch
from pyro import poutine
from pyro.ops.indexing import Vindex
from torch.distributions.utils import probs_to_logits

from models.declaration import (
    ACTION,
    DTYPE,
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    cluster_site,
    end_site,
    initial_site,
    param_site,
)
from models.evidence import Evidence
from models.params import LinearGaussian, NetworkParams, Softmax, Table

ENUM = {"enumerate": "parallel"}


def effect_model(
    net: EffectNetwork,
    params: NetworkParams,
    data: Mapping[str, object] | None = None,
    *,
    n_rows: int | None = None,
    masks: Mapping[str, torch.Tensor] | None = None,
    end_sites: Collection[str] | None = None,
    collapse: bool = False,
) -> dict[str, torch.Tensor]:
    """Pyro model of an effect network.

    Parameters
    ----------
    net, params
        Structure and fitted (or initial) conditional distributions.
    data
        Observed values by site name: state labels and numbers (see
        :meth:`EffectNetwork.encode`), or :class:`~models.evidence.Evidence`. Absent sites
        are latent.
    n_rows
        Number of rows when ``data`` holds no site (default: the rows of an empty
        :class:`~models.evidence.Evidence`, else 1); must agree with ``data``.
    masks
        Optional ``(n,)`` bool per discrete site: False where that row's value is missing
        (it is then enumerated for that row; used when fitting with gaps).
    end_sites
        End sites to sample (default: all). End sites have no children, so leaving out
        one that is neither observed nor asked about changes no other site's marginal;
        queries use this to skip work.
    collapse
        Integrate unknown parameter values (NaN rows, or the site not given) out in
        closed form instead of sampling them: the form of the exact queries.

    Returns
    -------
    dict
        The value of every site (enumerated values carry their enumeration dims).
    """
    data = net.encode(data) if data is not None else Evidence(net, {}, 0)
    n = _rows(data, n_rows)
    masks = dict(masks or {})
    log_tables = _LogTables(params)
    values: dict[str, torch.Tensor] = {}
    with pyro.plate("rows", n, dim=-1):
        for f in net.features:
            if f.initial:
                site = initial_site(f.name)
                cpd = params[site]
                if isinstance(f, Discrete):
                    fn = dist.Categorical(logits=log_tables[site])
                    values[site] = _discrete(site, fn, data, masks)
                else:
                    fn = dist.MultivariateNormal(cpd.bias, scale_tril=cpd.scale_tril)
                    values[site] = _continuous(site, pyro.sample(site, fn, obs=data.get(site)))

        action = _discrete(ACTION, dist.Categorical(logits=log_tables[ACTION]), data, masks)
        values[ACTION] = action

        known: dict[str, torch.Tensor | None] = {}
        for p in net.parameters:
            theta, known[p.name] = _parameter(
                net, params, log_tables, p, action, data, masks, collapse, n
            )
            values[cluster_site(p.name)] = theta[0]
            values[param_site(p.name)] = theta[1]

        for f in net.features:
            site = end_site(f.name)
            if end_sites is not None and site not in end_sites:
                continue
            index = [values[s] for s in net.discrete_parents(f.name)]
            cpd = params[site]
            if isinstance(f, Discrete):
                if isinstance(cpd, Table):
                    fn = dist.Categorical(logits=Vindex(log_tables[site])[(*index, slice(None))])
                else:
                    assert isinstance(cpd, Softmax)
                    x = _concat([values[s] for s in net.continuous_parents(f.name)])
                    logits = _linear(Vindex(cpd.weight)[(*index, slice(None), slice(None))], x)
                    fn = dist.Categorical(logits=logits + Vindex(cpd.bias)[(*index, slice(None))])
                values[site] = _discrete(site, fn, data, masks)
            else:
                assert isinstance(f, Continuous) and isinstance(cpd, LinearGaussian)
                fn = _continuous_end(net, params, f, index, values, known)
                values[site] = _continuous(site, pyro.sample(site, fn, obs=data.get(site)))
    return values


class _LogTables:
    """Log-probabilities of the model's tables, each taken once per model call, on demand.

    A Categorical built from probabilities takes their log lazily, over its whole batch:
    for a table gathered at enumerated parents (and broadcast over rows) that is the
    enumerated tensor, far larger than the table. Gathering log-probabilities instead
    takes each log once, on the table. The values are those ``Categorical(probs)``
    computes (normalised, clamped to ``[eps, 1 - eps]``, then log), so a zero
    probability stays finite, as it was.
    """

    def __init__(self, params: NetworkParams):
        self._params = params
        self._logs: dict[str, torch.Tensor] = {}

    def __getitem__(self, site: str) -> torch.Tensor:
        if site not in self._logs:
            probs = self._params[site].probs
            self._logs[site] = probs_to_logits(probs / probs.sum(-1, keepdim=True))
        return self._logs[site]


def _rows(data: Evidence, n_rows: int | None) -> int:
    if len(data):
        if n_rows is not None and n_rows != data.n_rows:
            raise ValueError(f"n_rows={n_rows} but the data has {data.n_rows} rows")
        n = data.n_rows
    else:
        n = n_rows if n_rows is not None else (data.n_rows or 1)
    if not isinstance(n, int) or n < 1:
        raise ValueError(
            f"the model needs at least one row, got {n!r} (queries answer empty evidence "
            "with empty results without running the model)"
        )
    return n


def _parameter(net, params, log_tables, p: Parameter, action, data, masks, collapse, n):
    """Sample ``cluster.p`` and ``param.p``; return them, and the rows where the value is
    known (bool, the parameter's batch shape)."""
    c_site, p_site = cluster_site(p.name), param_site(p.name)
    uses = net.parameter_in_use(p, action)  # (E..., n or 1)
    x = data.get(p_site)
    cluster_fn = dist.Categorical(logits=Vindex(log_tables[c_site])[action, :])
    if c_site in data or x is None:
        cluster = _discrete(c_site, cluster_fn, data, masks)
    else:
        # The cell of a given parameter is the cluster; rows whose action does not use
        # the parameter sit on cell 0; rows with an unknown value leave it latent.
        given = ~torch.isnan(x).any(-1)
        cell = torch.where(uses, p.cluster_of(x.nan_to_num()), 0)
        observed = given | ~uses
        mask = None if bool(observed.all()) else observed
        cluster = _discrete(c_site, cluster_fn, {c_site: cell}, {c_site: mask})
    cpd = params[p_site]
    loc = Vindex(cpd.bias)[cluster, :]
    tril = Vindex(cpd.scale_tril)[cluster, :, :]
    if collapse:
        obs = x if x is not None else torch.full((n, p.dim), torch.nan, dtype=DTYPE)
        with poutine.mask(mask=uses):
            theta = pyro.sample(p_site, _UnknownWhereNaN(loc, scale_tril=tril), obs=obs)
    else:
        if x is not None and bool((torch.isnan(x).any(-1) & uses).any()):
            row = int((torch.isnan(x).any(-1) & uses).nonzero()[0, -1])
            raise ValueError(
                f"site {p_site!r}: row {row} holds NaN (unknown) for an action that uses "
                f"{p.name!r}; the model samples a parameter that is not given, so leave the "
                "site out, or run it with collapse=True to integrate unknown values out"
            )
        with poutine.mask(mask=uses):
            theta = pyro.sample(
                p_site,
                dist.MultivariateNormal(loc, scale_tril=tril),
                obs=x.nan_to_num() if x is not None else None,
            )
    theta = _continuous(p_site, theta)
    known = ~torch.isnan(theta).any(-1)
    cell_factor = torch.zeros((), dtype=DTYPE)
    if bool(known.any()):
        wrong_cell = uses & known & (p.cluster_of(theta.nan_to_num()) != cluster)
        cell_factor = cell_factor.masked_fill(wrong_cell, -torch.inf)
    pyro.factor(f"{c_site}.cell", cell_factor)
    return (cluster, theta), known


def _continuous_end(net, params, f: Continuous, index, values, known) -> dist.MultivariateNormal:
    """The affected feature given the parameter where known, integrated out where not."""
    site = end_site(f.name)
    cpd = params[site]
    parents = net.continuous_parents(f.name)
    p = net.parameter_of(f.name)
    parts = [values[s] for s in parents]
    known_rows = known[p.name] if p is not None else None
    everywhere = known_rows is None or bool(known_rows.all())
    nowhere = known_rows is not None and not bool(known_rows.any())
    if not nowhere:  # the parameter known in some rows: condition on it there
        loc = Vindex(cpd.bias)[(*index, slice(None))]
        tril = Vindex(cpd.scale_tril)[(*index, slice(None), slice(None))]
        weight = Vindex(cpd.weight)[(*index, slice(None), slice(None))]
        if p is not None:
            uses = net.parameter_in_use(p, values[ACTION])
            parts[-1] = torch.where(uses[..., None], parts[-1].nan_to_num(), 0.0)
        x = _concat(parts)
        if x is not None:
            loc = loc + _linear(weight, x)
    if not everywhere:
        # Rows with an unknown parameter: y = W_x x + W_p theta + b + e, theta ~ N(m_c, S_c).
        offset, marginal_tril, w_x = collapsed_tables(net, params, p)
        m_loc = Vindex(offset)[(*index, slice(None))]
        m_tril = Vindex(marginal_tril)[(*index, slice(None), slice(None))]
        xs = _concat(parts[:-1])
        if xs is not None:
            m_loc = m_loc + _linear(Vindex(w_x)[(*index, slice(None), slice(None))], xs)
        if nowhere:
            loc, tril = m_loc, m_tril
        else:
            loc = torch.where(known_rows[..., None], loc, m_loc)
            tril = torch.where(known_rows[..., None, None], tril, m_tril)
    return dist.MultivariateNormal(loc, scale_tril=tril)


class _UnknownWhereNaN(dist.MultivariateNormal):
    """A Gaussian whose NaN observations are unknown values: their factor is one."""

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        given = ~torch.isnan(value).any(-1)
        if not bool(given.any()):
            shape = torch.broadcast_shapes(self.batch_shape, value.shape[:-1])
            return torch.zeros(shape, dtype=self.loc.dtype)
        return torch.where(given, super().log_prob(value.nan_to_num()), 0.0)


def _discrete(site: str, fn: dist.Categorical, data: Mapping, masks: Mapping) -> torch.Tensor:
    """Sample a discrete site: observed, enumerated, or enumerated where a mask says missing."""
    value = data.get(site)
    mask = masks.get(site)
    if value is None or mask is None:
        return _index(site, pyro.sample(site, fn, obs=value, infer=ENUM))
    latent = _index(site, pyro.sample(site, fn, infer=ENUM))
    agree = torch.zeros((), dtype=DTYPE).masked_fill(latent != value, -torch.inf)
    pyro.factor(f"{site}.observed", torch.where(mask, agree, 0.0))
    return latent


def _index(site: str, value: object) -> torch.Tensor:
    """A discrete site's value as long state indices (what reaches it through handlers)."""
    if isinstance(value, torch.Tensor) and not value.is_floating_point():
        return value if value.dtype == torch.long else value.long()
    raise ValueError(
        f"site {site!r} received {value!r}: the model's discrete values are state indices "
        "(a long tensor). Condition on labels through the network's encoding, e.g. "
        "pyro.condition(effect_model, data=net.encode({...}))"
    )


def _continuous(site: str, value: object) -> torch.Tensor:
    """A continuous site's value in float64 (float32 from a handler is accepted)."""
    if isinstance(value, torch.Tensor) and value.is_floating_point():
        return value if value.dtype == DTYPE else value.to(DTYPE)
    raise ValueError(f"site {site!r} received {value!r}: expected a float tensor of shape (n, dim)")


def _concat(parts: list[torch.Tensor]) -> torch.Tensor | None:
    if not parts:
        return None
    if len(parts) == 1:
        return parts[0]
    batch = torch.broadcast_shapes(*[p.shape[:-1] for p in parts])
    return torch.cat([p.expand(*batch, p.shape[-1]) for p in parts], dim=-1)


def _linear(weight: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``weight @ x`` over the last dims: ``(..., d, p) x (..., p) -> (..., d)``."""
    return (weight @ x.unsqueeze(-1)).squeeze(-1)


def collapsed_tables(
    net: EffectNetwork, params: NetworkParams, parameter: Parameter
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The affected feature's CPD with ``parameter`` integrated out, per configuration.

    Returns ``offset`` ``(P..., d)`` (``b + W_p m_c``), ``scale_tril`` ``(P..., d, d)``
    (Cholesky of ``R + W_p S_c W_p^T``) and ``w_x`` ``(P..., d, p - k)``, over the
    affected end site's discrete parents ``P...`` (the action second to last, the cluster
    last). For actions not using the parameter ``W_p`` counts as zero (the rule of
    :meth:`EffectNetwork.parameter_in_use`).
    """
    cpd = params[end_site(parameter.affects)]
    prior = params[param_site(parameter.name)]
    k = parameter.dim
    q = cpd.weight.shape[-1]
    w_x, w_p = cpd.weight[..., : q - k], cpd.weight[..., q - k :]  # (..., A, C, d, *)
    actions = torch.arange(len(net.actions))
    uses = net.parameter_in_use(parameter, actions).to(w_p.dtype)
    w_p = w_p * uses[:, None, None, None]
    offset = cpd.bias + _linear(w_p, prior.bias)  # prior.bias (C, k) aligns with the cluster axis
    cov = cpd.covariance + w_p @ prior.covariance @ w_p.mT
    return offset, torch.linalg.cholesky(cov), w_x
