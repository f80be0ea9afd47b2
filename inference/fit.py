"""Maximum-likelihood fitting of effect networks.

Two routes to the same optimum, both on the likelihood that :func:`models.effect_model`
defines:

* :func:`fit` -- closed form wherever it exists: tables are normalised counts,
  conditional linear Gaussians are per-configuration least squares with the residual
  covariance, cluster Gaussians are sample means and covariances. Softmax CPDs (a discrete
  child of continuous parents) have no closed form and are fitted by gradient on the
  model's log-likelihood; so are all CPDs when some rows miss a discrete value (the
  marginal likelihood, with the missing values summed out by enumeration).
* :func:`fit_gradient` -- ``TraceEnum_ELBO`` with an empty guide, minimised with Adam on
  tensors local to the call (Pyro's global parameter store is left alone): with no
  latent continuous sites, the ELBO *is* the (marginal) log-likelihood.

The rule that an action which does not use a parameter ignores it
(:meth:`EffectNetwork.parameter_in_use`) holds in training too: a row whose action does
not use ``p`` must leave ``param.p`` NaN (a value there is refused, not silently used),
and the affected feature's weights on ``p`` are zero for such actions.

Every loop is bounded and every input checked: a value whose square would overflow
(beyond ``MAX_MAGNITUDE``), a non-finite or negative setting, zero rows, or a covariance
that no jitter makes positive definite raise a ``ValueError`` naming the site.

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
from pyro.infer import TraceEnum_ELBO
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
from models.evidence import Evidence
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
    _check_settings(pseudo_count=pseudo_count, min_variance=min_variance, steps=steps, lr=lr)
    enc = _complete(net, data)
    masks = _masks(net, masks, enc.n_rows)
    complete = torch.ones(enc.n_rows, dtype=torch.bool)
    for m in masks.values():
        complete &= m
    rows = enc.rows(complete)
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
    """Maximum likelihood by gradient: ``TraceEnum_ELBO`` with an empty guide.

    With no latent continuous site (unknown parameters are integrated out in closed
    form, missing discrete values are enumerated) the ELBO *is* the marginal
    log-likelihood, so its gradient is the likelihood's. ``sites`` limits the fitted
    CPDs (the others stay at ``init``); ``init`` defaults to uniform tables, standard
    Gaussians and zero softmax weights. The optimiser's tensors are local: Pyro's global
    parameter store is neither read nor changed.
    """
    _check_settings(pseudo_count=pseudo_count, steps=steps, lr=lr)
    enc = _complete(net, data)
    masks = _masks(net, masks, enc.n_rows)
    init = init or _default_params(net, pseudo_count)
    sites = list(init.cpds) if sites is None else list(sites)
    unknown = [s for s in sites if s not in init.cpds]
    if unknown:
        raise ValueError(f"sites {unknown} are not sites of this network")
    fixed_cluster_rows = {cluster_site(p.name): ~net.uses_parameter(p) for p in net.parameters}
    lower_cholesky = dist.transforms.LowerCholeskyTransform()

    # Unconstrained tensors, one set per fitted CPD.
    free: dict[str, dict[str, torch.Tensor]] = {}
    for site in sites:
        c = init.cpds[site]
        if isinstance(c, Table):
            free[site] = {"logits": c.probs.clamp_min(1e-12).log()}
        elif isinstance(c, LinearGaussian):
            free[site] = {
                "weight": c.weight,
                "bias": c.bias,
                "tril": lower_cholesky.inv(c.scale_tril),
            }
        else:
            free[site] = {"weight": c.weight, "bias": c.bias}
    tensors = [t.detach().clone().requires_grad_() for f in free.values() for t in f.values()]
    it = iter(tensors)
    free = {site: {k: next(it) for k in f} for site, f in free.items()}

    def current() -> NetworkParams:
        cpds = dict(init.cpds)
        for site, f in free.items():
            c = init.cpds[site]
            if isinstance(c, Table):
                probs = f["logits"].softmax(-1)
                if site in fixed_cluster_rows:  # actions not using the parameter: cell 0
                    probs = torch.where(fixed_cluster_rows[site][:, None], c.probs, probs)
                cpds[site] = Table(probs, c.n)
            elif isinstance(c, LinearGaussian):
                cpds[site] = LinearGaussian(f["weight"], f["bias"], lower_cholesky(f["tril"]), c.n)
            else:
                cpds[site] = Softmax(f["weight"], f["bias"], c.n)
        return NetworkParams(cpds, init.pseudo_count)

    n = enc.n_rows
    # With every value given, the end sites that are not fitted add a constant to the
    # loss: leave them out (with gaps, their factors join the marginal and stay).
    gaps = any(not bool(m.all()) for m in masks.values())
    end_sites = None if gaps else {s for s in sites if net.site(s).role == "end"}

    def model():
        # Scale to a per-row loss so that one learning rate suits any data size.
        with pyro.poutine.scale(scale=1.0 / n):
            effect_model(net, current(), enc, masks=masks, collapse=True, end_sites=end_sites)

    def guide():
        pass

    elbo = TraceEnum_ELBO(max_plate_nesting=1)
    optimiser = torch.optim.Adam(tensors, lr=lr)
    losses = []
    for _ in tqdm(range(steps), desc="fit (gradient)", disable=not progress):
        optimiser.zero_grad()
        with pyro.validation_enabled(False):  # the rows were validated when encoded
            loss = elbo.differentiable_loss(model, guide)
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    with torch.no_grad():
        params = current().map(lambda t: t.detach().clone())
    return FitResult(params, tuple(losses))


def _check_settings(**settings: float) -> None:
    """Refuse settings that would make fitting spin or return NaN."""
    for name, value in settings.items():
        ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        if name == "steps":
            ok = isinstance(value, int) and not isinstance(value, bool) and value >= 1
        elif name == "lr":
            ok = ok and value > 0
        else:
            ok = ok and value >= 0
        if not ok:
            want = (
                "a positive int"
                if name == "steps"
                else ("a finite number > 0" if name == "lr" else "a finite number >= 0")
            )
            raise ValueError(f"{name} must be {want}, got {value!r}")


def _masks(
    net: EffectNetwork, masks: Mapping[str, object] | None, n: int
) -> dict[str, torch.Tensor]:
    out = {}
    for k, v in (masks or {}).items():
        if not net.site(k).discrete:
            raise ValueError(f"masks are for discrete sites; {k!r} is continuous")
        m = torch.as_tensor(v, dtype=torch.bool).reshape(-1)
        if m.shape[0] != n:
            raise ValueError(f"masks[{k!r}] has {m.shape[0]} rows, the data {n}")
        out[k] = m
    return out


# ---------------------------------------------------------------------------- closed form
def _complete(net: EffectNetwork, data: Mapping[str, object]) -> Evidence:
    """Encode training rows, check them, and add each parameter's cluster (its cell)."""
    enc = net.encode(data)
    if not len(enc) or enc.n_rows == 0:
        raise ValueError("no training rows: fit needs at least one row of every site")
    missing = [s.name for s in net.sites if s.name not in enc and s.role != "cluster"]
    if missing:
        raise ValueError(
            f"training data must give every site; missing {missing}. (Give parameters as NaN in "
            f"rows whose action does not use them; mark missing discrete values with `masks`.)"
        )
    clusters = {}
    for p in net.parameters:
        p_site = param_site(p.name)
        uses = net.parameter_in_use(p, enc[ACTION])
        present = ~torch.isnan(enc[p_site]).any(-1)
        for bad, why in (
            (uses & ~present, "uses the parameter, but the row gives no value"),
            (~uses & present, "does not use the parameter, but the row gives a value (give NaN)"),
        ):
            if bad.any():
                row = int(bad.nonzero()[0])
                raise ValueError(
                    f"site {p_site!r}: row {row} has action "
                    f"{net.actions[int(enc[ACTION][row])]!r}, which {why}"
                )
        derived = torch.where(uses, p.cluster_of(enc[p_site].nan_to_num()), 0)
        given = enc.get(cluster_site(p.name))
        if given is not None and not torch.equal(given, derived):
            raise ValueError(
                f"site {cluster_site(p.name)!r} disagrees with the equidistant cells of its parameter"
            )
        clusters[cluster_site(p.name)] = derived
    for site, value in enc.items():
        if not net.site(site).discrete:
            _check_magnitude(site, value)
    return enc | net.encode_indices(clusters) if clusters else enc


