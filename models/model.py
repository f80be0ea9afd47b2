"""The effect network as a Pyro model: the one definition fitting and every query run on.

Sites, for features ``f`` and an action parameter ``p`` acting on feature ``g``, in the
order of ``net.sites`` (parents first); each site's distribution is its kind's
(:meth:`EffectNetwork.cpd`, :mod:`models.cpds`) given its declared parents (Fig. 1's:
every initial site and the action for every end site)::

    initial.f  ~ Categorical(table)              | MVN(mean, cov)            (roots)
    action     ~ Categorical(table)                                           (enumerated)
    cluster.p  ~ Categorical(table[action])      one-hot on cell 0 for actions not using p
    param.p    ~ MVN(mean[cluster], cov[cluster])   density left out for actions not using p
    end.f      ~ Categorical(table[discrete parents...])                        discrete f
               | Categorical(softmax(W[...] @ continuous parents + b[...]))    with cont. parents
               | MVN(W[...] @ [continuous parents, param] + b[...], cov[...])   continuous f

Every discrete site carries ``infer={"enumerate": "parallel"}``; rows live in
``pyro.plate("rows", n, dim=-1)``, so enumeration takes dims -2, -3, ... . The set of
sites never depends on what ``data`` holds: a site missing from ``data`` is latent
(sampled, or enumerated under ``poutine.enum``), and Pyro's handlers
(``pyro.condition``, ``Predictive``, ``infer_discrete``, ``TraceEnum_ELBO``) see the
same model that fitting and the queries use.

Two rules shape the parameter sites:

* **An action that does not use a parameter ignores it**
  (:meth:`EffectNetwork.parameter_in_use`): its value has no effect on the affected
  feature, its density is left out, its cluster sits on cell 0 (probability one; the
  other cells are impossible, not merely improbable).
* **One generative model: a plain mixture, the cluster part of the data.** For an action
  using ``p``: ``cluster.p ~ Categorical(table[action])``, then
  ``param.p ~ MVN(mean[cluster], cov[cluster])``, untruncated (a drawn value may lie
  outside its cluster's cell), then the affected features given both. Nothing in the
  model ties a cluster to a cell. Under the grid layout the *data* do: a row that gives
  ``param.p`` without ``cluster.p`` (training rows, query evidence, the model's
  ``data``) is read as observing the value's equidistant cell as its cluster, which is
  how the paper's training rows are clustered; a row that gives the cluster keeps it
  (:func:`inference.simulate` returns the cluster it drew, :func:`inference.fit` uses
  it). A value conditioned through a handler (``pyro.condition``) is conditioned in the
  generative model: its cluster's posterior is the mixture's responsibility. Under the
  adaptive layout (``Parameter(layout="adaptive")``) no cell is ever read: a known
  value leaves its cluster latent.

``collapse=True`` is the form the exact queries run (and the one to give Pyro's exact
sums, ``TraceEnum_ELBO`` and ``infer_discrete``). An unobserved continuous end site is
then integrated out: it has no children, so its integral is one; it is still drawn, with
its factor masked. A parameter given as NaN in a
row, or not given at all, is then *unknown* in that row and is integrated out in closed
form (the default form's density integrated over the value, exactly: the cluster's
Gaussian is untruncated): the affected feature follows the marginal
``MVN(W_x x + W_p mean[c] + b, cov + W_p cov_p[c] W_p^T)`` given the cluster ``c`` (a
linear-Gaussian identity), so no continuous site is latent and every discrete sum is
exact. Several parameters on one feature add their terms; a parameter acting on several
continuous features couples them, which are then sampled last (they have no children),
the observed ones first (those observed in part after those observed in full), each
given the value's Gaussian conditioned on those before it
(:class:`models.cpds.ParameterMixture`). A discrete feature a parameter acts on depends
on its cluster, an enumerated site. In the default form a parameter is an ordinary
sample site: given, or sampled.

An end feature observed in some dimensions only (:class:`models.evidence.Partial`:
NaN in the others) contributes the density of those dimensions' marginal.

Values that reach the model through Pyro's handlers are the model's own: state indices
for discrete sites (``net.encode`` turns labels into them), numbers for continuous ones
(float32 is accepted and computed in float64).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import pyro
import pyro.distributions as dist
import torch
from effect_networks.models.cpds import ParameterMixture, concat_inputs
from effect_networks.models.cpds.mixture import affected_gaussian
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.dtype import DTYPE
from effect_networks.models.evidence import Evidence, is_partial
from effect_networks.models.gaussian import partial_log_density
from effect_networks.models.params import NetworkParams, check_bound
from pyro import poutine

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
        End sites to sample (default: all), with the end sites they depend on. An end
        site that no kept site depends on changes no other site's marginal when left
        out; queries use this to skip work.
    collapse
        Integrate unknown parameter values (NaN rows, or the site not given) out in
        closed form instead of sampling them, and unobserved continuous end sites out
        (drawn, their factor masked: they have no children): the form of the exact
        queries, exact under ``TraceEnum_ELBO`` and ``infer_discrete``.

    Returns
    -------
    dict
        The value of every site (enumerated values carry their enumeration dims).
    """
    check_bound(net, params)
    data = net.encode(data) if data is not None else Evidence(net, {}, 0)
    n = _rows(data, n_rows)
    masks = dict(masks or {})
    wanted = None if end_sites is None else net.end_sites_needed(_site_names(net, end_sites))
    mixtures = {m.cluster.site: m for m in net.mixtures}
    acting: dict[str, tuple[ParameterMixture, ...]] = {}  # continuous site -> its parameters
    shared = [m for m in net.mixtures if len(m.continuous) > 1]
    for m in net.mixtures:
        if m.child is not None:
            acting[m.child] = (*acting.get(m.child, ()), m)
    # A value acting on several continuous sites couples them where it is unknown: they
    # are sampled last (they have no children), the observed ones first, each given
    # the value's Gaussian conditioned on those before it.
    deferred = {s for m in shared for s in m.continuous}
    cache: dict[str, torch.Tensor] = {}  # per-call tables (a table's logs, once)
    values: dict[str, torch.Tensor] = {}
    known: dict[str, torch.Tensor] = {}  # per parameter: the rows where its value is known
    with pyro.plate("rows", n, dim=-1):
        for spec in net.sites:
            site = spec.name
            if spec.role == "param":
                continue  # sampled with its cluster
            if wanted is not None and spec.role == "end" and site not in wanted:
                continue  # no kept site depends on it (see end_sites)
            if site in deferred:
                continue
            if site in mixtures:
                m = mixtures[site]
                cluster, theta, known[m.parameter.name] = _parameter(
                    m, params, values[m.action], data, masks, collapse, n, cache
                )
                values[site], values[m.value.site] = cluster, theta
                continue
            cpd = net.cpd(site)
            index = [values[s] for s in cpd.parents]
            inputs = [values[s] for s in cpd.inputs]
            if site in acting:
                action = values[acting[site][0].action]
                fn = affected_gaussian(acting[site], params, cpd, index, inputs, action, known)
            else:
                fn = cpd.distribution(params[site], index, concat_inputs(inputs), cache)
            if spec.discrete:
                values[site] = _discrete(site, fn, data, masks)
            else:
                values[site] = _observe(site, fn, data.get(site), collapse and spec.role == "end")
        for m in shared:
            sites = [s for s in m.continuous if wanted is None or s in wanted]
            belief = None
            # observed ones first, then those observed in part (each of them given every
            # fully observed one), then the latent ones
            for site in sorted(sites, key=lambda s: (s not in data, _partly(data, s))):
                cpd = net.cpd(site)
                index = [values[s] for s in cpd.parents]
                inputs = [values[s] for s in cpd.inputs]
                action = values[m.action]
                args = (params, cpd, index, inputs, action)
                fn = m.shared_gaussian(*args, known[m.parameter.name], belief)
                values[site] = _observe(site, fn, data.get(site), collapse)
                if site in data:
                    belief = m.update(*args, values[site], belief)
    return values


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


