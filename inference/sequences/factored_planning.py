r"""Plans whose cost follows the goal and the network's structure, not its state space.

The dense planner reads a tensor over (state, action, next state): ``4^k`` numbers for
``k`` binary features. Two exact facts make most of that unnecessary:

* **Projection.** Whether the goal is reached depends on the goal's features only, and
  their next values on the features their step reads
  (:meth:`~inference.sequences.factored_steps.StepModel.relevant`: the goal's features and
  their ancestors through the step, closed). The step restricted to those *relevant*
  features is exact: the best policy reads them alone and its values are the dense
  planner's (factored-MDP abstraction).
* **Factor by factor.** A backup ``q(s, a) = sum over s' of P(s' | s, a) v(s')`` never
  needs ``P`` whole: ``v`` is a tensor with one axis per relevant feature, and each step
  factor is multiplied in and its site summed out in turn (one ``einsum`` with a
  contraction order chosen by ``opt_einsum``), so a backup costs about the relevant
  states times the actions times the widest factor.

:func:`factored_plan` runs the ``"projected"`` route when the relevant features have at
most ``budget`` joint states. Beyond it, the ``"approximate"`` route plans exactly on the
goal's nearest relevant features that fit the budget, the others held at their start
values, and evaluates that policy in the full relevant model by Monte Carlo: its
``success`` is a lower bound that holds with the stated confidence (Hoeffding), with the
seed that reproduces it (:class:`~inference.sequences.plans.Certificate`).
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterable, Mapping, Sequence

import torch
from effect_networks.inference.sequences.dynamic_programming import (
    ExactPlan,
    induction,
    unseen_along,
)
from effect_networks.inference.sequences.factored_steps import (
    EINSUM_LETTERS,
    OFFERED,
    Letters,
    StepFactor,
    StepModel,
    chain_product,
    product_form,
)
from effect_networks.inference.sequences.plans import Certificate, Plan, allowed_mask
from effect_networks.inference.sequences.states import ProjectedSpace, Selection, state_index
from effect_networks.models.declaration import DTYPE, end_site, initial_site

#: The most joint states of the relevant features the exact factored route plans over.
MAX_RELEVANT_STATES = 1 << 14
#: Simulated runs of an approximate plan's policy in the full relevant model.
EPISODES = 40_000
#: The confidence of an approximate plan's lower bound on its success.
CONFIDENCE = 0.95
#: A projected space whose ``(S, A, S)`` tensor holds at most this many numbers is
#: backed up through that tensor (built once from the factors); a larger one factor by factor.
SMALL_PROJECTION = 1 << 18
#: Rows of a plan's value table kept in full when the values converge before the horizon.
KEEP_ROWS = 1 << 22


def factored_plan(
    model: StepModel,
    start: Selection | Sequence[Hashable],
    goal: Selection,
    horizon: int,
    allowed: Iterable[str] | torch.Tensor | None = None,
    *,
    avoid_unseen: bool = False,
    budget: int = MAX_RELEVANT_STATES,
    episodes: int = EPISODES,
    seed: int = 0,
) -> Plan:
    """The best policy to reach ``goal`` within ``horizon`` actions, by the network's structure.

    Parameters
    ----------
    model
        The step model (:func:`~inference.sequences.factored_steps.step_model`).
    start
        A full state (a label tuple or ``{feature: label}`` naming every state feature),
        or labels of some features (``{feature: label}``): the relevant features it does
        not name are weighted by the network's initial-state tables.
    goal
        Labels of some features (``{"door": "open"}``); a predicate on a state's
        ``{feature: label}`` reads every feature, so nothing is projected away.
    horizon
        The most actions, ``>= 1``.
    allowed
        The actions the plan may take: labels, or an ``(A,)`` bool mask.
    avoid_unseen
        Never take an action whose step (of the relevant features) rests mostly on
        configurations no training row reached, unless a state has no other.
    budget
        The most joint states of the relevant features planned over exactly.
    episodes, seed
        The approximate route's simulated runs and their seed.

    Returns
    -------
    Plan
        ``route`` ``"projected"`` (exact) or ``"approximate"`` (``success`` the certified
        lower bound, ``certificate`` the evaluation).
    """
    _check(horizon, budget, episodes)
    goal_features = _goal_features(model, goal)
    relevant = model.relevant(goal_features)
    by_name = {f.name: f for f in model.features}
    full = math.prod(by_name[n].cardinality for n in relevant)
    if full > budget and not isinstance(goal, Mapping):
        raise ValueError(
            f"a predicate goal reads every feature ({full} joint states, more than "
            f"budget={budget}): give the goal as labels of the features it reads "
            "({feature: label}), which the plan projects onto"
        )
    if full <= budget:
        planned, route = relevant, "projected"
    else:
        planned, route = _nearest(model, goal_features, relevant, budget), "approximate"
    space = ProjectedSpace(tuple(by_name[n] for n in planned), model.features)
    held = {}
    if route == "approximate":
        held = _held(model, start, relevant, planned)
    backup = _Backup(model, space, held)
    goal_mask = space.mask(goal)
    if not bool(goal_mask.any()):
        raise ValueError(f"goal {goal!r} picks no state of the features {space.names}")
    mask = allowed_mask(
        allowed, len(space), len(model.actions), model.action_index, per_state=False
    )
    unseen = backup.unseen()
    if avoid_unseen:
        seen = mask & (unseen <= 0.5)
        mask = torch.where(seen.any(-1, keepdim=True), seen, mask)
    exact = induction(backup, goal_mask, horizon, mask)
    policy = exact.policy.clone()
    policy[:, goal_mask] = -1
    policy[:, ~mask.any(-1)] = -1
    start_dist = _start(model, space, start)
    row = min(horizon, exact.value.shape[0] - 1)
    success = float(start_dist @ exact.value[row])
    p_unseen = unseen_along(
        backup.forward,
        lambda acts: unseen.gather(1, acts[:, None]).squeeze(1),
        policy,
        start_dist,
        goal_mask,
        horizon,
    )
    certificate = None
    if route == "approximate":
        certificate = _certify(model, relevant, space, policy, goal, start, horizon, episodes, seed)
        certificate = Certificate(**{**certificate.__dict__, "projected": success})
        success = certificate.lower
    steps = horizon if exact.converged is None else min(horizon, exact.converged + len(space))
    path, p = _greedy_path(backup, policy, goal_mask, start_dist, horizon, steps)
    labelled = tuple(space.state(x) if i % 2 == 0 else model.actions[x] for i, x in enumerate(path))
    value, policy = _rows(exact, policy, horizon)
    return Plan(
        None,
        goal_mask,
        start_dist,
        horizon,
        value,
        policy,
        success,
        labelled,
        p,
        space=space,
        route=route,
        features=space.names,
        unseen=p_unseen,
        certificate=certificate,
        converged=exact.converged,
        actions=model.actions,
    )


def _check(horizon, budget, episodes) -> None:
    if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
        raise ValueError(f"horizon must be an int >= 1, got {horizon!r}")
    if not isinstance(budget, int) or budget < 1:
        raise ValueError(f"budget must be an int >= 1, got {budget!r}")
    if not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be an int >= 1, got {episodes!r}")


def _goal_features(model: StepModel, goal: Selection) -> tuple[str, ...]:
    if isinstance(goal, Mapping):
        if not goal:
            raise ValueError("goal names no feature")
        unknown = [n for n in goal if n not in model.names]
        if unknown:
            raise ValueError(f"goal names {unknown}, which are not state features {model.names}")
        return tuple(goal)
    if callable(goal):
        return model.names
    raise ValueError(f"a goal is a mapping feature -> label or a predicate, got {goal!r}")


def _nearest(model, goal_features, relevant, budget) -> tuple[str, ...]:
    """The goal's features, then the relevant ones nearest them in the step, within ``budget``."""
    by_name = {f.name: f for f in model.features}
    kept = list(dict.fromkeys(goal_features))
    size = math.prod(by_name[n].cardinality for n in kept)
    if size > budget:
        raise ValueError(
            f"the goal's own features have {size} joint states, more than budget={budget}"
        )
    frontier = list(kept)
    while frontier:
        reads = model.relevant(frontier)
        new = [n for n in reads if n not in kept and n in relevant]
        frontier = []
        for n in new:
            k = by_name[n].cardinality
            if size * k <= budget:
                kept.append(n)
                frontier.append(n)
                size *= k
    return tuple(n for n in model.names if n in kept)


