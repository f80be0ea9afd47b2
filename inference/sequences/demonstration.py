"""A demonstration read: what each of its states shows, per time.

As the network's state space and arrays.

:func:`explain <inference.sequences.explanation.explain>` reads its ``states`` here.
:class:`~inference.sequences.states.StateSpace` numbers the configurations of a
network's state (its discrete features with both an initial and an end node);
:class:`Demonstrations` holds, per
demonstration and time, the states consistent with what that time shows, the
continuous values and the discrete outcomes, and groups the steps that observe the same
(:meth:`Demonstrations.step_keys`), so that a step table is read off the model once per
distinct observation.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch
from effect_networks.inference.queries.sampling import simulate
from effect_networks.inference.sequences.states import StateSpace, state_features
from effect_networks.models.cpds import TableParams
from effect_networks.models.declaration import ACTION, DTYPE, Continuous, Discrete, EffectNetwork
from effect_networks.models.params import NetworkParams
from effect_networks.models.sites import end_site, initial_site


@dataclass(frozen=True)
class Demonstrations:
    """A batch read.

    ``shown`` ``(n, T + 1, F)`` long: per state feature (declaration order) the state index each
    time shows, -1 where not observed; ``allowed`` ``(n, T + 1, S)`` the states of a listed space
    consistent with what each time shows (``None`` where read without a space);
    ``continuous[f]`` ``(n, T + 1, d)`` (NaN: not observed); ``outcomes[f]`` ``(n, T + 1)``
    state indices of discrete outcome features (-1: not observed).
    """

    allowed: torch.Tensor | None
    continuous: dict[str, np.ndarray]
    outcomes: dict[str, np.ndarray]
    shown: torch.Tensor

    @property
    def shape(self) -> tuple[int, int]:
        """``(n, T)``."""
        return self.shown.shape[0], self.shown.shape[1] - 1

    @staticmethod
    def read(net: EffectNetwork, space: StateSpace | None, states) -> Demonstrations:
        """Read ``states`` against ``space`` (``None``: every combination, ``allowed`` not built).

        ``states`` is :func:`~inference.sequences.explanation.explain`'s one demonstration or batch; a
        ``ValueError`` names the feature, the value and what was expected.
        """
        batch = _as_batch(net, states)
        lengths = {np.shape(v)[:2] for v in batch.values() if v is not None}
        if not isinstance(states, Mapping):
            lengths.add((1, len(states)))
        if len(lengths) != 1:
            raise ValueError(
                "states: every feature needs the same (n, T + 1) leading shape, got "
                f"{ {f: np.shape(v)[:2] for f, v in batch.items()} }"
            )
        n, times = lengths.pop()
        if times < 2:
            raise ValueError(f"states: a demonstration needs at least 2 states, got {times}")
        continuous, outcomes, indices = {}, {}, {}
        for f in net.features:
            value = batch.get(f.name)
            if isinstance(f, Discrete):
                index = indices[f.name] = _discrete_indices(net, f, value, (n, times))
                if not f.initial:
                    _unobserved_first(f, index[:, 0] >= 0)
                    outcomes[f.name] = index
            else:
                x = _continuous_values(f, value, (n, times))
                if f.initial:
                    if np.isnan(x).any():
                        raise ValueError(
                            f"states[{f.name!r}]: a continuous feature with an initial node must "
                            "be observed at every time (NaN found)"
                        )
                else:
                    _unobserved_first(f, ~np.isnan(x[:, 0]).all(-1))
                continuous[f.name] = x
        state = state_features(net)
        shown = torch.from_numpy(
            np.stack([indices[f.name] for f in state], -1)
            if state
            else np.zeros((n, times, 0), dtype=np.int64)
        )
        if space is None:
            return Demonstrations(None, continuous, outcomes, shown)
        allowed = torch.ones(n, times, len(space), dtype=torch.bool)
        for j, digit in enumerate(space.index.T):
            index = shown[..., j, None]
            allowed &= (index < 0) | (index == digit)
        empty = ~allowed.any(-1)
        if bool(empty.any()):
            i, t = (int(x) for x in empty.nonzero()[0])
            seen = {f.name: f.states[indices[f.name][i, t]] for f in space.features}
            raise ValueError(
                f"states: demonstration {i} at time {t} shows {seen}, which no state of "
                f"the state space ({len(space)} states) matches"
            )
        return Demonstrations(allowed, continuous, outcomes, shown)

    def split(self, size: int) -> list[Demonstrations]:
        """The batch in parts of ``size`` demonstrations (the last may be shorter)."""
        return [self.part(slice(i, i + size)) for i in range(0, self.shape[0], size)]

    def part(self, rows: slice) -> Demonstrations:
        """The demonstrations ``rows`` of the batch."""
        return Demonstrations(
            None if self.allowed is None else self.allowed[rows],
            {f: x[rows] for f, x in self.continuous.items()},
            {f: x[rows] for f, x in self.outcomes.items()},
            self.shown[rows],
        )

    def step_keys(self) -> tuple[np.ndarray, np.ndarray]:
        """Each step's observation as an index among the distinct ones, and the distinct ones.

        ``(n, T)`` the index of each step's observation among the distinct ones, and the distinct
        ones ``(K, m)``: each step's continuous values at its start and end and its outcomes (-1 /
        NaN: not observed). Steps that observe the same get one step table.
        """
        n, steps = self.shape
        columns = []
        for x in self.continuous.values():
            columns += [x[:, :-1].reshape(n * steps, -1), x[:, 1:].reshape(n * steps, -1)]
        for index in self.outcomes.values():
            outcome = index[:, 1:].reshape(n * steps, 1)
            columns.append(np.where(outcome < 0, np.nan, outcome.astype(np.float64)))
        if not columns:
            return np.zeros((n, steps), dtype=np.int64), np.zeros((1, 0))
        rows = np.concatenate(columns, 1)
        rows = np.where(np.isnan(rows), np.inf, rows)  # np.unique tells NaNs apart: one marker
        keys, inverse = np.unique(rows, axis=0, return_inverse=True)
        keys = np.where(np.isinf(keys), np.nan, keys)
        return inverse.reshape(n, steps), keys


def _as_batch(net: EffectNetwork, states) -> dict[str, object]:
    names = {f.name for f in net.features}
    if isinstance(states, Mapping):
        batch = dict(states)
    elif isinstance(states, Sequence) and not isinstance(states, str | bytes):
        if not all(isinstance(s, Mapping) for s in states):
            raise ValueError(
                "states: a demonstration is a sequence of mappings feature -> value, or a "
                "batch is one mapping feature -> (n, T + 1) array"
            )
        seen = {k for s in states for k in s}
        batch = {}
        for name in seen & names:
            f = net.feature(name)
            if isinstance(f, Discrete):
                batch[name] = np.array([[s.get(name) for s in states]], dtype=object)
            else:
                batch[name] = np.array(
                    [[np.full(f.dim, np.nan) if s.get(name) is None else s[name] for s in states]],
                    dtype=np.float64,
                )
        batch |= {k: None for k in seen - names}  # reported below
    else:
        raise ValueError(
            f"states must be a sequence of mappings or a mapping of arrays, got {type(states).__name__}"
        )
    unknown = sorted(set(batch) - names)
    if unknown:
        raise ValueError(f"states name unknown features {unknown}; features: {sorted(names)}")
    return batch


def _discrete_indices(net: EffectNetwork, f: Discrete, value, shape) -> np.ndarray:
    """``shape`` state indices of ``value``, -1 where unobserved.

    ``value`` holds labels, ``None`` for unobserved (everywhere for ``None``); labels are read as
    the network reads them.
    """
    index = np.full(shape, -1, dtype=np.int64)
    if value is None:
        return index
    labels = np.asarray(value)
    if labels.shape != shape:
        raise ValueError(f"states[{f.name!r}]: expected shape {shape}, got {labels.shape}")
    observed = np.ones(shape, dtype=bool)
    if labels.dtype == object:
        observed = labels != None  # noqa: E711 (elementwise)
        if not observed.all():
            labels = labels[observed]
        labels = np.array(labels.reshape(-1).tolist())  # typed where the labels agree
    site = initial_site(f.name) if f.initial else end_site(f.name)
    if labels.size:
        try:
            index[observed] = net.encode({site: labels.reshape(-1)})[site].numpy()
        except ValueError as error:
            raise ValueError(f"states[{f.name!r}]: {error}") from None
    return index


def _continuous_values(f: Continuous, value, shape: tuple[int, int]) -> np.ndarray:
    if value is None:
        if f.initial:
            raise ValueError(
                f"states: continuous feature {f.name!r} is missing; a demonstration observes "
                "its continuous features with an initial node at every time"
            )
        return np.full((*shape, f.dim), np.nan)
    x = np.asarray(value, dtype=np.float64)
    if x.shape == shape and f.dim == 1:
        x = x[..., None]
    if x.shape != (*shape, f.dim):
        raise ValueError(f"states[{f.name!r}]: expected shape {(*shape, f.dim)}, got {x.shape}")
    partly = np.isnan(x).any(-1) & ~np.isnan(x).all(-1)
    if partly.any():
        raise ValueError(
            f"states[{f.name!r}]: a value is observed in some dimensions only; give all or none"
        )
    if np.isinf(x).any():
        raise ValueError(f"states[{f.name!r}]: values must be finite, got inf")
    return x


def _unobserved_first(f, observed: np.ndarray) -> None:
    if observed.any():
        raise ValueError(
            f"states[{f.name!r}]: an outcome feature (initial=False) exists after a step only; "
            "state 0 must leave it unobserved (None / NaN)"
        )


def key_columns(net: EffectNetwork, demo: Demonstrations) -> dict[str, slice]:
    """Where each site's value lies in a step key (:meth:`Demonstrations.step_keys`)."""
    out, at = {}, 0
    for name, x in demo.continuous.items():
        d = x.shape[-1]
        if net.feature(name).initial:
            out[initial_site(name)] = slice(at, at + d)
        out[end_site(name)] = slice(at + d, at + 2 * d)
        at += 2 * d
    for name in demo.outcomes:
        out[end_site(name)] = slice(at, at + 1)
        at += 1
    return out


