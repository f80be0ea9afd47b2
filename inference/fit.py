"""Maximum-likelihood fitting of effect networks.

Two routes to the same optimum, both on the likelihood that :func:`models.effect_model`
defines:

* :func:`fit` -- closed form wherever it exists: tables are normalised counts,
  conditional linear Gaussians are per-configuration least squares with the residual
  covariance, cluster Gaussians are sample means and covariances. Softmax CPDs (a discrete
  child of continuous parents) have no closed form and are fitted by gradient on the
  model's log-likelihood; so are all CPDs when some rows miss a discrete value (the
  marginal likelihood, with the missing values summed out by enumeration).
* :func:`fit_gradient` -- SVI with an empty guide and ``TraceEnum_ELBO``: with no latent
  continuous sites, the ELBO *is* the (marginal) log-likelihood.

Pseudo-count policy (``pseudo_count``, written alpha): a table row is
``(counts + alpha) / (n + K alpha)``, so a parent configuration no sample reached is
uniform; a Gaussian configuration gets alpha pseudo-rows of the pooled statistics of its
site (all rows together), so an unseen one is the pooled fit and a rarely seen one is
shrunk towards it. Covariances get ``min_variance`` on the diagonal so that a
configuration with fewer rows than dimensions stays positive definite. ``alpha = 0`` and
``min_variance = 0`` give the plain sample statistics where every configuration is seen.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import pyro
import pyro.distributions as dist
import torch
from pyro.infer import SVI, TraceEnum_ELBO
from pyro.optim import Adam
from tqdm.auto import tqdm

from models.declaration import (
    ACTION,
    DTYPE,
    Continuous,
    Discrete,
    EffectNetwork,
    cluster_site,
    end_site,
    initial_site,
    param_site,
)
from models.model import effect_model
from models.params import (
    LinearGaussian,
    NetworkParams,
    Softmax,
    Table,
    check_params,
    expected_shapes,
)


@dataclass(frozen=True)
class FitResult:
    """What fitting returns: new parameters, and the loss per gradient step (if any)."""

    params: NetworkParams
    losses: tuple[float, ...] = ()


def fit(
    net: EffectNetwork,
    data: Mapping[str, object],
    *,
    pseudo_count: float = 0.01,
    min_variance: float = 1e-6,
    masks: Mapping[str, torch.Tensor] | None = None,
    steps: int = 500,
    lr: float = 0.05,
    progress: bool = False,
) -> FitResult:
    """Fit every CPD of ``net`` by maximum likelihood.

    Parameters
    ----------
    data
        Training rows by site name (see :meth:`EffectNetwork.encode`); every site of the
        network must be present. ``param.p`` holds NaN in rows whose action does not use
        ``p``.
    masks
        ``(n,)`` bool per discrete site, False where the row's value is missing.
    steps, lr, progress
        Gradient settings, used only for Softmax CPDs or when ``masks`` has gaps.
    """
    if pseudo_count < 0 or min_variance < 0:
        raise ValueError(
            f"pseudo_count and min_variance must be >= 0, got {pseudo_count}, {min_variance}"
        )
    enc = _complete(net, data)
    masks = {k: torch.as_tensor(v, dtype=torch.bool) for k, v in (masks or {}).items()}
    for k in masks:
        if not net.site(k).discrete:
            raise ValueError(f"masks are for discrete sites; {k!r} is continuous")
    complete = torch.ones(_rows(enc), dtype=torch.bool)
    for m in masks.values():
        complete &= m
    rows = {k: v[complete] for k, v in enc.items()}
    if not complete.any():
        raise ValueError(
            "every row misses some value; at least one complete row is needed to start"
        )
    cpds = _closed_form(net, rows, pseudo_count, min_variance)
    params = NetworkParams(cpds, pseudo_count)
    gradient_sites = [s for s, c in cpds.items() if isinstance(c, Softmax)]
    if not complete.all():
        gradient_sites = list(cpds)
    if not gradient_sites:
        return FitResult(params)
    return fit_gradient(
        net,
        enc,
        init=params,
        sites=gradient_sites,
        masks=masks,
        steps=steps,
        lr=lr,
        progress=progress,
    )


def fit_gradient(
    net: EffectNetwork,
    data: Mapping[str, object],
    *,
    init: NetworkParams | None = None,
    sites: list[str] | None = None,
    masks: Mapping[str, torch.Tensor] | None = None,
    steps: int = 1000,
    lr: float = 0.05,
    pseudo_count: float = 0.01,
    progress: bool = False,
) -> FitResult:
    """Maximum likelihood by gradient: SVI, empty guide, ``TraceEnum_ELBO``.

    ``sites`` limits the fitted CPDs (the others stay at ``init``); ``init`` defaults to
    uniform tables, standard Gaussians and zero softmax weights.
    """
    enc = _complete(net, data)  # idempotent on rows it already encoded
    n = _rows(enc)
    init = init or _default_params(net, enc, pseudo_count)
    sites = list(init.cpds) if sites is None else sites
    masks = dict(masks or {})
    pyro.clear_param_store()
    fixed_cluster_rows = {cluster_site(p.name): ~net.uses_parameter(p) for p in net.parameters}

    def current() -> NetworkParams:
        cpds = dict(init.cpds)
        for site in sites:
            c = init.cpds[site]
            if isinstance(c, Table):
                logits = pyro.param(f"{site}.logits", c.probs.clamp_min(1e-12).log())
                probs = logits.softmax(-1)
                if site in fixed_cluster_rows:  # actions not using the parameter: cell 0
                    probs = torch.where(fixed_cluster_rows[site][:, None], c.probs, probs)
                cpds[site] = Table(probs, c.n)
            elif isinstance(c, LinearGaussian):
                cpds[site] = LinearGaussian(
                    pyro.param(f"{site}.weight", c.weight),
                    pyro.param(f"{site}.bias", c.bias),
                    pyro.param(
                        f"{site}.scale_tril",
                        c.scale_tril,
                        constraint=dist.constraints.lower_cholesky,
                    ),
                    c.n,
                )
            else:
                cpds[site] = Softmax(
                    pyro.param(f"{site}.weight", c.weight), pyro.param(f"{site}.bias", c.bias), c.n
                )
        return NetworkParams(cpds, init.pseudo_count)

    def model():
        # Scale to a per-row loss so that one learning rate suits any data size.
        with pyro.poutine.scale(scale=1.0 / n):
            effect_model(net, current(), enc, masks=masks)

    def guide():
        pass

    svi = SVI(model, guide, Adam({"lr": lr}), TraceEnum_ELBO(max_plate_nesting=1))
    losses = []
    for _ in tqdm(range(steps), desc="fit (gradient)", disable=not progress):
        losses.append(svi.step())
    with torch.no_grad():
        params = current().map(lambda t: t.detach().clone())
    return FitResult(params, tuple(losses))


# ---------------------------------------------------------------------------- closed form
def _complete(net: EffectNetwork, data: Mapping[str, object]) -> dict[str, torch.Tensor]:
    enc = net.encode(data)
    missing = [s.name for s in net.sites if s.name not in enc and s.role != "cluster"]
    if missing:
        raise ValueError(
            f"training data must give every site; missing {missing}. (Give parameters as NaN in "
            f"rows whose action does not use them; mark missing discrete values with `masks`.)"
        )
    if not enc:
        raise ValueError("no training data")
    for p in net.parameters:
        uses = net.uses_parameter(p)[enc[ACTION]]
        present = ~torch.isnan(enc[param_site(p.name)]).any(-1)
        bad = uses & ~present
        if bad.any():
            row = int(bad.nonzero()[0])
            raise ValueError(
                f"site {param_site(p.name)!r}: row {row} has action "
                f"{net.actions[int(enc[ACTION][row])]!r}, which uses the parameter, but no value"
            )
        derived = torch.where(uses, p.cluster_of(enc[param_site(p.name)].nan_to_num()), 0)
        given = enc.get(cluster_site(p.name))
        if given is not None and not torch.equal(given, derived):
            raise ValueError(
                f"site {cluster_site(p.name)!r} disagrees with the equidistant cells of its parameter"
            )
        enc[cluster_site(p.name)] = derived
    return enc


def _rows(enc: Mapping[str, torch.Tensor]) -> int:
    return next(iter(enc.values())).shape[0]


def _flat_index(
    enc: Mapping[str, torch.Tensor], sites: tuple[str, ...], net: EffectNetwork
) -> tuple[torch.Tensor, tuple[int, ...]]:
    card = tuple(net.site(s).size for s in sites)
    index = torch.zeros(_rows(enc), dtype=torch.long)
    for s, k in zip(sites, card, strict=True):
        index = index * k + enc[s]
    return index, card


def _table(
    index: torch.Tensor, child: torch.Tensor, card: tuple[int, ...], k: int, alpha: float
) -> Table:
    size = math.prod(card)
    counts = torch.bincount(index * k + child, minlength=size * k).reshape(*card, k).to(DTYPE)
    n = counts.sum(-1)
    probs = (counts + alpha) / (n + k * alpha).clamp_min(1e-300)[..., None]
    probs = torch.where((n == 0)[..., None], torch.full_like(probs, 1.0 / k), probs)
    return Table(probs, n)


def _linear_gaussian(
    index: torch.Tensor,
    x: torch.Tensor | None,
    y: torch.Tensor,
    card: tuple[int, ...],
    alpha: float,
    min_variance: float,
) -> LinearGaussian:
    """Per-configuration least squares of y on [x, 1] with pooled pseudo-rows."""
    groups = math.prod(card)
    n_rows, d = y.shape
    z = (
        torch.cat([x, torch.ones(n_rows, 1, dtype=DTYPE)], -1)
        if x is not None
        else torch.ones(n_rows, 1, dtype=DTYPE)
    )
    q = z.shape[-1]
    szz = torch.zeros(groups, q, q, dtype=DTYPE).index_add_(0, index, z[:, :, None] * z[:, None, :])
    szy = torch.zeros(groups, q, d, dtype=DTYPE).index_add_(0, index, z[:, :, None] * y[:, None, :])
    syy = torch.zeros(groups, d, d, dtype=DTYPE).index_add_(0, index, y[:, :, None] * y[:, None, :])
    n = torch.bincount(index, minlength=groups).to(DTYPE)
    if n_rows:
        # alpha pseudo-rows of the pooled statistics (an unseen configuration = the pooled fit)
        w = alpha / n_rows
        szz, szy, syy = szz + w * szz.sum(0), szy + w * szy.sum(0), syy + w * syy.sum(0)
    total = n + (alpha if n_rows else 0.0)
    unseen = total == 0
    if unseen.any():  # alpha == 0: fall back on the pooled fit all the same
        szz[unseen], szy[unseen], syy[unseen], total[unseen] = (
            szz.sum(0),
            szy.sum(0),
            syy.sum(0),
            float(n_rows),
        )
    ridge = 1e-10 * szz.diagonal(dim1=-2, dim2=-1).mean(-1).clamp_min(1e-12)
    beta = torch.linalg.solve(
        szz + ridge[:, None, None] * torch.eye(q, dtype=DTYPE), szy
    )  # (G, q, d)
    resid = syy - szy.mT @ beta - beta.mT @ szy + beta.mT @ szz @ beta
    cov = resid / total.clamp_min(1e-300)[:, None, None]
    cov = 0.5 * (cov + cov.mT) + min_variance * torch.eye(d, dtype=DTYPE)
    tril = _safe_cholesky(cov)
    return LinearGaussian(
        beta[:, : q - 1, :].mT.reshape(*card, d, q - 1),
        beta[:, q - 1, :].reshape(*card, d),
        tril.reshape(*card, d, d),
        n.reshape(card),
    )


def _safe_cholesky(cov: torch.Tensor) -> torch.Tensor:
    tril, info = torch.linalg.cholesky_ex(cov)
    jitter = 1e-12
    while (info > 0).any():
        bad = info > 0
        scale = cov[bad].diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(1.0)
        cov[bad] = cov[bad] + (jitter * scale)[:, None, None] * torch.eye(
            cov.shape[-1], dtype=cov.dtype
        )
        tril, info = torch.linalg.cholesky_ex(cov)
        jitter *= 10
    return tril


def _closed_form(
    net: EffectNetwork, enc: dict[str, torch.Tensor], alpha: float, min_variance: float
) -> dict:
    cpds: dict = {}
    n = _rows(enc)
    no_parent = torch.zeros(n, dtype=torch.long)
    for f in net.features:
        if f.initial:
            site = initial_site(f.name)
            if isinstance(f, Discrete):
                cpds[site] = _table_root(_table(no_parent, enc[site], (), f.cardinality, alpha))
            else:
                cpds[site] = _strip(
                    _linear_gaussian(no_parent, None, enc[site], (), alpha, min_variance)
                )
    cpds[ACTION] = _table_root(_table(no_parent, enc[ACTION], (), len(net.actions), alpha))
    for p in net.parameters:
        c_site, p_site = cluster_site(p.name), param_site(p.name)
        uses = net.uses_parameter(p)[enc[ACTION]]
        table = _table(
            enc[ACTION][uses], enc[c_site][uses], (len(net.actions),), p.n_clusters, alpha
        )
        fixed = torch.zeros(p.n_clusters, dtype=DTYPE)
        fixed[0] = 1.0
        probs = torch.where(net.uses_parameter(p)[:, None], table.probs, fixed)
        cpds[c_site] = Table(probs, table.n)
        cpds[p_site] = _linear_gaussian(
            enc[c_site][uses], None, enc[p_site][uses], (p.n_clusters,), alpha, min_variance
        )
    for f in net.features:
        site = end_site(f.name)
        index, card = _flat_index(enc, net.discrete_parents(f.name), net)
        cont = [enc[s].nan_to_num() for s in net.continuous_parents(f.name)]
        x = torch.cat(cont, -1) if cont else None
        if isinstance(f, Continuous):
            cpds[site] = _linear_gaussian(index, x, enc[site], card, alpha, min_variance)
        elif x is None:
            cpds[site] = _table(index, enc[site], card, f.cardinality, alpha)
        else:
            # Softmax: start from the table's log-frequencies with zero slopes; gradient follows.
            t = _table(index, enc[site], card, f.cardinality, max(alpha, 1e-3))
            cpds[site] = Softmax(
                torch.zeros(*card, f.cardinality, x.shape[-1], dtype=DTYPE), t.probs.log(), t.n
            )
    ordered = {name: cpds[name] for name in expected_shapes(net)}
    check_params(net, NetworkParams(ordered, alpha))
    return ordered


def _table_root(t: Table) -> Table:
    return Table(t.probs.reshape(-1), t.n.reshape(()))


def _strip(g: LinearGaussian) -> LinearGaussian:
    d = g.bias.shape[-1]
    return LinearGaussian(
        g.weight.reshape(d, 0), g.bias.reshape(d), g.scale_tril.reshape(d, d), g.n.reshape(())
    )


def _default_params(
    net: EffectNetwork, enc: dict[str, torch.Tensor], alpha: float
) -> NetworkParams:
    """Uniform tables, zero-slope unit Gaussians and zero softmax: the gradient route's start."""
    cpds = {}
    for site, (kind, shapes) in expected_shapes(net).items():
        if kind == "Table":
            k = shapes["probs"][-1]
            cpds[site] = Table(
                torch.full(shapes["probs"], 1.0 / k, dtype=DTYPE),
                torch.zeros(shapes["n"], dtype=DTYPE),
            )
        elif kind == "LinearGaussian":
            d = shapes["bias"][-1]
            eye = torch.eye(d, dtype=DTYPE).expand(shapes["scale_tril"]).clone()
            cpds[site] = LinearGaussian(
                torch.zeros(shapes["weight"], dtype=DTYPE),
                torch.zeros(shapes["bias"], dtype=DTYPE),
                eye,
                torch.zeros(shapes["n"], dtype=DTYPE),
            )
        else:
            cpds[site] = Softmax(
                torch.zeros(shapes["weight"], dtype=DTYPE),
                torch.zeros(shapes["bias"], dtype=DTYPE),
                torch.zeros(shapes["n"], dtype=DTYPE),
            )
    for p in net.parameters:  # actions not using a parameter sit on cell 0
        t = cpds[cluster_site(p.name)]
        fixed = torch.zeros(p.n_clusters, dtype=DTYPE)
        fixed[0] = 1.0
        cpds[cluster_site(p.name)] = Table(
            torch.where(net.uses_parameter(p)[:, None], t.probs, fixed), t.n
        )
    return NetworkParams(cpds, alpha)