def _held(model, start, relevant, planned) -> dict[str, int]:
    """The relevant features left out of an approximate plan, at their start labels."""
    labels = _full_labels(model, start, relevant)
    by_name = {f.name: f for f in model.features}
    return {n: state_index(by_name[n], labels[n]) for n in relevant if n not in planned}


def _full_labels(model, start, features) -> dict[str, Hashable]:
    if isinstance(start, Mapping):
        labels = dict(start)
    elif isinstance(start, Sequence) and not isinstance(start, str | bytes):
        if len(start) != len(model.names):
            raise ValueError(f"a start state has one label per state feature {model.names}")
        labels = dict(zip(model.names, start, strict=True))
    else:
        raise ValueError(f"a start is a state or labels of some features, got {start!r}")
    missing = [n for n in features if n not in labels]
    if missing:
        raise ValueError(
            f"the approximate route starts from known values of every relevant feature; the "
            f"start does not name {missing}"
        )
    return labels


class _Backup:
    """``q(s, a)`` from ``v`` over a projected space, one einsum over the step's factors."""

    def __init__(self, model: StepModel, space: ProjectedSpace, held: Mapping[str, int]):
        self.space = space
        self.n_actions = len(model.actions)
        form = product_form(model, space.names, held)
        self.form = form
        self.tables, self.terms, self.sizes = form.tables, form.terms, form.sizes
        self.now, self.act, self.then = form.now, form.act, form.then
        # a small projected space: its (S, A, S) tensor once, then products
        s, a = len(space), self.n_actions
        self.matrix = form.matrix().reshape(s, a, s) if s * a * s <= SMALL_PROJECTION else None

    def __call__(self, v: torch.Tensor) -> torch.Tensor:
        """``q[s, a]``."""
        if self.matrix is not None:
            return self.matrix @ v
        q = chain_product(
            v.reshape(self.sizes), self.then, self.tables, self.terms, self.now + self.act
        )
        return q.reshape(len(self.space), self.n_actions)

    def _forward(self, taken: torch.Tensor) -> torch.Tensor:
        if self.matrix is not None:
            s = len(self.space)
            return (taken.reshape(s * self.n_actions) @ self.matrix.reshape(-1, s)).reshape(
                self.sizes
            )
        return chain_product(taken, self.now + self.act, self.tables, self.terms, self.then)

    def forward(self, mass: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """The next states' mass from ``mass`` ``(S,)``, each state taking ``actions[s]``."""
        taken = torch.zeros(len(self.space), self.n_actions, dtype=DTYPE)
        taken[torch.arange(len(self.space)), actions] = mass
        return self._forward(taken.reshape(*self.sizes, self.n_actions)).reshape(-1)

    def next_states(self, s: int, a: int) -> torch.Tensor:
        """``P(s' | s, a)`` ``(S,)`` for one state and action."""
        point = torch.zeros(len(self.space), self.n_actions, dtype=DTYPE)
        point[s, a] = 1.0
        return self._forward(point.reshape(*self.sizes, self.n_actions)).reshape(-1)

    def unseen(self) -> torch.Tensor:
        """``(S, A)``: the probability each step rests on a configuration no row reached."""
        tables = [t * s for t, s in zip(self.tables, self.form.seen, strict=True)]
        one = torch.ones((), dtype=DTYPE)
        seen = chain_product(one, "", tables, self.terms, self.now + self.act)
        seen = seen.reshape(len(self.space), self.n_actions)
        return (1 - seen).clamp(0, 1)


def _start(model: StepModel, space: ProjectedSpace, start) -> torch.Tensor:
    """The start's distribution over the projected states."""
    if callable(start) and not isinstance(start, Mapping):
        raise ValueError(
            "a predicate start reads every feature: name the start's labels, or plan on "
            "the dense route (route='dense')"
        )
    if isinstance(start, Sequence) and not isinstance(start, str | bytes):
        out = torch.zeros(len(space), dtype=DTYPE)
        out[space.index_of(start)] = 1.0
        return out
    if not isinstance(start, Mapping):
        raise ValueError(f"a start is a state or labels of some features, got {start!r}")
    unknown = [n for n in start if n not in model.names]
    if unknown:
        raise ValueError(f"start names {unknown}, which are not state features {model.names}")
    if all(n in start for n in space.names):
        out = torch.zeros(len(space), dtype=DTYPE)
        out[space.index_of(start)] = 1.0
        return out
    return _prior_over(model, space, start)


def _prior_over(model: StepModel, space: ProjectedSpace, start: Mapping) -> torch.Tensor:
    """``P(projected state | the named labels)`` under the initial-state tables."""
    by_site = {f.site: f for f in model.prior}
    todo = [initial_site(n) for n in (*space.names, *start)]
    kept: dict[str, StepFactor] = {}
    while todo:  # the initial sites' ancestors: the others sum to one
        site = todo.pop()
        if site in kept or site not in by_site:
            continue
        kept[site] = by_site[site]
        todo.extend(by_site[site].scope)
    by_name = {f.name: f for f in model.features}
    fixed = {initial_site(n): state_index(by_name[n], v) for n, v in start.items()}
    free = {q for f in kept.values() for q in f.scope if q not in fixed}
    free |= {initial_site(n) for n in space.names}
    if len(free) > len(EINSUM_LETTERS):
        raise ValueError(
            f"a partial start leaves {len(free)} initial sites to weigh by the initial "
            f"tables, more than {len(EINSUM_LETTERS)}: name more of the start's features"
        )
    letters = Letters()
    tables, terms = [], []
    for f in kept.values():
        tables.append(f.log_table[tuple(fixed.get(q, slice(None)) for q in f.scope)].exp())
        terms.append(letters.term(q for q in f.scope if q not in fixed))
    target = letters.term(initial_site(n) for n in space.names)
    tables += [torch.ones(k, dtype=DTYPE) for k in space.sizes]  # every projected axis kept
    terms += list(target)
    one = torch.ones((), dtype=DTYPE)
    weight = chain_product(one, "", tables, terms, target).reshape(-1)
    for n, v in start.items():
        if n in space.names:
            weight = weight * space.mask({n: v}).to(DTYPE)
    total = weight.sum()
    if not total > 0:
        raise ValueError(f"start {dict(start)!r} has no weight under the initial-state tables")
    return weight / total


def _greedy_path(backup: _Backup, policy, goal, start, horizon, steps):
    """The most likely start, then the most likely next state under the policy, to the goal.

    Within ``steps`` actions.
    """
    s = int(start.argmax())
    p = float(start[s])
    path = [s]
    rows = policy.shape[0] - 1
    for t in range(steps + 1):
        if bool(goal[s]):
            return path, p
        if t == steps:
            break
        a = int(policy[min(horizon - t, rows), s])
        if a < 0:
            break
        after = backup.next_states(s, a)
        s = int(after.argmax())
        p *= float(after[s])
        path += [a, s]
    return (), 0.0


def _rows(exact: ExactPlan, policy: torch.Tensor, horizon: int):
    """Every row up to the horizon where that is small, else the rows up to convergence."""
    if exact.converged is None:
        return exact.value, policy
    s = exact.value.shape[1]
    if (horizon + 1) * s > KEEP_ROWS:
        return exact.value, policy
    more = horizon - exact.converged
    return (
        torch.cat([exact.value, exact.value[-1:].expand(more, s)]),
        torch.cat([policy, policy[-1:].expand(more, s)]),
    )


def _certify(model, relevant, space, policy, goal, start, horizon, episodes, seed) -> Certificate:
    """The policy run ``episodes`` times in the step of the relevant features (exact)."""
    gen = torch.Generator().manual_seed(seed)
    by_name = {f.name: f for f in model.features}
    labels = _full_labels(model, start, relevant)
    state = {
        n: torch.full((episodes,), state_index(by_name[n], labels[n]), dtype=torch.long)
        for n in relevant
    }
    goal_of = _goal_test(model, goal)
    factors = _ancestral(model.step_factors(relevant))
    reached = goal_of(state)
    rows = policy.shape[0] - 1
    radix = [by_name[n].cardinality for n in space.names]
    for t in range(horizon):
        index = torch.zeros(episodes, dtype=torch.long)
        for n, k in zip(space.names, radix, strict=True):
            index = index * k + state[n]
        act = policy[min(horizon - t, rows)][index]
        moving = ~reached & (act >= 0)
        if not bool(moving.any()):
            break
        values = {initial_site(n): state[n] for n in relevant} | {OFFERED: act.clamp_min(0)}
        for f in factors:
            probs = f.log_table[tuple(values[q] for q in f.parents)].exp()
            cdf = probs.cumsum(-1)
            u = torch.rand(episodes, 1, generator=gen, dtype=DTYPE) * cdf[:, -1:]
            values[f.site] = (u >= cdf).sum(-1).clamp_max(probs.shape[-1] - 1)
        state = {n: torch.where(moving, values[end_site(n)], state[n]) for n in relevant}
        reached = reached | (moving & goal_of(state))
    estimate = float(reached.to(DTYPE).mean())
    margin = math.sqrt(math.log(1 / (1 - CONFIDENCE)) / (2 * episodes))
    return Certificate(estimate, max(estimate - margin, 0.0), episodes, CONFIDENCE, seed, math.nan)


def _goal_test(model: StepModel, goal):
    by_name = {f.name: f for f in model.features}
    if isinstance(goal, Mapping):
        wanted = {n: state_index(by_name[n], v) for n, v in goal.items()}

        def test(state):
            out = torch.ones_like(next(iter(state.values())), dtype=torch.bool)
            for n, i in wanted.items():
                out &= state[n] == i
            return out

        return test

    def test_predicate(state):
        n = len(next(iter(state.values())))
        return torch.tensor(
            [bool(goal({f: by_name[f].states[int(state[f][i])] for f in state})) for i in range(n)]
        )

    return test_predicate


def _ancestral(factors: Sequence[StepFactor]) -> list[StepFactor]:
    """The factors in an order where each one's parents come first."""
    out, done = [], set()
    todo = list(factors)
    sites = {f.site for f in factors}
    while todo:
        ready = [f for f in todo if all(q not in sites or q in done for q in f.parents)]
        if not ready:
            raise ValueError("the step's factors form a cycle")
        for f in ready:
            out.append(f)
            done.add(f.site)
        todo = [f for f in todo if f.site not in done]
    return out
