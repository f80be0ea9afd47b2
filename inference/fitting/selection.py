"""Choosing an action parameter's clusters from the data: how many, and which layout.

A parameter's clusters (:class:`models.features.Parameter`: ``bins`` cells per
dimension, the grid or the adaptive layout) trade resolution against rows per cluster:
too few pieces miss the shape of the parameter's effect, too many fit each piece to a
handful of rows. :func:`select_clusters` fits the network once per candidate and scores
it by the held-out log-likelihood (:func:`inference.fitting.scores.cross_validate`,
higher is better) or the BIC (:func:`inference.fitting.scores.bic` of the fit on all
rows, lower is better), so a user with logged trials chooses without a simulator to
re-throw in. Each candidate is fitted as its layout is: :func:`inference.fit` for the
grid, :func:`inference.fit_em` for adaptive clusters.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from effect_networks.inference.fitting.em import fit_em
from effect_networks.inference.fitting.maximum_likelihood import fit
from effect_networks.inference.fitting.reading import read_rows
from effect_networks.inference.fitting.scores import cross_validate, log_likelihood, n_parameters
from effect_networks.models.declaration import LAYOUTS, EffectNetwork, cluster_site
from effect_networks.models.evidence import Evidence

__all__ = ["ClusterScore", "ClusterSelection", "SCORES", "select_clusters"]

#: The criteria :func:`select_clusters` chooses by.
SCORES = ("heldout", "bic")


@dataclass(frozen=True)
class ClusterScore:
    """One candidate of :func:`select_clusters`.

    Attributes
    ----------
    bins : tuple of int
        Cells per dimension of the parameter.
    layout : str
        ``"grid"`` or ``"adaptive"``.
    n_clusters : int
        ``prod(bins)``.
    n_parameters : int
        The network's free parameters (:func:`inference.fitting.scores.n_parameters`).
    log_likelihood : float
        The held-out log-likelihood summed over the folds (``score="heldout"``), or the
        log-likelihood of the fit on all rows (``score="bic"``).
    bic : float or None
        ``-2 log_likelihood + n_parameters ln n`` (``score="bic"`` only).
    """

    bins: tuple[int, ...]
    layout: str
    n_clusters: int
    n_parameters: int
    log_likelihood: float
    bic: float | None = None


@dataclass(frozen=True)
class ClusterSelection:
    """What :func:`select_clusters` returns: every candidate's score and the chosen one.

    The chosen one has the highest held-out log-likelihood, or the lowest BIC; the first on a tie.
    """

    parameter: str
    score: str
    candidates: tuple[ClusterScore, ...]
    chosen: ClusterScore

    def table(self) -> list[dict]:
        """One dict per candidate (its fields, and ``chosen``), in the order tried."""
        return [dataclasses.asdict(c) | {"chosen": c == self.chosen} for c in self.candidates]

    def to_markdown(self) -> str:
        """The table as Markdown, the chosen candidate in bold."""
        value = "held-out log-likelihood" if self.score == "heldout" else "BIC"
        lines = [
            f"| bins | layout | clusters | free parameters | {value} |",
            "|---|---|---:|---:|---:|",
        ]
        for c in self.candidates:
            v = c.log_likelihood if self.score == "heldout" else c.bic
            cells = ["x".join(map(str, c.bins)), c.layout, c.n_clusters, c.n_parameters]
            cells.append(f"{v:.1f}")
            if c == self.chosen:
                cells = [f"**{x}**" for x in cells]
            lines.append("| " + " | ".join(map(str, cells)) + " |")
        return "\n".join(lines)


def select_clusters(
    net_or_factory: EffectNetwork | Callable[[tuple[int, ...], str], EffectNetwork],
    data: Mapping[str, object],
    candidates: Iterable[int | Sequence[int]],
    *,
    parameter: str | None = None,
    layouts: Sequence[str] = ("grid",),
    score: str = "heldout",
    folds: int = 5,
    seed: int = 0,
    **fit_kwargs,
) -> ClusterSelection:
    """Score a parameter's cluster counts and layouts on rows and choose the best.

    Parameters
    ----------
    net_or_factory
        A network whose parameter ``parameter`` takes each candidate's ``bins`` and
        layout (everything else kept), or a function ``(bins, layout) -> EffectNetwork``.
    data
        Training rows as :func:`inference.fit` takes them, without the parameter's
        cluster (its meaning changes with ``bins``).
    candidates
        Cells per dimension: an int (the same on every dimension) or a sequence of one
        int per dimension; a factory gets each as given.
    parameter
        The parameter's name; may be left out for a network with one parameter, and is
        not used with a factory.
    layouts
        The layouts to try with every candidate (:data:`models.features.LAYOUTS`).
    score
        ``"heldout"``: ``folds``-fold cross-validation with ``seed``
        (:func:`inference.fitting.scores.cross_validate`); ``"bic"``: the BIC of the fit
        on all rows.
    **fit_kwargs
        Passed to every fit (``pseudo_count``, ``min_variance``, ``steps``, ...);
        ``masks`` marks missing discrete values, as :func:`inference.fit` takes them, for
        the fits and the scores alike.

    Returns
    -------
    ClusterSelection
        Per candidate and layout its score, and the chosen one.

    Raises
    ------
    ValueError
        For an unknown score, layout or parameter, no candidates, a candidate that is
        not a positive int per dimension, or rows that give the parameter's cluster.

    Examples
    --------
    >>> from models.humanoid_throw import throw_network
    >>> choice = select_clusters(throw_network(), rows, [2, 4, 8], score="bic")  # doctest: +SKIP
    >>> choice.chosen.bins  # doctest: +SKIP
    (8, 8)
    """
    if score not in SCORES:
        raise ValueError(f"score must be one of {SCORES}, got {score!r}")
    layouts = tuple(layouts)
    bad = [x for x in layouts if x not in LAYOUTS]
    if bad or not layouts:
        raise ValueError(f"layouts must be some of {LAYOUTS}, got {layouts!r}")
    make, name = _factory(net_or_factory, parameter)
    candidates = list(candidates)
    if not candidates:
        raise ValueError("candidates is empty; give at least one cluster count")
    if isinstance(data, Evidence):
        raise ValueError(
            "data is Evidence, encoded for one network; each candidate is another network: "
            "give the rows by site as labels and numbers"
        )
    masks = fit_kwargs.pop("masks", None)  # read with the rows, for the fits and the scores
    scored = []
    for bins in candidates:
        for layout in layouts:
            net = make(bins, layout)
            p = next(q for q in net.parameters if name is None or q.name == name)
            if cluster_site(p.name) in data:
                raise ValueError(
                    f"data gives {cluster_site(p.name)!r}, whose meaning changes with bins: "
                    "leave it out (each row's cluster is then its value's cell, or latent "
                    "when adaptive)"
                )
            rows = read_rows(net, data, masks)  # each candidate's rows, read as fit reads them
            if score == "heldout":
                ll = cross_validate(net, rows, folds, seed, **fit_kwargs).total
                scored.append(ClusterScore(p.bins, layout, p.n_clusters, n_parameters(net), ll))
            else:
                if layout == "adaptive":
                    params = fit_em(net, rows, **fit_kwargs).params
                else:
                    params = fit(net, rows, **fit_kwargs).params
                result = log_likelihood(net, params, rows)
                scored.append(
                    ClusterScore(
                        p.bins, layout, p.n_clusters, result.n_parameters, result.total, result.bic
                    )
                )
    if score == "heldout":
        chosen = max(scored, key=lambda c: c.log_likelihood)
    else:
        chosen = min(scored, key=lambda c: c.bic)
    label = name if name is not None else "(factory)"
    return ClusterSelection(label, score, tuple(scored), chosen)


def _factory(net_or_factory, parameter):
    """``(make(bins, layout) -> EffectNetwork, the parameter's name or None)``."""
    if not isinstance(net_or_factory, EffectNetwork):
        if not callable(net_or_factory):
            raise ValueError(
                "net_or_factory must be an EffectNetwork or a function (bins, layout) -> "
                f"EffectNetwork, got {type(net_or_factory).__name__}"
            )
        return lambda bins, layout: net_or_factory(_bins(bins, None), layout), parameter
    net = net_or_factory
    names = [p.name for p in net.parameters]
    if parameter is None:
        if len(names) != 1:
            raise ValueError(f"parameter: name one of the network's parameters {names}")
        parameter = names[0]
    if parameter not in names:
        raise ValueError(f"parameter {parameter!r} is not one of the network's {names}")
    target = next(p for p in net.parameters if p.name == parameter)

    def make(bins, layout):
        changed = dataclasses.replace(target, bins=_bins(bins, target.dim), layout=layout)
        params = tuple(changed if p.name == parameter else p for p in net.parameters)
        return EffectNetwork(
            net.features, net.actions, params, parents=dict(net.parents), kinds=dict(net.kinds)
        )

    return make, parameter


def _bins(bins, dim: int | None):
    """A candidate as one int per dimension (``dim``), checked.

    ``dim=None`` (a factory's candidate): as given.
    """
    if isinstance(bins, int) and not isinstance(bins, bool) and bins >= 1:
        return bins if dim is None else (bins,) * dim
    out = tuple(bins) if isinstance(bins, Sequence) else ()
    if not out or not all(isinstance(b, int) and not isinstance(b, bool) and b >= 1 for b in out):
        raise ValueError(f"candidate {bins!r}: expected a positive int or one per dimension")
    if dim is not None and len(out) != dim:
        raise ValueError(f"candidate {bins!r}: the parameter has {dim} dimensions")
    return out