def key_evidence(net: EffectNetwork, keys: np.ndarray, columns, k: torch.Tensor) -> dict:
    """Evidence by site for rows of the distinct observations ``keys[k]``.

    ``columns``: :func:`key_columns`; an outcome a pattern does not observe (NaN) is left
    out (the rows share one pattern).
    """
    ev: dict[str, torch.Tensor] = {}
    for site, cols in columns.items():
        value = torch.from_numpy(keys[k.numpy(), cols])
        if bool(torch.isnan(value).any()):
            continue  # an outcome this pattern does not observe
        ev[site] = value[:, 0].long() if net.site(site).discrete else value
    return ev


def with_action_prior(
    net: EffectNetwork, params: NetworkParams, prior: Mapping[str, float] | Sequence[float] | None
) -> NetworkParams:
    """``params`` with the action table replaced by ``prior``.

    ``prior``: a mapping action -> probability, an ``(A,)`` sequence, or ``None`` for uniform.
    """
    a = len(net.actions)
    if prior is None:
        probs = torch.full((a,), 1.0 / a, dtype=DTYPE)
    elif isinstance(prior, Mapping):
        unknown = set(prior) - set(net.actions)
        if unknown:
            raise ValueError(
                f"prior names unknown actions {sorted(unknown)}; actions: {net.actions}"
            )
        probs = torch.tensor([float(prior.get(x, 0.0)) for x in net.actions], dtype=DTYPE)
    else:
        probs = torch.as_tensor(np.asarray(prior, dtype=np.float64))
        if probs.shape != (a,):
            raise ValueError(
                f"prior must have one probability per action ({a}), got shape {tuple(probs.shape)}"
            )
    if (
        not bool(torch.isfinite(probs).all())
        or bool((probs < 0).any())
        or not math.isclose(float(probs.sum()), 1.0, abs_tol=1e-9)
    ):
        raise ValueError(f"prior must be non-negative and sum to 1, got {probs.tolist()}")
    table = params[ACTION]
    cpds = dict(params.cpds)
    cpds[ACTION] = TableParams(probs.to(table.probs.dtype), table.n)
    return replace(params, cpds=cpds)


