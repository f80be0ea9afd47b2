"""A parameter's clusters drawn as their Gaussians.

Ellipses over the value (or over the value and an affected feature), intervals for a
one-dimensional value, over the training rows.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from effect_networks.inference.plots._common import new_axes
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.params import NetworkParams, check_params


def _ellipse(mean, cov, sigma: float, **style):
    """The ``sigma``-contour of a 2-D Gaussian as an Ellipse patch."""
    from matplotlib.patches import Ellipse

    values, vectors = np.linalg.eigh(np.asarray(cov, dtype=float))
    angle = math.degrees(math.atan2(vectors[1, -1], vectors[0, -1]))
    width, height = 2 * sigma * np.sqrt(np.clip(values[::-1], 0.0, None))
    return Ellipse(tuple(mean), width, height, angle=angle, **style)


def _column(data: Mapping, site: str, dim: int) -> np.ndarray:
    if site not in data:
        raise ValueError(f"data has no {site!r}; it gives {sorted(data)}")
    value = data[site]
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu()
    return np.asarray(value, dtype=float).reshape(len(value), -1)[:, dim]


def _joint(net, params, m, feature: str, given: Mapping, dims: tuple[int, int]):
    """Per cluster, the joint Gaussian of a value's dimension and a feature's.

    The value's dimension ``dims[0]`` and the feature's dimension ``dims[1]``, the
    feature's other parents fixed at ``given``: ``theta ~ N(m_c, S_c)``,
    ``y = W_x x + W_p theta + b + e``, so the cross covariance is ``W_p S_c`` and ``y``'s
    covariance ``R + W_p S_c W_p^T``.
    """
    site = f"end.{feature}"
    if net.acting_on(site) != (m,):
        raise ValueError(
            f"feature {feature!r}: several parameters act on it "
            f"({[a.parameter.name for a in net.acting_on(site)]}); its joint with one of "
            "them depends on the others"
        )
    child = net.cpd(site)
    actions = [a for a in m.parameter.actions]
    given = dict(given)
    given.setdefault(ACTION, actions[0])
    if given[ACTION] not in actions:
        raise ValueError(
            f"given action {given[ACTION]!r} does not use parameter {m.parameter.name!r}; "
            f"its actions are {actions}"
        )
    others = child.parents[:-1] + child.inputs[:-1]
    unknown = [s for s in given if s not in others]
    if unknown:
        raise ValueError(
            f"given names {unknown}, which are not parents of {site!r}; its parents other "
            f"than the parameter's sites are {list(others)}"
        )
    needed = [p for p in others if p not in given]
    if needed:
        raise ValueError(
            f"feature {feature!r} also depends on {needed}; give their values in `given` "
            "(labels for discrete sites, numbers for continuous ones)"
        )
    index = {p: int(net.encode({p: [given[p]]})[p][0]) for p in child.parents[:-1]}
    cpd, prior = params[site], params[m.value.site]
    x = []
    for s in child.inputs[:-1]:
        value = torch.as_tensor(given[s], dtype=cpd.weight.dtype).reshape(-1)
        if value.shape[0] != net.site(s).size:
            raise ValueError(
                f"given {s!r} has {value.shape[0]} numbers; the site has dimension "
                f"{net.site(s).size}"
            )
        x.append(value)
    k = m.parameter.dim
    i, j = dims
    out, slopes = [], []
    for c in range(m.parameter.n_clusters):
        at = (*index.values(), c)
        weight, bias, noise = cpd.weight[at], cpd.bias[at], cpd.covariance[at]
        w_x, w_p = weight[:, : weight.shape[-1] - k], weight[:, weight.shape[-1] - k :]
        mean_theta, cov_theta = prior.bias[c], prior.covariance[c]
        mean_y = bias + w_p @ mean_theta + (w_x @ torch.cat(x) if x else 0.0)
        cov_y = noise + w_p @ cov_theta @ w_p.mT
        cross = (w_p @ cov_theta)[j, i]
        mean = [float(mean_theta[i]), float(mean_y[j])]
        cov = [[float(cov_theta[i, i]), float(cross)], [float(cross), float(cov_y[j, j])]]
        out.append((mean, cov))
        slopes.append(np.asarray(w_x[j], dtype=float))
    x_given = np.asarray(torch.cat(x), dtype=float) if x else np.zeros(0)
    return out, index, np.stack(slopes), x_given


def _feature_rows(net, params, m, feature, data, index, dims, slopes, x_given):
    """The rows of ``data`` whose action and discrete parents have the states ``index``.

    The value's dimension ``dims[0]`` and the feature's ``dims[1]``, the latter moved to
    the given continuous inputs along the fitted slope of the row's cluster,
    ``y + W_x (x_given - x)`` (the row's cluster: from ``data``, else the value's cell
    under the grid layout, else the cluster most probable for the value).
    """
    site = f"end.{feature}"
    rows = np.ones(len(_column(data, m.value.site, 0)), dtype=bool)
    for s, state in index.items():
        if s in data:
            rows &= net.encode({s: data[s]})[s].numpy() == state
    theta = _column(data, m.value.site, dims[0])[rows]
    y = _column(data, site, dims[1])[rows]
    if not x_given.size:
        return theta, y
    inputs = net.cpd(site).inputs[:-1]
    x = np.concatenate(
        [np.stack([_column(data, s, d) for d in range(net.site(s).size)], 1) for s in inputs], 1
    )[rows]
    value = np.stack([_column(data, m.value.site, d) for d in range(m.parameter.dim)], 1)[rows]
    if m.cluster.site in data:
        cluster = np.asarray(data[m.cluster.site], dtype=int)[rows]
    elif not m.parameter.adaptive:
        cluster = m.parameter.cluster_of(torch.as_tensor(value)).numpy()
    else:
        prior = params[m.value.site]
        a = index[ACTION]
        density = torch.distributions.MultivariateNormal(prior.bias, scale_tril=prior.scale_tril)
        logs = density.log_prob(torch.as_tensor(value)[:, None, :])
        logs = logs + params[m.cluster.site].probs[a].clamp_min(1e-300).log()
        cluster = logs.argmax(-1).numpy()
    return theta, y + np.einsum("nq,nq->n", slopes[cluster], x_given - x)


def plot_clusters(
    net: EffectNetwork,
    params: NetworkParams,
    parameter: str,
    data: Mapping[str, object] | None = None,
    ax=None,
    *,
    feature: str | None = None,
    given: Mapping[str, object] | None = None,
    dims: tuple[int, int] | None = None,
    sigmas: Sequence[float] = (1.0, 2.0),
):
    """Draw a parameter's clusters: each cluster's Gaussian over the parameter's value.

    Without ``feature``: over the value itself, one ellipse per cluster and sigma over the
    value's dimensions ``dims`` (a value of two or more dimensions), or one interval
    ``mean +- sigma * sd`` per cluster and sigma, a row per cluster (a one-dimensional
    value). With ``feature``: over the value's dimension ``dims[0]`` and the affected
    continuous feature's dimension ``dims[1]``, the joint of the cluster's Gaussian and
    the feature's linear Gaussian, one ellipse per cluster and sigma. Under the grid
    layout the cells' edges are drawn too (lines whose ``gid`` is ``"cell edge"``); a
    cluster no training row reached is dashed.

    Parameters
    ----------
    net : EffectNetwork
        The declaration ``params`` were fitted for.
    params : NetworkParams
        Fitted numbers (:func:`inference.fit` or, for the adaptive layout,
        :func:`inference.fit_em`).
    parameter : str
        The parameter's name (not its site's).
    data : mapping, optional
        Rows by site name as :func:`inference.fit` reads them (:func:`inference.simulate`
        draws such rows): ``param.<parameter>`` ``(n, d)``, NaN where the action does not
        use it, and with ``feature`` also ``end.<feature>``; drawn as points (rows with a
        NaN value left out). With ``feature``: the rows whose action and discrete parents
        are the ones given, each moved to the given continuous parents along its
        cluster's fitted slope (``y + W_x (x_given - x)``), so that they scatter as the
        ellipses' Gaussians do.
    ax : matplotlib.axes.Axes, optional
        Where to draw; a new figure when ``None``.
    feature : str, optional
        A continuous feature the parameter acts on (alone).
    given : mapping, optional
        With ``feature``: the feature's other parents' values (labels for discrete sites,
        numbers for continuous ones); ``action`` defaults to the first action using the
        parameter.
    dims : (int, int), optional
        The dimensions drawn (see above); ``(0, 1)`` by default, ``(0, 0)`` with
        ``feature``.
    sigmas : sequence of float
        The contours drawn, in standard deviations.

    Returns
    -------
    matplotlib.axes.Axes
        The axes, with ``n_clusters * len(sigmas)`` patches: Ellipses in two dimensions,
        Rectangles for the intervals of a one-dimensional value.

    Raises
    ------
    ValueError
        Naming the parameter, feature, site or dimension that is not known, a feature the
        parameter does not act on alone, or a parent of the feature left out of ``given``;
        or if ``params`` do not fit ``net`` (:func:`models.params.check_params`).
    """
    check_params(net, params)
    m = net.mixture(parameter)
    p = m.parameter
    prior = params[m.value.site]
    means = np.asarray(prior.bias.detach().cpu(), dtype=float)
    covs = np.asarray(prior.covariance.detach().cpu(), dtype=float)
    dashed = np.asarray(prior.n.detach().cpu()) == 0  # clusters no training row reached
    edges = [np.linspace(lo, hi, b + 1) for lo, hi, b in zip(p.low, p.high, p.bins, strict=True)]
    if feature is None and given is not None:
        raise ValueError("given names the parents of an affected feature; pass it with feature=")
    if feature is None and p.dim == 1:
        ax = _intervals(new_axes(ax), m, means[:, 0], np.sqrt(covs[:, 0, 0]), data, sigmas, dashed)
        cells = (edges[0], ())
    elif feature is None:
        dims = (0, 1) if dims is None else dims
        _check_dims(parameter, dims, (p.dim, p.dim), None)
        i, j = dims
        gaussians = [(means[c, [i, j]], covs[c][np.ix_([i, j], [i, j])]) for c in range(len(means))]
        points = None if data is None else [_column(data, m.value.site, d) for d in dims]
        ax = _ellipses(new_axes(ax), gaussians, points, sigmas, dashed)
        ax.set_xlabel(f"{m.value.site}[{i}]")
        ax.set_ylabel(f"{m.value.site}[{j}]")
        cells = (edges[i], edges[j])
    else:
        site = f"end.{feature}"
        if site not in m.continuous:
            raise ValueError(
                f"feature {feature!r}: parameter {parameter!r} acts on the continuous "
                f"sites {list(m.continuous)} only"
            )
        dims = (0, 0) if dims is None else dims
        _check_dims(parameter, dims, (p.dim, net.site(site).size), feature)
        gaussians, index, slopes, x_given = _joint(net, params, m, feature, given or {}, dims)
        points = None
        if data is not None:
            points = _feature_rows(net, params, m, feature, data, index, dims, slopes, x_given)
        ax = _ellipses(new_axes(ax), gaussians, points, sigmas, dashed)
        ax.set_xlabel(f"{m.value.site}[{dims[0]}]")
        ax.set_ylabel(f"{site}[{dims[1]}]")
        ax.set_title(f"{m.cluster.site} given action = {net.actions[index[ACTION]]}", fontsize=9)
        cells = (edges[dims[0]], ())
    if not p.adaptive:
        for edge in cells[0]:
            ax.axvline(edge, color="0.85", linewidth=0.6, zorder=0, gid="cell edge")
        for edge in cells[1]:
            ax.axhline(edge, color="0.85", linewidth=0.6, zorder=0, gid="cell edge")
    ax.autoscale_view()
    return ax


def _style(c: int, sigma: float, dashed: np.ndarray) -> dict:
    return {
        "facecolor": "none",
        "edgecolor": f"C{c % 10}",
        "linestyle": "--" if dashed[c] else "-",
        "linewidth": 1.5 / sigma,
    }


def _ellipses(ax, gaussians, points, sigmas, dashed):
    """One ellipse per 2-D Gaussian and sigma, numbered, over ``points`` (x, y) if any."""
    if points is not None:
        ax.scatter(*points, s=6, c="0.5", alpha=0.5, linewidths=0)
    for c, (mean, cov) in enumerate(gaussians):
        for sigma in sigmas:
            ax.add_patch(_ellipse(mean, cov, sigma, **_style(c, sigma, dashed)))
        ax.text(*mean, str(c), color=f"C{c % 10}", ha="center", va="center", fontsize=8)
    return ax


def _intervals(ax, m, means, sds, data, sigmas, dashed):
    """One interval ``mean +- sigma * sd`` per cluster and sigma, a row per cluster.

    The rows' values are drawn as a rug in a row below.
    """
    from matplotlib.patches import Rectangle

    for c, (mean, sd) in enumerate(zip(means, sds, strict=True)):
        for sigma in sigmas:
            corner = (mean - sigma * sd, c - 0.3)
            ax.add_patch(Rectangle(corner, 2 * sigma * sd, 0.6, **_style(c, sigma, dashed)))
        ax.plot(mean, c, "o", color=f"C{c % 10}", markersize=4)
    ticks = [str(c) for c in range(len(means))]
    if data is not None:
        theta = _column(data, m.value.site, 0)
        theta = theta[~np.isnan(theta)]
        ax.plot(theta, np.full_like(theta, -1.0), "|", color="0.4", alpha=0.5)
        ticks = ["rows", *ticks]
    ax.set_yticks(range(len(means) - len(ticks), len(means)), ticks)
    ax.set_ylabel(m.cluster.site)
    ax.set_xlabel(m.value.site)
    return ax


def _check_dims(parameter: str, dims, sizes: tuple[int, int], feature: str | None) -> None:
    names = (f"parameter {parameter!r}", f"feature {feature!r}" if feature else None)
    if len(dims) != 2:
        raise ValueError(f"dims must be two dimensions, got {dims!r}")
    for d, size, name in zip(dims, sizes, (names[0], names[1] or names[0]), strict=True):
        if not 0 <= d < size:
            raise ValueError(f"dims {tuple(dims)}: {name} has dimensions 0..{size - 1}")
    if feature is None and dims[0] == dims[1]:
        raise ValueError(f"dims {tuple(dims)}: name two different dimensions of {names[0]}")
