"""How well a fitted network explains rows: log-likelihood, BIC, AIC and held-out scores.

**What the likelihood is of.** Every site the network models, jointly, per row: the
initial features and the action are roots with their own tables and Gaussians
(:mod:`models.model`), then each parameter's cluster and value, then the end features::

    log p(row) = sum over initial sites      log p(initial.f)
               + log p(action)
               + sum over parameters p        log p(cluster.p | action) + log N(param.p | cluster.p)
               + sum over end sites           log p(end.f | its parents)

(the factors of a parameter left out where the row's action does not use it). This is
the score pgmpy gives a discrete network: one term per node's CPD. Declarations that
differ only in the parents of end sites share the initial and action terms, so these
cancel when such networks are compared. A row's value is read as the model reads it:
under the grid layout a value given without its cluster observes its cell as the
cluster; under the adaptive layout the cluster is latent and summed out.

**Missing values** are marked as :func:`inference.fit` reads them (in the rows: None or
NaN for a discrete label, NaN for a continuous value or some of its dimensions; or by
``masks``) and summed or integrated out exactly, row by row:

* a row whose continuous values are all given goes through the traced model
  (:func:`inference.exact.enumeration.enumerate_model`), its missing discrete values
  enumerated;
* a row that misses a continuous value goes through the continuous sites' joint
  Gaussian given each completion of its discrete values
  (:func:`inference.fitting.missing.gaussian_row_log_likelihoods`): the density of its
  observed dimensions, the missing ones integrated out, times the completion's discrete
  factors, summed over the completions. This needs what :func:`inference.fit` needs
  there, and what has no closed form is refused by name: a continuous site of a kind
  other than the linear Gaussian, or a discrete site (a softmax) that reads the missing
  value.

Where the action is missing in a network with parameters, only the actions that agree
with the parameters the row gives count (a row gives a parameter's value exactly when
its action uses it), as in :func:`inference.fitting.missing.fit_missing`. The rows'
log-likelihoods sum to :func:`inference.fitting.missing.missing_log_likelihood`, the
quantity EM raises; a complete row scores the same whatever the other rows miss.

**Free parameters** (:func:`n_parameters`), per parent configuration a row can reach
(every one of them, seen in the rows or not, as pgmpy counts):

================================  ===============================================
kind                              free parameters per parent configuration
================================  ===============================================
table, ``K`` states               ``K - 1``
softmax, ``K`` states, ``p`` in   ``(K - 1) (p + 1)`` (slopes and offsets, one class fixed)
linear Gaussian, ``d``-dim        ``d p`` weights, ``d`` offsets, ``d (d + 1) / 2``
                                  for the full covariance
parameter cluster ``C`` cells     ``C - 1`` per action using the parameter (0 for
                                  the others: pinned on cell 0)
parameter value ``k``-dim         ``k + k (k + 1) / 2`` per cluster (mean, covariance)
================================  ===============================================

A weight the structure fixes at zero (on a parameter, for an action that does not use
it) is not counted, nor is a configuration no row can reach (an action that does not
use a parameter together with a cluster other than 0).

**BIC and AIC**, lower is better (the Schwarz and Akaike criteria as R and statsmodels
write them), for ``n`` rows, ``k`` free parameters and the total log-likelihood ``L``::

    bic = -2 L + k ln n          aic = -2 L + 2 k

pgmpy's ``BIC`` structure score (higher is better) is ``L - k/2 ln n = -bic / 2``:
:attr:`LogLikelihood.bic_score`. It is a sum of one term per site (the site's
log-likelihood less ``ln n / 2`` times its free parameters), so a score computed family
by family for the same declaration adds up to it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from effect_networks.inference.exact.enumeration import (
    enumerate_model,
    enumeration_size,
    row_chunks,
)
from effect_networks.inference.exact.gaussian_gaps import continuous_gaps, refuse_open_forms
from effect_networks.inference.exact.traced import Enumerated
from effect_networks.inference.fitting.em import fit_em
from effect_networks.inference.fitting.maximum_likelihood import fit
from effect_networks.inference.fitting.missing import actions_allowed, gaussian_row_log_likelihoods
from effect_networks.inference.fitting.reading import TrainingRows, read_rows
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.dtype import DTYPE
from effect_networks.models.evidence import Evidence, Partial
from effect_networks.models.params import NetworkParams, check_params

__all__ = [
    "CrossValidation",
    "LogLikelihood",
    "aic",
    "bic",
    "cross_validate",
    "log_likelihood",
    "n_parameters",
    "take_rows",
]


@dataclass(frozen=True)
class LogLikelihood:
    """What :func:`log_likelihood` returns.

    Attributes
    ----------
    per_row : torch.Tensor
        ``(n,)`` float64, each row's log-likelihood (natural log; densities of
        continuous values in their units), missing values summed and integrated out.
    n_parameters : int
        The network's free parameters (:func:`n_parameters`).
    """

    per_row: torch.Tensor
    n_parameters: int

    @property
    def n_rows(self) -> int:
        """The rows scored, ``n``."""
        return int(self.per_row.shape[0])

    @property
    def total(self) -> float:
        """The log-likelihood of all rows, ``L``."""
        return float(self.per_row.sum())

    @property
    def bic(self) -> float:
        """``-2 L + k ln n``: lower is better."""
        return -2.0 * self.total + self.n_parameters * math.log(self.n_rows)

    @property
    def aic(self) -> float:
        """``-2 L + 2 k``: lower is better."""
        return -2.0 * self.total + 2.0 * self.n_parameters

    @property
    def bic_score(self) -> float:
        """``L - k/2 ln n = -bic / 2``: pgmpy's ``BIC`` structure score, higher is better."""
        return self.total - 0.5 * self.n_parameters * math.log(self.n_rows)


