"""What the queries answer: one frozen result type per question.

Every field is batched over the evidence rows (leading axis ``n``).

* :class:`Prediction` -- :func:`~inference.queries.forward.predict`, the end state;
  :class:`GaussianMixture` -- a continuous end feature's (or a parameter's) distribution.
* :class:`ImitationCheck` -- :func:`~inference.queries.forward.imitation_check`.
* :class:`ActionPosterior` -- :func:`~inference.queries.action.infer_action`.
* :class:`ParameterPosterior` -- :func:`~inference.queries.parameter.infer_parameter`,
  the parameter posterior.
* :class:`ParameterForEffect` -- :func:`~inference.queries.inverse.parameter_for_effect`,
  the inverse model.

Each has ``to_frame()``: a pandas ``DataFrame``, one row per evidence row, with labels
rather than indices. A probability of a state is a column ``site=label``
(``end.visible=True``, ``action=tap``), the most probable label the column named like
the site (``end.visible``, ``action``); a vector of dimension ``d > 1`` takes the
columns ``name[0]`` ... ``name[d-1]``, as in :mod:`models.frames`.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Any

import torch
from effect_networks.models.declaration import Parameter, end_site
from effect_networks.models.frames import require_pandas


@dataclass(frozen=True)
class GaussianMixture:
    """Per row a mixture: ``weights`` ``(n, M)``, ``means`` ``(n, M, d)``, ``covs`` ``(n, M, d, d)``."""

    weights: torch.Tensor
    means: torch.Tensor
    covs: torch.Tensor

    @property
    def mean(self) -> torch.Tensor:
        """``(n, d)`` mixture mean."""
        return (self.weights[..., None] * self.means).sum(1)

    @property
    def cov(self) -> torch.Tensor:
        """``(n, d, d)`` mixture covariance (law of total covariance)."""
        diff = self.means - self.mean[:, None, :]
        spread = diff[..., :, None] * diff[..., None, :]
        return (self.weights[..., None, None] * (self.covs + spread)).sum(1)


@dataclass(frozen=True)
class Prediction:
    """The end features' distributions, discrete and continuous.

    ``discrete[feature]``: ``(n, K)`` probabilities over the feature's states in declaration order
    (``states[feature]``); ``continuous[feature]``: a mixture.
    """

    discrete: dict[str, torch.Tensor]
    continuous: dict[str, GaussianMixture]
    unseen: torch.Tensor  # (n,) probability of resting on an unseen configuration
    states: dict[str, tuple] = field(default_factory=dict)
    implausible: torch.Tensor | None = None  # (n,) bool; see inference.queries.implausibility

    def prob(self, feature: str, state: Hashable) -> torch.Tensor:
        """``(n,)`` probability that ``feature`` ends in ``state`` (a label)."""
        states = self._states(feature)
        if state not in states:
            raise ValueError(f"feature {feature!r} has no state {state!r}; states: {states}")
        return self.discrete[feature][:, states.index(state)]

    def most_likely(self, feature: str) -> tuple:
        """The most probable end state of ``feature`` per row, as labels."""
        states = self._states(feature)
        return tuple(states[i] for i in self.discrete[feature].argmax(-1).tolist())

    def to_frame(self, index: Any = None) -> Any:
        """The prediction as a ``DataFrame``, one row per evidence row.

        Parameters
        ----------
        index
            The frame's index (the evidence frame's, say); ``0..n-1`` by default.

        Returns
        -------
        pandas.DataFrame
            Per discrete feature ``f``: ``end.f``, the most likely state's label, and
            ``end.f=<state>``, each state's probability; per continuous feature: its
            predicted mean, ``end.f`` (dimension 1) or ``end.f[i]``; then ``unseen``
            and, where computed, ``implausible``.
        """
        columns: dict[str, Any] = {}
        for feature, probs in self.discrete.items():
            columns[end_site(feature)] = list(self.most_likely(feature))
            for k, state in enumerate(self._states(feature)):
                columns[f"{end_site(feature)}={state}"] = _numpy(probs[:, k])
        for feature, mixture in self.continuous.items():
            columns |= _vector(end_site(feature), mixture.mean)
        columns["unseen"] = _numpy(self.unseen)
        if self.implausible is not None:
            columns["implausible"] = _numpy(self.implausible)
        return _frame(columns, index)

    def _states(self, feature: str) -> tuple:
        if feature not in self.discrete:
            raise ValueError(
                f"no discrete prediction for {feature!r}; predicted: {sorted(self.discrete)}"
            )
        return self.states[feature]


@dataclass(frozen=True)
class ActionPosterior:
    """The action posterior and its best action per row.

    ``probs`` ``(n, A)`` over ``actions``; ``best`` ``(n,)`` index; ``unseen`` ``(n, A)``;
    ``implausible`` ``(n,)`` bool: the observed end state has (almost) no probability under the
    model (see :mod:`inference.queries.implausibility`; ``None`` from the compiled queries), so
    ``best`` answers a question the model cannot explain.
    """

    probs: torch.Tensor
    best: torch.Tensor
    best_names: tuple[str, ...]
    log_evidence: torch.Tensor
    unseen: torch.Tensor
    actions: tuple[str, ...] = ()
    implausible: torch.Tensor | None = None

    def prob(self, action: str) -> torch.Tensor:
        """``(n,)`` posterior probability of the action named ``action``."""
        if action not in self.actions:
            raise ValueError(f"unknown action {action!r}; actions are {list(self.actions)}")
        return self.probs[:, self.actions.index(action)]

    def to_frame(self, index: Any = None) -> Any:
        """The posterior as a ``DataFrame``, one row per evidence row.

        Parameters
        ----------
        index
            The frame's index (the evidence frame's, say); ``0..n-1`` by default.

        Returns
        -------
        pandas.DataFrame
            ``action``: the most probable action's name; ``action=<a>``: each action's
            posterior probability; ``log_evidence``; ``unseen|action=<a>``: the
            probability of an unseen configuration had ``a`` been done; and, where
            computed, ``implausible``.
        """
        columns: dict[str, Any] = {"action": list(self.best_names)}
        for k, action in enumerate(self.actions):
            columns[f"action={action}"] = _numpy(self.probs[:, k])
        columns["log_evidence"] = _numpy(self.log_evidence)
        for k, action in enumerate(self.actions):
            columns[f"unseen|action={action}"] = _numpy(self.unseen[:, k])
        if self.implausible is not None:
            columns["implausible"] = _numpy(self.implausible)
        return _frame(columns, index)


@dataclass(frozen=True)
class ImitationCheck:
    """What :func:`~inference.queries.forward.imitation_check` answers, per evidence row, ``(n,)`` each.

    With ``E`` the row's evidence other than its observed end sites (the initial state,
    the executed action, a parameter if given) and ``o*`` the observed end state (the
    observed discrete end features' states, the continuous ones' values in their
    observed dimensions):

    * ``log_likelihood``: ``log p(o* | E)``, every latent site summed or integrated out
      (a log-probability for discrete end features, a log-density for continuous ones).
    * ``surprise`` in [0, 1]: ``P_{O ~ p(. | E)}(p(O | E) > p(o* | E))``, the predictive
      probability of the outcomes strictly more likely than the observed one. 0: the
      most likely outcome; near 1: the action did not do what it usually does. For one
      Gaussian component it is the chi-square CDF of the squared Mahalanobis distance,
      ``P(chi2_d < D^2)``.
    * ``unseen``: the posterior probability that the observed end sites' configuration
      was never reached in training.
    * ``implausible`` bool (see :mod:`inference.queries.implausibility`).
    """

    log_likelihood: torch.Tensor
    surprise: torch.Tensor
    unseen: torch.Tensor
    implausible: torch.Tensor | None = None

    def to_frame(self, index: Any = None) -> Any:
        """The check as a ``DataFrame``, one row per evidence row.

        The columns ``log_likelihood``, ``surprise``, ``unseen`` and, where computed,
        ``implausible``; its index is ``index``, ``0..n-1`` by default.
        """
        columns = {
            "log_likelihood": _numpy(self.log_likelihood),
            "surprise": _numpy(self.surprise),
            "unseen": _numpy(self.unseen),
        }
        if self.implausible is not None:
            columns["implausible"] = _numpy(self.implausible)
        return _frame(columns, index)


@dataclass(frozen=True)
class ParameterPosterior:
    """The cluster posterior and the parameter given the best cluster.

    ``cluster_probs`` ``(n, C)``, ``best_cluster`` ``(n,)``; the parameter given the best cluster
    (the paper's answer): ``mean`` ``(n, d)``, ``cov`` ``(n, d, d)``.

    ``outside`` ``(n,)`` bool: that mean lies outside the parameter's ``[low, high]`` (an
    action the declaration does not cover). ``mixture``: with ``mixture=True``, the full
    posterior of the parameter, one Gaussian per cluster weighted by ``cluster_probs``.
    ``implausible`` ``(n,)`` bool: the observed end state has (almost) no probability
    under the model (see :mod:`inference.queries.implausibility`; ``None`` from the compiled query).
    """

    cluster_probs: torch.Tensor
    best_cluster: torch.Tensor
    mean: torch.Tensor
    cov: torch.Tensor
    unseen: torch.Tensor
    outside: torch.Tensor | None = None
    mixture: GaussianMixture | None = None
    implausible: torch.Tensor | None = None

    def to_frame(self, index: Any = None) -> Any:
        """The posterior as a ``DataFrame``, one row per evidence row.

        Parameters
        ----------
        index
            The frame's index (the evidence frame's, say); ``0..n-1`` by default.

        Returns
        -------
        pandas.DataFrame
            ``cluster``: the best cluster; ``cluster=<c>``: each cluster's posterior
            probability; ``mean`` and ``sd`` (dimension 1) or ``mean[i]`` and ``sd[i]``:
            the parameter given the best cluster (``sd`` the square root of the
            covariance's diagonal); ``unseen``; and, where computed, ``outside`` and
            ``implausible``.
        """
        columns: dict[str, Any] = {"cluster": _numpy(self.best_cluster)}
        for c in range(self.cluster_probs.shape[-1]):
            columns[f"cluster={c}"] = _numpy(self.cluster_probs[:, c])
        columns |= _vector("mean", self.mean)
        columns |= _vector("sd", self.cov.diagonal(dim1=-2, dim2=-1).sqrt())
        columns["unseen"] = _numpy(self.unseen)
        for name in ("outside", "implausible"):
            if getattr(self, name) is not None:
                columns[name] = _numpy(getattr(self, name))
        return _frame(columns, index)


@dataclass(frozen=True)
class ParameterForEffect:
    """What :func:`~inference.queries.inverse.parameter_for_effect` answers, per evidence row.

    ``value`` ``(n, d)``: the parameter value to use; ``cluster`` ``(n,)``: the cluster
    whose linear Gaussian it inverts; ``log_density`` ``(n,)``: ``log p(value, evidence)``,
    the posterior density of ``value`` up to the evidence's own probability; ``miss``
    ``(n,)``: the observed effect's squared Mahalanobis distance from that cluster's
    prediction at ``value`` (zero: the value produces the effect exactly; large: the
    effect lies outside what the cluster reaches). ``candidates`` ``(n, C, d)`` and
    ``candidate_log_density`` ``(n, C)``: every cluster's value and its score.
    ``outside`` ``(n,)`` bool: ``value`` lies outside the parameter's ``[low, high]``.
    """

    value: torch.Tensor
    cluster: torch.Tensor
    log_density: torch.Tensor
    miss: torch.Tensor
    candidates: torch.Tensor
    candidate_log_density: torch.Tensor
    outside: torch.Tensor

    def to_frame(self, index: Any = None) -> Any:
        """The answer as a ``DataFrame``, one row per evidence row.

        Its index is ``index``, ``0..n-1`` by default; the columns ``value`` (dimension 1) or
        ``value[i]``, ``cluster``, ``log_density``, ``miss`` and ``outside``.
        """
        columns = _vector("value", self.value) | {
            "cluster": _numpy(self.cluster),
            "log_density": _numpy(self.log_density),
            "miss": _numpy(self.miss),
            "outside": _numpy(self.outside),
        }
        return _frame(columns, index)


def outside_range(p: Parameter, value: torch.Tensor) -> torch.Tensor:
    """``(n,)`` bool: a parameter value ``(n, d)`` outside ``[low, high]`` in some dim."""
    low, high = value.new_tensor(p.low), value.new_tensor(p.high)
    return ((value < low) | (value > high)).any(-1)


def _numpy(t: torch.Tensor) -> Any:
    return t.detach().cpu().numpy()


def _vector(name: str, value: torch.Tensor) -> dict[str, Any]:
    """``(n, d)`` values as one column ``name`` (``d`` 1) or ``name[0]`` ... ``name[d-1]``."""
    if value.shape[-1] == 1:
        return {name: _numpy(value[:, 0])}
    return {f"{name}[{i}]": _numpy(value[:, i]) for i in range(value.shape[-1])}


def _frame(columns: dict[str, Any], index: Any) -> Any:
    pandas = require_pandas()
    return pandas.DataFrame(columns, index=index)
