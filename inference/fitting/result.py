"""What a fit returns, and the warning of a fit that stopped before it settled."""

from __future__ import annotations

from dataclasses import dataclass

from effect_networks.models.params import NetworkParams

__all__ = ["ConvergenceWarning", "FitResult"]


@dataclass(frozen=True)
class FitResult:
    """What fitting returns.

    New parameters; for an iterative fit the loss curve (the per-row negative log-likelihood, the
    softmax prior included: at each Newton iteration, EM step or gradient evaluation) and whether it
    settled within the tolerance. EM over missing values also gives ``log_likelihoods``: the summed
    log-likelihood of the rows (missing values summed and integrated out, no prior) at the start and
    after each step, never falling. ``tol`` and ``max_steps``: the stopping rule EM ran under (a
    step that gains less than ``tol``, relative, per row ends it; at most ``max_steps`` steps),
    ``None`` for a fit that is not EM over gaps.
    """

    params: NetworkParams
    losses: tuple[float, ...] = ()
    converged: bool = True
    log_likelihoods: tuple[float, ...] = ()
    tol: float | None = None
    max_steps: int | None = None


class ConvergenceWarning(UserWarning):
    """A gradient fit stopped before its loss settled (the CPDs are named)."""
