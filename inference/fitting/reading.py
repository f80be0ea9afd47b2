"""Training rows read one way, by :func:`read_rows`.

It is the reading every function that takes training rows calls first (:func:`inference.fit` and its chunks, the scores and
:func:`inference.cross_validate`, :func:`inference.select_clusters`,
:func:`inference.fit_em`, :func:`inference.learn_structure`): a ``DataFrame``
(:func:`models.frames.as_data`, labels read back from text), a mapping of arrays, lists
or tensors, or encoded :class:`Evidence` become one :class:`TrainingRows`: the encoded,
checked rows with their gaps marked. Its :meth:`TrainingRows.take` cuts rows out of it,
NaN and masks with them, so cross-validation folds are cut from what was read, not from
the rows as given.

The checks themselves (every site given, a parameter's value where its action uses it,
the masks) live in :mod:`inference.fitting.rows`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from effect_networks.inference.fitting.rows import rows_with_gaps
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.evidence import Evidence
from effect_networks.models.frames import as_data, columns

__all__ = ["TrainingRows", "read_rows"]


@dataclass(frozen=True)
class TrainingRows:
    """Training rows read once (:func:`read_rows`): encoded, checked, their gaps marked.

    Attributes
    ----------
    net : EffectNetwork
        The network they were read for.
    enc : Evidence
        ``n`` rows, every site, every parameter's cluster included; NaN where a
        continuous initial or end value is missing, a placeholder state where a discrete
        one is.
    masks : dict of str to torch.Tensor
        ``(n,)`` bool per discrete site that ``masks`` or the rows marked, False where
        the value is missing.
    unread : tuple of str
        The parameters' clusters the rows did not give (each a value's cell under the
        grid layout, latent under the adaptive one or where the action is missing).
    """

    net: EffectNetwork
    enc: Evidence
    masks: dict[str, torch.Tensor]
    unread: tuple[str, ...]

    @property
    def n_rows(self) -> int:
        """The rows, ``n``."""
        return self.enc.n_rows

    @property
    def gaps(self) -> dict[str, torch.Tensor]:
        """The masks that leave some discrete value missing."""
        return {s: m for s, m in self.masks.items() if not bool(m.all())}

    def missing(self) -> dict[str, int]:
        """Per site with gaps (discrete or continuous), how many rows miss its value."""
        out = {s: int((~m).sum()) for s, m in self.gaps.items()}
        for spec in self.net.sites:
            value = self.enc.get(spec.name)
            if spec.discrete or spec.role == "param" or value is None:
                continue
            rows = int(torch.isnan(value).any(-1).sum())
            if rows:
                out[spec.name] = rows
        return dict(sorted(out.items()))

    def missing_text(self) -> str:
        """The sites with gaps and how many rows miss each, for a message."""
        missing = self.missing()
        counts = ", ".join(f"{k} of the {self.n_rows} rows miss {s!r}" for s, k in missing.items())
        return f"{list(missing)} ({counts})"

    def dropna_text(self) -> str:
        """How to drop the incomplete rows of a frame: the columns of the sites with gaps.

        A bare ``dropna()`` would drop every row whose action leaves a parameter NaN too.
        """
        subset = [c for site in self.missing() for c in columns(self.net, site)]
        return f"frame.dropna(subset={subset})"

    def take(self, index: torch.Tensor) -> TrainingRows:
        """The rows ``index`` (``(m,)`` long, or ``(n,)`` bool), their gaps with them."""
        if index.dtype == torch.bool:
            index = index.nonzero().squeeze(-1)
        masks = {s: m[index] for s, m in self.masks.items()}
        return TrainingRows(self.net, self.enc.rows(index), masks, self.unread)


def read_rows(
    net: EffectNetwork,
    data: object,
    masks: Mapping[str, object] | None = None,
) -> TrainingRows:
    """Training rows in any of the forms the toolkit takes, read the one way they all are.

    Parameters
    ----------
    net
        The network the rows are for.
    data
        Rows by site: a mapping of arrays, lists or tensors (labels for discrete sites,
        ``(n, d)`` numbers for continuous ones, :class:`Partial` for some dimensions of
        an end feature), a pandas ``DataFrame`` (:mod:`models.frames`, labels read back
        from text included), encoded :class:`Evidence`, or :class:`TrainingRows` already
        read for ``net`` (returned as they are). Missing values: None or NaN for a
        discrete label, NaN for a continuous initial or end value or some of its
        dimensions.
    masks
        Per discrete site, one bool (or 0/1) per row, False where missing; joined with
        the rows' own marks.

    Returns
    -------
    TrainingRows
        The rows as :func:`rows_with_gaps` checks them, and the clusters they did not give.

    Raises
    ------
    ValueError
        For data that is none of these forms, rows read for another network, ``masks``
        beside rows already read, or what :func:`rows_with_gaps` refuses (naming the site).
    """
    if isinstance(data, TrainingRows):
        if data.net is not net and data.net != net:
            raise ValueError("the rows were read for another network: read them for this one")
        if masks:
            raise ValueError("masks: the rows were read with their masks; give them to read_rows")
        return data
    data = as_data(net, data)
    if not isinstance(data, Mapping):
        raise ValueError(
            "data must be rows by site (a mapping of arrays, lists or tensors, or a pandas "
            f"DataFrame), got {type(data).__name__}"
        )
    given = {m.cluster.site for m in net.mixtures if m.cluster.site in data}
    enc, masks = rows_with_gaps(net, data, masks)
    unread = tuple(m.cluster.site for m in net.mixtures if m.cluster.site not in given)
    return TrainingRows(net, enc, masks, unread)
