"""Fitted numbers of an effect network: one conditional distribution per site.

Shapes use ``P...`` for the cardinalities of a site's discrete parents, in the order
:meth:`EffectNetwork.discrete_parents` gives (for roots, ``P...`` is empty), ``K`` for a
discrete site's states, ``d`` for a continuous site's dimension and ``p`` for the summed
dimension of its continuous parents.

``n`` counts the training rows that reached each parent configuration: ``n == 0`` marks a
configuration no sample reached, whose distribution comes from the pseudo-count policy
alone (uniform table, pooled Gaussian) and which queries report as unseen.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import torch
from effect_networks.models.cpds import CPD as KindCPD
from effect_networks.models.cpds import (
    Counts,
    LinearGaussianCPD,
    LinearGaussianParams,
    Moments,
    SoftmaxParams,
    TableParams,
    map_tensors,
)
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.files import stored_members, target_file, write_atomically

FORMAT = "effect-networks"
#: Version 2 added the content checksum (``sha256``); files of other versions are refused.
FORMAT_VERSION = 2
#: The entries of a saved file's payload; a file holding anything else is refused.
#: ``statistics`` is optional (a file without it loads, its parameters carry none).
PAYLOAD_KEYS = frozenset(
    {"format", "version", "declaration", "pseudo_count", "cpds", "sha256", "statistics"}
)
#: The containers of sufficient statistics a saved file may hold, by their saved names.
STATISTICS_TYPES: dict[str, type] = {"Counts": Counts, "Moments": Moments}
#: The largest pickled part of a file (its structure, declaration and numbers' headers:
#: the numbers themselves are separate members) that :func:`load` reads.
MAX_STRUCTURE_BYTES = 16 * 2**20


#: The fitted numbers of one site: one of the toolkit's containers (a user kind adds its own).
SiteParams = TableParams | LinearGaussianParams | SoftmaxParams

#: The ``type`` a saved file gives a site's numbers. The toolkit's containers keep the
#: names format 2 was written with (their classes were named ``Table``, ``Softmax`` and
#: ``LinearGaussian`` then), so files saved before and after the rename read alike; a
#: user kind's container is saved under its class name.
SAVED_NAMES: dict[type, str] = {
    TableParams: "Table",
    SoftmaxParams: "Softmax",
    LinearGaussianParams: "LinearGaussian",
}


def saved_name(container: type) -> str:
    """The ``type`` under which :func:`save` writes a container (:data:`SAVED_NAMES`)."""
    return SAVED_NAMES.get(container, container.__name__)


@dataclass(frozen=True)
class NetworkParams:
    """One conditional distribution per site, keyed by site name, and how they were fitted.

    ``network``: the declaration the parameters were fitted for. Every toolkit function
    that makes parameters (:func:`inference.fit`, :func:`random_params`, :func:`load`,
    ...) sets it, and :func:`check_params` refuses them for a declaration whose
    :meth:`~models.declaration.EffectNetwork.identity` differs (states in another order,
    other actions, another parameter layout, ...): the same numbers would mean other
    things there. Parameters assembled by hand without it are checked by shape only.

    ``statistics``: the summed sufficient statistics the closed-form fit computed them
    from, per site (:class:`~models.cpds.table.Counts` of a table or softmax,
    :class:`~models.cpds.linear_gaussian.Moments` of a linear Gaussian), which
    :func:`inference.fit_update` continues from; ``None`` where the parameters did not
    come from such a fit (EM, the gradient route, by hand, a file saved without them).
    """

    cpds: dict[str, SiteParams]
    pseudo_count: float
    network: EffectNetwork | None = field(default=None, repr=False, compare=False)
    statistics: dict[str, Counts | Moments] | None = field(default=None, repr=False, compare=False)

    def __getitem__(self, site: str) -> SiteParams:
        return self.cpds[site]

    def map(self, fn) -> NetworkParams:
        """Apply ``fn`` to every tensor (e.g. ``lambda t: t.double()``), statistics included."""
        statistics = self.statistics
        if statistics is not None:
            statistics = {k: map_tensors(c, fn) for k, c in statistics.items()}
        return NetworkParams(
            {k: map_tensors(c, fn) for k, c in self.cpds.items()},
            self.pseudo_count,
            self.network,
            statistics,
        )


def check_params(net: EffectNetwork, params: NetworkParams) -> None:
    """Raise ``ValueError`` unless ``params`` fit ``net``.

    ``params`` must have the right CPD for every site of ``net`` and have been fitted for a
    declaration with ``net``'s identity (:func:`check_bound`).
    """
    if not isinstance(params, NetworkParams):
        raise ValueError(f"params must be NetworkParams, got {type(params).__name__}")
    check_bound(net, params)
    missing = {s.name for s in net.sites} - set(params.cpds)
    extra = set(params.cpds) - {s.name for s in net.sites}
    if missing or extra:
        raise ValueError(
            f"parameters do not match the network: missing {sorted(missing)}, extra {sorted(extra)}"
        )
    for spec in net.sites:
        net.cpd(spec.name).check(params.cpds[spec.name])


def check_bound(net: EffectNetwork, params: NetworkParams) -> None:
    """Raise ``ValueError`` if ``params`` were fitted for a declaration other than ``net``'s.

    Naming the first site that differs and how, if the declaration's identity differs from ``net``'s
    (:meth:`~models.declaration.EffectNetwork.identity`). Cheap where they are the same declaration:
    the model runs it on every call.
    """
    fitted = getattr(params, "network", None)
    if fitted is None or fitted is net:
        return
    ours, theirs = net.identity(), fitted.identity()
    if ours == theirs:
        return
    for site in ours:
        if site not in theirs:
            raise ValueError(
                f"site {site!r}: the parameters were fitted for a network without it (its "
                f"sites: {list(theirs)}); fit them for this network"
            )
        for (what, value), (_, fitted_value) in zip(ours[site], theirs[site], strict=False):
            if value != fitted_value:
                raise ValueError(
                    f"site {site!r}: the parameters were fitted for {what} {fitted_value!r}, "
                    f"this network has {what} {value!r}; the same numbers mean other things "
                    "here. Fit them for this network (or use the network they were fitted for)"
                )
        if ours[site] != theirs[site]:
            raise ValueError(
                f"site {site!r}: the parameters were fitted for {theirs[site]}, this network "
                f"has {ours[site]}; fit them for this network"
            )
    unknown = [site for site in theirs if site not in ours]
    raise ValueError(
        f"site {unknown[0]!r}: the parameters were fitted for a network with it, this one has "
        f"no such site (its sites: {list(ours)}); fit them for this network"
    )


def save(path: str | Path, net: EffectNetwork, params: NetworkParams) -> Path:
    """Save a fitted network (declaration and parameters) to one versioned file.

    The file is written beside ``path`` under a temporary name and renamed over it once
    complete, so a failed save (a full disk, a kill) leaves the file that was there. It
    holds a checksum of its content (sha256) that :func:`load` verifies. Tensors are
    saved on the CPU. The parameters' sufficient statistics (``NetworkParams.statistics``)
    are saved with them where they are the toolkit's containers, so that a loaded fit
    can be continued (:func:`inference.fit_update`).

    Parameters
    ----------
    path
        The file to write (its folder is made if missing); a file there is replaced.
    net, params
        The network's declaration and its fitted parameters (checked to fit each other).

    Returns
    -------
    pathlib.Path
        ``path``, as a ``Path``: what :func:`load` reads back.
    """
    check_params(net, params)
    path = target_file(path)
    cpds = {
        site: {
            "type": saved_name(type(c)),
            **{f.name: _cpu(getattr(c, f.name)) for f in fields(c)},
        }
        for site, c in params.cpds.items()
    }
    payload = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "declaration": json.dumps(net.to_dict()),
        "pseudo_count": float(params.pseudo_count),
        "cpds": cpds,
    }
    statistics = _saved_statistics(params)
    if statistics is not None:
        payload["statistics"] = statistics
    payload["sha256"] = _checksum(payload)
    # the archive is built in memory (a model's numbers are small), so that a disk that
    # fills is Python's OSError on our write, not an error deep inside torch's zip writer
    content = io.BytesIO()
    torch.save(payload, content)
    write_atomically(path, content.getbuffer())
    return path


def load(
    path: str | Path, kinds: Iterable[type[KindCPD]] = ()
) -> tuple[EffectNetwork, NetworkParams]:
    """Load a network saved by :func:`save`.

    ``kinds``: the classes of the user-defined kinds it names (the toolkit's own are known).

    Nothing in the file is executed (``torch.load(weights_only=True)``), and nothing is
    inflated before it is known: the file's members must be stored uncompressed, as
    :func:`save` writes them, its pickled structure at most :data:`MAX_STRUCTURE_BYTES`;
    its numbers are mapped, not read, until the payload holds exactly
    :data:`PAYLOAD_KEYS`. Then the content's checksum is verified, before the declaration
    is parsed or any CPD built; then every site must hold a CPD of its declared shape and
    nothing else, and the numbers are copied into memory.


    Parameters
    ----------
    path
        A file :func:`save` wrote.
    kinds
        The classes of the user-defined kinds it names (the toolkit's own are known).

    Returns
    -------
    tuple of (EffectNetwork, NetworkParams)
        The declaration and the parameters, as they were saved (with their sufficient
        statistics where they were saved, so that :func:`inference.fit_update` continues
        the fit).

    Raises
    ------
    ValueError
        If the file is not an effect-network file, is corrupt (its checksum differs),
        has another format version, holds unknown entries, or its parameters do not fit
        its declaration.
    """
    path = Path(path)
    _check_archive(path)
    try:
        payload = torch.load(path, weights_only=True, mmap=True)
    except FileNotFoundError:
        raise
    except Exception as exc:  # torch raises several types for a damaged file
        raise ValueError(
            f"{path} is not a readable effect-network file ({type(exc).__name__}: {exc})"
        ) from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path} is not an effect-network file (no {FORMAT!r} header)")
    if payload.get("version") != FORMAT_VERSION:
        raise ValueError(
            f"{path} has format version {payload.get('version')!r}; this toolkit reads version "
            f"{FORMAT_VERSION}. Re-fit the network or load it with the matching toolkit version."
        )
    unknown = sorted(map(str, set(payload) - PAYLOAD_KEYS))
    if unknown:
        raise ValueError(
            f"{path} holds unknown entries {unknown}; an effect-network file holds only "
            f"{sorted(PAYLOAD_KEYS)}"
        )
    try:
        verified = payload.get("sha256") == _checksum(payload)
    except (AttributeError, KeyError, TypeError, ValueError) as exc:  # not the saved layout
        raise ValueError(
            f"{path} is a damaged effect-network file ({type(exc).__name__}: {exc})"
        ) from exc
    if not verified:
        raise ValueError(
            f"{path} is damaged: its content does not match the sha256 checksum saved with it "
            "(a changed byte); re-save the network from its source"
        )
    try:
        net = EffectNetwork.from_dict(json.loads(payload["declaration"]), kinds)
        cpds = {}
        for site, entry in payload["cpds"].items():
            entry = dict(entry)
            cls = net.cpd(site).params_type
            if entry.pop("type") != saved_name(cls):
                raise ValueError(f"site {site!r} holds no {cls.__name__} ({saved_name(cls)!r})")
            names = {f.name for f in fields(cls)}
            if set(entry) != names:
                raise ValueError(
                    f"site {site!r}: its {cls.__name__} holds {sorted(entry)}, expected "
                    f"{sorted(names)}"
                )
            if not all(isinstance(v, torch.Tensor) for v in entry.values()):
                raise ValueError(f"site {site!r}: its {cls.__name__} holds other than tensors")
            cpds[site] = cls(**entry)
        statistics = _loaded_statistics(net, payload.get("statistics"))
        params = NetworkParams(cpds, float(payload["pseudo_count"]), net, statistics)
        check_params(net, params)  # shapes only: nothing has been read yet
    except (KeyError, TypeError, ValueError, RecursionError) as exc:
        # RecursionError: a declaration nested deeper than any network's (a crafted file)
        raise ValueError(
            f"{path} is a damaged effect-network file ({type(exc).__name__}: {exc})"
        ) from exc
    return net, params.map(lambda t: t.clone())  # off the mapped file


def _saved_statistics(params: NetworkParams) -> dict | None:
    """The statistics entry of a saved file, or ``None`` (none kept, or a user's container)."""
    if params.statistics is None or set(params.statistics) != set(params.cpds):
        return None
    names = {cls: name for name, cls in STATISTICS_TYPES.items()}
    if not all(type(c) in names for c in params.statistics.values()):
        return None
    return {
        site: {"type": names[type(c)], **{f.name: _cpu(getattr(c, f.name)) for f in fields(c)}}
        for site, c in params.statistics.items()
    }


def _loaded_statistics(net: EffectNetwork, entries: object) -> dict | None:
    """A saved statistics entry, checked against ``net``'s kinds and shapes (or ``None``)."""
    if entries is None:
        return None
    if not isinstance(entries, dict) or set(entries) != {s.name for s in net.sites}:
        raise ValueError("its statistics do not name every site of its declaration")
    statistics = {}
    for site, entry in entries.items():
        entry = dict(entry)
        cls = STATISTICS_TYPES.get(entry.pop("type", None))
        cpd = net.cpd(site)
        expected = Moments if isinstance(cpd, LinearGaussianCPD) else Counts
        if cls is not expected:
            raise ValueError(f"site {site!r}: its statistics are not {expected.__name__}")
        groups, d, q = math.prod(cpd.card), cpd.size, cpd.width + 1
        shapes = (
            {"zz": (groups, q, q), "zy": (groups, q, d), "yy": (groups, d, d), "n": (groups,)}
            if cls is Moments
            else {"counts": (*cpd.card, cpd.size)}
        )
        if set(entry) != set(shapes) or not all(
            isinstance(v, torch.Tensor) and v.dtype == torch.float64 and tuple(v.shape) == shapes[k]
            for k, v in entry.items()
        ):
            raise ValueError(
                f"site {site!r}: its {cls.__name__} statistics are not float64 tensors of "
                f"shapes {shapes}"
            )
        statistics[site] = cls(**entry)
    return statistics


def _cpu(value):
    return value.detach().cpu() if isinstance(value, torch.Tensor) else value


def _checksum(payload: dict) -> str:
    """sha256 of a payload's content.

    Its header, declaration and pseudo-count, and every site's tensors (dtype, shape and bytes),
    sites and fields in sorted order.
    """
    cpds = dict(payload["cpds"])
    if "statistics" in payload:  # optional: a file without it keeps its checksum
        cpds |= {f"statistics:{site}": entry for site, entry in payload["statistics"].items()}
    h = hashlib.sha256()
    header = {
        "format": payload["format"],
        "version": payload["version"],
        "declaration": payload["declaration"],
        "pseudo_count": repr(float(payload["pseudo_count"])),
        "cpds": {
            site: {
                k: [str(v.dtype), list(v.shape)] if isinstance(v, torch.Tensor) else repr(v)
                for k, v in entry.items()
            }
            for site, entry in cpds.items()
        },
    }
    h.update(json.dumps(header, sort_keys=True).encode())
    for site in sorted(cpds):
        for name in sorted(cpds[site]):
            value = cpds[site][name]
            if isinstance(value, torch.Tensor):
                # numpy's bytes in C order, whatever the strides: a fitted tensor may be a
                # view whose size-1 dimensions have any stride, which torch's byte view refuses
                h.update(np.ascontiguousarray(value.detach().cpu().numpy()).tobytes())
    return h.hexdigest()


def _check_archive(path: Path) -> None:
    """Refuse, before anything is inflated, a file too large to open safely.

    That is a file whose members are compressed (a small file can inflate to gigabytes; :func:`save`
    compresses nothing) or whose pickled structure is larger than :data:`MAX_STRUCTURE_BYTES`.
    """
    for m in stored_members(path, "effect-network file"):
        if m.filename.endswith("/data.pkl") and m.file_size > MAX_STRUCTURE_BYTES:
            raise ValueError(
                f"{path}: its structure {m.filename!r} has {m.file_size} bytes, more than "
                f"MAX_STRUCTURE_BYTES = {MAX_STRUCTURE_BYTES}; refused unread"
            )


def check_seed(seed: object) -> int:
    """``seed`` as a Python int, a Python or numpy integer in -2**63..2**64 - 1 (torch's range)."""
    if (
        not isinstance(seed, int | np.integer)
        or isinstance(seed, bool)
        or not -(2**63) <= int(seed) < 2**64
    ):
        raise ValueError(f"seed={seed!r} is invalid; expected an int in -2**63..2**64 - 1")
    return int(seed)


def random_params(net: EffectNetwork, seed: int, *, unseen: float = 0.0) -> NetworkParams:
    """Valid random parameters for ``net``: for tests, priors and simulation studies.

    Each kind draws its own (:meth:`models.cpds.CPD.initialize`): tables are
    Dirichlet-like draws (softmax of scaled normals), linear Gaussians have
    standard-normal weights and offsets and well-conditioned covariances, softmax CPDs
    normal weights. Each parameter's cluster Gaussian lies inside its own cell (mean
    drawn in the cell's middle half, standard deviation an eighth of the cell), as a
    fitted one does, and actions not using the parameter sit on cell 0. ``unseen``: the
    share of parent configurations marked as reached by no training row (``n = 0``).

    Parameters
    ----------
    net
        The network to draw parameters for.
    seed
        Seeds the draw: the same seed gives the same parameters.
    unseen
        The share of parent configurations marked as reached by no training row, in
        ``[0, 1]``.

    Returns
    -------
    NetworkParams
        A CPD per site of ``net``, with pseudo-count 0.01.
    """
    seed = check_seed(seed)
    if not 0.0 <= unseen <= 1.0:
        raise ValueError(f"unseen must lie in [0, 1], got {unseen!r}")
    g = torch.Generator().manual_seed(seed)
    cpds = {s.name: net.cpd(s.name).initialize(g, unseen) for s in net.sites}
    for m in net.mixtures:
        cpds[m.value.site] = m.randomize(cpds[m.value.site], g)
    return NetworkParams(cpds, 0.01, net)


def initial_params(net: EffectNetwork, pseudo_count: float) -> NetworkParams:
    """Every kind's neutral start: the gradient route's default.

    Uniform tables, zero-slope unit Gaussians, zero softmax.
    """
    return NetworkParams(
        {s.name: net.cpd(s.name).initialize() for s in net.sites}, pseudo_count, net
    )