def log_likelihood(
    net: EffectNetwork,
    params: NetworkParams,
    data: Mapping[str, object],
    *,
    masks: Mapping[str, object] | None = None,
) -> LogLikelihood:
    """Each row's exact log-likelihood under the fitted network (see the module).

    Parameters
    ----------
    net, params
        The declaration and its fitted parameters.
    data
        Rows as :func:`inference.fit` takes them (a mapping or a ``DataFrame``): every
        site given (labels for discrete values, ``(n, d)`` numbers for continuous ones,
        ``param.p`` NaN where the action does not use ``p``); ``cluster.p`` optional.
        A missing value is None or NaN (a discrete label) or NaN (a continuous value,
        whole or in some dimensions): summed or integrated out.
    masks
        ``(n,)`` bool per discrete site, False where the row's value is missing (it is
        summed out; the value there is ignored).

    Returns
    -------
    LogLikelihood
        ``per_row`` ``(n,)``, ``total``, and the free parameters with the BIC and AIC.

    Raises
    ------
    ValueError
        For rows or masks :func:`inference.fit` would refuse (a missing continuous value
        that a discrete site reads, or at a site that is not a linear Gaussian: no closed
        form), or ``params`` fitted for another network.

    Examples
    --------
    >>> from inference import fit
    >>> from models.declaration import Discrete, EffectNetwork
    >>> net = EffectNetwork(features=(Discrete("lit", (False, True)),), actions=("flip",))
    >>> rows = {"initial.lit": [False, True], "action": ["flip"] * 2, "end.lit": [True, False]}
    >>> ll = log_likelihood(net, fit(net, rows, pseudo_count=0).params, rows)
    >>> round(ll.total, 4)  # log (1/2) for each row's initial.lit; the rest is certain
    -1.3863
    """
    check_params(net, params)
    enc, gaps, unread = _scored_rows(net, data, masks)
    return LogLikelihood(_per_row(net, params, enc, gaps, unread), n_parameters(net))


def n_parameters(net: EffectNetwork) -> int:
    """The free parameters of a declaration: the sum over its sites (see the module's table).

    They depend on the declaration only, not on fitted numbers.


    Parameters
    ----------
    net
        The network's declaration.

    Returns
    -------
    int
        The number of free parameters, summed over the sites.

    Raises
    ------
    NotImplementedError
        For a user-defined kind that does not count its free parameters (``n_free``).
    """
    return sum(net.cpd(s.name).n_free(_reachable(net, s.name)) for s in net.sites)


