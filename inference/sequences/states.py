"""A network's state space.

The discrete features that have both an initial and an end node, their joint states enumerated as
label tuples.

A state is one label per state feature, in the network's feature order: in a door world
with ``door`` in (``"shut"``, ``"open"``) and ``lock`` in (``"off"``, ``"on"``), the states
are ``("shut", "off")``, ``("shut", "on")``, ``("open", "off")``, ``("open", "on")``, the
last feature varying fastest. Where only some of the product's states occur (the can
world's physically possible configurations, each with its count), the space is built
from those alone (``states=``); every question over states (transitions, plans,
demonstrations) then works on that list, in its order.

:class:`StateSpace` turns states into indices and back, and a partial assignment (labels
of some features) or a predicate over states into a mask or a distribution over the
space.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Hashable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from effect_networks.models.declaration import DTYPE, Discrete, EffectNetwork

#: The most states a space enumerates from the product of its features' states; past it
#: the caller names the states it needs (``states=``).
MAX_STATES = 1 << 16

State = tuple[Hashable, ...]
#: What a caller may give for states: a label tuple (feature order) or ``{feature: label}``.
StateLike = Sequence[Hashable] | Mapping[str, Hashable]
#: What selects states: labels of some features, or a predicate on a state's labels.
Selection = Mapping[str, Hashable] | Callable[[Mapping[str, Hashable]], bool]


def state_features(net: EffectNetwork) -> tuple[Discrete, ...]:
    """The features that make a network's state.

    Discrete, with an initial node (every declared feature has an end node), in declaration order.
    """
    return tuple(f for f in net.features if isinstance(f, Discrete) and f.initial)


@dataclass(frozen=True)
class StateSpace:
    """The states of a network, each a tuple of labels, one per state feature.

    Build it with :meth:`of`. ``index`` ``(S, F)`` long holds each state's state index per
    feature (row ``i`` is state ``i``).

    Examples
    --------
    >>> from models import Discrete, EffectNetwork
    >>> net = EffectNetwork(
    ...     features=(Discrete("door", ("shut", "open")), Discrete("lock", ("off", "on"))),
    ...     actions=("push", "unlock"),
    ... )
    >>> space = StateSpace.of(net)
    >>> space.states
    (('shut', 'off'), ('shut', 'on'), ('open', 'off'), ('open', 'on'))
    >>> space.index_of({"door": "open", "lock": "on"})
    3
    >>> space.mask({"door": "shut"}).tolist()
    [True, True, False, False]
    """

    features: tuple[Discrete, ...]
    states: tuple[State, ...]
    index: torch.Tensor = field(repr=False, compare=False)
    _position: dict[State, int] = field(repr=False, compare=False)

    @classmethod
    def of(
        cls,
        net: EffectNetwork,
        states: Iterable[StateLike] | None = None,
        *,
        stateless: bool = False,
    ) -> StateSpace:
        """The state space of ``net``.

        Every combination of its state features' states (the last feature fastest), or only
        ``states`` (label tuples in feature order or ``{feature: label}`` mappings, each naming
        every state feature), in their order.

        ``stateless=True`` gives a network without a state feature its one state ``()``
        (a demonstration of such a network is still a sequence of actions); without it
        such a network is refused, since there is nothing to plan over.

        Raises
        ------
        ValueError
            The network has no state feature (and not ``stateless``); a state names an
            unknown feature or label,
            misses a feature, or is repeated; the product exceeds :data:`MAX_STATES`
            (then pass ``states=``).
        """
        features = state_features(net)
        if not features and stateless and states is None:
            return cls((), ((),), torch.zeros(1, 0, dtype=torch.long), {(): 0})
        if not features:
            raise ValueError(
                "the network has no state: no discrete feature with an initial node "
                f"(features: {[f.name for f in net.features]})"
            )
        if states is None:
            size = math.prod(f.cardinality for f in features)
            if size > MAX_STATES:
                raise ValueError(
                    f"the state space of {[f.name for f in features]} has {size} states, "
                    f"more than {MAX_STATES}: pass states= (the states that occur), or keep the "
                    "step factored (step_model; plan does by itself)"
                )
            index = list(itertools.product(*(range(f.cardinality) for f in features)))
        else:
            if isinstance(states, str | bytes | Mapping):
                raise ValueError(
                    f"states must be a sequence of states, got {states!r}; one state is "
                    "written [state]"
                )
            index = [_indices(features, s) for s in states]
            if not index:
                raise ValueError("states is empty: name at least one state")
            seen: dict[tuple, int] = {}
            for i, ix in enumerate(index):
                if ix in seen:
                    raise ValueError(
                        f"states[{i}] repeats states[{seen[ix]}]: {_labels(features, ix)}"
                    )
                seen[ix] = i
        labels = tuple(_labels(features, ix) for ix in index)
        tensor = torch.tensor(index, dtype=torch.long).reshape(len(index), len(features))
        return cls(features, labels, tensor, {s: i for i, s in enumerate(labels)})

    # ------------------------------------------------------------------ reading
    @property
    def names(self) -> tuple[str, ...]:
        """The state features' names, in label order."""
        return tuple(f.name for f in self.features)

    def __len__(self) -> int:
        return len(self.states)

    def __iter__(self) -> Iterator[State]:
        return iter(self.states)

    def __contains__(self, state: object) -> bool:
        try:
            self.index_of(state)  # type: ignore[arg-type]
        except ValueError:
            return False
        return True

    def labels(self, i: int) -> dict[str, Hashable]:
        """State ``i`` as ``{feature: label}``."""
        return dict(zip(self.names, self.states[i], strict=True))

    def index_of(self, state: StateLike | int) -> int:
        """The index of a state, checked.

        The state is given as a label tuple, a ``{feature: label}`` mapping naming every state
        feature, or an index.
        """
        if isinstance(state, int) and not isinstance(state, bool):
            if not 0 <= state < len(self):
                raise ValueError(f"state index {state} outside 0..{len(self) - 1}")
            return state
        labels = _labels(self.features, _indices(self.features, state))
        try:
            return self._position[labels]
        except KeyError:
            raise ValueError(
                f"state {labels} is not in this state space ({len(self)} states given)"
            ) from None

    # ---------------------------------------------------------------- selecting
    def mask(self, selection: Selection) -> torch.Tensor:
        """``(S,)`` bool: the states that ``selection`` picks.

        Labels of some features (``{"door": "open"}``: every state whose door is open) or a
        predicate called with each state's ``{feature: label}``.
        """
        if callable(selection) and not isinstance(selection, Mapping):
            out = [bool(selection(self.labels(i))) for i in range(len(self))]
            return torch.tensor(out, dtype=torch.bool)
        if not isinstance(selection, Mapping):
            raise ValueError(
                f"a selection of states is a mapping feature -> label or a predicate on a "
                f"state's labels, got {selection!r}"
            )
        keep = torch.ones(len(self), dtype=torch.bool)
        for name, label in selection.items():
            j = self._feature(name)
            keep &= self.index[:, j] == state_index(self.features[j], label)
        return keep

    def distribution(
        self, selection: Selection | StateLike, prior: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``(S,)`` float64: the states ``selection`` picks, weighted and normalised.

        ``selection`` is a partial assignment, a full state or a predicate; weighted by ``prior``
        ``(S,)`` (uniform by default) and normalised. ``ValueError`` if it picks no state of
        positive weight.
        """
        if isinstance(selection, Sequence) and not isinstance(selection, str | bytes):
            keep = torch.zeros(len(self), dtype=torch.bool)
            keep[self.index_of(selection)] = True
        else:
            keep = self.mask(selection)  # type: ignore[arg-type]
        weight = torch.ones(len(self), dtype=DTYPE) if prior is None else prior.to(DTYPE)
        if weight.shape != (len(self),) or bool((weight < 0).any()):
            raise ValueError(
                f"prior must be ({len(self)},) non-negative, got {tuple(weight.shape)}"
            )
        weight = torch.where(keep, weight, 0.0)
        total = weight.sum()
        if not total > 0:
            raise ValueError(
                f"{selection!r} picks no state of this space with positive weight "
                f"(features {self.names}, {len(self)} states)"
            )
        return weight / total

    def _feature(self, name: str) -> int:
        if name not in self.names:
            raise ValueError(
                f"{name!r} is not a state feature; the state features are {self.names}"
            )
        return self.names.index(name)


def state_index(feature: Discrete, label: Hashable) -> int:
    """The index of ``label`` among ``feature``'s states (``ValueError`` naming them)."""
    for i, s in enumerate(feature.states):  # by type too: 1 is not True
        if s == label and type(s) is type(label):
            return i
    if label in feature.states:
        return feature.states.index(label)
    raise ValueError(
        f"feature {feature.name!r} has no state {label!r}; its states are {feature.states}"
    )


def _indices(features: tuple[Discrete, ...], state: StateLike) -> tuple[int, ...]:
    names = tuple(f.name for f in features)
    if isinstance(state, Mapping):
        unknown = sorted(set(state) - set(names), key=str)
        missing = [n for n in names if n not in state]
        if unknown or missing:
            raise ValueError(
                f"state {dict(state)!r} must name exactly the state features {names} "
                f"(unknown: {unknown}, missing: {missing})"
            )
        state = tuple(state[n] for n in names)
    if isinstance(state, str | bytes) or not isinstance(state, Sequence):
        raise ValueError(
            f"a state is a tuple of labels for {names} or a mapping feature -> label, got {state!r}"
        )
    if len(state) != len(features):
        raise ValueError(f"state {tuple(state)!r} needs one label for each of {names}")
    return tuple(state_index(f, s) for f, s in zip(features, state, strict=True))


def _labels(features: tuple[Discrete, ...], index: tuple[int, ...]) -> State:
    return tuple(f.states[i] for f, i in zip(features, index, strict=True))


@dataclass(frozen=True)
class ProjectedSpace:
    """The joint states of some of the state features: a projection of the full space.

    A plan whose goal reads a few features needs only them and the features their next
    values depend on (:meth:`~inference.sequences.factored_steps.StepModel.relevant`); its
    states are the combinations of those, numbered in mixed radix (the last feature
    fastest), never listed. A full state (every state feature's label, as a tuple or a
    mapping) is read by its projected features' labels; so is a mapping naming at least
    them, or a tuple of the projected features' labels alone.

    Examples
    --------
    >>> from effect_networks.models import Discrete
    >>> door, lock, light = (Discrete(n, (0, 1)) for n in ("door", "lock", "light"))
    >>> space = ProjectedSpace((door, light), (door, lock, light))
    >>> len(space), space.index_of((1, 0, 1)), space.state(3)
    (4, 3, (1, 1))
    """

    features: tuple[Discrete, ...]
    all_features: tuple[Discrete, ...]

    @property
    def names(self) -> tuple[str, ...]:
        """The projected features' names."""
        return tuple(f.name for f in self.features)

    @property
    def sizes(self) -> tuple[int, ...]:
        """The projected features' numbers of states."""
        return tuple(f.cardinality for f in self.features)

    def __len__(self) -> int:
        return math.prod(self.sizes)

    def state(self, i: int) -> State:
        """State ``i``'s labels, one per projected feature."""
        digits = []
        for k in reversed(self.sizes):
            i, d = divmod(i, k)
            digits.append(d)
        return _labels(self.features, tuple(reversed(digits)))

    @property
    def states(self) -> Iterator[State]:
        """Every projected state's labels, in index order (generated, not stored)."""
        return (self.state(i) for i in range(len(self)))

    def labels(self, i: int) -> dict[str, Hashable]:
        """State ``i`` as ``{feature: label}``."""
        return dict(zip(self.names, self.state(i), strict=True))

    def index_of(self, state: StateLike | int) -> int:
        """The index of a state's projection (a full state, or the projected labels)."""
        if isinstance(state, int) and not isinstance(state, bool):
            if not 0 <= state < len(self):
                raise ValueError(f"state index {state} outside 0..{len(self) - 1}")
            return state
        if isinstance(state, Mapping):
            missing = [n for n in self.names if n not in state]
            unknown = sorted(set(state) - {f.name for f in self.all_features}, key=str)
            if missing or unknown:
                raise ValueError(
                    f"state {dict(state)!r} must name the features {self.names} (missing: "
                    f"{missing}) and only state features (unknown: {unknown})"
                )
            labels = tuple(state[n] for n in self.names)
        elif isinstance(state, Sequence) and not isinstance(state, str | bytes):
            if len(state) == len(self.all_features):
                full = dict(zip((f.name for f in self.all_features), state, strict=True))
                labels = tuple(full[n] for n in self.names)
            elif len(state) == len(self.features):
                labels = tuple(state)
            else:
                raise ValueError(
                    f"state {tuple(state)!r} needs one label for each state feature "
                    f"{tuple(f.name for f in self.all_features)} (or each of {self.names})"
                )
        else:
            raise ValueError(f"a state is a tuple of labels or a mapping, got {state!r}")
        index = 0
        for f, label in zip(self.features, labels, strict=True):
            index = index * f.cardinality + state_index(f, label)
        return index

    def digits(self) -> torch.Tensor:
        """``(S, F)`` long: every projected state's index per feature."""
        grids = torch.meshgrid(*(torch.arange(k) for k in self.sizes), indexing="ij")
        return torch.stack([g.reshape(-1) for g in grids], -1).reshape(len(self), -1)

    def mask(self, selection: Selection) -> torch.Tensor:
        """``(S,)`` bool: the projected states ``selection`` picks.

        Labels of some projected features, or a predicate on a state's ``{feature: label}``.
        """
        if callable(selection) and not isinstance(selection, Mapping):
            return torch.tensor([bool(selection(self.labels(i))) for i in range(len(self))])
        if not isinstance(selection, Mapping):
            raise ValueError(
                f"a selection is a mapping feature -> label or a predicate, got {selection!r}"
            )
        digits = self.digits()
        keep = torch.ones(len(self), dtype=torch.bool)
        for name, label in selection.items():
            if name not in self.names:
                raise ValueError(f"{name!r} is not one of the features {self.names}")
            j = self.names.index(name)
            keep &= digits[:, j] == state_index(self.features[j], label)
        return keep
