"""How much probability the model gives a row's observed end state: the ``implausible`` flag.

Two numbers per evidence row, each 1 where the row observes no end feature of its kind:

* ``discrete`` -- the probability of the observed *discrete* end features given the rest
  of the evidence (initial state, and the action and parameters where given), every
  latent site summed out under the model: ``p(end_d | initial, ...)``. A locked door
  that ends open, when no action ever opens a locked door, gets only the pseudo-count
  mass (about ``α / n`` per configuration).
* ``tail`` -- for the observed *continuous* end features, the chi-square tail
  probability ``P(χ²_d > D²)`` of their squared Mahalanobis distance ``D²`` to the
  closest Gaussian component the evidence leaves possible (every configuration of the
  latent discrete sites with non-zero weight, the observed discrete ones included), with
  ``d`` the summed dimensions (the observed ones, where the evidence is partial). Under
  its own component an observation has ``D² ~ χ²_d``, so ``tail`` is the probability
  that a draw from the model's best component lies at least this far out.

And one number per observed continuous *initial* feature (``initial[site]``), the same
chi-square tail of its squared Mahalanobis distance under the Gaussian the model fitted
to the training rows' initial states: evidence far outside the training data (a distance
of 1e6 m where training covered 0.1-1.2 m) is answered by extrapolating every linear
map, and is flagged as such.

A row is *implausible* when any number is below a threshold (default
:data:`IMPLAUSIBLE_BELOW`). The flag warns: queries still answer such rows; an initial
state outside the training data is also named in a :class:`OutsideTrainingData` warning.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import torch
from effect_networks.inference.exact.elimination import maximum
from effect_networks.inference.exact.enumeration import (
    conditional_log_evidence,
    over_row_chunks,
)
from effect_networks.models.cpds import concat_inputs
from effect_networks.models.declaration import DTYPE, EffectNetwork, end_site
from effect_networks.models.evidence import Evidence, observed_dims
from effect_networks.models.gaussian import mahalanobis
from effect_networks.models.params import NetworkParams

IMPLAUSIBLE_BELOW = 1e-4
"""Default threshold: evidence the model gives less than 1 in 10,000 is flagged (a
continuous observation beyond about 3.9 standard deviations in one dimension)."""


class OutsideTrainingData(UserWarning):
    """An observed continuous initial state lies far outside what the model was fitted on.

    Its tail under the fitted initial Gaussian is below the threshold.
    """


@dataclass(frozen=True)
class Plausibility:
    """How plausible the observed end and initial states are under the model.

    ``discrete`` ``(n,)``: p(observed discrete end state | the rest of the evidence); ``tail``
    ``(n,)``: chi-square tail probability of the observed continuous end state under its closest
    possible component. Both 1 where nothing of the kind is observed. ``initial``: per observed
    continuous initial site, ``(n,)`` the chi-square tail of its value under the model's fitted
    Gaussian of that initial state.
    """

    discrete: torch.Tensor
    tail: torch.Tensor
    initial: dict[str, torch.Tensor] = field(default_factory=dict)

    def outside(self, below: float = IMPLAUSIBLE_BELOW) -> dict[str, torch.Tensor]:
        """Per continuous initial site, ``(n,)`` bool: its value lies outside the training data.

        Its tail is below ``below``.
        """
        return {site: tail < below for site, tail in self.initial.items()}

    def implausible(self, below: float = IMPLAUSIBLE_BELOW) -> torch.Tensor:
        """``(n,)`` bool: any probability below ``below``.

        Warns (:class:`OutsideTrainingData`), naming the site and the first row, where an initial
        state lies outside the training data.
        """
        return (self.discrete < below) | (self.tail < below) | outside_training(self.initial, below)


def check_threshold(below: float) -> float:
    """``below`` validated: a probability strictly between 0 and 1."""
    if not isinstance(below, (int, float)) or not 0 < below < 1:
        raise ValueError(
            f"implausible_below must be a probability in (0, 1), got {below!r} "
            f"(default {IMPLAUSIBLE_BELOW})"
        )
    return float(below)


def plausibility(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    *,
    log_evidence: torch.Tensor | None = None,
    log_prior: torch.Tensor | None = None,
) -> Plausibility:
    """The two plausibility numbers of every row of encoded ``evidence`` (at least one row).

    A query that has already summed the model may pass ``log_evidence`` ``(n,)``
    (log p(evidence)) and ``log_prior`` (log p(evidence without its end sites)) to save
    the sums; ``log_evidence`` is used only where no continuous end site is observed.
    """
    ends = [end_site(f.name) for f in net.features if end_site(f.name) in evidence]
    discrete = [s for s in ends if net.site(s).discrete]
    continuous = [s for s in ends if not net.site(s).discrete]
    ones = torch.ones(evidence.n_rows, dtype=DTYPE)
    p_discrete = ones
    if discrete:
        if log_evidence is None or continuous:
            given = evidence.without(*continuous)
            log_evidence = over_row_chunks(
                net, params, given, (), lambda e, *_: e.log_evidence, contracted=True
            )
        prior = evidence.without(*ends)
        if log_prior is None:
            log_prior = (  # nothing observed: probability 1
                over_row_chunks(
                    net, params, prior, (), lambda e, *_: e.log_evidence, contracted=True
                )
                if len(prior)
                else torch.zeros(evidence.n_rows, dtype=DTYPE)
            )
        if len(prior):
            given = evidence.without(*continuous)
            log_p = conditional_log_evidence(net, params, given, prior, log_evidence, log_prior)
        else:
            log_p = log_evidence - log_prior
        p_discrete = log_p.exp().clamp(0, 1)
    tail = ones
    if continuous:
        d2, dof = _closest_distance(net, params, evidence, continuous)
        tail = torch.special.gammaincc(dof.clamp_min(1) / 2, d2 / 2)
        tail = torch.where(dof > 0, tail, 1.0)  # a row that observes no dimension
    return Plausibility(p_discrete, tail, initial_tails(net, params, evidence))


def outside_training(initial: dict[str, torch.Tensor], below: float) -> torch.Tensor | bool:
    """``(n,)`` bool: some initial state's tail (:func:`initial_tails`) below ``below``.

    ``False`` without any site; warns (:class:`OutsideTrainingData`) naming each such site and its
    first row.
    """
    flag = False
    for site, tail in initial.items():
        outside = tail < below
        if bool(outside.any()):
            row = int(outside.nonzero()[0])
            warnings.warn(
                f"{site}: {int(outside.sum())} row(s), the first row {row}, lie far outside "
                f"the training data (tail {float(tail[row]):.3g} under the fitted initial "
                f"state, below {below:g}); their answers extrapolate",
                OutsideTrainingData,
                stacklevel=4,
            )
        flag = flag | outside
    return flag


def initial_tails(net: EffectNetwork, params: NetworkParams, evidence) -> dict[str, torch.Tensor]:
    """Per continuous initial site, the chi-square tail of its value under the model.

    For every site in ``evidence`` (encoded) whose parents are all given, ``(n,)`` the chi-square
    tail ``P(chi2_d > D^2)`` of its value's squared Mahalanobis distance ``D^2`` under the model's
    own distribution of that initial state.
    """
    out = {}
    cache: dict[str, torch.Tensor] = {}
    for spec in net.sites:
        if spec.role != "initial" or spec.discrete or spec.name not in evidence:
            continue
        cpd = net.cpd(spec.name)
        if any(q not in evidence for q in (*cpd.parents, *cpd.inputs)):
            continue  # a latent parent: no one Gaussian to measure against
        index = [evidence[q] for q in cpd.parents]
        x = concat_inputs([evidence[q] for q in cpd.inputs])
        fn = cpd.distribution(params[spec.name], index, x, cache)
        d2 = mahalanobis(fn, evidence[spec.name])
        out[spec.name] = torch.special.gammaincc(torch.tensor(spec.size / 2, dtype=DTYPE), d2 / 2)
    return out


def _closest_distance(net, params, evidence, sites) -> tuple[torch.Tensor, torch.Tensor]:
    """``(n,)`` smallest squared Mahalanobis distance over possible configurations.

    And ``(n,)`` the summed dimension of ``sites`` observed in each row (partial evidence: the
    distance of the observed dimensions under their marginal).
    """
    dof = sum(observed_dims(evidence[s]).sum(-1) for s in sites).to(DTYPE)

    def fn(e, *_):
        if e.contracted:  # the largest of -d2 over the possible configurations
            d2 = [-mahalanobis(e.trace.nodes[s]["fn"], e.trace.nodes[s]["value"]) for s in sites]
            possible = [torch.where(torch.isfinite(f), 0.0, -torch.inf) for f in e.factors]
            top = maximum([*d2, *possible], list(e.dims.values()))
            return -top.reshape(-1).expand(e.n_rows)
        d2 = torch.zeros((), dtype=DTYPE)
        for s in sites:
            node = e.trace.nodes[s]
            d2 = d2 + mahalanobis(node["fn"], node["value"])
        w = e.log_weight
        d2 = torch.where(torch.isfinite(w), d2.expand_as(w), torch.inf)
        return d2.reshape(-1, w.shape[-1]).min(0).values

    return over_row_chunks(net, params, evidence, (), fn, contracted=True), dof
