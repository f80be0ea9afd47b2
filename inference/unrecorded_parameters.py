r"""Action parameters that a demonstration did not record: the columns EM reads them from.

A person tapping a can does not say how hard: a demonstration's step may record its
action's parameter (``{"force": [4.2]}``) or not. Training rows follow a rule that
demonstrations cannot: a row gives a parameter's value exactly where its action uses the
parameter, so a NaN there says the action does not. In a demonstration a recorded value
still says that the step's action uses the parameter, but an unrecorded one says nothing:
it is a hidden value of its step, which EM integrates out exactly through the parameter's
clusters (:mod:`inference.fitting.completion`).

This module turns the per-step records into what the fit reads:

* :func:`parameter_columns`: each parameter's ``(steps, d)`` column (NaN where not
  recorded) and the ``(steps,)`` mask of the unrecorded steps;
* :func:`placeholders`: the columns as the training rows' checks read them (a labelled
  step whose action uses the parameter holds a stand-in value; EM sets it back to unknown);
* :func:`spread_values` and :func:`for_actions`: the stand-ins EM's starts are fitted on
  (the unrecorded values spread uniformly over the parameter's range), and those columns
  under the actions a start gives the steps (NaN where the action does not use the
  parameter, as training rows have it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from effect_networks.models.declaration import ACTION, EffectNetwork

__all__ = ["for_actions", "parameter_columns", "placeholders", "spread_values"]


def parameter_columns(
    net: EffectNetwork,
    demonstrations: Sequence[Sequence[Mapping]],
    steps_rows: dict[str, np.ndarray],
    parameters: Sequence[Sequence[Mapping[str, object] | None]] | None,
) -> dict[str, torch.Tensor]:
    """Add each parameter's column to ``steps_rows``; return the unrecorded steps' masks.

    ``steps_rows[param.p]``: ``(steps, d)`` float, NaN where step did not record ``p``. The
    masks: ``(steps,)`` bool per parameter site, True where not recorded. ``ValueError``
    names a step whose record is not a mapping, names no parameter of the network, is not
    ``d`` finite numbers, or gives a value its labelled action does not use.
    """
    n_steps = len(steps_rows[ACTION])
    if parameters is None:
        parameters = [[None] * (len(d) - 1) for d in demonstrations]
    if isinstance(parameters, Mapping) or len(parameters) != len(demonstrations):
        raise ValueError(
            "parameters must hold one sequence of step records per demonstration "
            f"({len(demonstrations)}), each record {{parameter: value}} or None"
        )
    names = {p.name for p in net.parameters}
    columns = {m.value.site: np.full((n_steps, m.parameter.dim), math.nan) for m in net.mixtures}
    at = 0
    for i, (demo, records) in enumerate(zip(demonstrations, parameters, strict=True)):
        if records is None:  # a demonstration that recorded nothing
            records = [None] * (len(demo) - 1)
        if isinstance(records, Mapping) or len(records) != len(demo) - 1:
            raise ValueError(
                f"parameters[{i}] must hold {len(demo) - 1} step records (or be None), got "
                f"{records!r}"
            )
        for t, record in enumerate(records):
            if record is None:
                continue
            if not isinstance(record, Mapping) or set(record) - names:
                raise ValueError(
                    f"parameters[{i}][{t}] must map parameter names {sorted(names)} to values, "
                    f"got {record!r}"
                )
            for m in net.mixtures:
                value = record.get(m.parameter.name)
                if value is None:
                    continue
                value = np.asarray(value, dtype=np.float64).reshape(-1)
                if value.shape != (m.parameter.dim,) or (
                    not np.isnan(value).all() and not np.isfinite(value).all()
                ):
                    raise ValueError(
                        f"parameters[{i}][{t}][{m.parameter.name!r}] must be "
                        f"{m.parameter.dim} finite numbers (or NaN: not recorded), got {value}"
                    )
                label = steps_rows[ACTION][at + t]
                if not np.isnan(value).all() and label is not None:
                    if not bool(m.uses[net.action_index(label)]):
                        raise ValueError(
                            f"parameters[{i}][{t}] records {m.parameter.name!r}, which the "
                            f"step's action {label!r} does not use"
                        )
                columns[m.value.site][at + t] = value
        at += len(demo) - 1
    steps_rows.update(columns)
    return {site: torch.from_numpy(np.isnan(c).any(-1)) for site, c in columns.items()}


def placeholders(
    net: EffectNetwork, data: Mapping[str, np.ndarray], unrecorded: Mapping[str, torch.Tensor]
) -> dict[str, np.ndarray]:
    """``data`` with a stand-in value where a labelled step's action uses an unrecorded parameter.

    The range's middle: what the training rows' checks read; the fit sets it back to unknown.
    """
    out = dict(data)
    labels = data[ACTION]
    for m in net.mixtures:
        site = m.value.site
        column = np.array(data[site], dtype=np.float64, copy=True)
        middle = (np.asarray(m.parameter.low) + np.asarray(m.parameter.high)) / 2
        open_ = unrecorded[site].numpy()
        for row in np.flatnonzero(open_):
            label = labels[row]
            if label is not None and bool(m.uses[net.action_index(label)]):
                column[row] = middle
        out[site] = column
    return out


def spread_values(
    net: EffectNetwork, data: Mapping[str, np.ndarray], unrecorded: Mapping[str, torch.Tensor], seed
) -> dict[str, np.ndarray]:
    """``data`` with every unrecorded value drawn uniformly over its parameter's range.

    What EM's starts are fitted on: a value that says nothing of where it lies.
    """
    out = dict(data)
    generator = np.random.default_rng(seed)
    for m in net.mixtures:
        site = m.value.site
        column = np.array(data[site], dtype=np.float64, copy=True)
        open_ = unrecorded[site].numpy()
        low, high = np.asarray(m.parameter.low), np.asarray(m.parameter.high)
        column[open_] = generator.uniform(low, high, (int(open_.sum()), m.parameter.dim))
        out[site] = column
    return out


def for_actions(
    net: EffectNetwork, rows: Mapping[str, np.ndarray], labels: np.ndarray
) -> dict[str, np.ndarray]:
    """Each parameter's column under the actions ``labels``: NaN where the action ignores it."""
    index = torch.tensor([net.action_index(a) for a in labels], dtype=torch.long)
    out = {}
    for m in net.mixtures:
        uses = m.in_use(index).numpy()
        column = np.array(rows[m.value.site], dtype=np.float64, copy=True)
        column[~uses] = math.nan
        out[m.value.site] = column
    return out
