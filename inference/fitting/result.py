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
    after each step, never falling.
    """

    params: NetworkParams
    losses: tuple[float, ...] = ()
    converged: bool = True
    log_likelihoods: tuple[float, ...] = ()


class ConvergenceWarning(UserWarning):
    """A gradient fit stopped before its loss settled (the CPDs are named)."""
