"""Missing continuous values: the closed-form Gaussian part of EM's E-step.

Given every discrete value of a row (observed, or one completion of the missing ones),
the continuous initial and end sites of the row form a linear-Gaussian network: each is
``y = W x + b + noise`` in its continuous parents ``x`` (initial sites, and the values of
the action parameters, which training rows always give or leave unused), the weights,
offset and noise picked by the discrete parents. Their values are therefore jointly
Gaussian (:func:`joint_gaussian`, built site by site in the network's order). Where some
dimensions are NaN (missing), :func:`condition` gives

* the density of the observed dimensions (the marginal of the joint: the missing ones
  integrated out exactly), which joins the discrete factors of the completion in the
  posterior over completions and in the log-likelihood;
* the conditional mean and covariance of the missing dimensions given the observed ones.

EM's M-step needs, per linear Gaussian, the expected sums ``E[z z^T]``, ``E[z y^T]``,
``E[y y^T]`` (``z = [x, 1]``). They are the sums of the completed row with every missing
value at its conditional mean, plus the conditional covariance of the row's ``z`` and
``y`` (:func:`covariance_moments`): ``E[v v^T] = E[v] E[v]^T + Cov[v]``.

The closed form needs every continuous initial and end site to be a linear Gaussian and
no discrete site to read a missing continuous value (a softmax of a Gaussian has no
closed-form integral): :func:`refuse_open_forms` names the sites where that fails.
"""

from __future__ import annotations

import math

import torch
from effect_networks.models.cpds import LinearGaussianCPD, Moments
from effect_networks.models.cpds.table import flat_index
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.dtype import DTYPE
from effect_networks.models.evidence import Evidence
from effect_networks.models.params import NetworkParams

__all__ = [
    "condition",
    "continuous_gaps",
    "continuous_sites",
    "covariance_moments",
    "joint_gaussian",
    "refuse_open_forms",
]


def continuous_sites(net: EffectNetwork, parameters: bool = False) -> dict[str, slice]:
    """The continuous initial and end sites, each with its dimensions' slice of the joint vector.

    With ``parameters`` the parameters' values too; in the network's order.
    """
    roles = ("initial", "end", "param") if parameters else ("initial", "end")
    out, start = {}, 0
    for spec in net.sites:
        if not spec.discrete and spec.role in roles:
            out[spec.name] = slice(start, start + spec.size)
            start += spec.size
    return out


def continuous_gaps(net: EffectNetwork, enc: Evidence) -> dict[str, torch.Tensor]:
    """``(n, d)`` bool per continuous initial or end site that misses some value (NaN)."""
    return {
        s: torch.isnan(enc[s]) for s in continuous_sites(net) if bool(torch.isnan(enc[s]).any())
    }


def refuse_open_forms(net: EffectNetwork, enc: Evidence, gaps: dict[str, torch.Tensor]) -> None:
    """Refuse what has no closed-form E-step or M-step.

    A kind with neither a closed form nor a ``maximise`` method, a continuous site of a kind other
    than the linear Gaussian, or a discrete site whose continuous parent misses a value.
    """
    if not gaps:
        return
    unfit = [
        s.name
        for s in net.sites
        if not net.cpd(s.name).closed_form
        and not callable(getattr(net.cpd(s.name), "maximise", None))
    ]
    if unfit:
        raise ValueError(
            f"sites {unfit} have neither a closed form nor a maximise method: EM over "
            "missing values has no M-step for them"
        )
    other = [s for s in continuous_sites(net) if not isinstance(net.cpd(s), LinearGaussianCPD)]
    if other:
        kinds = sorted({net.cpd(s).name for s in other})
        raise ValueError(
            f"sites {other} are {'/'.join(kinds)} CPDs: missing continuous values are "
            "integrated out in closed form only where every continuous site is a linear "
            "Gaussian"
        )
    for spec in net.sites:
        if not spec.discrete or spec.role == "cluster":
            continue
        for parent in net.cpd(spec.name).inputs:
            if parent in gaps:
                row = int(gaps[parent].any(-1).nonzero()[0])
                raise ValueError(
                    f"site {parent!r}: row {row} misses a value, and the discrete site "
                    f"{spec.name!r} ({net.cpd(spec.name).name}) depends on it; a discrete "
                    "child of a missing continuous value has no closed-form integral, so "
                    f"such rows cannot be used (drop them, or give {parent!r})"
                )