def _parameter(m: ParameterMixture, params, action, data, masks, collapse, n, cache):
    """Sample ``cluster.p`` and ``param.p``.

    Return them, and the rows where the value is known (bool, the parameter's batch shape).
    """
    c_site, p_site = m.sites
    p = m.parameter
    uses = m.in_use(action)  # (E..., n or 1)
    x = data.get(p_site)
    cluster_fn = m.cluster.distribution(params[c_site], [action], None, cache)
    if c_site in data or x is None or p.adaptive:  # adaptive: no cell fixes the cluster
        cluster = _discrete(c_site, cluster_fn, data, masks)
    else:
        # A value given without its cluster comes with its cell (the grid layout's reading
        # of such rows); rows whose action does not use the parameter sit on cell 0; rows
        # with an unknown value leave it latent.
        given = ~torch.isnan(x).any(-1)
        cell = m.cells(x, action)
        observed = given | ~uses
        mask = None if bool(observed.all()) else observed
        cluster = _discrete(c_site, cluster_fn, {c_site: cell}, {c_site: mask})
    loc, tril = m.value.loc_tril(params[p_site], [cluster], None)
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
    return cluster, theta, ~torch.isnan(theta).any(-1)


class _UnknownWhereNaN(dist.MultivariateNormal):
    """A Gaussian whose NaN observations are unknown values: their factor is one."""

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        given = ~torch.isnan(value).any(-1)
        if not bool(given.any()):
            shape = torch.broadcast_shapes(self.batch_shape, value.shape[:-1])
            return torch.zeros(shape, dtype=self.loc.dtype)
        return torch.where(given, super().log_prob(value.nan_to_num()), 0.0)


