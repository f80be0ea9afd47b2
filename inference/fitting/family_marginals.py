"""Expected family counts of discrete rows with gaps, by elimination over the families.

The E-step of EM over missing values needs, per site, the expected counts of its family
(the site and its parents): the sum over rows of the posterior of the family's
configuration given the row. :func:`inference.fitting.missing.fit_missing`'s general route
completes every row once per assignment of all its network's missing sites (the Pyro
model enumerated over their joint), which costs the product of their sizes per row. Where
every site is a discrete table, this module computes the same counts from the network's
factors alone:

* every site is a dim of its own (``(K_{S-1}, ..., K_0, n)``, as
  :mod:`inference.exact.elimination` lays factors out); its table is one log-factor over
  its family, shared by all rows, and its evidence another, per row, 0 at the observed
  state (every state where the row misses the value) and ``-inf`` elsewhere;
* ``log Z`` of a row, its log-likelihood with the missing values summed out, is the
  contraction of these factors (:func:`inference.exact.elimination.contract`: the sites
  summed out one at a time, each over the factors that touch it), so the cost per row is
  the largest family-sized intermediate the elimination order builds, not the joint;
* the derivative of ``sum_rows log Z`` with respect to a site's log-table entry is the
  sum over rows of the posterior of that family configuration: exactly the expected
  counts. One backward pass through the contraction (torch's autograd) gives every
  family's counts at once, as a junction tree's calibration would.

The route covers networks whose every site is a discrete table (no continuous site, no
action parameter), up to :data:`MAX_SITES` sites; :func:`covers` says which. Elsewhere the
general route serves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from effect_networks.inference.exact.elimination import contract, plan, scope
from effect_networks.inference.exact.enumeration import row_chunks
from effect_networks.models.cpds import TableCPD
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.evidence import DTYPE, Evidence
from effect_networks.models.params import NetworkParams

__all__ = ["MAX_SITES", "FamilyCounts", "covers", "family_counts"]

#: The most sites the route lays out: one dim each, and the rows', in a torch tensor of at
#: most 64 dims. A larger network takes the completed rows.
MAX_SITES = 63


@dataclass(frozen=True)
class FamilyCounts:
    """What :func:`family_counts` returns.

    ``counts``: per site, its expected counts ``(P..., K)`` (the table's layout, parents in
    the CPD's order then the site's states); ``per_row``: ``(n,)`` each row's log-likelihood,
    its missing values summed out; ``log_lik``: their sum.
    """

    counts: dict[str, torch.Tensor]
    per_row: torch.Tensor
    log_lik: float


def covers(net: EffectNetwork) -> bool:
    """Whether every site of ``net`` is a discrete table without pinned states.

    There is then no action parameter, no continuous site, no softmax; and at most
    :data:`MAX_SITES` sites.
    """
    if net.mixtures or len(net.sites) > MAX_SITES:
        return False
    for spec in net.sites:
        cpd = net.cpd(spec.name)
        if not spec.discrete or type(cpd) is not TableCPD or cpd.pinned is not None:
            return False
    return True


def family_counts(
    net: EffectNetwork,
    params: NetworkParams,
    enc: Evidence,
    masks: dict[str, torch.Tensor],
) -> FamilyCounts:
    """Every site's expected family counts over the rows, by elimination.

    ``enc``: checked rows of a network :func:`covers` takes (any state where a value is
    missing); ``masks``: ``(n,)`` bool per site, False where the row misses the value
    (a site not named is observed everywhere).

    Raises
    ------
    ValueError
        Naming a row whose observed values have probability 0 under ``params`` (no posterior
        exists).
    """
    assert covers(net), "family_counts covers networks of discrete tables only"
    names = [s.name for s in net.sites]
    depth = len(names) + 1
    dim = {site: -(i + 2) for i, site in enumerate(names)}
    leaves = {}
    for spec in net.sites:
        logs = net.cpd(spec.name).log_table(params[spec.name], None).detach().to(DTYPE)
        assert bool(torch.isfinite(logs).all()), spec.name  # the model clamps to [eps, 1 - eps]
        leaves[spec.name] = logs.clone().requires_grad_(True)
    families = {s.name: (*net.cpd(s.name).parents, s.name) for s in net.sites}

    def laid_out() -> list[torch.Tensor]:
        return [_laid_out(leaves[s], families[s], dim, depth) for s in names]

    table_scopes = tuple(scope(t) for t in laid_out())
    evidence_scopes = tuple(frozenset({(dim[s.name], s.size)}) for s in net.sites)
    scopes = table_scopes + evidence_scopes
    order = frozenset(dim.values())
    largest = plan(scopes, order)[1]
    # the autograd graph keeps a few intermediates per step: a share of the chunk budget
    chunks = row_chunks(enc.n_rows, largest * max(1, len(names) // 2))
    counts = {site: torch.zeros_like(leaf) for site, leaf in leaves.items()}
    per_row = []
    for chunk in chunks:
        rows = enc.rows(chunk)
        evidence = [
            _evidence(rows[s.name], _mask(masks, s.name, chunk, rows.n_rows), s.size, dim[s.name])
            for s in net.sites
        ]
        log_z = contract([*laid_out(), *evidence], list(order), scopes).reshape(-1)
        log_z = log_z.expand(rows.n_rows)
        if not bool((log_z > -torch.inf).all()):
            bad = int((log_z == -torch.inf).nonzero()[0]) + (chunk.start or 0)
            raise ValueError(
                f"training row {bad} has probability 0 under every completion of its missing "
                "values: no posterior exists"
            )
        grads = torch.autograd.grad(log_z.sum(), list(leaves.values()))
        for site, g in zip(leaves, grads, strict=True):
            counts[site] += g
        per_row.append(log_z.detach())
    scores = torch.cat(per_row)
    return FamilyCounts(counts, scores, float(scores.sum()))


def _laid_out(
    table: torch.Tensor, family: tuple[str, ...], dim: dict[str, int], depth: int
) -> torch.Tensor:
    """The table ``(P..., K)`` over ``family`` as a factor of rank ``depth``, rows last (1)."""
    axes = sorted(range(len(family)), key=lambda a: dim[family[a]])  # leftmost dim first
    moved = table.permute(*axes)
    shape = [1] * depth
    for a in axes:
        shape[depth + dim[family[a]]] = table.shape[a]
    return moved.reshape(shape)


def _evidence(values: torch.Tensor, given: torch.Tensor, size: int, at: int) -> torch.Tensor:
    """The log-factor ``(K, 1, ..., 1, n)`` of a site's evidence at dim ``at``.

    0 at the observed state, or at every state where the row misses the value; ``-inf`` elsewhere.
    """
    states = torch.arange(size)[:, None]
    allowed = (states == values[None, :]) | ~given[None, :]
    factor = torch.zeros(size, len(values), dtype=DTYPE).masked_fill_(~allowed, -math.inf)
    return factor.reshape(size, *([1] * (-at - 2)), len(values))


def _mask(masks: dict[str, torch.Tensor], site: str, chunk: slice, n: int) -> torch.Tensor:
    if site not in masks:
        return torch.ones(n, dtype=torch.bool)
    return masks[site][chunk]
