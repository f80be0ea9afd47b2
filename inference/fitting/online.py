"""Online updates: a closed-form fit continued with new rows.

The closed form is a function of sufficient statistics that merge by addition
(:mod:`inference.fitting.sufficient_statistics`), and :func:`inference.fit` keeps the
summed statistics in the parameters it returns (``NetworkParams.statistics``, saved and
loaded with them). :func:`fit_update` adds the new rows' statistics to them and applies
the closed form again, so that fitting rows ``a``, then updating with rows ``b``, gives
the parameters of one fit on ``a`` and ``b`` together (tables exactly, Gaussians to the
rounding of another order of float additions), under the same prior and settings.

Parameters without statistics cannot be continued and are refused: those of EM (with
gaps the statistics are expectations under the parameters of the last step, and a
continued EM would need the old rows again), of the gradient route, of :func:`fit_pooled`,
made by hand, or loaded from a file saved without them; so are networks with a softmax
CPD (Newton's method runs on the rows themselves: no sum of them determines the fit).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from effect_networks.inference.fitting.maximum_likelihood import fit_statistics
from effect_networks.inference.fitting.priors import Prior, site_priors
from effect_networks.inference.fitting.reading import TrainingRows, read_rows
from effect_networks.inference.fitting.result import FitResult
from effect_networks.inference.fitting.rows import check_settings, refuse_adaptive
from effect_networks.inference.fitting.sufficient_statistics import (
    Statistics,
    params_from_statistics,
    statistics,
)
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.frames import as_data
from effect_networks.models.params import NetworkParams, check_params

__all__ = ["fit_update"]


def fit_update(
    net: EffectNetwork,
    params: NetworkParams,
    data: Mapping[str, object] | Iterable[Mapping[str, object]],
    *,
    pseudo_count: float | None = None,
    prior: Prior | None = None,
    estimate: str = "mean",
    min_variance: float = 1e-6,
    progress: bool = False,
) -> FitResult:
    """Continue a closed-form fit with new rows (see the module).

    Parameters
    ----------
    net
        The network ``params`` were fitted for.
    params
        Parameters from :func:`inference.fit` (or a previous :func:`fit_update`, or
        :func:`models.load` of either), carrying their sufficient statistics.
    data
        The new rows, as :func:`inference.fit` reads them: a mapping by site, a
        ``DataFrame`` or an iterable of such chunks; every value given (no gaps).
    pseudo_count, prior, estimate, min_variance
        As in :func:`inference.fit`; give the values of the first fit to continue it
        (``pseudo_count`` defaults to ``params.pseudo_count``, the others to ``fit``'s
        defaults: the parameters keep their statistics, not their prior).

    Returns
    -------
    FitResult
        The parameters of the old and new rows together, carrying the summed statistics.

    Raises
    ------
    ValueError
        If ``params`` carry no statistics, ``net`` has a softmax CPD (or another kind
        without a closed form) or adaptive clusters, or a new row misses a value.
    """
    check_params(net, params)
    refuse_adaptive(net, "fit_update")
    if params.statistics is None:
        raise ValueError(
            "these parameters carry no sufficient statistics (they come from EM over gaps, "
            "the gradient route, fit_pooled, by hand, or a file saved without them), so the "
            "fit cannot be continued; fit all rows at once with fit"
        )
    open_forms = [s.name for s in net.sites if not net.cpd(s.name).closed_form]
    if open_forms:
        kinds = "/".join(sorted({net.cpd(s).name for s in open_forms}))
        raise ValueError(
            f"sites {open_forms} are {kinds} CPDs: their fit is iterative on the rows "
            "themselves and no sum of the rows determines it, so it cannot be continued; "
            "fit all rows at once with fit"
        )
    if isinstance(prior, int | float) and not isinstance(prior, bool):
        pseudo_count = prior
    pseudo_count = params.pseudo_count if pseudo_count is None else pseudo_count
    check_settings(pseudo_count=pseudo_count, min_variance=min_variance)
    alpha = site_priors(net, prior, pseudo_count, estimate)
    data = as_data(net, data)
    if isinstance(data, Mapping | TrainingRows):
        rows = read_rows(net, data)
        if rows.missing():
            raise ValueError(
                f"the new rows miss values of {rows.missing_text()}; an update adds complete "
                "rows' statistics (EM over gaps needs every row each step): fit all rows at "
                "once with fit"
            )
        new = statistics(net, rows.enc)
    else:
        new = fit_statistics(net, data, progress=progress)
    merged = {site: params.statistics[site] + s for site, s in new.sites.items()}
    cpds = params_from_statistics(net, Statistics(merged, new.rows), alpha, min_variance)
    return FitResult(NetworkParams(cpds, pseudo_count, net, merged))