#: Largest magnitude whose second moments, summed over 10^7 rows, stay finite in float64.
MAX_MAGNITUDE = 1e150


def _check_magnitude(site: str, value: torch.Tensor) -> None:
    big = value.nan_to_num().abs().amax(-1) > MAX_MAGNITUDE
    if big.any():
        row = int(big.nonzero()[0])
        raise ValueError(
            f"site {site!r}: row {row} holds {value[row].tolist()}, beyond +-{MAX_MAGNITUDE:g}; "
            "its squares overflow the fit's statistics. Rescale the feature (other units)"
        )


def _flat_index(
    enc: Mapping[str, torch.Tensor], sites: tuple[str, ...], net: EffectNetwork
) -> tuple[torch.Tensor, tuple[int, ...]]:
    card = tuple(net.site(s).size for s in sites)
    index = torch.zeros(enc.n_rows, dtype=torch.long)
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
    site: str,
    zero_weights: torch.Tensor | None = None,
) -> LinearGaussian:
    """Per-configuration least squares of y on [x, 1] with pooled pseudo-rows.

    ``zero_weights`` ``(G, p)`` bool: weights fixed at zero per configuration (the
    least squares then runs without those columns there).
    """
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
    if not all(bool(t.isfinite().all()) for t in (szz, szy, syy)):
        raise ValueError(
            f"site {site!r}: the fit's second moments overflow float64; rescale the data"
        )
    if zero_weights is not None and bool(zero_weights.any()):
        drop = torch.cat([zero_weights, torch.zeros(groups, 1, dtype=torch.bool)], -1)
        keep = (~drop).to(DTYPE)
        szz = szz * keep[:, :, None] * keep[:, None, :] + torch.diag_embed(drop.to(DTYPE))
        szy = szy * keep[:, :, None]
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
    tril = _safe_cholesky(cov, site)
    return LinearGaussian(
        beta[:, : q - 1, :].mT.reshape(*card, d, q - 1),
        beta[:, q - 1, :].reshape(*card, d),
        tril.reshape(*card, d, d),
        n.reshape(card),
    )