def bic(
    net: EffectNetwork,
    params: NetworkParams,
    data: Mapping[str, object],
    *,
    masks: Mapping[str, object] | None = None,
) -> float:
    """``-2 L + k ln n`` (lower is better) of the rows (see :func:`log_likelihood`).

    pgmpy's ``BIC`` score is ``-bic / 2`` (:attr:`LogLikelihood.bic_score`).

    Parameters
    ----------
    net, params
        The network and its fitted parameters.
    data
        The rows, as :func:`inference.fit` reads them (gaps summed out).
    masks
        ``(n,)`` bool per discrete site, False where a row's value is missing.

    Returns
    -------
    float
        ``-2 L + k ln n``, with ``L`` the rows' log-likelihood, ``k`` :func:`n_parameters`
        and ``n`` the number of rows.
    """
    return log_likelihood(net, params, data, masks=masks).bic


def aic(
    net: EffectNetwork,
    params: NetworkParams,
    data: Mapping[str, object],
    *,
    masks: Mapping[str, object] | None = None,
) -> float:
    """``-2 L + 2 k`` (lower is better) of the rows (see :func:`log_likelihood`).

    Parameters
    ----------
    net, params
        The network and its fitted parameters.
    data
        The rows, as :func:`inference.fit` reads them (gaps summed out).
    masks
        ``(n,)`` bool per discrete site, False where a row's value is missing.

    Returns
    -------
    float
        ``-2 L + 2 k``, with ``L`` the rows' log-likelihood and ``k`` :func:`n_parameters`.
    """
    return log_likelihood(net, params, data, masks=masks).aic


@dataclass(frozen=True)
class CrossValidation:
    """What :func:`cross_validate` returns.

    Attributes
    ----------
    per_row : torch.Tensor
        ``(n,)`` float64, each row's log-likelihood under the network fitted on the other
        folds, in the rows' order.
    fold : torch.Tensor
        ``(n,)`` long, the fold each row was held out in (``0 .. folds - 1``).
    """

    per_row: torch.Tensor
    fold: torch.Tensor

    @property
    def folds(self) -> int:
        """The number of folds."""
        return int(self.fold.max()) + 1

    @property
    def per_fold(self) -> torch.Tensor:
        """``(folds,)`` each fold's held-out log-likelihood (summed over its rows)."""
        return torch.zeros(self.folds, dtype=DTYPE).index_add_(0, self.fold, self.per_row)

    @property
    def total(self) -> float:
        """The held-out log-likelihood of all rows."""
        return float(self.per_row.sum())

    @property
    def mean(self) -> float:
        """The held-out log-likelihood per row."""
        return self.total / self.per_row.shape[0]


def cross_validate(
    net: EffectNetwork,
    data: Mapping[str, object],
    folds: int = 5,
    seed: int = 0,
    *,
    masks: Mapping[str, object] | None = None,
    **fit_kwargs,
) -> CrossValidation:
    """Held-out log-likelihood by ``folds``-fold cross-validation.

    The rows are shuffled with ``seed`` and cut into ``folds`` parts of sizes that
    differ by at most one; each part is scored (:func:`log_likelihood`) under the
    network fitted on the others: :func:`inference.fit`, or :func:`inference.fit_em`
    where some parameter's clusters are adaptive.

    Parameters
    ----------
    net
        The declaration.
    data
        Rows as :func:`inference.fit` takes them (one mapping or ``DataFrame``). A
        missing value marked in the rows stays in its fold: the fit on the other folds
        runs EM over it, and the held-out fold is scored with it summed or integrated
        out (not with adaptive clusters).
    folds
        Parts, ``2 <= folds <= n``.
    seed
        Seeds the shuffle (>= 0).
    masks
        Missing discrete values, as :func:`inference.fit` takes them (not with adaptive
        clusters).
    **fit_kwargs
        Passed to the fit (``pseudo_count``, ``min_variance``, ``steps``, ...).

    Returns
    -------
    CrossValidation
        Per row its held-out log-likelihood and its fold; per fold the sums.

    Raises
    ------
    ValueError
        For ``folds`` or ``seed`` out of range, or what the fit refuses.
    """
    rows = read_rows(net, data, masks)  # once: the folds are cut from what was read
    fold = fold_of_rows(rows.n_rows, folds, seed)
    per_row = torch.empty(rows.n_rows, dtype=DTYPE)
    adaptive = any(p.adaptive for p in net.parameters)
    missing = rows.missing()
    if adaptive and (masks or missing):
        what = "masks" if masks else f"data (missing values at {sorted(missing)})"
        raise ValueError(
            f"{what}: inference.fit_em fits adaptive "
            "clusters from complete rows only; score a network with missing values under "
            "the grid layout"
        )
    for f in range(folds):
        held, rest = (fold == f).nonzero().squeeze(-1), (fold != f).nonzero().squeeze(-1)
        train = rows.take(rest)
        if adaptive:
            params = fit_em(net, train, **fit_kwargs).params
        else:
            params = fit(net, train, **fit_kwargs).params
        per_row[held] = log_likelihood(net, params, rows.take(held)).per_row
    return CrossValidation(per_row, fold)


