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

import json
from collections.abc import Iterable
from dataclasses import dataclass, fields
from pathlib import Path

import torch

from models.cpds import CPD as KindCPD
from models.cpds import LinearGaussian, Softmax, Table, map_tensors
from models.declaration import EffectNetwork

FORMAT = "effect-networks"
FORMAT_VERSION = 1


CPD = Table | LinearGaussian | Softmax  # the toolkit's containers (a user kind adds its own)


@dataclass(frozen=True)
class NetworkParams:
    """One conditional distribution per site, keyed by site name, and how they were fitted."""

    cpds: dict[str, CPD]
    pseudo_count: float

    def __getitem__(self, site: str) -> CPD:
        return self.cpds[site]

    def map(self, fn) -> NetworkParams:
        """Apply ``fn`` to every tensor (e.g. ``lambda t: t.double()``)."""
        return NetworkParams(
            {k: map_tensors(c, fn) for k, c in self.cpds.items()}, self.pseudo_count
        )


def check_params(net: EffectNetwork, params: NetworkParams) -> None:
    """Raise ``ValueError`` unless ``params`` has the right CPD for every site of ``net``."""
    missing = {s.name for s in net.sites} - set(params.cpds)
    extra = set(params.cpds) - {s.name for s in net.sites}
    if missing or extra:
        raise ValueError(
            f"parameters do not match the network: missing {sorted(missing)}, extra {sorted(extra)}"
        )
    for spec in net.sites:
        net.cpd(spec.name).check(params.cpds[spec.name])


def save(path: str | Path, net: EffectNetwork, params: NetworkParams) -> Path:
    """Save a fitted network (declaration and parameters) to one versioned file."""
    check_params(net, params)
    path = Path(path)
    payload = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "declaration": json.dumps(net.to_dict()),
        "pseudo_count": float(params.pseudo_count),
        "cpds": {
            site: {"type": type(c).__name__, **{f.name: getattr(c, f.name) for f in fields(c)}}
            for site, c in params.cpds.items()
        },
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, path)
    return path


def load(
    path: str | Path, kinds: Iterable[type[KindCPD]] = ()
) -> tuple[EffectNetwork, NetworkParams]:
    """Load a network saved by :func:`save`; ``kinds``: the classes of the user-defined
    kinds it names (the toolkit's own are known).

    Raises
    ------
    ValueError
        If the file is not an effect-network file, is corrupt, has another format version,
        or its parameters do not fit its declaration.
    """
    path = Path(path)
    try:
        payload = torch.load(path, weights_only=True)
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
    try:
        net = EffectNetwork.from_dict(json.loads(payload["declaration"]), kinds)
        cpds = {}
        for site, entry in payload["cpds"].items():
            entry = dict(entry)
            cls = net.cpd(site).params_type
            if entry.pop("type") != cls.__name__:
                raise ValueError(f"site {site!r} holds no {cls.__name__}")
            cpds[site] = cls(**entry)
        params = NetworkParams(cpds, float(payload["pseudo_count"]))
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
        raise ValueError(
            f"{path} is a damaged effect-network file ({type(exc).__name__}: {exc})"
        ) from exc
    check_params(net, params)
    return net, params


def random_params(net: EffectNetwork, seed: int, *, unseen: float = 0.0) -> NetworkParams:
    """Valid random parameters for ``net``: for tests, priors and simulation studies.

    Each kind draws its own (:meth:`models.cpds.CPD.initialize`): tables are
    Dirichlet-like draws (softmax of scaled normals), linear Gaussians have
    standard-normal weights and offsets and well-conditioned covariances, softmax CPDs
    normal weights. Each parameter's cluster Gaussian lies inside its own cell (mean
    drawn in the cell's middle half, standard deviation an eighth of the cell), as a
    fitted one does, and actions not using the parameter sit on cell 0. ``unseen``: the
    share of parent configurations marked as reached by no training row (``n = 0``).
    """
    if not 0.0 <= unseen <= 1.0:
        raise ValueError(f"unseen must lie in [0, 1], got {unseen!r}")
    g = torch.Generator().manual_seed(int(seed))
    cpds = {s.name: net.cpd(s.name).initialize(g, unseen) for s in net.sites}
    for m in net.mixtures:
        cpds[m.value.site] = m.randomize(cpds[m.value.site], g)
    return NetworkParams(cpds, 0.01)


def initial_params(net: EffectNetwork, pseudo_count: float) -> NetworkParams:
    """Every kind's neutral start (uniform tables, zero-slope unit Gaussians, zero
    softmax): the gradient route's default."""
    return NetworkParams({s.name: net.cpd(s.name).initialize() for s in net.sites}, pseudo_count)
