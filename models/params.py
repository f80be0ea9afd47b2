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
from dataclasses import dataclass, fields
from pathlib import Path

import torch

from models.declaration import (
    ACTION,
    DTYPE,
    EffectNetwork,
    cluster_site,
    end_site,
    initial_site,
    param_site,
)

FORMAT = "effect-networks"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class Table:
    """Categorical child of discrete parents: ``probs`` ``(P..., K)``, ``n`` ``(P...)``."""

    probs: torch.Tensor
    n: torch.Tensor


@dataclass(frozen=True)
class LinearGaussian:
    """Conditional linear Gaussian: ``x_child ~ N(weight @ x_parents + bias, scale_tril @ scale_tril.T)``.

    ``weight`` ``(P..., d, p)``, ``bias`` ``(P..., d)``, ``scale_tril`` ``(P..., d, d)``,
    ``n`` ``(P...)``. ``p`` may be 0 (no continuous parents).
    """

    weight: torch.Tensor
    bias: torch.Tensor
    scale_tril: torch.Tensor
    n: torch.Tensor

    @property
    def covariance(self) -> torch.Tensor:
        return self.scale_tril @ self.scale_tril.mT


@dataclass(frozen=True)
class Softmax:
    """Discrete child of continuous parents: ``logits = weight @ x_parents + bias``.

    ``weight`` ``(P..., K, p)``, ``bias`` ``(P..., K)``, ``n`` ``(P...)``.
    """

    weight: torch.Tensor
    bias: torch.Tensor
    n: torch.Tensor


CPD = Table | LinearGaussian | Softmax
_CPD_TYPES = {cls.__name__: cls for cls in (Table, LinearGaussian, Softmax)}


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
            {
                k: type(c)(**{f.name: fn(getattr(c, f.name)) for f in fields(c)})
                for k, c in self.cpds.items()
            },
            self.pseudo_count,
        )


def expected_shapes(net: EffectNetwork) -> dict[str, tuple[str, dict[str, tuple[int, ...]]]]:
    """The CPD type and tensor shapes every site of ``net`` must have."""
    shapes: dict[str, tuple[str, dict[str, tuple[int, ...]]]] = {}

    def parents_card(sites):
        return tuple(net.site(s).size for s in sites)

    def continuous_dim(sites):
        return sum(net.site(s).size for s in sites)

    for f in net.features:
        if f.initial:
            s = net.site(initial_site(f.name))
            shapes[s.name] = _shape_of(s.discrete, (), s.size, 0)
    shapes[ACTION] = ("Table", {"probs": (len(net.actions),), "n": ()})
    for p in net.parameters:
        shapes[cluster_site(p.name)] = (
            "Table",
            {"probs": (len(net.actions), p.n_clusters), "n": (len(net.actions),)},
        )
        shapes[param_site(p.name)] = _shape_of(False, (p.n_clusters,), p.dim, 0)
    for f in net.features:
        s = net.site(end_site(f.name))
        card = parents_card(net.discrete_parents(f.name))
        cont = continuous_dim(net.continuous_parents(f.name))
        shapes[s.name] = _shape_of(s.discrete, card, s.size, cont)
    return shapes


def _shape_of(discrete: bool, card: tuple[int, ...], size: int, cont: int):
    if discrete and cont == 0:
        return "Table", {"probs": (*card, size), "n": card}
    if discrete:
        return "Softmax", {"weight": (*card, size, cont), "bias": (*card, size), "n": card}
    return "LinearGaussian", {
        "weight": (*card, size, cont),
        "bias": (*card, size),
        "scale_tril": (*card, size, size),
        "n": card,
    }


def check_params(net: EffectNetwork, params: NetworkParams) -> None:
    """Raise ``ValueError`` unless ``params`` has the right CPD for every site of ``net``."""
    expected = expected_shapes(net)
    missing = set(expected) - set(params.cpds)
    extra = set(params.cpds) - set(expected)
    if missing or extra:
        raise ValueError(
            f"parameters do not match the network: missing {sorted(missing)}, extra {sorted(extra)}"
        )
    for site, (kind, shapes) in expected.items():
        cpd = params.cpds[site]
        if type(cpd).__name__ != kind:
            raise ValueError(f"site {site!r}: expected a {kind} CPD, got {type(cpd).__name__}")
        for name, shape in shapes.items():
            got = tuple(getattr(cpd, name).shape)
            if got != shape:
                raise ValueError(f"site {site!r}: {kind}.{name} has shape {got}, expected {shape}")


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


