"""What every query does with its evidence rows before it answers.

The evidence checked and encoded (:func:`prepare`), the actions a row permits
(:func:`allowed_actions`), the placeholder row that stands in for empty evidence and the
answer cut back to zero rows (:func:`placeholder_row`, :func:`no_rows`), the tie rule for a
best answer (:func:`first_best`, :data:`TIE_TOLERANCE`), the posterior mass on
configurations no training row reached (:func:`unseen_indicator`), and the checks shared by
the two queries about an unknown parameter, the parameter posterior and the inverse model
(:func:`check_parameter_evidence`, :func:`given_other_parameters`,
:func:`parameter_placeholder`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields, is_dataclass, replace

import numpy as np
import torch
from effect_networks.inference.exact.traced import Enumerated
from effect_networks.models.cpds.table import gather
from effect_networks.models.declaration import (
    ACTION,
    DTYPE,
    EffectNetwork,
    cluster_site,
    param_site,
)
from effect_networks.models.evidence import Evidence
from effect_networks.models.params import NetworkParams, check_params

#: relative: scores this close to the maximum count as tied
TIE_TOLERANCE = 1e-9


def first_best(score: torch.Tensor, top: torch.Tensor | None = None) -> torch.Tensor:
    """``(n,)`` index of the best score per row; among ties the lowest index.

    Ties are within a relative ``TIE_TOLERANCE`` of the maximum, so that rounding does not decide.
    ``top``: the rows' maxima ``(n,)``, if already known.
    """
    top = score.max(-1).values if top is None else top
    return (score >= (top - TIE_TOLERANCE * top.abs())[:, None]).int().argmax(-1)


def prepare(net: EffectNetwork, params: NetworkParams, evidence: Mapping[str, object]) -> Evidence:
    """``evidence`` encoded by ``net`` after ``params`` are checked against it.

    A ``ValueError`` for evidence with no rows.
    """
    check_params(net, params)
    enc = net.encode(evidence)
    if not len(enc):
        raise ValueError("evidence is empty: give at least the initial state")
    return enc


def allowed_actions(net: EffectNetwork, allowed: object, n: int) -> torch.Tensor | None:
    """``allowed`` as an ``(A,)`` or ``(n, A)`` bool mask with at least one action per row.

    Accepts ``None``, a bool mask ``(A,)`` or ``(n, A)``, or a collection of action names.
    """
    if allowed is None:
        return None
    a = len(net.actions)
    if isinstance(allowed, str):
        allowed = [allowed]
    if not isinstance(allowed, torch.Tensor) and all(isinstance(x, str) for x in allowed):
        mask = torch.zeros(a, dtype=torch.bool)
        for name in allowed:
            mask[net.action_index(name)] = True
    else:
        mask = torch.as_tensor(
            np.asarray(allowed) if not isinstance(allowed, torch.Tensor) else allowed
        )
        if mask.dtype != torch.bool:
            raise ValueError(f"allowed must be action names or a bool mask, got dtype {mask.dtype}")
        if mask.shape not in ((a,), (n, a)):
            raise ValueError(
                f"allowed has shape {tuple(mask.shape)}; expected ({a},) or ({n}, {a}) "
                f"(one flag per action), or a list of action names"
            )
    none = ~mask.reshape(-1, a).any(-1)
    if none.any():
        row = int(none.nonzero()[0])
        where = "" if mask.dim() == 1 else f" in row {row}"
        raise ValueError(f"allowed permits no action{where}: allow at least one")
    return mask


def placeholder_row(enc: Evidence) -> Evidence:
    """A placeholder row (state 0, zeros) that stands in for empty evidence.

    A query runs on it and cuts its answer to zero rows (:func:`no_rows`).
    """
    values = {k: torch.zeros(1, *v.shape[1:], dtype=v.dtype) for k, v in enc.items()}
    return Evidence(enc.net, values, 1)


def no_rows(result):
    """``result`` (a query's answer for one placeholder row) cut to zero rows."""
    if isinstance(result, torch.Tensor):
        return result[:0]
    if isinstance(result, tuple):
        return ()
    if isinstance(result, dict):
        return {k: no_rows(v) for k, v in result.items()}
    if is_dataclass(result):
        return replace(
            result,
            **{
                f.name: no_rows(getattr(result, f.name))
                for f in fields(result)
                if f.name not in ("states", "actions")
            },
        )
    return result


def unseen_indicator(
    net: EffectNetwork, params: NetworkParams, e: Enumerated, sites: list[str]
) -> torch.Tensor:
    """Joint-posterior-weighted indicator that any of ``sites`` sits on an unseen configuration."""
    flag = torch.zeros((), dtype=torch.bool)
    for one in unseen_flags(net, params, e, sites):
        flag = flag | one
    return flag.to(DTYPE)


def unseen_flags(
    net: EffectNetwork, params: NetworkParams, e: Enumerated, sites: list[str]
) -> list[torch.Tensor]:
    """Per site of ``sites``, whether each configuration of its parents is unseen.

    A bool tensor over the parents' enumerated dims.
    """
    values = {name: s["value"] for name, s in e.trace.nodes.items() if s["type"] == "sample"}
    flags = []
    for site in sites:
        cpd = net.cpd(site)
        index = [values[s] for s in cpd.parents]
        flags.append(~gather(cpd.seen(params[site]), tuple(index)))
    return flags


def unseen_mass(
    net: EffectNetwork,
    params: NetworkParams,
    e: Enumerated,
    sites: list[str],
    keep: tuple[str, ...] = (),
) -> torch.Tensor:
    """Posterior probability that any of ``sites`` sits on an unseen configuration.

    By contraction: one minus that of every one seen, whose factors (0 or ``-inf`` per site) join
    the contraction. Over the rows, or given each state of the one site in ``keep`` (``(n, K)``; 0
    where that state is impossible). ``-inf`` weight rows: 0.
    """
    flags = unseen_flags(net, params, e, sites)
    log_all = e.log_sum(keep)
    if any(bool(f.any()) for f in flags):
        seen = [torch.where(f, -torch.inf, 0.0).to(DTYPE) for f in flags]
        log_seen = e.log_sum(keep, seen)
        possible = log_all > -torch.inf
        p_seen = (log_seen - torch.where(possible, log_all, 0.0)).exp()
        mass = torch.where(possible, 1.0 - p_seen, 0.0).clamp(0, 1)
    else:
        mass = torch.zeros_like(log_all)
    mass = mass.expand(*mass.shape[:-1], e.n_rows).reshape(-1, e.n_rows).T
    return mass if keep else mass[:, 0]


def parameter_placeholder(m, enc: Evidence) -> Evidence:
    """A placeholder row for an empty query about a parameter, with an action using it."""
    placeholder = placeholder_row(enc)
    if ACTION in placeholder:
        placeholder = placeholder.without(ACTION) | {ACTION: [m.parameter.actions[0]]}
    return placeholder


def check_parameter_evidence(net, m, enc: Evidence, query: str) -> tuple[Evidence, list[str]]:
    """Check the evidence of a query about a parameter.

    The parameter unknown, an effect of it observed, an action using it in every row (filled in when
    only one action does). Returns the evidence with the action, and the observed sites the
    parameter acts on.
    """
    p = m.parameter
    if param_site(p.name) in enc or cluster_site(p.name) in enc:
        raise ValueError(
            f"evidence gives {param_site(p.name)!r} or {cluster_site(p.name)!r}, which this query infers"
        )
    observed = [s for s in m.affected if s in enc]
    if not observed or m.child is not None and m.child not in enc and len(m.affected) == 1:
        y_site = m.child or m.affected[0]
        raise ValueError(
            f"{query} needs the observed end state {y_site!r} of the feature {p.name!r} acts on"
            + (f" (or one of {list(m.affected)})" if len(m.affected) > 1 else "")
        )
    if ACTION not in enc:
        if len(p.actions) != 1:
            raise ValueError(f"give the action (one of {list(p.actions)}) that used {p.name!r}")
        action = torch.full((enc.n_rows,), net.action_index(p.actions[0]))
        enc = Evidence(net, dict(enc) | {ACTION: action}, enc.n_rows)
    not_using = ~m.in_use(enc[ACTION])
    if not_using.any():
        row = int(not_using.nonzero()[0])
        raise ValueError(
            f"row {row}: action {net.actions[int(enc[ACTION][row])]!r} does not use {p.name!r}"
        )
    return enc, observed


def given_other_parameters(net, m, enc: Evidence, children, query: str):
    """The other parameters acting on the same feature, given where their action uses them.

    They must be given in every row whose action uses them (elsewhere they are ignored, NaN or
    absent). Returns the evidence with their cells as clusters, and every parameter acting on the
    feature (in input order). Checks that the observed children's discrete parents are given.
    """
    p = m.parameter
    acting = net.acting_on(m.child) if m.child is not None else (m,)
    for q in acting:
        if q is m:
            continue
        uses = q.in_use(enc[q.action])
        theta = enc.get(q.value.site)
        if theta is None:
            theta = torch.full((enc.n_rows, q.parameter.dim), float("nan"), dtype=DTYPE)
        unknown = torch.isnan(theta).any(-1) & uses
        if bool(unknown.any()):
            row = int(unknown.nonzero()[0])
            raise ValueError(
                f"{query}({p.name!r}) needs {q.value.site!r} in every row whose action uses "
                f"it: it acts on {m.child!r} too (row {row} leaves it unknown)"
            )
        enc = enc | net.encode_indices({q.cluster.site: q.cells(theta, enc[q.action])})
    for child in children:
        missing = [s for s in child.parents if s not in enc and s != m.cluster.site]
        if missing:
            raise ValueError(
                f"{query} needs the discrete parents {missing} of {child.site!r} as evidence"
            )
    return enc, acting
