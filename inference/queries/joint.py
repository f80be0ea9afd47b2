"""The joint of the discrete end features.

:func:`predict_joint`, the twin of :func:`~inference.queries.forward.predict` that keeps the end
features together.

:func:`~inference.queries.forward.predict` gives each end feature's marginal. Where end
features depend on each other (declared end -> end parents, a shared end-only feature,
one unknown parameter cluster acting on several), the joint is not the product of the
marginals, and a step of a plan needs the joint. It is summed here from the same traced
model, every other latent site summed out by contraction
(:meth:`~inference.exact.traced.Enumerated.joint`).
"""

from __future__ import annotations

import itertools
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, replace

import torch
from effect_networks.inference.exact.enumeration import over_row_chunks
from effect_networks.inference.queries.batching import placeholder_row, prepare, unseen_mass
from effect_networks.inference.queries.implausibility import (
    IMPLAUSIBLE_BELOW,
    check_threshold,
    plausibility,
)
from effect_networks.models.declaration import Discrete, EffectNetwork, end_site
from effect_networks.models.params import NetworkParams


@dataclass(frozen=True)
class JointPrediction:
    """Per row, the joint over the discrete end features ``features``.

    ``probs`` ``(n, K_1 * ... * K_m)``: per row the joint over the discrete end features
    ``features``, over their joint states ``states`` (label tuples, the first feature varying
    slowest).

    ``unseen`` ``(n,)``: the probability that the prediction rests on a parent
    configuration no training row reached; ``implausible`` ``(n,)`` bool: the observed end
    features (if any) have almost no probability (:mod:`inference.queries.implausibility`).
    """

    features: tuple[str, ...]
    states: tuple[tuple[Hashable, ...], ...]
    probs: torch.Tensor
    unseen: torch.Tensor
    implausible: torch.Tensor

    def prob(self, state: Sequence[Hashable] | Mapping[str, Hashable]) -> torch.Tensor:
        """``(n,)`` the probability of one joint state.

        Labels in ``features`` order, or ``{feature: label}``.
        """
        if isinstance(state, Mapping):
            if set(state) != set(self.features):
                raise ValueError(f"name exactly the features {self.features}, got {dict(state)}")
            state = tuple(state[f] for f in self.features)
        state = tuple(state)
        if state not in self.states:
            raise ValueError(f"{state!r} is not a joint state of {self.features}")
        return self.probs[:, self.states.index(state)]

    def marginal(self, feature: str) -> torch.Tensor:
        """``(n, K)`` one feature's marginal (what :func:`predict` gives)."""
        if feature not in self.features:
            raise ValueError(f"no joint over {feature!r}; features: {self.features}")
        j = self.features.index(feature)
        sizes = [len({s[i] for s in self.states}) for i in range(len(self.features))]
        p = self.probs.reshape(-1, *sizes)
        others = [d + 1 for d in range(len(sizes)) if d != j]
        return p.sum(others) if others else p

    def most_likely(self) -> tuple[tuple[Hashable, ...], ...]:
        """The most probable joint state per row, by labels."""
        return tuple(self.states[i] for i in self.probs.argmax(-1).tolist())


def predict_joint(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Mapping[str, object],
    *,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> JointPrediction:
    """The joint distribution of every discrete end feature not in ``evidence``.

    ``evidence`` follows :func:`~inference.queries.forward.predict`'s convention (state
    labels, numbers, NaN for an unknown parameter); unknown discrete sites and
    parameters are summed and integrated out, continuous end features left out.


    Parameters
    ----------
    net, params
        The network and its fitted parameters.
    evidence
        ``n`` rows of what is known, by site name (labels, numbers, NaN where unknown):
        see :meth:`models.EffectNetwork.encode`.
    implausible_below
        The probability under which a row's observed end features are flagged.

    Returns
    -------
    JointPrediction
        Per row, the joint distribution over the unobserved discrete end features' states.

    Examples
    --------
    >>> from models import Discrete, EffectNetwork, random_params
    >>> net = EffectNetwork(
    ...     features=(Discrete("door", ("shut", "open")), Discrete("lock", ("off", "on"))),
    ...     actions=("push", "wait"),
    ...     parents={"end.lock": ("initial.lock", "action", "end.door")},
    ... )
    >>> p = predict_joint(net, random_params(net, 0), {"initial.door": ["shut"],
    ...     "initial.lock": ["on"], "action": ["push"]})
    >>> p.features, p.states[1], p.probs.shape
    (('door', 'lock'), ('shut', 'on'), torch.Size([1, 4]))
    """
    below = check_threshold(implausible_below)
    enc = prepare(net, params, evidence)
    if enc.n_rows == 0:
        one = predict_joint(net, params, placeholder_row(enc), implausible_below=below)
        return replace(
            one, probs=one.probs[:0], unseen=one.unseen[:0], implausible=one.implausible[:0]
        )
    targets = [f for f in net.features if isinstance(f, Discrete) and end_site(f.name) not in enc]
    if not targets:
        raise ValueError(
            "predict_joint: every discrete end feature is in the evidence; nothing to predict"
        )
    sites = [end_site(f.name) for f in targets]
    probs = over_row_chunks(
        net, params, enc, set(sites), lambda e, *_: e.joint(sites), contracted=True
    )
    mass = over_row_chunks(
        net,
        params,
        enc,
        set(sites),
        lambda e, *_: unseen_mass(net, params, e, sites),
        contracted=True,
    ).clamp(0, 1)
    flag = plausibility(net, params, enc).implausible(below)
    states = tuple(itertools.product(*(f.states for f in targets)))
    return JointPrediction(tuple(f.name for f in targets), states, probs, mass, flag)
