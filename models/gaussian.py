"""Closed-form Gaussian identities the model and the queries share.

For ``theta ~ N(m, S)`` and ``y = W theta + b + e`` with ``e ~ N(0, R)``:

* marginal: ``y ~ N(W m + b, W S W^T + R)``
* posterior: ``theta | y ~ N(m + K (y - W m - b), S - K W S)``, ``K = S W^T (W S W^T + R)^-1``

All functions broadcast over leading batch dims.
"""

from __future__ import annotations

import torch


def linear_gaussian_marginal(
    mean: torch.Tensor,
    cov: torch.Tensor,
    weight: torch.Tensor,
    offset: torch.Tensor,
    noise_cov: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean ``(..., d)`` and covariance ``(..., d, d)`` of ``y = W theta + b + e``."""
    loc = (weight @ mean.unsqueeze(-1)).squeeze(-1) + offset
    return loc, weight @ cov @ weight.mT + noise_cov


def condition_linear_gaussian(
    mean: torch.Tensor,
    cov: torch.Tensor,
    weight: torch.Tensor,
    offset: torch.Tensor,
    noise_cov: torch.Tensor,
    y: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Posterior mean ``(..., k)`` and covariance ``(..., k, k)`` of ``theta`` given ``y``."""
    y_loc, y_cov = linear_gaussian_marginal(mean, cov, weight, offset, noise_cov)
    cross = cov @ weight.mT  # (..., k, d)
    chol = torch.linalg.cholesky(y_cov)
    gain = torch.cholesky_solve(cross.mT, chol).mT  # S W^T (W S W^T + R)^-1
    post_mean = mean + (gain @ (y - y_loc).unsqueeze(-1)).squeeze(-1)
    post_cov = cov - gain @ weight @ cov
    return post_mean, 0.5 * (post_cov + post_cov.mT)
