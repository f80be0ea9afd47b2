r"""A discrete network in the files pgmpy and pyAgrum read: BIF, XMLBIF and UAI.

BIF and XMLBIF go through pgmpy's writers and readers; UAI, a list of numbers, is
written and parsed here (see :func:`write_uai` for why). Every reader ends in
:func:`~models.interop.from_pgmpy`'s checks. The
conventions are the same for the three: one variable per site, named by site
(``initial.<f>``, ``action``, ``end.<f>``); a network with sites a discrete network
cannot hold (continuous features, action parameters, softmax CPDs) is refused, naming
them (save it with :func:`~models.portable.save_npz`); counts and the pseudo-count are
not stored, so a reader is told ``n``. The formats differ in what they keep of a label:

========  ==============================  ============================================
format    a label is stored as            the declared labels come back
========  ==============================  ============================================
BIF       ``str(label)``                  from ``states=`` (matched by ``str``)
XMLBIF    :func:`xmlbif_text` of it       from ``states=`` (matched by that text)
          (white space refused)
UAI       nothing: variables ``0..N-1``   from the declaration ``read_uai`` is given
          and states ``0..K-1``
========  ==============================  ============================================

A writer refuses labels whose stored texts a reader cannot tell apart (two labels of a
site with the same text, or a text the format cannot hold), naming the site.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Hashable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from effect_networks.models.declaration import ACTION, EffectNetwork, FeatureKind
from effect_networks.models.files import target_file, write_atomically
from effect_networks.models.interop import (
    check_discrete,
    discrete_part,
    network_from_model,
    pgmpy_model,
    require_pgmpy,
    site_states,
    table_counts,
)
from effect_networks.models.params import NetworkParams, TableParams, check_params

#: What a BIF label's text may not hold: the grammar's punctuation and comment markers.
BIF_FORBIDDEN = (",", ";", "{", "}", "(", ")", "|", '"', "//", "/*", "\n")


def xmlbif_text(label: Hashable) -> str:
    """The text XMLBIF stores for ``label``.

    pgmpy's XMLBIFWriter keeps ASCII letters, digits and ``_`` and replaces every run of
    other characters by one ``_`` (``-1`` is ``_1``, ``a b`` is ``a_b``).
    """
    return re.sub(r"[^A-Za-z0-9_]+", "_", str(label))


def write_bif(path: str | Path, net: EffectNetwork, params: NetworkParams) -> Path:
    """Write a discrete network to a BIF file (via :func:`to_pgmpy` and pgmpy's BIFWriter).

    BIF stores every state label as its ``str()``; :func:`read_bif` with
    ``states=`` restores the declared labels. Counts and the pseudo-count are not
    stored. The file lists variables sorted by name.

    Parameters
    ----------
    path
        The file to write (its folder is made if missing).
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
        sites: use :func:`models.save_npz` for those), or if a label's ``str()`` cannot be
        read back from BIF (empty, padded with spaces, holding one of
        ``, ; { } ( ) | "``, ``//``, ``/*`` or a line break, or equal to another
        label's of the same site), or if two site names differ only in case (the
        reader folds case).
    """
    require_pgmpy()
    from pgmpy.readwrite import BIFWriter

    def refuses(text: str) -> str | None:
        if text and text == text.strip() and not any(c in text for c in BIF_FORBIDDEN):
            return None
        return (
            f"must be non-empty, without surrounding spaces and without "
            f"{' '.join(BIF_FORBIDDEN[:-1])} or a line break"
        )

    model = _model(net, params, "BIF", str, refuses, fold_case=True)
    BIFWriter(model).write(str(_target(path)))
    return Path(path)


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
    require_pgmpy()
    from pgmpy.readwrite import BIFReader

    model = BIFReader(path=str(path)).get_model()
    return network_from_model(
        model,
        n=n,
        actions_node=actions_node,
        kind=kind,
        order=order,
        pseudo_count=pseudo_count,
        relabel=states,
    )


def write_xmlbif(path: str | Path, net: EffectNetwork, params: NetworkParams) -> Path:
    """Write a discrete network to an XMLBIF file (pgmpy's XMLBIFWriter).

    Every label is stored as its :func:`xmlbif_text`; :func:`read_xmlbif` with
    ``states=`` restores the declared labels. Counts and the pseudo-count are not stored.
    A label whose text holds white space is refused (pgmpy keeps some and replaces
    other, depending on its neighbours).

    Parameters
    ----------
    path
        The file to write (its folder is made if missing).
    net, params
        A discrete network (tables only) and its fitted parameters.

    Returns
    -------
    pathlib.Path
        ``path``, as a ``Path``.

    Raises
    ------
    ValueError
        If the network has sites XMLBIF cannot hold (continuous, parameter or softmax
        sites: use :func:`models.save_npz` for those), or a label's text is empty, holds
        white space or equals another label's of the same site (``-1`` and ``_1`` are
        both ``_1``).
    """
    require_pgmpy()
    from pgmpy.readwrite import XMLBIFWriter

    model = _model(net, params, "XMLBIF", xmlbif_text, _xmlbif_refuses)
    XMLBIFWriter(model).write(str(_target(path)))
    return Path(path)


def read_xmlbif(
    path: str | Path,
    *,
    n: float | Mapping[str, Any],
    states: Mapping[str, Sequence[Hashable]] | None = None,
    actions_node: str = ACTION,
    kind: FeatureKind | Mapping[str, FeatureKind] = "object",
    order: Sequence[str] | None = None,
    pseudo_count: float = 0.01,
) -> tuple[EffectNetwork, NetworkParams]:
    """Read an XMLBIF file (pgmpy's XMLBIFReader) into a declaration and parameters.

    As :func:`read_bif`, except that ``states`` are matched to the file's state names by
    :func:`xmlbif_text` (the text :func:`write_xmlbif` stored); without ``states`` the
    labels are those texts. Action names come back as the file's texts.

    Parameters
    ----------
    path
        The XMLBIF file.
    n, states, actions_node, kind, order, pseudo_count
        As :func:`read_bif`'s: the counts the tables stand for, the declared labels by
        feature, the action's node, the features' kinds, their order and the
        pseudo-count.

    Returns
    -------
    tuple of EffectNetwork and NetworkParams
        The declaration read from the file and its parameters.
    """
    require_pgmpy()
    from pgmpy.readwrite import XMLBIFReader

    try:
        model = XMLBIFReader(path=str(path)).get_model()
    except FileNotFoundError:
        raise
    except Exception as exc:  # ElementTree's ParseError, pgmpy's KeyError and others
        raise ValueError(
            f"{path} is not a readable XMLBIF file ({type(exc).__name__}: {exc})"
        ) from exc
    return network_from_model(
        model,
        n=n,
        actions_node=actions_node,
        kind=kind,
        order=order,
        pseudo_count=pseudo_count,
        relabel=states,
        text=xmlbif_text,
    )


def write_uai(path: str | Path, net: EffectNetwork, params: NetworkParams) -> Path:
    """Write a discrete network to a UAI file (a ``BAYES`` network), atomically.

    UAI stores no names: variable ``i`` is the ``i``-th site of :func:`uai_sites` and its
    states ``0..K-1`` are the declared labels in order; :func:`read_uai` needs the
    declaration to restore them. Each table's scope lists the site's parents
    (``net.cpd(site).parents``) then the site, and its values run with the last scope
    variable fastest (the format's order, our tables' row-major order), written as
    ``repr`` of each float, so they read back bit for bit.

    pgmpy's UAIWriter is not used: it writes a table's values with the child slowest
    under a scope that lists the child last, and its UAIReader orders a table's parents
    by the graph's predecessor order (which varies between runs), so its files of
    tables with two or more parents do not round-trip.

    Parameters
    ----------
    path
        The file to write (its folder is made if missing).
    net, params
        A discrete network (tables only) and its fitted parameters.

    Returns
    -------
    pathlib.Path
        ``path``, as a ``Path``.

    Raises
    ------
    ValueError
        If the network has sites UAI cannot hold (continuous, parameter or softmax
        sites: use :func:`models.save_npz` for those).
    """
    check_params(net, params)
    check_discrete(net, "UAI")
    sites = uai_sites(net)
    index = {site: i for i, site in enumerate(sites)}
    scopes = [[index[p] for p in net.cpd(site).parents] + [index[site]] for site in sites]
    lines = ["BAYES", str(len(sites)), " ".join(str(net.site(site).size) for site in sites)]
    lines += [str(len(sites)), *(" ".join(map(str, [len(sc), *sc])) for sc in scopes), ""]
    for site in sites:
        values = params[site].probs.detach().cpu().to(torch.float64).reshape(-1).tolist()
        lines += [str(len(values)), " ".join(map(repr, values)), ""]
    return write_atomically(target_file(path), "\n".join(lines).encode())


def read_uai(
    path: str | Path,
    net: EffectNetwork,
    *,
    n: float | Mapping[str, Any],
    pseudo_count: float = 0.01,
) -> tuple[EffectNetwork, NetworkParams]:
    """Read a UAI ``BAYES`` file of the declaration ``net`` (as :func:`write_uai` writes).

    UAI holds numbers only, so ``net`` names them: the file's variable ``i`` is the
    ``i``-th site of :func:`uai_sites` and its state ``k`` the site's ``k``-th label. The
    file must hold ``net``'s structure: as many variables, each with the site's number of
    states, one table per site whose scope ends with the site and holds its declared
    parents (in any order: the table is rearranged). The tables then pass
    :func:`from_pgmpy`'s checks (columns summing to 1, ...).

    Parameters
    ----------
    path : str or Path
        The UAI file.
    net : EffectNetwork
        The all-discrete declaration the file was written for.
    n, pseudo_count
        As in :func:`from_pgmpy`.

    Returns
    -------
    (EffectNetwork, NetworkParams)
        ``net`` itself, and the file's tables bound to it.

    Raises
    ------
    ValueError
        If ``net`` has sites UAI cannot hold, the file is not a UAI ``BAYES`` network, or
        its structure is not ``net``'s (naming the variable, its site and what differs).
    """
    DiscreteBayesianNetwork, TabularCPD = require_pgmpy()
    check_discrete(net, "UAI")
    sites = uai_sites(net)
    cards, scopes, tables = _parse_uai(Path(path))
    size = {site: net.site(site).size for site in sites}
    if cards != [size[site] for site in sites]:
        raise ValueError(
            f"{path} has variables of {cards} states; the declaration's sites {sites} have "
            f"{[size[site] for site in sites]}: the file is not of this network"
        )
    model = DiscreteBayesianNetwork()
    model.add_nodes_from(sites)
    seen = set()
    for scope, values in zip(scopes, tables, strict=True):
        site = sites[scope[-1]]
        given = [sites[i] for i in scope[:-1]]
        parents = list(net.cpd(site).parents)
        if site in seen or sorted(given) != sorted(parents) or len(set(scope)) != len(scope):
            raise ValueError(
                f"{path}: the table of var {scope[-1]} (site {site!r}) is over {given}; the "
                f"declaration's {site!r} has one table, over {parents}"
            )
        seen.add(site)
        table = values.reshape([size[v] for v in [*given, site]])
        table = table.transpose([given.index(p) for p in parents] + [len(given)])
        model.add_edges_from((p, site) for p in parents)
        model.add_cpds(
            TabularCPD(
                site,
                size[site],
                table.reshape(-1, size[site]).T,
                evidence=parents or None,
                evidence_card=[size[p] for p in parents] or None,
                state_names={v: list(site_states(net, v)) for v in [site, *parents]},
            )
        )
    missing = [site for site in sites if site not in seen]
    if missing:
        raise ValueError(f"{path} has no table for the sites {missing}")
    back, read = network_from_model(  # from_pgmpy's checks of every column
        model,
        n=0,  # the counts follow, in the declaration's parent order
        actions_node=ACTION,
        kind={f.name: f.kind for f in net.features},
        order=[f.name for f in net.features],
        pseudo_count=pseudo_count,
        relabel=None,
    )
    counts = table_counts(n, {s.name: net.cpd(s.name).shapes() for s in net.sites})
    tables = {}
    for site in sites:  # from_pgmpy orders parents its own way; the declaration may not
        found, parents = back.cpd(site).parents, net.cpd(site).parents
        axes = [found.index(p) for p in parents] + [len(parents)]
        tables[site] = TableParams(read[site].probs.permute(axes).contiguous(), counts[site])
    params = NetworkParams(tables, read.pseudo_count, net)
    check_params(net, params)
    return net, params


def uai_sites(net: EffectNetwork) -> list[str]:
    """The sites of an all-discrete ``net`` that a UAI file numbers ``0, 1, ...``: its site order."""
    kept, _ = discrete_part(net)
    return kept


# ----------------------------------------------------------------------------- helpers
def _model(
    net: EffectNetwork,
    params: NetworkParams,
    holder: str,
    text: Callable[[Hashable], str],
    refuses: Callable[[str], str | None],
    fold_case: bool = False,
):
    """The pgmpy network a writer hands on: checked, its labels the texts ``holder`` stores."""
    require_pgmpy()
    check_params(net, params)
    check_discrete(net, holder)
    kept, _ = discrete_part(net)
    folded: dict[str, str] = {}
    for site in kept:
        other = folded.setdefault(site.lower(), site)
        if fold_case and other != site:
            raise ValueError(
                f"sites {other!r} and {site!r} differ only in case; {holder} readers fold "
                "case. Rename one of the features"
            )
        seen: dict[str, Hashable] = {}
        for label in site_states(net, site):
            stored = text(label)
            why = refuses(str(label)) or ("must be non-empty" if not stored else None)
            if why:
                raise ValueError(
                    f"site {site!r}: label {label!r} cannot be written to {holder} (its text "
                    f"{stored!r} {why})"
                )
            if stored in seen:
                raise ValueError(
                    f"site {site!r}: labels {seen[stored]!r} and {label!r} are both "
                    f"{stored!r} in {holder}; give them distinct texts"
                )
            seen[stored] = label
    return pgmpy_model(net, params, kept, text)


def _parse_uai(path: Path) -> tuple[list[int], list[list[int]], list[np.ndarray]]:
    """A UAI ``BAYES`` file's cardinalities, function scopes and tables, checked for form."""
    tokens = path.read_text().split()
    position = 0

    def take(what: str, count: int = 1) -> list[str]:
        nonlocal position
        if count < 0 or position + count > len(tokens):
            raise ValueError(f"{path} is not a UAI file: it ends before its {what}")
        position += count
        return tokens[position - count : position]

    def integers(what: str, count: int = 1) -> list[int]:
        words = take(what, count)
        if not all(w.isdigit() for w in words):
            raise ValueError(f"{path} is not a UAI file: its {what} {words} are not counts")
        return [int(w) for w in words]

    (kind,) = take("type")
    if kind != "BAYES":
        raise ValueError(f"{path} is a UAI {kind!r} network; expected 'BAYES' (tables)")
    (variables,) = integers("number of variables")
    cards = integers("cardinalities", variables)
    (functions,) = integers("number of tables")
    scopes = []
    for i in range(functions):
        (length,) = integers(f"table {i}'s scope size")
        scope = integers(f"table {i}'s scope", length)
        if not scope or max(scope) >= variables:
            raise ValueError(
                f"{path}: table {i}'s scope {scope} names no variable of 0..{variables - 1}"
            )
        scopes.append(scope)
    tables = []
    for i, scope in enumerate(scopes):
        (count,) = integers(f"table {i}'s number of values")
        expected = math.prod(cards[v] for v in scope)
        if count != expected:
            raise ValueError(
                f"{path}: table {i} has {count} values; its scope {scope} needs {expected}"
            )
        try:
            tables.append(np.array([float(w) for w in take(f"table {i}'s values", count)]))
        except ValueError as exc:
            raise ValueError(
                f"{path}: table {i} holds a value that is not a number ({exc})"
            ) from exc
    if position != len(tokens):
        raise ValueError(f"{path} has {len(tokens) - position} words after its last table")
    return cards, scopes, tables


def _xmlbif_refuses(text: str) -> str | None:
    # pgmpy keeps white space in a state name, or folds it into a "_", depending on its
    # neighbours; XML readers may normalise it. A label with none reads back as written.
    return "must be without white space" if any(c.isspace() for c in text) else None


def _target(path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path
