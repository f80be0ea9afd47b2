"""What every conditional-distribution kind provides.

A kind is the structure of one site's conditional distribution: the site, its discrete
parents (the axes of its tables), its continuous parents (the inputs of its linear
maps) and its own size. It is frozen and holds no fitted numbers; those live in the
kind's typed container, named for it (``params_type``: ``TableCPD`` fits a
:class:`~models.cpds.table.TableParams`, ...). Like dynamax's emission components, a kind owns everything that depends on its form:

* ``distribution(params, index, x, cache)`` -- the Pyro distribution of the site given
  its discrete parents' values ``index`` (state indices, broadcastable) and its
  continuous parents' values ``x`` ``(..., width)`` (``None`` without any);
* ``initialize(generator)`` -- a neutral start (``generator=None``: uniform tables,
  zero slopes, unit covariances) or a valid random draw;
* ``statistics(index, x, y, weights)`` and ``m_step(stats, alpha, min_variance)`` -- the
  sufficient statistics of rows (they merge by ``+``) and the maximum-likelihood
  parameters they give (closed form, or the start of an iterative fit where
  ``closed_form`` is False);
* optionally, where ``closed_form`` is False, ``maximise(index, x, y, start, weights=,
  l2=, steps=)`` -- the kind's own optimiser on (weighted) rows, which :func:`inference.fit`
  and its EM over missing values use (the softmax's Newton method); a kind without one
  is fitted by the gradient route on complete rows, and refused by EM;
* ``free(params)``, ``bound(free, params)``, ``penalised(free)`` -- the unconstrained
  tensors the gradient route optimises, the parameters they stand for, and the tensors
  that carry the L2 prior;
* ``n_free(reachable)`` -- the number of free parameters (what a likelihood penalty such
  as BIC counts) in the parent configurations ``reachable`` ``(P...)`` bool marks
  (default: all, seen by rows or not), less what the structure fixes;
* ``check(params)`` -- validation against the declared shapes; the save format names
  the container by its class name (the toolkit's own by their names of format 2,
  :data:`models.params.SAVED_NAMES`).

Shapes use ``P...`` for the parents' cardinalities ``card``, ``K`` for a discrete
site's states and ``d`` for a continuous site's dimension (both ``size``), and ``p``
for ``width``, the summed dimension of the continuous parents.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import ClassVar

import torch
from effect_networks.models.dtype import DTYPE


@dataclass(frozen=True)
class CPD:
    """The structure of one site's conditional distribution (see the module)."""

    site: str
    parents: tuple[str, ...]  # discrete parent sites, in table-axis order
    card: tuple[int, ...]  # their numbers of states
    size: int  # states of a discrete site, dimension of a continuous one
    inputs: tuple[str, ...] = ()  # continuous parent sites, concatenated in this order
    width: int = 0  # their summed dimension

    #: the name a declaration and a saved file use for the kind
    name: ClassVar[str] = ""
    #: the typed container of the kind's fitted numbers
    params_type: ClassVar[type]
    #: a discrete child (states) or a continuous one (a vector)
    discrete: ClassVar[bool]
    #: whether ``m_step`` is the maximum-likelihood estimate (else the gradient's start)
    closed_form: ClassVar[bool] = True
    #: a table over discrete parents only (what a discrete Bayesian network holds)
    tabular: ClassVar[bool] = False

    @classmethod
    def refuses(cls, discrete: bool, width: int) -> str | None:
        """Why this kind cannot model a site, or ``None`` if it can.

        The site is discrete or not, with ``width`` continuous inputs.
        """
        if discrete != cls.discrete:
            return f"it models a {'discrete' if cls.discrete else 'continuous'} child"
        return None

    def shapes(self) -> dict[str, tuple[int, ...]]:
        """The shape of every tensor of the kind's container."""
        raise NotImplementedError

    def n_free(self, reachable: torch.Tensor | None = None) -> int:
        """The number of free parameters, less what the structure fixes.

        Counted in the parent configurations ``reachable`` ``(P...)`` bool marks (default: every
        one, reached by rows or not).
        """
        raise NotImplementedError(
            f"site {self.site!r}: the kind {type(self).__name__} does not count its free "
            "parameters; define n_free() to score it"
        )

    def configurations(self, reachable: torch.Tensor | None = None) -> torch.Tensor:
        """The parent configurations ``reachable`` marks, checked for shape.

        ``(P...)`` bool; all by default.
        """
        if reachable is None:
            return torch.ones(self.card, dtype=torch.bool)
        assert reachable.shape == self.card, (self.site, tuple(reachable.shape), self.card)
        return reachable.to(torch.bool)

    def check(self, params: object) -> None:
        """Raise ``ValueError`` unless ``params`` is this kind's container with the declared shapes."""
        kind = self.params_type.__name__
        if type(params) is not self.params_type:
            raise ValueError(
                f"site {self.site!r}: expected {kind} (the numbers of a {self.name!r} site), "
                f"got {type(params).__name__}"
            )
        for name, shape in self.shapes().items():
            got = tuple(getattr(params, name).shape)
            if got != shape:
                raise ValueError(
                    f"site {self.site!r}: {kind}.{name} has shape {got}, expected {shape}"
                )

    def initialize(self, generator: torch.Generator | None = None, unseen: float = 0.0):
        """A neutral start (``generator=None``) or valid random parameters.

        With a generator, ``unseen`` is the share of configurations marked as reached by no row.
        """
        raise NotImplementedError

    def distribution(self, params, index: list[torch.Tensor], x: torch.Tensor | None, cache):
        """The site's Pyro distribution given its parents (see the module)."""
        raise NotImplementedError

    def statistics(
        self,
        index: torch.Tensor,
        x: torch.Tensor | None,
        y: torch.Tensor,
        weights: torch.Tensor | None = None,
    ):
        """Sufficient statistics of rows.

        ``index`` ``(n,)`` the flattened parent configuration, ``x`` ``(n, width)`` or ``None``,
        ``y`` the site's values, ``weights`` ``(n,)`` each row's weight (default 1; fractional in an
        EM step).
        """
        raise NotImplementedError

    def m_step(self, stats, alpha: float, min_variance: float):
        """Parameters from summed statistics under the pseudo-count policy ``alpha``."""
        raise NotImplementedError

    def free(self, params) -> dict[str, torch.Tensor]:
        """Unconstrained tensors standing for ``params`` (the gradient route's variables)."""
        raise NotImplementedError

    def bound(self, free: dict[str, torch.Tensor], params):
        """The parameters ``free`` stands for (``params`` supplies what is not fitted)."""
        raise NotImplementedError

    def penalised(self, free: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        """Tensors that carry the gradient route's L2 prior (none by default)."""
        return []

    def seen(self, params) -> torch.Tensor:
        """``(P...)`` bool: the configurations some training row reached."""
        return params.n > 0

    def noise(self, generator: torch.Generator, shape: tuple[int, ...]) -> torch.Tensor:
        """Standard normal draws (the random initialisation's source)."""
        return torch.randn(shape, generator=generator, dtype=DTYPE)

    def counts_reached(self, generator: torch.Generator, unseen: float) -> torch.Tensor:
        """``n`` for a random initialisation.

        5 rows per configuration, 0 for a share ``unseen`` of them.
        """
        n = torch.rand(self.card, generator=generator, dtype=DTYPE) >= unseen
        return n.to(DTYPE) * 5


def map_tensors(container, fn):
    """A container of the same type with ``fn`` applied to every tensor."""
    return type(container)(**{f.name: fn(getattr(container, f.name)) for f in fields(container)})


def concat_inputs(parts: list[torch.Tensor]) -> torch.Tensor | None:
    """Continuous parents' values side by side ``(..., width)``.

    Broadcast over their batch dims; ``None`` without any.
    """
    if not parts:
        return None
    if len(parts) == 1:
        return parts[0]
    batch = torch.broadcast_shapes(*[p.shape[:-1] for p in parts])
    return torch.cat([p.expand(*batch, p.shape[-1]) for p in parts], dim=-1)