def load(path: str | Path) -> tuple[EffectNetwork, NetworkParams]:
    """Load a network saved by :func:`save`.

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
        net = EffectNetwork.from_dict(json.loads(payload["declaration"]))
        cpds = {}
        for site, entry in payload["cpds"].items():
            entry = dict(entry)
            cls = _CPD_TYPES[entry.pop("type")]
            cpds[site] = cls(**entry)
        params = NetworkParams(cpds, float(payload["pseudo_count"]))
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as exc:
        raise ValueError(
            f"{path} is a damaged effect-network file ({type(exc).__name__}: {exc})"
        ) from exc
    check_params(net, params)
    return net, params


def cell_zero_for_unused(net: EffectNetwork, parameter, probs: torch.Tensor) -> torch.Tensor:
    """A cluster table ``(A, C)`` with the rows of actions not using ``parameter`` on cell 0.

    The rule of :meth:`EffectNetwork.parameter_in_use` for the cluster site: such an
    action ignores the parameter, so its cluster is fixed, not fitted.
    """
    fixed = torch.zeros(parameter.n_clusters, dtype=probs.dtype)
    fixed[0] = 1.0
    return torch.where(net.uses_parameter(parameter)[:, None], probs, fixed)


def random_params(net: EffectNetwork, seed: int, *, unseen: float = 0.0) -> NetworkParams:
    """Valid random parameters for ``net``: for tests, priors and simulation studies.

    Tables are Dirichlet-like draws (softmax of scaled normals), linear Gaussians have
    standard-normal weights and offsets and well-conditioned covariances, softmax CPDs
    normal weights. Each parameter's cluster Gaussian lies inside its own cell (mean
    drawn in the cell's middle half, standard deviation an eighth of the cell), as a
    fitted one does, and actions not using the parameter sit on cell 0. ``unseen``: the
    share of parent configurations marked as reached by no training row (``n = 0``).
    """
    if not 0.0 <= unseen <= 1.0:
        raise ValueError(f"unseen must lie in [0, 1], got {unseen!r}")
    g = torch.Generator().manual_seed(int(seed))

    def normal(shape):
        return torch.randn(shape, generator=g, dtype=DTYPE)

    cpds = {}
    for site, (kind, shapes) in expected_shapes(net).items():
        n = (torch.rand(shapes["n"], generator=g, dtype=DTYPE) >= unseen).to(DTYPE) * 5
        if kind == "Table":
            cpds[site] = Table((2 * normal(shapes["probs"])).softmax(-1), n)
        elif kind == "LinearGaussian":
            d = shapes["bias"][-1]
            a = normal(shapes["scale_tril"])
            cov = a @ a.mT / d + 0.3 * torch.eye(d, dtype=DTYPE)
            cpds[site] = LinearGaussian(
                normal(shapes["weight"]), normal(shapes["bias"]), torch.linalg.cholesky(cov), n
            )
        else:
            cpds[site] = Softmax(normal(shapes["weight"]), normal(shapes["bias"]), n)
    for p in net.parameters:
        c_site, p_site = cluster_site(p.name), param_site(p.name)
        t = cpds[c_site]
        cpds[c_site] = Table(cell_zero_for_unused(net, p, t.probs), t.n)
        width = (torch.tensor(p.high, dtype=DTYPE) - torch.tensor(p.low, dtype=DTYPE)) / (
            torch.tensor(p.bins, dtype=DTYPE)
        )
        offset = (torch.rand(p.n_clusters, p.dim, generator=g, dtype=DTYPE) - 0.5) * 0.5
        mean = p.cluster_centres() + offset * width
        tril = torch.diag_embed((width / 8).expand(p.n_clusters, p.dim))
        prior = cpds[p_site]
        cpds[p_site] = LinearGaussian(prior.weight, mean, tril, prior.n)
    return NetworkParams(cpds, 0.01)
