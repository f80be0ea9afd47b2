r"""Interoperation with pgmpy: a network's discrete part as a pgmpy network, and back.

An effect network whose features are all discrete is an ordinary discrete Bayesian
network; with the paper's Fig. 1 structure::

    initial.f1  initial.f2  action        roots, one table each
          \   \  /  /   /
           end.f1   end.f2               one table per end site, over every initial
                                          node and the action

and with declared parent sets (``EffectNetwork(parents=...)``) any structure in which
the action is a root, initial nodes have only initial parents, and end nodes have
initial nodes, the action and other end nodes as parents.

* :func:`to_pgmpy` writes that part as a ``pgmpy.models.DiscreteBayesianNetwork``: one
  node per site (``initial.<f>``, ``action``, ``end.<f>``), the declared state labels
  as pgmpy state names, unchanged (str, int, float, bool or None: pgmpy accepts any
  hashable), and one ``TabularCPD`` per table whose evidence order is
  :meth:`EffectNetwork.discrete_parents`. Everything else is left out and named:
  continuous features, action parameters (``param.<p>``, ``cluster.<p>``) and discrete
  end sites with continuous parents (softmax CPDs).
* :func:`from_pgmpy` reads a pgmpy network of such a structure back into a declaration
  (its parent sets declared where they are not Fig. 1's) and parameters; a structure a
  declaration cannot express (an action with parents, an initial node with an end or
  action parent, a node of another name, a parameter's node) is refused, naming it. A pgmpy CPD holds probabilities only, so the caller states the training
  rows behind every parent configuration (``n``; ``n == 0`` marks a configuration as
  unseen, which every query reports).
* :func:`write_bif` and :func:`read_bif` do the same through a BIF file (pgmpy's
  ``BIFWriter`` and ``BIFReader``). BIF stores state names as text, so labels come back
  as ``str`` unless ``states=`` gives the declared labels.

pgmpy is a development dependency only; it is imported when one of these functions runs.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch
from effect_networks.models.declaration import (
    ACTION,
    DTYPE,
    Discrete,
    EffectNetwork,
    FeatureKind,
    end_site,
    initial_site,
)
from effect_networks.models.params import NetworkParams, TableParams, check_params

if TYPE_CHECKING:
    from pgmpy.models import DiscreteBayesianNetwork

SUM_TOLERANCE = 0.01  # pgmpy's own check_model tolerance on a column's sum
EXACT_SUM = 1e-12  # columns this close to 1 are kept bit for bit (no renormalising)
_BIF_FORBIDDEN = (",", ";", "{", "}", "(", ")", "|", '"', "//", "/*", "\n")


class PgmpyNetwork(NamedTuple):
    """What :func:`to_pgmpy` returns (unpacks as ``model, left_out = to_pgmpy(...)``).

    Attributes
    ----------
    model : pgmpy.models.DiscreteBayesianNetwork
        The network's discrete part; ``model.check_model()`` passes.
    left_out : tuple of str
        The sites not in ``model``, in the network's site order: continuous sites,
        ``param.<p>`` and ``cluster.<p>``, and discrete end sites with a softmax CPD.
    """

    model: DiscreteBayesianNetwork
    left_out: tuple[str, ...]


def to_pgmpy(net: EffectNetwork, params: NetworkParams) -> PgmpyNetwork:
    """The discrete part of a fitted network as a pgmpy ``DiscreteBayesianNetwork``.

    Parameters
    ----------
    net : EffectNetwork
        The declaration.
    params : NetworkParams
        Its parameters (checked against ``net``). The counts ``TableParams.n`` and the
        pseudo-count are not part of a pgmpy network and are dropped.

    Returns
    -------
    PgmpyNetwork
        ``(model, left_out)``. Nodes are named by site and added in the network's site
        order; state names are the declared labels (action names for ``action``);
        each end node's ``TabularCPD`` has evidence ``net.discrete_parents(feature)``
        in that order (pgmpy's columns: the first evidence variable varies slowest,
        as ``TableParams.probs.reshape(-1, K)`` rows do).

    Raises
    ------
    ImportError
        If pgmpy is not installed.
    ValueError
        If ``params`` does not fit ``net``.
    """
    DiscreteBayesianNetwork, TabularCPD = _pgmpy()
    check_params(net, params)
    kept, kept_names = [], set()
    for s in net.sites:  # parents first: a table whose parents are all kept is kept
        cpd = net.cpd(s.name)
        if s.role in ("initial", "action", "end") and cpd.tabular:
            if set(cpd.parents) <= kept_names:
                kept.append(s)
                kept_names.add(s.name)
    left_out = tuple(s.name for s in net.sites if s.name not in kept_names)
    states = {s.name: list(_site_states(net, s.name)) for s in kept}

    model = DiscreteBayesianNetwork()
    model.add_nodes_from([s.name for s in kept])
    cpds = []
    for s in kept:
        probs = params[s.name].probs.detach().cpu().numpy().astype(np.float64)
        parents = list(net.cpd(s.name).parents)
        model.add_edges_from((p, s.name) for p in parents)
        cpds.append(
            TabularCPD(
                s.name,
                s.size,
                probs.reshape(-1, s.size).T,
                evidence=parents or None,
                evidence_card=[len(states[p]) for p in parents] or None,
                state_names={v: states[v] for v in [s.name, *parents]},
            )
        )
    model.add_cpds(*cpds)
    model.check_model()
    return PgmpyNetwork(model, left_out)


def from_pgmpy(
    model: DiscreteBayesianNetwork,
    *,
    n: float | Mapping[str, Any],
    actions_node: str = ACTION,
    kind: FeatureKind | Mapping[str, FeatureKind] = "object",
    order: Sequence[str] | None = None,
    pseudo_count: float = 0.01,
) -> tuple[EffectNetwork, NetworkParams]:
    """Read a discrete pgmpy network with an effect network's structure.

    The network's nodes are ``initial.<f>``, ``end.<f>`` (``f`` a Python identifier)
    and the action node. The action node is a root; an initial node's parents are
    initial nodes; an end node's parents are any initial nodes, the action node and
    other end nodes (Fig. 1: every initial node and the action). Each node's parents
    become its declared ``parents=`` (stored where they differ from Fig. 1's). Every
    ``initial.<f>`` needs its ``end.<f>``; an ``end.<f>`` without ``initial.<f>``
    declares ``Discrete(f, ..., initial=False)``.

    Parameters
    ----------
    model : pgmpy.models.DiscreteBayesianNetwork
        With a ``TabularCPD`` per node. Its state names become the declared labels (in
        the order of the initial node's CPD, else the end node's; both must hold the
        same labels); the action node's state names become the action names, as
        ``str``. Parent order and state order inside a CPD may be any: tables are
        rearranged by name. Each column must sum to 1 within ``SUM_TOLERANCE`` (pgmpy's
        own); one that misses 1 by more than ``EXACT_SUM`` (rounded tables, as in a BIF
        file written with few decimals) is divided by its sum, the others are kept bit
        for bit.
    n : float or mapping of str to float or array
        Training rows behind each parent configuration; pgmpy CPDs hold none. A number
        states it for every configuration of every table. A mapping states it per site
        of the result (``initial.<f>``, ``action``, ``end.<f>``; the action site is
        ``"action"`` whatever ``actions_node`` is): every site, each a number or an
        array of the site's parent shape: the cardinalities of
        ``net.cpd(site).parents`` (``()`` for roots; parents in the network's site
        order, parents before children). ``0`` marks a configuration
        unseen; queries report it.
    actions_node : str
        Name of the action node in ``model``.
    kind : {"object", "meta", "world"} or mapping of feature to it
        Feature kind, for all features or per feature (missing ones: ``"object"``).
    order : sequence of str, optional
        The features in declaration order (their names); default: the order of the
        end nodes in ``model.nodes()``.
    pseudo_count : float
        Recorded in the returned ``NetworkParams`` (the policy the tables are said to
        follow; the tables are used as given).

    Returns
    -------
    (EffectNetwork, NetworkParams)

    Raises
    ------
    ImportError
        If pgmpy is not installed.
    ValueError
        Naming the node and what was expected: a node with another name (or a
        parameter's ``cluster.<p>``/``param.<p>``), a missing action node, an action
        node with parents, an initial node with other than initial parents, a missing
        or non-tabular CPD, a CPD pgmpy's
        ``check_model`` refuses, an initial and end node with different labels, or
        counts of the wrong shape or sign.
    """
    return _from_pgmpy(
        model,
        n=n,
        actions_node=actions_node,
        kind=kind,
        order=order,
        pseudo_count=pseudo_count,
        relabel=None,
    )


def write_bif(path: str | Path, net: EffectNetwork, params: NetworkParams) -> Path:
    """Write a discrete network to a BIF file (via :func:`to_pgmpy` and pgmpy's BIFWriter).

    BIF stores every state label as its ``str()``; :func:`read_bif` with
    ``states=`` restores the declared labels. Counts and the pseudo-count are not
    stored. The file lists variables sorted by name.


    Parameters
    ----------
    path
        The BIF file to write.
    net, params
        A discrete network (tables only) and its fitted parameters.

    Returns
    -------
    pathlib.Path
        ``path``, as a ``Path``.

    Raises
    ------
    ValueError
        If the network has sites BIF cannot hold (continuous, parameter or softmax
        sites: use :func:`models.save` for those), or if a label's ``str()`` cannot be
        read back from BIF (empty, padded with spaces, holding one of
        ``, ; { } ( ) | "``, ``//``, ``/*`` or a line break, or equal to another
        label's of the same site), or if two site names differ only in case (the
        reader folds case).
    """
    _pgmpy()
    from pgmpy.readwrite import BIFWriter

    exported = to_pgmpy(net, params)
    if exported.left_out:
        raise ValueError(
            f"BIF holds discrete tables only; this network's sites {list(exported.left_out)} "
            "are not tables of discrete parents. Save the whole network with models.save"
        )
    folded: dict[str, str] = {}
    for node in exported.model.nodes():
        other = folded.setdefault(node.lower(), node)
        if other != node:
            raise ValueError(
                f"sites {other!r} and {node!r} differ only in case; BIF readers fold case. "
                "Rename one of the features"
            )
        seen: dict[str, Hashable] = {}
        for label in _site_states(net, node):
            text = str(label)
            bad = [c for c in _BIF_FORBIDDEN if c in text]
            if not text or text != text.strip() or bad:
                raise ValueError(
                    f"site {node!r}: label {label!r} cannot be written to BIF (its text "
                    f"{text!r} must be non-empty, without surrounding spaces and without "
                    f"{' '.join(_BIF_FORBIDDEN[:-1])} or a line break)"
                )
            if text in seen:
                raise ValueError(
                    f"site {node!r}: labels {seen[text]!r} and {label!r} are both {text!r} "
                    "in BIF; give them distinct texts"
                )
            seen[text] = label
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    BIFWriter(exported.model).write(str(path))
    return path


def read_bif(
    path: str | Path,
    *,
    n: float | Mapping[str, Any],
    states: Mapping[str, Sequence[Hashable]] | None = None,
    actions_node: str = ACTION,
    kind: FeatureKind | Mapping[str, FeatureKind] = "object",
    order: Sequence[str] | None = None,
    pseudo_count: float = 0.01,
) -> tuple[EffectNetwork, NetworkParams]:
    """Read a BIF file (pgmpy's BIFReader) into a declaration and parameters.

    Parameters
    ----------
    path : str or Path
        The BIF file.
    n, actions_node, kind, order, pseudo_count
        As in :func:`from_pgmpy`; ``n`` must be stated.
    states : mapping of feature name to labels, optional
        The declared labels of a feature, matched to the file's state texts by
        ``str(label)``: BIF stores text, so without this every label is a ``str``
        (``True`` comes back as ``"True"``). The labels' order is the declared order.

    Returns
    -------
    (EffectNetwork, NetworkParams)

    Raises
    ------
    ValueError
        As :func:`from_pgmpy`, and if ``states`` names an unknown feature or its
        labels' texts are not the file's states.
    """
    _pgmpy()
    from pgmpy.readwrite import BIFReader

    model = BIFReader(path=str(path)).get_model()
    return _from_pgmpy(
        model,
        n=n,
        actions_node=actions_node,
        kind=kind,
        order=order,
        pseudo_count=pseudo_count,
        relabel=states,
    )


# ----------------------------------------------------------------------------- helpers
def _pgmpy():
    try:
        from pgmpy.factors.discrete import TabularCPD
        from pgmpy.models import DiscreteBayesianNetwork
    except ImportError as exc:
        raise ImportError(
            "models.interop needs pgmpy >= 1.0, the `interop` extra of effect-networks: "
            "install it with `pip install 'effect-networks[interop]'` (or `pip install pgmpy`)"
        ) from exc
    return DiscreteBayesianNetwork, TabularCPD


def _site_states(net: EffectNetwork, site: str) -> tuple:
    if site == ACTION:
        return net.actions
    feature = net.feature(net.site(site).feature)
    assert isinstance(feature, Discrete)
    return feature.states


def _from_pgmpy(model, *, n, actions_node, kind, order, pseudo_count, relabel):
    DiscreteBayesianNetwork, TabularCPD = _pgmpy()
    if not isinstance(model, DiscreteBayesianNetwork):
        raise TypeError(
            f"model must be a pgmpy DiscreteBayesianNetwork, got {type(model).__name__}"
        )
    number = isinstance(pseudo_count, int | float) and not isinstance(pseudo_count, bool)
    if not number or not math.isfinite(pseudo_count) or pseudo_count < 0:
        raise ValueError(f"pseudo_count must be a finite number >= 0, got {pseudo_count!r}")
    nodes = list(model.nodes())
    initial, ends = _classify(nodes, actions_node)
    _check_structure(model, initial, actions_node)

    cpds = {}
    for node in nodes:
        cpd = model.get_cpds(node)
        if cpd is None:
            raise ValueError(f"node {node!r} has no CPD; add a TabularCPD for it")
        if not isinstance(cpd, TabularCPD):
            raise ValueError(f"node {node!r} has a {type(cpd).__name__}; expected a TabularCPD")
        cpds[node] = cpd
    try:
        model.check_model()
    except ValueError as exc:
        raise ValueError(f"pgmpy's check_model refuses the network: {exc}") from exc

    names = list(ends)  # feature names in the model's end-node order
    if order is not None:
        order = list(order)
        if sorted(order) != sorted(names):
            raise ValueError(
                f"order {order} must list every feature once; the features are {sorted(names)}"
            )
        names = order
    relabel = dict(relabel or {})
    unknown = set(relabel) - set(names)
    if unknown:
        raise ValueError(
            f"states names unknown features {sorted(unknown)}; the features are {sorted(names)}"
        )
    kinds = dict(kind) if isinstance(kind, Mapping) else dict.fromkeys(names, kind)
    unknown = set(kinds) - set(names)
    if unknown:
        raise ValueError(
            f"kind names unknown features {sorted(unknown)}; the features are {sorted(names)}"
        )

    # perm[node][i]: position, in the node's own state names, of declared state i
    perm: dict[str, list[int]] = {}
    labels: dict[str, tuple] = {}
    features = []
    for f in names:
        nodes_of_f = [initial_site(f), end_site(f)] if f in initial else [end_site(f)]
        own = {
            node: Discrete(f, _relabel(node, cpds[node].state_names[node], relabel.get(f))).states
            for node in nodes_of_f
        }
        declared = tuple(relabel[f]) if f in relabel else own[nodes_of_f[0]]
        feature = Discrete(f, declared, kinds.get(f, "object"), initial=f in initial)
        features.append(feature)
        for node in nodes_of_f:
            if set(own[node]) != set(feature.states):
                raise ValueError(
                    f"node {node!r} has states {list(own[node])} but feature {f!r} has "
                    f"{list(feature.states)}; a feature's initial and end nodes need the "
                    "same labels"
                )
            perm[node] = [own[node].index(label) for label in feature.states]
            labels[node] = feature.states
    raw_actions = list(cpds[actions_node].state_names[actions_node])
    actions = tuple(str(a) for a in raw_actions)
    if len(set(actions)) != len(actions):
        raise ValueError(
            f"node {actions_node!r}: its states {raw_actions} give repeated action names "
            f"{list(actions)} as str; rename them"
        )
    perm[actions_node] = list(range(len(actions)))
    labels[actions_node] = actions
    net = EffectNetwork(tuple(features), actions, parents=_declared(model, features, actions_node))

    node_of = {ACTION: actions_node}
    node_of |= {initial_site(f.name): initial_site(f.name) for f in features if f.initial}
    node_of |= {end_site(f.name): end_site(f.name) for f in features}
    shapes = {s.name: net.cpd(s.name).shapes() for s in net.sites}
    counts = _counts(n, shapes)
    tables = {}
    for site, node in node_of.items():
        cpd = cpds[node]
        parents = list(net.cpd(site).parents)
        axes = [node_of[p] for p in parents] + [node]
        values = np.asarray(cpd.values, dtype=np.float64)
        values = values.transpose([list(cpd.variables).index(v) for v in axes])
        values = values[np.ix_(*[perm[v] for v in axes])]
        total = values.sum(-1, keepdims=True)
        bad = (
            ~np.isfinite(values).all(-1)
            | (values < 0).any(-1)
            | (np.abs(total[..., 0] - 1) > SUM_TOLERANCE)
        )
        if bad.any():
            where = tuple(int(i) for i in np.argwhere(bad)[0])
            given = {v: labels[v][i] for v, i in zip(axes[:-1], where, strict=True)}
            raise ValueError(
                f"node {node!r}: the column for parents {given} is {values[where].tolist()}; "
                f"expected non-negative probabilities summing to 1 (within {SUM_TOLERANCE})"
            )
        values = np.where(np.abs(total - 1) > EXACT_SUM, values / total, values)
        probs = torch.as_tensor(values, dtype=DTYPE)
        assert tuple(probs.shape) == shapes[site]["probs"], (site, probs.shape)
        tables[site] = TableParams(probs, counts[site])
    params = NetworkParams({s: tables[s] for s in shapes}, float(pseudo_count), net)
    check_params(net, params)
    return net, params


def _classify(nodes: list[str], actions_node: str) -> tuple[list[str], list[str]]:
    """Feature names of the initial and the end nodes, in node order."""
    if actions_node not in nodes:
        raise ValueError(
            f"the network has no action node {actions_node!r} (nodes: {nodes}); name it "
            "with actions_node="
        )
    initial, ends = [], []
    for node in nodes:
        if node == actions_node:
            continue
        role, _, feature = str(node).partition(".")
        if role in ("cluster", "param"):
            raise ValueError(
                f"node {node!r}: an action parameter has a continuous value (a Gaussian per "
                "cluster), which a discrete pgmpy network cannot hold; read the network "
                "without it, then declare the Parameter and fit it"
            )
        if role not in ("initial", "end") or not feature.isidentifier():
            raise ValueError(
                f"node {node!r} is not an effect-network site: expected the action node "
                f"{actions_node!r}, 'initial.<feature>' or 'end.<feature>' (feature a "
                "Python identifier)"
            )
        (initial if role == "initial" else ends).append(feature)
    for f in initial:
        if f not in ends:
            raise ValueError(
                f"node {initial_site(f)!r} has no end node {end_site(f)!r}; every feature "
                "needs its end node"
            )
    if not ends:
        raise ValueError(f"the network has no 'end.<feature>' node (nodes: {nodes})")
    return initial, ends


def _check_structure(model, initial: list[str], actions_node: str) -> None:
    """Refuse, naming the node, parents a declaration cannot express."""
    parents = sorted(model.get_parents(actions_node))
    if parents:
        raise ValueError(
            f"node {actions_node!r} (the action) has parents {parents}; in an effect network "
            "the action is a root (it is chosen, not caused)"
        )
    for node in map(initial_site, initial):
        bad = sorted(q for q in model.get_parents(node) if not str(q).startswith("initial."))
        if bad:
            raise ValueError(
                f"node {node!r} has parents {bad}; an initial node's parents can only be other "
                "initial nodes (the initial state is before the action)"
            )


def _declared(model, features: list[Discrete], actions_node: str) -> dict[str, tuple[str, ...]]:
    """Every initial and end site's parents in ``model`` as sites.

    The action node as ``action``: initial sites first, then the action, then end sites, each in
    feature order.
    """
    order = [initial_site(f.name) for f in features if f.initial]
    order += [actions_node, *(end_site(f.name) for f in features)]
    site = {node: node for node in order} | {actions_node: ACTION}
    return {
        node: tuple(site[q] for q in order if q in set(model.get_parents(node)))
        for node in order
        if node != actions_node
    }


def _relabel(node: str, raw: list, labels: Sequence[Hashable] | None) -> list:
    """The node's state names, or the given labels matched to them by ``str()``."""
    if labels is None:
        return raw
    labels = list(labels)
    by_text = {str(label): label for label in labels}
    if len(by_text) != len(labels) or sorted(by_text) != sorted(map(str, raw)):
        raise ValueError(
            f"node {node!r}: states {labels} (as text {[str(v) for v in labels]}) do not "
            f"match its state names {[str(v) for v in raw]} one to one"
        )
    return [by_text[str(s)] for s in raw]


def _counts(n, shapes) -> dict[str, torch.Tensor]:
    """``n`` per site, as a float tensor of the site's parent shape."""
    if isinstance(n, Mapping):
        missing = set(shapes) - set(n)
        extra = set(n) - set(shapes)
        if missing or extra:
            raise ValueError(
                f"n must state the counts of every site and no other: missing "
                f"{sorted(missing)}, unknown {sorted(extra)}"
            )
        given = dict(n)
    else:
        given = dict.fromkeys(shapes, n)
    counts = {}
    for site, shape in shapes.items():
        value = given[site]
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        array = np.asarray(value)
        if array.dtype.kind not in "iuf":
            raise ValueError(f"n[{site!r}] must be numbers, got {value!r}")
        if array.ndim == 0:
            array = np.full(shape["n"], float(array))
        if array.shape != shape["n"]:
            raise ValueError(
                f"n[{site!r}] has shape {array.shape}; expected {shape['n']} (the site's "
                "discrete parents' cardinalities) or a single number"
            )
        if not np.isfinite(array).all() or (array < 0).any():
            raise ValueError(f"n[{site!r}] must be finite and >= 0, got {array.tolist()}")
        counts[site] = torch.as_tensor(array, dtype=DTYPE)
    return counts