def joint_gaussian(
    net: EffectNetwork, params: NetworkParams, rows: Evidence, parameters: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """The joint Gaussian of the continuous initial and end sites of each row.

    Given its discrete values (every one given) and its parameters' values: mean ``(n, D)`` and
    covariance ``(n, D, D)``, the sites' dimensions in :func:`continuous_sites` order.

    With ``parameters``, the parameters' values are part of the joint (each its
    cluster's Gaussian), so that an unknown one is integrated out; otherwise they are
    given (NaN where the row's action does not use them). Either way a value counts only
    where the row's action uses it.
    """
    layout = continuous_sites(net, parameters)
    mixtures = {m.value.site: m for m in net.mixtures}
    dim = sum(s.stop - s.start for s in layout.values())
    n = rows.n_rows
    mean = torch.zeros(n, dim, dtype=DTYPE)
    cov = torch.zeros(n, dim, dim, dtype=DTYPE)
    for site, own in layout.items():
        cpd, p = net.cpd(site), params[site]
        index = tuple(rows[q] for q in cpd.parents)
        weight = p.weight[index] if index else p.weight.expand(n, *p.weight.shape)
        shift = (p.bias[index] if index else p.bias.expand(n, -1)).clone()
        tril = p.scale_tril[index] if index else p.scale_tril.expand(n, -1, -1)
        # the site as a linear map of the joint vector (its continuous parents' part)
        # plus a shift (its offset and the parameters' values)
        lift = torch.zeros(n, own.stop - own.start, dim, dtype=DTYPE)
        col = 0
        for q in cpd.inputs:
            k = net.site(q).size
            w = weight[..., col : col + k]
            col += k
            if q in mixtures:  # an action that does not use a parameter ignores it
                w = w * mixtures[q].in_use(rows[ACTION]).to(DTYPE)[:, None, None]
            if q in layout:
                lift[..., layout[q]] += w
            else:  # a parameter's value: given, or NaN where the action does not use it
                shift += (w @ rows[q].nan_to_num()[:, :, None]).squeeze(-1)
        cross = lift @ cov  # the site's covariance with every dimension before it
        mean[:, own] = (lift @ mean[:, :, None]).squeeze(-1) + shift
        cov[:, own, :] = cross
        cov[:, :, own] = cross.mT
        cov[:, own, own] = cross @ lift.mT + tril @ tril.mT
    return mean, cov


def condition(
    mean: torch.Tensor, cov: torch.Tensor, value: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The Gaussian ``N(mean, cov)`` observed where ``value`` ``(n, D)`` is not NaN.

    Returns
    -------
    log_density
        ``(n,)`` the log-density of the observed dimensions' marginal (0 where none is).
    mean
        ``(n, D)`` the conditional mean of every dimension (the value where observed).
    cov
        ``(n, D, D)`` the conditional covariance (zero rows and columns where observed).
    """
    missing = torch.isnan(value)
    observed = ~missing
    both = observed[:, :, None] & observed[:, None, :]
    # the observed block, the missing dimensions' block replaced by the identity: one
    # factorisation per row of any pattern, its inverse the observed block's inverse
    # beside the identity
    padded = torch.where(both, cov, 0.0) + torch.diag_embed(missing.to(DTYPE))
    padded = 0.5 * (padded + padded.mT)
    tril, info = torch.linalg.cholesky_ex(padded)
    if bool((info > 0).any()):
        row = int((info > 0).nonzero()[0])
        raise ValueError(
            f"row {row}: the covariance of its observed continuous values is not positive "
            f"definite ({padded[row].tolist()}); check the fitted noise (min_variance > 0)"
        )
    residual = torch.where(observed, value - mean, 0.0)
    solved = torch.cholesky_solve(residual[:, :, None], tril)  # (n, D, 1)
    half_log_det = tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    log_density = (
        -0.5 * (residual[:, :, None] * solved).sum((-2, -1))
        - half_log_det
        - 0.5 * math.log(2 * math.pi) * observed.sum(-1).to(DTYPE)
    )
    across = torch.where(observed[:, None, :], cov, 0.0)  # Cov(every dim, observed dims)
    post_mean = mean + (across @ solved).squeeze(-1)
    post_mean = torch.where(observed, value, post_mean)
    post_cov = cov - across @ torch.cholesky_solve(across.mT, tril)
    post_cov = torch.where(missing[:, :, None] & missing[:, None, :], post_cov, 0.0)
    return log_density, post_mean, 0.5 * (post_cov + post_cov.mT)


def covariance_moments(
    net: EffectNetwork,
    rows: Evidence,
    cov: torch.Tensor,
    weights: torch.Tensor,
    parameters: bool = False,
) -> dict[str, Moments]:
    """Per continuous initial or end site, the weighted sums of the conditional covariance.

    Of its ``z = [x, 1]`` and ``y`` (``cov`` ``(n, D, D)`` over the joint vector, zero where
    observed): what the expected sums add to those of the row with its missing values at their
    conditional means. With ``parameters`` the joint vector holds the parameters' values too
    (:func:`joint_gaussian`), and their cluster Gaussians get their sums as well (``cov`` zero
    where the row's action does not use the value).
    """
    layout = continuous_sites(net, parameters)
    dim = cov.shape[-1]
    padded = torch.zeros(cov.shape[0], dim + 1, dim + 1, dtype=DTYPE)
    padded[:, :dim, :dim] = cov * weights.to(DTYPE)[:, None, None]  # index dim: zeros
    out = {}
    for site, own in layout.items():
        cpd = net.cpd(site)
        where = []  # each entry of z: its dimension of the joint vector, or dim (fixed)
        for q in cpd.inputs:
            k = net.site(q).size
            where += list(range(layout[q].start, layout[q].stop)) if q in layout else [dim] * k
        z = torch.tensor([*where, dim])
        y = torch.arange(own.start, own.stop)
        groups = math.prod(cpd.card)
        index = flat_index(rows, cpd.parents, cpd.card)
        block = padded[:, :, z]
        zz = torch.zeros(groups, len(z), len(z), dtype=DTYPE).index_add_(0, index, block[:, z])
        zy = torch.zeros(groups, len(z), len(y), dtype=DTYPE).index_add_(
            0, index, padded[:, z][:, :, y]
        )
        yy = torch.zeros(groups, len(y), len(y), dtype=DTYPE).index_add_(
            0, index, padded[:, y][:, :, y]
        )
        out[site] = Moments(zz, zy, yy, torch.zeros(groups, dtype=DTYPE))
    return out
