"""Queries with an unknown continuous initial feature, integrated out in closed form.

A continuous initial site has a density in every network (a linear Gaussian of its
initial parents; by default a Gaussian prior). Given every discrete value of a row (the
evidence's, and one configuration of the enumerated sites), the continuous initial and
end sites form a linear-Gaussian network, hence one joint Gaussian
(:func:`inference.exact.gaussian_gaps.joint_gaussian`); the unknown initial values and
the unobserved end dimensions are integrated out of it exactly. So the model is traced
as for any query, the unknown initial values filled with a placeholder and every
continuous initial and end site's own factor left out, and one factor takes their place:
the density of the observed continuous dimensions per configuration. Each continuous
end site's traced distribution becomes its conditional given the configuration and the
observed values before it: the end sites observed in full in the network's order, then
each other one given all of those and the other observed dimensions (what
:func:`inference.predict` reads for a target, and the plausibility's distances add up
to the joint one; exact where at most one end site is observed in part).

No closed form exists, and the query is refused naming the site, where a discrete site
(a softmax) reads the unknown value, where a continuous site is of a kind other than the
linear Gaussian, or where a parameter's value is unknown in a row whose action may use it
(its integral couples the features it acts on; give the parameter). An unknown initial
feature is one left out of the evidence (every row).
"""

from __future__ import annotations

import pyro.distributions as dist
import torch
from effect_networks.inference.exact.gaussian_gaps import (
    condition,
    continuous_sites,
    joint_gaussian,
)
from effect_networks.inference.exact.traced import Enumerated, enumerate_traced
from effect_networks.models.cpds import LinearGaussianCPD
from effect_networks.models.declaration import ACTION, EffectNetwork
from effect_networks.models.dtype import DTYPE
from effect_networks.models.evidence import Evidence
from effect_networks.models.params import NetworkParams

__all__ = ["enumerate_unknown_initial"]


def enumerate_unknown_initial(
    net: EffectNetwork,
    params: NetworkParams,
    evidence: Evidence,
    unknown: list[str],
    *,
    keep: set[str],
    trace_only: set[str],
    masks,
):
    """:func:`~inference.exact.traced.enumerate_traced` without the continuous initial sites.

    For evidence that leaves the continuous initial sites ``unknown`` out (see the module).
    """
    _refuse_open_forms(net, evidence, unknown)
    layout = continuous_sites(net, parameters=True)
    n = evidence.n_rows
    placeholder = {s: torch.zeros(n, net.site(s).size, dtype=DTYPE) for s in unknown}
    filled = evidence | Evidence(net, placeholder, n)
    # their own factors are the joint Gaussian's (a parameter's value is always traced)
    own = {s for s in layout if s in filled or s in trace_only or net.site(s).role == "param"}
    e = enumerate_traced(net, params, filled, keep=keep, trace_only=trace_only | own, masks=masks)
    # the configurations of the enumerated sites the continuous ones depend on
    parents = {q for s in layout for q in net.cpd(s).parents}
    if net.mixtures:  # whether a parameter counts: its action
        parents.add(ACTION)
    depth = max([-d for d in e.dims.values()], default=1)
    shape = [1] * depth
    for site, d in e.dims.items():
        if site in parents:
            shape[d] = net.site(site).size
    shape[-1] = n
    grid = torch.arange(torch.Size(shape).numel()).reshape(shape)
    rows = evidence.rows(grid.reshape(-1) % n)
    values = {}
    for site, d in e.dims.items():
        if site in parents:
            states = torch.arange(shape[d]).reshape(shape[d], *([1] * (-d - 1)))
            values[site] = states.expand(shape).reshape(-1)
    completed = dict(rows.items()) | dict(net.encode_indices(values).items())
    for s in layout:  # an unknown or unobserved value: NaN, integrated out
        if s not in completed:
            completed[s] = torch.full((grid.numel(), net.site(s).size), torch.nan)
    for m in net.mixtures:
        action = completed[ACTION]
        theta = completed[m.value.site]
        # the value counts where the action uses it (the model leaves its density out
        # elsewhere); a given value without its cluster observes its cell
        completed[m.value.site] = torch.where(m.in_use(action)[:, None], theta, torch.nan)
        if m.cluster.site not in completed:
            completed[m.cluster.site] = m.cells(theta, action)
    completed = Evidence(net, completed, grid.numel())
    mean, cov = joint_gaussian(net, params, completed, parameters=True)
    value = torch.cat([completed[s] for s in layout], -1)
    log_density = condition(mean, cov, value)[0].reshape(shape)
    # each continuous end site in the trace: its conditional given the configuration and
    # the observed values before it (the end sites observed in full, in order, then
    # the others, each given every fully observed one): so the traced densities
    # multiply to the joint one, and the Mahalanobis distances add to the joint's
    full = [s for s in layout if s in evidence and not bool(evidence[s].isnan().any())]
    full = [s for s in full if net.site(s).role == "end"]
    for site, where in layout.items():
        if site in e.trace.nodes and net.site(site).role == "end":
            others = value.clone()
            later = full[full.index(site) :] if site in full else [site]
            for t in later:
                others[:, layout[t]] = torch.nan
            _, post_mean, post_cov = condition(mean, cov, others)
            loc = post_mean[:, where].reshape(*shape, -1)
            c = post_cov[:, where, where].reshape(*shape, where.stop - where.start, -1)
            e.trace.nodes[site]["fn"] = dist.MultivariateNormal(loc, covariance_matrix=c)
    offset = log_density.reshape(-1, n).amax(0)
    offset = torch.where(torch.isfinite(offset), offset, 0.0)
    factors = (*e.factors, log_density - offset)
    offsets = e.offsets | {"unknown initial": offset}
    return Enumerated(factors, e.dims, e.trace, offsets, n)


def _refuse_open_forms(net: EffectNetwork, evidence: Evidence, unknown: list[str]) -> None:
    """Refuse what has no closed-form integral over the unknown initial values."""
    for spec in net.sites:
        cpd = net.cpd(spec.name) if spec.role in ("initial", "end") else None
        if cpd is None:
            continue
        read = [q for q in cpd.inputs if q in unknown]
        if spec.discrete and read:
            raise ValueError(
                f"queries need the initial state of {read} here: the discrete site "
                f"{spec.name!r} ({cpd.name}) depends on it, and a softmax of an unknown "
                "Gaussian value has no closed-form integral; give it in the evidence"
            )
    other = [s for s in continuous_sites(net) if not isinstance(net.cpd(s), LinearGaussianCPD)]
    if other:
        raise ValueError(
            f"queries need the initial state of {unknown} here: sites {other} are not "
            "linear Gaussians, so the unknown value has no closed-form integral"
        )
