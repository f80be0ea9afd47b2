"""The effect network as a Pyro model: the one definition fitting and every query run on.

Sites, for features ``f`` and an action parameter ``p`` acting on feature ``g``::

    initial.f  ~ Categorical(table)              | MVN(mean, cov)            (roots)
    action     ~ Categorical(table)                                           (enumerated)
    cluster.p  ~ Categorical(table[action])      one-hot on cell 0 for actions not using p
    param.p    ~ MVN(mean[cluster], cov[cluster])   masked out for actions not using p
    end.f      ~ Categorical(table[initial discrete..., action])                discrete f
               | Categorical(softmax(W[...] @ initial continuous + b[...]))    with cont. parents
               | MVN(W[...] @ [initial continuous, param] + b[...], cov[...])   continuous f

Every discrete site carries ``infer={"enumerate": "parallel"}``; rows live in
``pyro.plate("rows", n, dim=-1)``, so enumeration takes dims -2, -3, ... (shapes in the
comments below: ``E...`` is whatever enumeration dims the site's parents carry).

When ``param.p`` is absent from the data it is integrated out in closed form: ``end.g``
is then the marginal ``MVN(W_x x + W_p mean[c] + b, cov + W_p cov_p[c] W_p^T)`` given the
cluster ``c`` (a linear-Gaussian identity), which keeps every query exact. When ``param.p``
is present and ``cluster.p`` is not, the cluster is read off the parameter by its
equidistant grid (the rule that defines it).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import pyro
import pyro.distributions as dist
import torch
from pyro import poutine
from pyro.ops.indexing import Vindex

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
from models.params import LinearGaussian, NetworkParams, Softmax, Table

ENUM = {"enumerate": "parallel"}


def effect_model(
    net: EffectNetwork,
    params: NetworkParams,
    data: Mapping[str, torch.Tensor] | None = None,
    *,
    n_rows: int | None = None,
    masks: Mapping[str, torch.Tensor] | None = None,
    end_sites: Collection[str] | None = None,
) -> dict[str, torch.Tensor]:
    """Pyro model of an effect network.

    Parameters
    ----------
    net, params
        Structure and fitted (or initial) conditional distributions.
    data
        Encoded values by site name (see :meth:`EffectNetwork.encode`): discrete
        ``(n,)`` long, continuous ``(n, d)`` float. ``param.p`` rows of actions that do not
        use ``p`` may hold NaN. Absent sites are latent (discrete: enumerated).
    n_rows
        Number of rows, needed only when ``data`` is empty.
    masks
        Optional ``(n,)`` bool per discrete site: False where that row's value is missing
        (it is then enumerated for that row; used when fitting with gaps).
    end_sites
        End sites to sample (default: all). End sites have no children, so leaving out
        one that is neither observed nor asked about changes no other site's marginal;
        queries use this to skip work.

    Returns
    -------
    dict
        The value of every site (enumerated values carry their enumeration dims).
    """
    data = dict(data or {})
    masks = dict(masks or {})
    n = n_rows if n_rows is not None else next(iter(data.values())).shape[0]
    values: dict[str, torch.Tensor] = {}
    with pyro.plate("rows", n, dim=-1):
        for f in net.features:
            if f.initial:
                site = initial_site(f.name)
                if isinstance(f, Discrete):
                    values[site] = _discrete(
                        site, dist.Categorical(params[site].probs), data, masks
                    )
                else:
                    cpd = params[site]
                    values[site] = pyro.sample(
                        site,
                        dist.MultivariateNormal(cpd.bias, scale_tril=cpd.scale_tril),
                        obs=data.get(site),
                    )

        action = _discrete(ACTION, dist.Categorical(params[ACTION].probs), data, masks)
        values[ACTION] = action

        collapsed: dict[str, bool] = {}
        for p in net.parameters:
            uses = net.uses_parameter(p)[action]  # (E..., n or 1)
            c_site, p_site = cluster_site(p.name), param_site(p.name)
            x = data.get(p_site)
            collapsed[p.name] = x is None
            if x is not None and c_site not in data:
                data[c_site] = torch.where(uses, p.cluster_of(x.nan_to_num()), 0)
            cluster_probs = Vindex(params[c_site].probs)[action, :]
            cluster = _discrete(c_site, dist.Categorical(cluster_probs), data, masks)
            values[c_site] = cluster
            if x is not None:
                present = ~torch.isnan(x).any(-1)
                cpd = params[p_site]
                with poutine.mask(mask=uses & present):
                    values[p_site] = pyro.sample(
                        p_site,
                        dist.MultivariateNormal(
                            Vindex(cpd.bias)[cluster, :],
                            scale_tril=Vindex(cpd.scale_tril)[cluster, :, :],
                        ),
                        obs=x.nan_to_num(),
                    )

        for f in net.features:
            site = end_site(f.name)
            if end_sites is not None and site not in end_sites:
                continue
            index = [values[s] for s in net.discrete_parents(f.name)]
            cpd = params[site]
            p = net.parameter_of(f.name)
            if isinstance(f, Discrete):
                if isinstance(cpd, Table):
                    fn = dist.Categorical(Vindex(cpd.probs)[(*index, slice(None))])
                else:
                    assert isinstance(cpd, Softmax)
                    x = _concat([values[s] for s in net.continuous_parents(f.name)])
                    logits = _linear(Vindex(cpd.weight)[(*index, slice(None), slice(None))], x)
                    fn = dist.Categorical(logits=logits + Vindex(cpd.bias)[(*index, slice(None))])
                values[site] = _discrete(site, fn, data, masks)
            else:
                assert isinstance(f, Continuous) and isinstance(cpd, LinearGaussian)
                parents = net.continuous_parents(f.name)
                if p is not None and collapsed[p.name]:
                    # Integrate param.p out, once per parent configuration (not per row):
                    # y = W_x x + W_p theta + b + e, theta ~ N(m_c, S_c).
                    offset, marginal_tril, w_x = collapsed_tables(net, params, p)
                    loc = Vindex(offset)[(*index, slice(None))]
                    tril = Vindex(marginal_tril)[(*index, slice(None), slice(None))]
                    x = _concat([values[s] for s in parents[:-1]])
                    if x is not None:
                        loc = loc + _linear(Vindex(w_x)[(*index, slice(None), slice(None))], x)
                    fn = dist.MultivariateNormal(loc, scale_tril=tril)
                else:
                    weight = Vindex(cpd.weight)[(*index, slice(None), slice(None))]
                    loc = Vindex(cpd.bias)[(*index, slice(None))]
                    tril = Vindex(cpd.scale_tril)[(*index, slice(None), slice(None))]
                    x = _concat([values[s] for s in parents])
                    if x is not None:
                        loc = loc + _linear(weight, x)
                    fn = dist.MultivariateNormal(loc, scale_tril=tril)
                values[site] = pyro.sample(site, fn, obs=data.get(site))
    return values


def _discrete(site: str, fn: dist.Categorical, data: Mapping, masks: Mapping) -> torch.Tensor:
    """Sample a discrete site: observed, enumerated, or enumerated where a mask says missing."""
    value = data.get(site)
    mask = masks.get(site)
    if value is None or mask is None:
        return pyro.sample(site, fn, obs=value, infer=ENUM)
    latent = pyro.sample(site, fn, infer=ENUM)
    zero = torch.zeros((), dtype=DTYPE)
    agree = torch.where(latent == value, zero, -torch.inf)
    pyro.factor(f"{site}.observed", torch.where(mask, agree, zero))
    return latent


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
    last). For actions not using the parameter ``W_p`` counts as zero.
    """
    cpd = params[end_site(parameter.affects)]
    prior = params[param_site(parameter.name)]
    k = parameter.dim
    q = cpd.weight.shape[-1]
    w_x, w_p = cpd.weight[..., : q - k], cpd.weight[..., q - k :]  # (..., A, C, d, *)
    w_p = w_p * net.uses_parameter(parameter).to(w_p.dtype)[:, None, None, None]
    offset = cpd.bias + _linear(w_p, prior.bias)  # prior.bias (C, k) aligns with the cluster axis
    cov = cpd.covariance + w_p @ prior.covariance @ w_p.mT
    return offset, torch.linalg.cholesky(cov), w_x