def _partly(data: Mapping, site: str) -> bool:
    return site in data and is_partial(data[site])


class _PartlyObserved(dist.MultivariateNormal):
    """A Gaussian observed in the dimensions where its value is not NaN.

    The density of those dimensions' marginal (partial evidence, :class:`models.evidence.Partial`).
    """

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        return partial_log_density(value, self.loc, self.scale_tril)


def _observe(
    site: str, fn: dist.MultivariateNormal, obs: torch.Tensor | None, leaf: bool = False
) -> torch.Tensor:
    """Sample a continuous site: latent, observed, or observed in some dimensions.

    NaN in the other dimensions: their marginal is the site's factor. A latent ``leaf`` (an end site
    in the collapsed form) is integrated out: nothing depends on it, so its integral is one; it is
    drawn, with its factor masked, so that exact sums stay exact.
    """
    if obs is not None and is_partial(obs):
        fn = _PartlyObserved(fn.loc, scale_tril=fn.scale_tril)
    if obs is None and leaf:
        with poutine.mask(mask=False):
            return _continuous(site, pyro.sample(site, fn))
    return _continuous(site, pyro.sample(site, fn, obs=obs))


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


def _site_names(net: EffectNetwork, end_sites: object) -> list[str]:
    """``end_sites`` as a list of the network's site names.

    A string (whose letters would be taken for names) or a name the network lacks is a
    ``ValueError``, since leaving an end site out changes the model silently. Names of other roles
    are ignored (the queries pass their whole evidence).
    """
    if isinstance(end_sites, str | bytes) or not hasattr(end_sites, "__iter__"):
        raise ValueError(
            f"end_sites must be a collection of end site names, got {end_sites!r} (one site "
            f"is written ({end_sites!r},))"
        )
    names = list(end_sites)
    sites = {s.name for s in net.sites}
    unknown = [name for name in names if name not in sites]
    if unknown:
        ends = [s.name for s in net.sites if s.role == "end"]
        raise ValueError(
            f"end_sites {unknown} are not sites of this network; its end sites: {ends}"
        )
    return names
