"""A demonstration read as the actions that produced it: :func:`explain`.

A demonstration of ``T`` steps is ``T + 1`` observed scene states; step ``t`` starts in
state ``t`` and ends in state ``t + 1``, so one step's end is the next step's start. The
network's *state* is its discrete features that have both an initial and an end node;
the parts of it a demonstration does not observe are latent, and they carry over from
one step to the next. That is a hidden Markov model::

    H_0 ──a_0──> H_1 ──a_1──> H_2  ...  ──a_{T-1}──> H_T      H_t: the discrete state
     │            │            │                      │
    x_0          x_1          x_2                    x_T      x_t: what state t shows

whose hidden variable at time ``t`` is what state ``t`` hides of ``H_t``: the
configurations of the state features not observed at ``t``, those observed fixed to
their values (:mod:`inference.sequences.hidden_steps`); whose start is the network's own
initial distribution given what state 0 shows; and whose step ``t`` is the action drawn from a prior (uniform unless given) and
the network's ``p(H_{t+1}, x_{t+1} | H_t, x_t, a_t)``: the end state given the initial
one, the action and the continuous features observed at both ends. Everything else the
network holds is summed or integrated out inside a step, exactly, by the model itself
(:mod:`inference.exact.enumeration`): an action parameter is not observed in a
demonstration, so each parameterised action counts as the mixture of its parameter's
clusters (the parameter integrated out in closed form); outcome features
(``initial=False``) that a state does not show are summed out.

Each step's table ``log p(H_{t+1}, x_{t+1} | H_t, x_t, a)`` spans (configurations hidden
at its start) x actions x (configurations hidden at its end): ``A`` entries where the
step is fully observed, ``2^(h + h')`` times as many where its start hides ``h`` binary
features and its end ``h'``, however many features the network has. It is read off the traced model (the action enumerated and
kept) once per distinct (observation, start, end), and the sums over paths run in log
space over the batch, over those configurations only
(:mod:`inference.sequences.hidden_paths`): forward-backward for the posterior over each
step's action and the demonstration's log-likelihood, Viterbi for the most probable
action sequence and state path, jointly. With every state fully observed nothing is
latent and each step is :func:`~inference.queries.action.infer_action`'s question, asked
with the same action prior. A step whose table would exceed
:data:`~inference.sequences.hidden_steps.MAX_STEP_TABLE` entries is refused, naming it.
The same question over every state at every time, the tests' twin, is
:func:`~inference.sequences.dense_explanation.explain_dense`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from effect_networks.inference.queries.implausibility import (
    IMPLAUSIBLE_BELOW,
    OutsideTrainingData,
    check_threshold,
)
from effect_networks.inference.sequences.demonstration import Demonstrations, with_action_prior
from effect_networks.inference.sequences.hidden_paths import over_hidden_paths
from effect_networks.inference.sequences.hidden_steps import (
    MAX_STEP_TABLE,
    ProductStates,
    StateCodes,
    configuration_counts,
    hidden_configurations,
    read_step_tables,
    step_pairs,
)
from effect_networks.inference.sequences.states import StateSpace, state_features
from effect_networks.models.declaration import DTYPE, EffectNetwork
from effect_networks.models.params import NetworkParams, check_params

#: Where ``S * A * S`` (states x actions x states) is at most this, as over the whole
#: state space (:mod:`inference.sequences.dense_explanation`), ``state_probs`` is a dense
#: tensor and ``states`` a tuple; past it ``state_probs`` is a sparse tensor of the same
#: shape and ``states`` a :class:`~inference.sequences.hidden_steps.ProductStates`.
DENSE_STATE_PROBS = MAX_STEP_TABLE
#: Entries of the step tables (pairs of configurations x actions) one part of the batch
#: holds at once; a larger batch is read part by part.
TABLE_ELEMENTS = 1 << 24


@dataclass(frozen=True)
class Explanation:
    """What :func:`explain` answers for ``n`` demonstrations of ``T`` steps each.

    ``probs`` ``(n, T, A)``: the posterior over each step's action given the whole
    demonstration (forward-backward). ``best`` ``(n, T)``: the actions of the most
    probable action sequence and state path, taken jointly (Viterbi); ``best_names``
    the same as names. ``path`` ``(n, T + 1)``: that path's states, indices into
    ``states`` (labels of ``features``, in declaration order: a tuple, or past
    :data:`DENSE_STATE_PROBS` a :class:`~inference.sequences.hidden_steps.ProductStates`
    that makes each state's labels on demand). ``state_probs`` ``(n, T + 1, S)``: the
    posterior over each time's state; past :data:`DENSE_STATE_PROBS` a sparse COO tensor
    holding each time's hidden configurations (``.to_dense()`` where it fits). ``log_likelihood`` ``(n,)``:
    ``log p(x_1, ..., x_T | x_0)``, the demonstration's probability (a density where it
    observes continuous features) given its first state, actions and latent parts summed
    out. ``implausible`` ``(n, T)`` bool: the step's observed end state has (almost) no
    probability under the model given everything observed before it
    (:func:`explain`'s notes).
    """

    probs: torch.Tensor
    best: torch.Tensor
    best_names: tuple[tuple[str, ...], ...]
    path: torch.Tensor
    state_probs: torch.Tensor
    log_likelihood: torch.Tensor
    implausible: torch.Tensor
    actions: tuple[str, ...]
    features: tuple[str, ...]
    states: tuple[tuple, ...]

    def prob(self, action: str) -> torch.Tensor:
        """``(n, T)`` posterior probability of the action named ``action`` at each step."""
        if action not in self.actions:
            raise ValueError(f"unknown action {action!r}; actions are {list(self.actions)}")
        return self.probs[..., self.actions.index(action)]

    def path_labels(self, i: int = 0) -> list[dict[str, object]]:
        """Demonstration ``i``'s most probable state path.

        One mapping feature -> label per time, ``T + 1`` of them.
        """
        return [
            dict(zip(self.features, self.states[s], strict=True)) for s in self.path[i].tolist()
        ]


def explain(
    net: EffectNetwork,
    params: NetworkParams,
    states: Sequence[Mapping[str, object]] | Mapping[str, object],
    *,
    prior: Mapping[str, float] | Sequence[float] | None = None,
    state_space: Sequence | None = None,
    implausible_below: float = IMPLAUSIBLE_BELOW,
) -> Explanation:
    """The actions that produced a demonstration.

    Per-step posterior, most probable sequence, log-likelihood.

    Parameters
    ----------
    net, params
        The network and its fitted parameters.
    states
        One demonstration: a sequence of ``T + 1`` mappings feature -> value, the scene
        at each time (labels for discrete features, numbers for continuous ones). Or a
        batch of ``n`` demonstrations as one mapping feature -> array: ``(n, T + 1)``
        labels for a discrete feature, ``(n, T + 1, d)`` (or ``(n, T + 1)`` for
        ``d = 1``) numbers for a continuous one. A discrete value that is ``None`` (or a
        feature left out) is not observed at that time; the state's unobserved parts are
        latent. Continuous features with an initial node are observed at every time. An
        outcome feature (``initial=False``) exists after a step only: its value at time
        ``t + 1`` is step ``t``'s outcome, ``None``/NaN where not observed; at time 0 it
        must be unobserved.
    prior
        The actions' prior at every step: a mapping action -> probability or an ``(A,)``
        sequence; default uniform. It replaces the network's fitted action table.
    state_space
        The states a demonstration may pass through: label tuples (one label per
        discrete feature with an initial node, in declaration order) or mappings feature
        -> label; default every combination. Naming the states that occur (the can
        world's possible configurations, each with its count) keeps the step tables to
        their size; the others then have probability 0.
    implausible_below
        A step is ``implausible`` where the probability of its observed discrete end
        features, given everything observed up to its start, or the chi-square tail of
        its observed continuous end features under the closest component the whole
        demonstration leaves possible (:mod:`inference.queries.implausibility`), is below
        this; or where a continuous initial value lies outside the training data
        (warned as :class:`~inference.queries.implausibility.OutsideTrainingData`). With
        every state fully observed these are the numbers
        :func:`~inference.queries.action.infer_action` flags a step by.

    Returns
    -------
    Explanation

    Notes
    -----
    An action parameter is never observed in a demonstration: each parameterised action
    is the mixture over its parameter's clusters that the network fitted, the value
    integrated out. The most probable sequence is the joint maximum over actions and
    latent states (Viterbi), which can differ from the per-step argmax of ``probs``.
    """
    check_params(net, params)
    below = check_threshold(implausible_below)
    features = state_features(net)
    space = None if state_space is None else StateSpace.of(net, state_space, stateless=True)
    demo = Demonstrations.read(net, space, states)
    params = with_action_prior(net, params, prior)
    a, (n, steps) = len(net.actions), demo.shape
    size = len(space) if space is not None else math.prod(f.cardinality for f in features)
    dense = size * a * size <= DENSE_STATE_PROBS
    if space is not None:
        labels = space.states
    elif dense:
        labels = StateSpace.of(net, stateless=True).states
    else:
        labels = ProductStates(features)
    names = tuple(f.name for f in features)
    codes = StateCodes.of(features, space)
    if n == 0:
        return _no_demonstrations(net, names, labels, steps, dense)
    counts = configuration_counts(demo, codes)
    entries = (counts[:, :-1] * counts[:, 1:]).sum(-1) * a  # (n,) each one's table entries
    parts = [_read_part(net, params, codes, demo, rows, below) for rows in _parts(entries)]
    answers = [x[0] for x in parts]
    initial = {site: torch.cat([x.initial[site] for x in answers]) for site in answers[0].initial}
    where = torch.cat([x[1][0] for x in parts], 1)
    config_probs = torch.cat([x[1][1] for x in parts])
    if dense:
        state_probs = torch.zeros(n, steps + 1, size, dtype=DTYPE)
        state_probs[tuple(where)] = config_probs
    else:  # each time's hidden configurations, in order: coalesced as built
        state_probs = torch.sparse_coo_tensor(
            where, config_probs, (n, steps + 1, size), is_coalesced=True, check_invariants=False
        )
    best = torch.cat([x.best for x in answers])
    flags = torch.cat([x.flags for x in answers])
    implausible = flags | outside_flags(initial, (n, steps), below)
    best_names = tuple(map(tuple, np.array(net.actions, dtype=object)[best.numpy()].tolist()))
    return Explanation(
        torch.cat([x.probs for x in answers]),
        best,
        best_names,
        torch.cat([x.path for x in answers]),
        state_probs,
        torch.cat([x.log_likelihood for x in answers]),
        implausible,
        net.actions,
        names,
        labels,
    )


def _parts(entries: torch.Tensor) -> list[slice]:
    """The batch in runs of demonstrations, each within :data:`TABLE_ELEMENTS` entries.

    ``entries`` ``(n,)``: each demonstration's step table entries; a demonstration that alone
    holds more is a run of its own.
    """
    parts, start, held = [], 0, 0
    for i, e in enumerate(entries.tolist()):
        if held and held + e > TABLE_ELEMENTS:
            parts.append(slice(start, i))
            start, held = i, 0
        held += e
    parts.append(slice(start, len(entries)))
    return parts


def _read_part(net, params, codes, demo, rows: slice, below: float):
    """The demonstrations ``rows`` of the batch, read.

    The passes' answers and the state posterior's entries: ``(3, M)`` indices
    (demonstration, time, state) and ``(M,)`` values.
    """
    demo = demo.part(rows)
    n, steps = demo.shape
    configs = hidden_configurations(demo, codes)
    pairs = step_pairs(configs, (n, steps), len(net.actions))
    tables = read_step_tables(net, params, codes, demo, configs, pairs)
    answers = over_hidden_paths(configs, pairs, tables, (n, steps), below)
    first = configs.owner // (steps + 1) + rows.start
    where = torch.stack([first, configs.owner % (steps + 1), configs.state])
    return answers, (where, answers.config_probs)


def _no_demonstrations(net: EffectNetwork, names, labels, steps: int, dense: bool) -> Explanation:
    """The answer to a batch of no demonstrations: every field with its shape, ``n = 0``."""
    a, s = len(net.actions), len(labels)
    state_probs = torch.sparse_coo_tensor(
        torch.zeros(3, 0, dtype=torch.long),
        torch.zeros(0, dtype=DTYPE),
        (0, steps + 1, s),
        check_invariants=False,
    )
    return Explanation(
        torch.zeros(0, steps, a, dtype=DTYPE),
        torch.zeros(0, steps, dtype=torch.long),
        (),
        torch.zeros(0, steps + 1, dtype=torch.long),
        state_probs.to_dense() if dense else state_probs,
        torch.zeros(0, dtype=DTYPE),
        torch.zeros(0, steps, dtype=torch.bool),
        net.actions,
        names,
        labels,
    )


def outside_flags(initial: dict[str, torch.Tensor], shape, below: float) -> torch.Tensor:
    """``shape`` ``(n, T)`` bool: a step's continuous initial state lies outside the training data.

    Warned, naming the site, the first demonstration and its step.
    """
    flag = torch.zeros(shape, dtype=torch.bool)
    for site, tail in initial.items():
        outside = tail < below
        if bool(outside.any()):
            i, t = (int(x) for x in outside.nonzero()[0])
            warnings.warn(
                f"{site}: {int(outside.sum())} step(s), the first demonstration {i} step {t}, "
                f"lie far outside the training data (tail below {below:g}); their answers "
                "extrapolate",
                OutsideTrainingData,
                stacklevel=3,
            )
        flag |= outside
    return flag