def fold_of_rows(n: int, folds: int, seed: int) -> torch.Tensor:
    """``(n,)`` long: each row's fold.

    The rows are shuffled with ``seed`` and cut into ``folds`` parts whose sizes differ by at most
    one.
    """
    for name, value, low, high in (("folds", folds, 2, n), ("seed", seed, 0, None)):
        ok = isinstance(value, int | np.integer) and not isinstance(value, bool)
        if not ok or value < low or (high is not None and value > high):
            limit = f"between {low} and the {n} rows" if high is not None else f">= {low}"
            raise ValueError(f"{name} must be an int {limit}, got {value!r}")
    order = torch.randperm(n, generator=torch.Generator().manual_seed(int(seed)))
    fold = torch.empty(n, dtype=torch.long)
    for f, part in enumerate(torch.tensor_split(order, folds)):
        fold[part] = f
    return fold


def take_rows(data: Mapping[str, object], index: torch.Tensor) -> Mapping[str, object]:
    """The rows ``index`` ``(m,)`` long of rows given by site.

    Labels in lists, arrays or tensors, :class:`~models.evidence.Partial` values (with
    per-row or shared observed dimensions); :class:`~models.evidence.Evidence`;
    :class:`~inference.fitting.reading.TrainingRows` (their masks cut with them).
    """
    if isinstance(data, Evidence | TrainingRows):
        return data.rows(index) if isinstance(data, Evidence) else data.take(index)
    out = {}
    positions = index.tolist()
    for site, values in data.items():
        if isinstance(values, Partial):  # a value and its observed dimensions, row by row
            observed = np.asarray(values.observed)
            if observed.ndim == 2:
                observed = observed[positions]
            out[site] = Partial(np.asarray(values.value)[positions], observed)
        elif isinstance(values, torch.Tensor):
            out[site] = values[index]
        elif isinstance(values, np.ndarray):
            out[site] = values[positions]
        else:
            values = list(values)
            out[site] = [values[i] for i in positions]
    return out


# ------------------------------------------------------------------------------ internals
def _scored_rows(
    net: EffectNetwork, data: object, masks: Mapping[str, object] | None
) -> tuple[Evidence, dict[str, torch.Tensor], tuple[str, ...]]:
    """The rows as :func:`inference.fit` reads them (:func:`~inference.fitting.reading.read_rows`).

    The encoded rows (NaN where a continuous value is missing), the masks that leave gaps
    (``masks`` and the rows' own marks), and the parameters' clusters the rows do not give.
    """
    rows = read_rows(net, data, masks)
    return rows.enc, rows.gaps, rows.unread


