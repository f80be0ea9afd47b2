"""Sufficient statistics of the closed-form fit, and the parameters they give.

Every closed-form CPD is a function of sums over rows: a table of its counts; a
conditional linear Gaussian of ``sum z z^T``, ``sum z y^T``, ``sum y y^T`` and the row
count per parent configuration (``z = [x, 1]``, its continuous parents and a one).
Sums merge by addition, which is associative and commutative, so a data set can be cut
into chunks (or partitions on a cluster), each chunk's :class:`Statistics` computed
apart, and the results added in any grouping: ``statistics(a) + statistics(b)`` is
``statistics(a ∪ b)`` up to the rounding of float additions (counts are exact).
:func:`params_from_statistics` then gives the same parameters as one pass over all rows.
Rows may carry weights (in an EM step, the posterior of a completion of a row's missing
values): each row's terms are multiplied by its weight, so a weight ``k`` counts as ``k``
copies of the row and fractional weights give the expected statistics.

Pseudo-count policy (``pseudo_count``, written alpha): a table row is
``(counts + alpha) / (n + K alpha)``, so a parent configuration no sample reached is
uniform; a Gaussian configuration gets alpha pseudo-rows of the pooled statistics of its
site (all rows together), so an unseen one is the pooled fit and a rarely seen one is
shrunk towards it. A covariance's eigenvalues are floored at ``min_variance``, so that a
configuration with fewer rows than dimensions stays positive definite; one whose spread
exceeds it in every direction keeps its estimate. ``alpha = 0`` gives the plain sample
statistics where every configuration is seen. Other priors (Dirichlet pseudo-counts
per table cell, a normal-inverse-Wishart per linear Gaussian) are in
:mod:`inference.fitting.priors`.

A kind without a closed form (softmax) has no sufficient statistics to sum: it is
maximised on the rows themselves, by its own ``maximise`` method (Newton's method per
parent configuration), which :func:`maximise_site` runs on complete, possibly weighted
rows for both :func:`inference.fit` and EM over missing values.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from effect_networks.models.cpds import Counts, Moments
from effect_networks.models.cpds.table import flat_index
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.evidence import Evidence


@dataclass(frozen=True)
class Statistics:
    """Sufficient statistics of every closed-form CPD of one network, per site.

    ``gradient`` names the sites whose kind has no closed form (their statistics only
    seed the gradient fit, which needs the rows themselves).
    """

    sites: dict[str, Counts | Moments]
    rows: int
    gradient: tuple[str, ...] = ()

    def __add__(self, other: Statistics) -> Statistics:
        if set(self.sites) != set(other.sites):
            raise ValueError("statistics of two different networks cannot be merged")
        merged = {site: self.sites[site] + other.sites[site] for site in self.sites}
        return Statistics(merged, self.rows + other.rows, self.gradient)

    def merged_into(self, total: Statistics | None) -> Statistics:
        """``total + self``, adding into ``total``'s tensors in place.

        No copy of a big table per chunk; ``self`` when ``total`` is ``None``.
        """
        if total is None:
            return self
        if set(self.sites) != set(total.sites):
            raise ValueError("statistics of two different networks cannot be merged")
        for site, s in self.sites.items():
            total.sites[site].add_(s)
        return Statistics(total.sites, total.rows + self.rows, total.gradient)


def statistics(
    net: EffectNetwork, enc: Evidence, weights: torch.Tensor | None = None
) -> Statistics:
    """The sums of one chunk of complete, checked rows (see :func:`inference.fit`).

    Each row counts ``weights`` ``(n,)`` (default 1; an EM step's responsibilities).
    """
    sites: dict = {}
    flat: dict[tuple[str, ...], torch.Tensor] = {}  # sites sharing their parents share the index
    for m in net.mixtures:
        c_site, p_site = m.sites
        sites |= m.statistics(enc[m.action], enc[c_site], enc[p_site], weights)
    for spec in net.sites:
        if spec.name in sites:
            continue
        cpd = net.cpd(spec.name)
        if cpd.parents not in flat:
            flat[cpd.parents] = flat_index(enc, cpd.parents, cpd.card)
        inputs = [enc[s].nan_to_num() for s in cpd.inputs]
        x = torch.cat(inputs, -1) if inputs else None
        args = (flat[cpd.parents], x, enc[spec.name])
        # a kind of the user's may take no weights: ask for them only when there are some
        sites[spec.name] = (
            cpd.statistics(*args) if weights is None else cpd.statistics(*args, weights)
        )
    gradient = tuple(s.name for s in net.sites if not net.cpd(s.name).closed_form)
    return Statistics({s.name: sites[s.name] for s in net.sites}, enc.n_rows, gradient)


def params_from_statistics(
    net: EffectNetwork, stats: Statistics, alpha: float | Mapping[str, object], min_variance: float
) -> dict:
    """Every kind's ``m_step``: the closed-form CPDs.

    For kinds without one, the gradient route's start. ``alpha``: the pseudo-count of
    every site, or each site's prior as :func:`inference.fitting.priors.site_priors`
    gives it (a mapping naming every site).

    Parameters
    ----------
    net
        The network the statistics are of.
    stats
        Sufficient statistics, as :func:`inference.fit_statistics` sums them.
    alpha
        The pseudo-count of every site, or each site's prior.
    min_variance
        The covariance floor of the linear Gaussians.

    Returns
    -------
    dict
        Site name -> its CPD (the closed form, or the gradient route's start).
    """
    priors = alpha if isinstance(alpha, Mapping) else dict.fromkeys(stats.sites, alpha)
    return {
        s.name: net.cpd(s.name).m_step(stats.sites[s.name], priors[s.name], min_variance)
        for s in net.sites
    }


def maximise_site(
    net: EffectNetwork,
    enc: Evidence,
    site: str,
    start,
    *,
    weights: torch.Tensor | None = None,
    l2: float,
    steps: int,
):
    """The optimum of one CPD with a ``maximise`` method on complete rows.

    Parameters
    ----------
    net
        The network.
    enc
        Complete, checked rows (:func:`inference.fitting.rows.training_rows`).
    site
        The site whose CPD is maximised; its kind has a ``maximise`` method.
    start
        The CPD's parameters to start from.
    weights
        ``(n,)`` row weights (an EM step's posterior weights); default 1.
    l2, steps
        The precision of the slopes' Gaussian prior and the most Newton iterations.

    Returns
    -------
    models.cpds.softmax.SoftmaxFit
        What the kind's ``maximise`` returns: ``params``, ``objectives`` (the penalised
        negative log-likelihood, summed over rows, at the start and per iteration) and
        ``converged``.
    """
    cpd = net.cpd(site)
    index = flat_index(enc, cpd.parents, cpd.card)
    x = torch.cat([enc[s].nan_to_num() for s in cpd.inputs], -1)
    return cpd.maximise(index, x, enc[site], start, weights=weights, l2=l2, steps=steps)