def simulate_demonstrations(
    net: EffectNetwork,
    params: NetworkParams,
    n: int,
    steps: int,
    *,
    prior: Mapping[str, float] | Sequence[float] | None = None,
    seed: int = 0,
) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Draw ``n`` demonstrations of ``steps`` steps from the model.

    The first state from the network's initial distribution, each step's action from ``prior``
    (uniform for ``None``), its parameter from the action's clusters, and each end state from the
    model given the step's start, which is the previous step's end.

    Returns
    -------
    states : dict
        :func:`~inference.sequences.explanation.explain`'s batch form, every value observed:
        per discrete feature ``(n, steps + 1)`` labels (an outcome feature ``None`` at
        time 0), per continuous feature ``(n, steps + 1, d)`` numbers (an outcome
        feature NaN at time 0).
    actions : numpy.ndarray
        ``(n, steps)`` the action names drawn.
    """
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be a positive int, got {steps!r}")
    params = with_action_prior(net, params, prior)
    rows = simulate(net, params, n, seed=seed)
    times: dict[str, list] = {f.name: [] for f in net.features}
    for f in net.features:
        if f.initial:
            times[f.name].append(_column(rows[initial_site(f.name)], f))
        else:
            times[f.name].append(
                np.full(n, None, dtype=object)
                if isinstance(f, Discrete)
                else np.full((n, f.dim), np.nan)
            )
    actions = []
    for t in range(steps):
        if t:
            start = {
                initial_site(f.name): rows[end_site(f.name)] for f in net.features if f.initial
            }
            rows = simulate(net, params, n, start, seed=seed + t)
        actions.append(np.asarray(rows[ACTION], dtype=object))
        for f in net.features:
            times[f.name].append(_column(rows[end_site(f.name)], f))
    states = {name: np.stack(values, 1) for name, values in times.items()}
    return states, np.stack(actions, 1)


def _column(value, f) -> np.ndarray:
    if isinstance(f, Discrete):
        out = np.empty(len(value), dtype=object)
        out[:] = list(value)
        return out
    return np.asarray(value, dtype=np.float64).reshape(-1, f.dim)