def _per_row(
    net: EffectNetwork,
    params: NetworkParams,
    enc: Evidence,
    gaps: dict[str, torch.Tensor],
    unread: tuple[str, ...],
) -> torch.Tensor:
    """``(n,)`` every row's log-evidence, its missing values summed and integrated out.

    The rows whose continuous values are all given go through the traced model
    (:func:`_enumerated_per_row`); the others through the continuous sites' joint
    Gaussian (:func:`inference.fitting.missing.gaussian_row_log_likelihoods`), which
    needs every continuous initial and end site to be a linear Gaussian and no discrete
    site to read a missing value (refused by name otherwise, as :func:`inference.fit`
    refuses them).
    """
    continuous = continuous_gaps(net, enc)
    if not continuous:
        return _enumerated_per_row(net, params, enc, gaps, unread)
    refuse_open_forms(net, enc, continuous)
    gapped = torch.zeros(enc.n_rows, dtype=torch.bool)
    for missing in continuous.values():
        gapped |= missing.any(-1)
    out = torch.empty(enc.n_rows, dtype=DTYPE)
    for rows, score in ((~gapped, _enumerated_per_row), (gapped, _gaussian_per_row)):
        if bool(rows.any()):
            part = enc.rows(rows)
            out[rows] = score(net, params, part, {s: m[rows] for s, m in gaps.items()}, unread)
    return out


def _enumerated_per_row(
    net: EffectNetwork,
    params: NetworkParams,
    enc: Evidence,
    gaps: dict[str, torch.Tensor],
    unread: tuple[str, ...] = (),
) -> torch.Tensor:
    """``(n,)`` every row's log-evidence, its missing discrete values summed out, in row chunks.

    The clusters ``unread`` are left to the model (a value's cell under the grid layout, latent
    under the adaptive one, or under each enumerated action where the action is missing).
    """
    enc = enc.without(*unread)
    allowed = actions_allowed(net, enc, gaps)  # (A, n), or None
    # masked sites are enumerated: sized as if absent
    size = enumeration_size(net, enc.without(*gaps), contracted=allowed is None)
    out = []
    for rows in row_chunks(enc.n_rows, size):
        chunk_masks = {s: m[rows] for s, m in gaps.items()}
        e = enumerate_model(net, params, enc.rows(rows), masks=chunk_masks)
        if allowed is not None:
            dim = e.dims[ACTION]
            agree = allowed[:, rows].reshape(len(net.actions), *([1] * (-dim - 2)), -1)
            e = Enumerated(
                (e.log_weight.masked_fill(~agree, -torch.inf),), e.dims, e.trace, e.offsets
            )
        out.append(e.log_evidence.reshape(-1).expand(rows.stop - rows.start))
    return torch.cat(out)


def _gaussian_per_row(
    net: EffectNetwork,
    params: NetworkParams,
    enc: Evidence,
    gaps: dict[str, torch.Tensor],
    unread: tuple[str, ...],
) -> torch.Tensor:
    """``(n,)`` the log-likelihood of rows that miss a continuous value: as EM's E-step weighs them.

    A grid cluster stays its value's cell; an adaptive one the rows do not give is summed out with
    the missing discrete values.
    """
    adaptive = {m.cluster.site for m in net.mixtures if m.parameter.adaptive}
    return gaussian_row_log_likelihoods(
        net, params, enc.without(*(s for s in unread if s in adaptive)), gaps
    )


def _reachable(net: EffectNetwork, site: str) -> torch.Tensor | None:
    """``(P...)`` bool: the parent configurations of ``site`` some row can reach.

    A configuration of an action that does not use a parameter with that parameter's cluster other
    than 0 cannot (the cluster is pinned on cell 0).
    """
    cpd = net.cpd(site)
    reachable = None
    for m in net.mixtures:
        if m.action not in cpd.parents or m.cluster.site not in cpd.parents:
            continue
        a, c = cpd.parents.index(m.action), cpd.parents.index(m.cluster.site)
        shape = [1] * len(cpd.card)
        shape[a], shape[c] = cpd.card[a], 1
        used = m.uses.reshape(shape)
        shape[a], shape[c] = 1, cpd.card[c]
        cell0 = (torch.arange(cpd.card[c]) == 0).reshape(shape)
        ok = (used | cell0).expand(cpd.card)
        reachable = ok if reachable is None else reachable & ok
    return reachable