def _safe_cholesky(cov: torch.Tensor, site: str, tries: int = 24) -> torch.Tensor:
    """Cholesky factors, adding a growing jitter where a covariance is not quite PD."""
    tril, info = torch.linalg.cholesky_ex(cov)
    jitter = 1e-12
    for _ in range(tries):
        bad = info > 0
        if not bad.any():
            return tril
        scale = cov[bad].diagonal(dim1=-2, dim2=-1).abs().mean(-1).clamp_min(1.0)
        cov[bad] = cov[bad] + (jitter * scale)[:, None, None] * torch.eye(
            cov.shape[-1], dtype=cov.dtype
        )
        tril, info = torch.linalg.cholesky_ex(cov)
        jitter *= 10
    if (info > 0).any():
        group = int((info > 0).nonzero()[0])
        raise ValueError(
            f"site {site!r}: configuration {group} has no positive definite covariance "
            f"({cov[group].tolist()}); check its rows for inf, NaN or huge values"
        )
    return tril


def _closed_form(net: EffectNetwork, enc: Evidence, alpha: float, min_variance: float) -> dict:
    cpds: dict = {}
    n = enc.n_rows
    no_parent = torch.zeros(n, dtype=torch.long)
    for f in net.features:
        if f.initial:
            site = initial_site(f.name)
            if isinstance(f, Discrete):
                cpds[site] = _table_root(_table(no_parent, enc[site], (), f.cardinality, alpha))
            else:
                cpds[site] = _strip(
                    _linear_gaussian(no_parent, None, enc[site], (), alpha, min_variance, site)
                )
    cpds[ACTION] = _table_root(_table(no_parent, enc[ACTION], (), len(net.actions), alpha))
    for p in net.parameters:
        c_site, p_site = cluster_site(p.name), param_site(p.name)
        uses = net.parameter_in_use(p, enc[ACTION])
        table = _table(
            enc[ACTION][uses], enc[c_site][uses], (len(net.actions),), p.n_clusters, alpha
        )
        fixed = torch.zeros(p.n_clusters, dtype=DTYPE)
        fixed[0] = 1.0
        probs = torch.where(net.uses_parameter(p)[:, None], table.probs, fixed)
        cpds[c_site] = Table(probs, table.n)
        cpds[p_site] = _linear_gaussian(
            enc[c_site][uses],
            None,
            enc[p_site][uses],
            (p.n_clusters,),
            alpha,
            min_variance,
            p_site,
        )
    for f in net.features:
        site = end_site(f.name)
        index, card = _flat_index(enc, net.discrete_parents(f.name), net)
        cont = [enc[s].nan_to_num() for s in net.continuous_parents(f.name)]
        x = torch.cat(cont, -1) if cont else None
        if isinstance(f, Continuous):
            cpds[site] = _linear_gaussian(
                index, x, enc[site], card, alpha, min_variance, site, _unused(net, f.name, card)
            )
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


def _unused(net: EffectNetwork, feature: str, card: tuple[int, ...]) -> torch.Tensor | None:
    """``(G, p)`` bool: the parameter's weights in configurations of actions not using it.

    The rule of :meth:`EffectNetwork.parameter_in_use`: such an action ignores the
    parameter, so its weights are zero, not fitted (pooled pseudo-rows would otherwise
    lend them the using actions' slope).
    """
    p = net.parameter_of(feature)
    if p is None:
        return None
    width = sum(net.site(s).size for s in net.continuous_parents(feature))
    actions = torch.arange(len(net.actions))
    unused = ~net.parameter_in_use(p, actions)  # the action axis is second to last
    unused = unused[:, None].expand(*card).reshape(-1)
    out = torch.zeros(unused.shape[0], width, dtype=torch.bool)
    out[:, width - p.dim :] = unused[:, None]
    return out


def _table_root(t: Table) -> Table:
    return Table(t.probs.reshape(-1), t.n.reshape(()))


def _strip(g: LinearGaussian) -> LinearGaussian:
    d = g.bias.shape[-1]
    return LinearGaussian(
        g.weight.reshape(d, 0), g.bias.reshape(d), g.scale_tril.reshape(d, d), g.n.reshape(())
    )


def _default_params(net: EffectNetwork, alpha: float) -> NetworkParams:
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
